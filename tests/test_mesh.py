"""cell.mesh: good meshes load in every supported format with correct figures; every bad input is refused with
a ConfigError that names the file and what was found."""

from __future__ import annotations

import itertools
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh

from cell.errors import ConfigError
from cell.mesh import MeshWarning, check_in_volume, check_units, load_mesh, mesh_summary


def _box(extents=(10.0, 20.0, 30.0)) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents)


def _refused(path: Path, *fragments: str) -> str:
    with pytest.raises(ConfigError) as info:
        load_mesh(path)
    message = str(info.value)
    assert str(path) in message
    for fragment in fragments:
        assert fragment in message, message
    return message


@pytest.mark.parametrize("suffix", [".stl", ".ply", ".obj"])
def test_box_loads_with_analytic_figures(tmp_path, suffix):
    path = tmp_path / f"box{suffix}"
    _box().export(path)
    summary = mesh_summary(load_mesh(path))
    assert summary["triangles"] == 12 and summary["vertices"] == 8  # STL's 36 corners merged
    np.testing.assert_allclose(summary["extents_mm"], [10, 20, 30])
    assert summary["watertight"]
    assert summary["area_mm2"] == pytest.approx(2 * (10 * 20 + 20 * 30 + 10 * 30))
    assert summary["volume_mm3"] == pytest.approx(6000.0)


def test_open_surface_loads_and_reports_not_watertight(tmp_path):
    box = _box()
    box.update_faces(np.arange(10))  # drop one side: a surface model, like many sheet-metal CADs
    path = tmp_path / "open.stl"
    box.export(path)
    summary = mesh_summary(load_mesh(path))
    assert not summary["watertight"] and summary["volume_mm3"] is None


def test_missing_file(tmp_path):
    _refused(tmp_path / "nope.stl", "not found")


def test_unsupported_suffix(tmp_path):
    path = tmp_path / "part.iges"
    path.write_text("x")
    _refused(path, "unsupported", ".stl")


def test_empty_file(tmp_path):
    path = tmp_path / "empty.stl"
    path.write_bytes(b"")
    _refused(path, "empty")


@pytest.mark.parametrize("suffix", [".stl", ".obj", ".ply"])
def test_garbage_bytes(tmp_path, suffix):
    path = tmp_path / f"garbage{suffix}"
    path.write_bytes(np.random.default_rng(7).bytes(500))
    message = _refused(path)
    # trimesh reads garbage either as a broken binary file or, where charset_normalizer is installed, as text
    # without triangles: both must be refused with the file named
    assert "unreadable" in message or "no triangles" in message, message


def test_file_without_triangles(tmp_path):
    path = tmp_path / "points.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    _refused(path, "no triangles")


def test_nan_vertex(tmp_path):
    path = tmp_path / "nan.obj"
    path.write_text("v 0 0 0\nv 10 0 0\nv nan 10 0\nv 0 0 10\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n")
    _refused(path, "1 of 4 vertices", "NaN")


def test_non_manifold_fan(tmp_path):
    # three triangles hinged on one edge (a fin): that edge has three faces
    v = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, -10, 0], [0, 0, 10.0]])
    path = tmp_path / "fan.stl"
    trimesh.Trimesh(v, [[0, 1, 2], [0, 1, 3], [0, 1, 4]], process=False).export(path)
    _refused(path, "non-manifold", "1 edge(s)", "at most 3")


def test_degenerate_triangles_removed_with_warning(tmp_path):
    box = _box()
    extra = np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2.0]]) + 100  # collinear: zero area
    mesh = trimesh.Trimesh(
        np.vstack([box.vertices, extra]), np.vstack([box.faces, [[8, 9, 10]]]), process=False
    )
    path = tmp_path / "degenerate.ply"
    mesh.export(path)
    with pytest.warns(MeshWarning, match=r"removed 1 zero-area triangle"):
        loaded = load_mesh(path)
    assert len(loaded.faces) == 12 and len(loaded.vertices) == 8
    assert mesh_summary(loaded)["degenerate_removed"] == 1


def test_only_degenerate_triangles(tmp_path):
    path = tmp_path / "flat.obj"
    path.write_text("v 0 0 0\nv 1 1 1\nv 2 2 2\nv 3 3 3\nf 1 2 3\nf 2 3 4\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # refused outright, no warning first
        _refused(path, "all 2 triangles have zero area")


def test_part_in_metres(tmp_path):
    path = tmp_path / "metres.stl"
    _box((0.45, 0.12, 0.05)).export(path)  # a 450 mm pillar written in metres
    _refused(path, "0.45 mm", "metres", "1000", "450 mm")


def test_part_in_micrometres(tmp_path):
    path = tmp_path / "microns.stl"
    _box((450_000.0, 120_000.0, 50_000.0)).export(path)
    _refused(path, "micrometres", "0.001", "450 mm")


def test_implausible_size_that_no_factor_fixes(tmp_path):
    with pytest.raises(ConfigError, match="no factor of 1000"):
        check_units(_box((1e-5, 1e-5, 1e-5)), tmp_path / "speck.stl")


def test_working_volume(tmp_path):
    box, path = _box((100.0, 100.0, 100.0)), tmp_path / "part.stl"
    check_in_volume(box, path, [-60, -60, -60], [60, 60, 60])
    with pytest.raises(ConfigError, match=r"larger than the working volume") as info:
        check_in_volume(box, path, [0, 0, 0], [90, 500, 500])
    assert str(path) in str(info.value)
    shifted = np.eye(4)
    shifted[0, 3] = 50.0  # fits in size, but placed half outside
    with pytest.raises(ConfigError, match=r"outside the working volume.*T_W_P"):
        check_in_volume(box, path, [-60, -60, -60], [60, 60, 60], T_W_P=shifted)


def _step_box(size: tuple[float, float, float]) -> str:
    """A minimal AP214 STEP text of an axis-aligned box (mm): 8 vertices, 12 line edges, 6 planar faces.

    Written here so the test needs no third-party CAD file; OpenCASCADE (through cascadio) reads it.
    """
    ents = []

    def add(s):
        ents.append(s)
        return len(ents)

    sx, sy, sz = size
    corners = {}
    vp = {}
    for i, j, k in itertools.product((0, 1), repeat=3):
        p = add(f"CARTESIAN_POINT('',({i * sx:.6f},{j * sy:.6f},{k * sz:.6f}))")
        corners[(i, j, k)] = p
        vp[(i, j, k)] = add(f"VERTEX_POINT('',#{p})")
    edges = {}

    def edge(a, b):
        key = tuple(sorted((a, b)))
        if key not in edges:
            a0, b0 = key
            d = [b0[n] - a0[n] for n in range(3)]
            dr = add(f"DIRECTION('',({d[0]:.1f},{d[1]:.1f},{d[2]:.1f}))")
            L = [sx, sy, sz][d.index(1)]
            vec = add(f"VECTOR('',#{dr},{L:.6f})")
            line = add(f"LINE('',#{corners[a0]},#{vec})")
            edges[key] = add(f"EDGE_CURVE('',#{vp[a0]},#{vp[b0]},#{line},.T.)")
        return edges[key], key[0] == a

    faces = []
    for axis in range(3):
        for side in (0, 1):
            # four corners of this face, ordered CCW seen from outside
            others = [n for n in range(3) if n != axis]
            quad = []
            for u, v in ((0, 0), (1, 0), (1, 1), (0, 1)):
                c = [0, 0, 0]
                c[axis] = side
                c[others[0]] = u
                c[others[1]] = v
                quad.append(tuple(c))
            normal = [0.0, 0.0, 0.0]
            normal[axis] = 1.0 if side else -1.0
            # CCW about +axis for (others[0], others[1]) when axis order is cyclic
            cyclic = (others[0] - axis) % 3 == 1
            if (side == 1) != cyclic:
                quad = quad[::-1]
            oes = []
            for a, b in zip(quad, quad[1:] + quad[:1], strict=True):
                e, same = edge(a, b)
                oes.append(add(f"ORIENTED_EDGE('',*,*,#{e},{'.T.' if same else '.F.'})"))
            loop = add("EDGE_LOOP('',(" + ",".join(f"#{o}" for o in oes) + "))")
            bound = add(f"FACE_OUTER_BOUND('',#{loop},.T.)")
            nd = add(f"DIRECTION('',({normal[0]},{normal[1]},{normal[2]}))")
            ref = [0.0, 0.0, 0.0]
            ref[others[0]] = 1.0
            rd = add(f"DIRECTION('',({ref[0]},{ref[1]},{ref[2]}))")
            ax = add(f"AXIS2_PLACEMENT_3D('',#{corners[quad[0]]},#{nd},#{rd})")
            plane = add(f"PLANE('',#{ax})")
            faces.append(add(f"ADVANCED_FACE('',(#{bound}),#{plane},.T.)"))
    shell = add("CLOSED_SHELL('',(" + ",".join(f"#{f}" for f in faces) + "))")
    brep = add(f"MANIFOLD_SOLID_BREP('box',#{shell})")
    o = add("CARTESIAN_POINT('',(0.,0.,0.))")
    z = add("DIRECTION('',(0.,0.,1.))")
    x = add("DIRECTION('',(1.,0.,0.))")
    ax = add(f"AXIS2_PLACEMENT_3D('',#{o},#{z},#{x})")
    unc = add("UNCERTAINTY_MEASURE_WITH_UNIT(LENGTH_MEASURE(1.E-07),#LEN,'distance_accuracy_value','')")
    lu = add("(LENGTH_UNIT()NAMED_UNIT(*)SI_UNIT(.MILLI.,.METRE.))")
    au = add("(NAMED_UNIT(*)PLANE_ANGLE_UNIT()SI_UNIT($,.RADIAN.))")
    su = add("(NAMED_UNIT(*)SI_UNIT($,.STERADIAN.)SOLID_ANGLE_UNIT())")
    ents[unc - 1] = ents[unc - 1].replace("#LEN", f"#{lu}")
    ctx = add(
        f"(GEOMETRIC_REPRESENTATION_CONTEXT(3)GLOBAL_UNCERTAINTY_ASSIGNED_CONTEXT((#{unc}))"
        f"GLOBAL_UNIT_ASSIGNED_CONTEXT((#{lu},#{au},#{su}))REPRESENTATION_CONTEXT('',''))"
    )
    rep = add(f"ADVANCED_BREP_SHAPE_REPRESENTATION('',(#{ax},#{brep}),#{ctx})")
    appc = add("APPLICATION_CONTEXT('automotive_design')")
    pc = add(f"PRODUCT_CONTEXT('',#{appc},'mechanical')")
    prod = add(f"PRODUCT('box','box','',(#{pc}))")
    pdf = add(f"PRODUCT_DEFINITION_FORMATION('','',#{prod})")
    pdc = add(f"PRODUCT_DEFINITION_CONTEXT('part definition',#{appc},'design')")
    pd = add(f"PRODUCT_DEFINITION('design','',#{pdf},#{pdc})")
    pds = add(f"PRODUCT_DEFINITION_SHAPE('','',#{pd})")
    add(f"SHAPE_DEFINITION_REPRESENTATION(#{pds},#{rep})")
    body = "\n".join(f"#{i}={e};" for i, e in enumerate(ents, 1))
    return (
        "ISO-10303-21;\nHEADER;\nFILE_DESCRIPTION((''),'2;1');\nFILE_NAME('box.step','',(''),(''),'','','');\n"
        "FILE_SCHEMA(('AUTOMOTIVE_DESIGN { 1 0 10303 214 1 1 1 1 }'));\nENDSEC;\nDATA;\n"
        + body
        + "\nENDSEC;\nEND-ISO-10303-21;\n"
    )


def test_step_box_is_tessellated_in_millimetres(tmp_path):
    pytest.importorskip("cascadio")
    path = tmp_path / "box.step"
    path.write_text(_step_box((10.0, 20.0, 30.0)))
    summary = mesh_summary(load_mesh(path))
    assert summary["watertight"] and summary["triangles"] == 12
    np.testing.assert_allclose(summary["extents_mm"], [10, 20, 30], rtol=1e-6)  # glTF metres scaled back
    assert summary["volume_mm3"] == pytest.approx(6000.0, rel=1e-6)


def test_step_without_cascadio_names_the_package(tmp_path, monkeypatch):
    path = tmp_path / "box.step"
    path.write_text(_step_box((10.0, 20.0, 30.0)))
    monkeypatch.setitem(sys.modules, "cascadio", None)  # makes the import fail
    _refused(path, "cascadio", "STL")


def test_opencascade_loads_only_when_a_step_file_is_read(tmp_path):
    pytest.importorskip("cascadio")
    path = tmp_path / "box.step"
    path.write_text(_step_box((10.0, 20.0, 30.0)))
    code = (
        "import sys\nimport cell.mesh, trimesh\nprint('before', 'cascadio' in sys.modules)\n"
        f"m = cell.mesh.load_mesh({str(path)!r})\nprint('after', 'cascadio' in sys.modules, len(m.faces))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "before False" in out.stdout and "after True 12" in out.stdout
