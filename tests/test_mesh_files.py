"""cell.mesh_files and cell.mesh.load_mesh_arrays read what trimesh reads: the same vertices and faces bit for
bit, the same checks with the same messages and warnings, and hand files they do not know to trimesh. A
plain file is read without importing trimesh at all."""

from __future__ import annotations

import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import trimesh

from cell.analysis.compare import load_cloud
from cell.errors import ConfigError
from cell.mesh import MeshArrays, MeshWarning, load_mesh, load_mesh_arrays, merge_vertices
from cell.mesh_files import read_binary_stl, read_plain_mesh, read_ply

REPO = Path(__file__).resolve().parent.parent


def write_ply(
    path: Path, vertices: np.ndarray, faces: np.ndarray | None, order: str = "<", extra: bool = False
):
    """A binary PLY written by hand: float32 x y z (and a double 'quality' before them with ``extra``), uchar
    counts and int indices."""
    props = [("quality", "f8")] if extra else []
    props += [("x", "f4"), ("y", "f4"), ("z", "f4")]
    names = {"f4": "float", "f8": "double"}
    head = f"ply\nformat binary_{'little' if order == '<' else 'big'}_endian 1.0\ncomment by hand\n"
    head += f"element vertex {len(vertices)}\n" + "".join(f"property {names[t]} {n}\n" for n, t in props)
    if faces is not None:
        head += f"element face {len(faces)}\nproperty list uchar int vertex_indices\n"
    head += "end_header\n"
    rec = np.zeros(len(vertices), dtype=[(n, order + t) for n, t in props])
    for k, n in enumerate("xyz"):
        rec[n] = vertices[:, k]
    body = rec.tobytes()
    if faces is not None:
        fr = np.zeros(len(faces), dtype=[("n", "u1"), ("v", order + "i4", (faces.shape[1],))])
        fr["n"], fr["v"] = faces.shape[1], faces
        body += fr.tobytes()
    path.write_bytes(head.encode() + body)
    return path


def meshes(tmp: Path) -> dict[str, Path]:
    """Files of every case: good meshes in each plain layout, and each check's failure."""
    box = trimesh.creation.box(extents=(10.0, 20.0, 30.0))
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=40.0)
    out = {}
    for name, mesh in (("box", box), ("sphere", sphere)):
        out[f"{name}.stl"] = tmp / f"{name}.stl"
        mesh.export(out[f"{name}.stl"])
    out["sphere big-endian.ply"] = write_ply(tmp / "sphere_be.ply", sphere.vertices, sphere.faces, order=">")
    out["sphere little-endian.ply"] = write_ply(tmp / "sphere_le.ply", sphere.vertices, sphere.faces)
    out["sphere with a property.ply"] = write_ply(tmp / "q.ply", sphere.vertices, sphere.faces, extra=True)
    quads = np.array([[0, 1, 2, 3], [0, 3, 4, 5]])
    out["quads.ply (trimesh's)"] = write_ply(tmp / "quads.ply", np.eye(6, 3) * 10 + 1, quads)
    out["recipe pillar.stl"] = REPO / "recipes" / "parts" / "pillar_nominal.stl"
    fin = trimesh.Trimesh(
        np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, -10, 0], [0, 0, 10.0]]),
        [[0, 1, 2], [0, 1, 3], [0, 1, 4]],
        process=False,
    )
    out["fin.stl"] = tmp / "fin.stl"
    fin.export(out["fin.stl"])
    flat = np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2.0]]) + 100
    degenerate = trimesh.Trimesh(
        np.vstack([box.vertices, flat]), np.vstack([box.faces, [[8, 9, 10]]]), process=False
    )
    out["degenerate.stl"] = tmp / "degenerate.stl"
    degenerate.export(out["degenerate.stl"])
    sliver = np.array([[0, 0, 0], [10, 0, 0], [5, 5e-8, 0]])  # 5e-8 mm high: kept (tol 1e-8 mm)
    out["sliver.stl"] = tmp / "sliver.stl"
    trimesh.Trimesh(
        np.vstack([box.vertices, sliver]), np.vstack([box.faces, [[8, 9, 10]]]), process=False
    ).export(out["sliver.stl"])
    out["only degenerate.stl"] = tmp / "flat.stl"
    trimesh.Trimesh(flat, [[0, 1, 2]], process=False).export(out["only degenerate.stl"])
    out["metres.stl"] = tmp / "metres.stl"
    trimesh.creation.box(extents=(0.45, 0.12, 0.05)).export(out["metres.stl"])
    nan = box.copy()
    nan.vertices[3, 1] = np.nan
    out["nan.stl"] = tmp / "nan.stl"
    nan.export(out["nan.stl"])
    out["short.stl"] = tmp / "short.stl"
    out["short.stl"].write_bytes(out["box.stl"].read_bytes()[:-7])
    return out


def outcome(load, path: Path):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            got = load(path)
        except ConfigError as exc:
            return ("error", str(exc)), [str(w.message) for w in caught]
    return got, [str(w.message) for w in caught if issubclass(w.category, MeshWarning)]


def test_load_mesh_arrays_is_load_mesh(tmp_path: Path) -> None:
    files = meshes(tmp_path)
    by_trimesh = {"quads.ply (trimesh's)", "short.stl"}
    assert {n for n, p in files.items() if read_plain_mesh(p) is None} == by_trimesh  # the rest: read here
    for name, path in files.items():
        (light, light_warned) = outcome(load_mesh_arrays, path)
        (full, full_warned) = outcome(load_mesh, path)
        assert light_warned == full_warned, name
        if isinstance(full, tuple):
            assert light == full, name
            continue
        assert isinstance(light, MeshArrays), (name, light)
        assert np.array_equal(light.vertices, full.vertices), name
        assert np.array_equal(light.faces, full.faces), name
        assert light.degenerate_removed == full.metadata.get("degenerate_removed", 0), name


def test_plain_files_read_as_trimesh_reads_them(tmp_path: Path) -> None:
    files = meshes(tmp_path)
    stl = read_binary_stl(files["sphere.stl"])
    loaded = trimesh.load(files["sphere.stl"], process=False)
    assert (
        stl is not None and np.array_equal(stl[0], loaded.vertices) and np.array_equal(stl[1], loaded.faces)
    )
    for name in ("sphere big-endian.ply", "sphere little-endian.ply", "sphere with a property.ply"):
        ply = read_ply(files[name], mesh=True)
        loaded = trimesh.load(files[name], process=False)
        assert ply is not None and np.array_equal(ply.vertices, loaded.vertices), name
        assert np.array_equal(ply.faces, loaded.faces), name
    assert read_ply(files["quads.ply (trimesh's)"], mesh=True) is None
    assert read_binary_stl(files["short.stl"]) is None


def test_a_cloud_reads_as_trimesh_reads_it(tmp_path: Path) -> None:
    pts = np.random.default_rng(3).normal(size=(5000, 3)) * 40
    for order in "<>":
        path = write_ply(tmp_path / f"cloud{order == '<'}.ply", pts, None, order=order, extra=True)
        assert np.array_equal(load_cloud(path), trimesh.load(path, process=False).vertices)
        assert read_ply(path, mesh=False) is not None  # read here, not by trimesh


def test_merging_is_trimeshs(tmp_path: Path) -> None:
    """Near-duplicates (1e-9 mm apart round alike, 3e-8 mm do not), unreferenced vertices, any order."""
    rng = np.random.default_rng(0)
    for _ in range(30):
        offsets = rng.choice([0.0, 1e-9, 3e-9, 3e-8, 1e-7], size=(200, 3))
        v = rng.integers(0, 30, size=(200, 3)) * 0.1 + offsets
        f = rng.integers(0, 200, size=(rng.integers(1, 300), 3))
        mesh = trimesh.Trimesh(v, f, process=False)
        mesh.merge_vertices()
        mv, mf = merge_vertices(v, f)
        assert np.array_equal(mesh.vertices, mv) and np.array_equal(mesh.faces, mf)


def test_a_plain_nominal_loads_without_trimesh(tmp_path: Path) -> None:
    path = meshes(tmp_path)["sphere.stl"]
    code = (
        "import sys\nfrom cell.mesh import load_mesh_arrays\n"
        f"m = load_mesh_arrays({str(path)!r})\nprint(len(m.faces), 'trimesh' in sys.modules)"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=60)
    assert proc.stdout.split() == ["5120", "False"], proc.stdout + proc.stderr
