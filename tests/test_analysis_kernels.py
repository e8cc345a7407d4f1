"""The ahead-of-time build of the compare path's kernels (numba.pycc, cell.analysis.kernels) gives the same
bits as numba's jit functions: error map (grid, point order, signed closest point, face, feature), point grid
(binning, nearest other point, radius groups) and the pictures' depth buffer (also checked against the numpy
passes it replaced), on a mesh whose points fall on faces, edges and vertices, inside and outside, near and
far. ``cell compare`` uses the build without importing numba, and numba's jit without the build or when the
build cannot be looked up.

Without a C compiler or the Python headers the build cannot run and these tests skip, unless
CELL_REQUIRE_KERNELS=1 (CI, .ci/run): then they fail."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
import trimesh

from cell.analysis import kernels
from cell.analysis._point_grid import point_grid
from cell.analysis.errormap import NominalMesh

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def aot_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The build `make kernels` made (read, never written), else one built in a temporary folder (~10 s of
    CPU); skips (fails under CELL_REQUIRE_KERNELS=1) when there is no compiler or no Python headers."""
    made = kernels.aot_path()
    if made.is_file():
        return made
    compiler = (sysconfig.get_config_var("CC") or "cc").split()[0]
    headers = Path(sysconfig.get_paths()["include"]) / "Python.h"
    if shutil.which(compiler) is None or not headers.is_file():
        message = f"the kernels cannot be compiled ahead of time: no {compiler} or no {headers}"
        if os.environ.get("CELL_REQUIRE_KERNELS") == "1":
            pytest.fail(message + " (CELL_REQUIRE_KERNELS=1)")
        pytest.skip(message)
    return kernels.build(tmp_path_factory.mktemp("kernels") / made.name)


@pytest.fixture(scope="module")
def aot(aot_file: Path) -> ModuleType:
    module = kernels.load_aot(aot_file)
    assert module is not None
    return module


def _same(a: tuple | np.ndarray, b: tuple | np.ndarray) -> None:
    a, b = (a if isinstance(a, tuple) else (a,)), (b if isinstance(b, tuple) else (b,))
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert x.dtype == y.dtype and x.shape == y.shape
        assert x.tobytes() == y.tobytes()  # bit for bit, NaN and signed zeros included


def test_error_map_kernels_give_jits_bits(aot: ModuleType) -> None:
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=20.0)
    rng = np.random.default_rng(5)
    on, _ = trimesh.sample.sample_surface(mesh, 3000, seed=2)
    pts = np.vstack(
        [
            on * rng.uniform(0.97, 1.03, (len(on), 1)),  # inside and outside, near the faces
            mesh.vertices * 1.01,  # closest to a vertex
            0.5 * (mesh.vertices[mesh.edges[:300, 0]] + mesh.vertices[mesh.edges[:300, 1]]) * 1.02,  # edges
            rng.uniform(-80, 80, (300, 3)),  # far, and around the centre
        ]
    )
    nominal = NominalMesh.from_arrays(mesh.vertices, mesh.faces)
    a, b = nominal.tri[:, 16:19].copy(), nominal.tri[:, 19:22].copy()
    grid = (nominal.grid_origin, nominal.grid_h, nominal.grid_dims)
    _same(aot.build_grid(a, b, *grid), kernels.jit("build_grid")(a, b, *grid))
    start, order = kernels.jit("_bin")(pts, *grid)  # the visiting order signed_distance uses
    _same(aot._bin(pts, *grid), (start, order))
    args = (
        pts,
        order,
        nominal.tri,
        nominal.grid_start,
        nominal.grid_items,
        nominal.grid_boxes,
        *grid,
        nominal.faces,
        nominal.edge_normals,
        nominal.vertex_normals,
    )
    got = aot.signed_closest(*args)
    _same(got, kernels.jit("signed_closest")(*args))
    assert set(np.unique(got[3])) == {0, 1, 2}  # faces, edges and vertices all exercised


def test_point_grid_kernels_give_jits_bits(aot: ModuleType) -> None:
    rng = np.random.default_rng(6)
    pts = np.vstack([rng.normal(0, 10, (4000, 3)), rng.normal(0, 10, (200, 3))[:50].repeat(2, 0)])
    g = point_grid(pts)
    cells = (g.origin, g.h, g.dims)
    _same(aot._bin(g.points, *cells), kernels.jit("_bin")(g.points, *cells))
    q = np.arange(0, len(pts), 3, dtype=np.int64)
    _same(
        aot._nearest_other(g.points, q, g.start, g.order, *cells),
        kernels.jit("_nearest_other")(g.points, q, g.start, g.order, *cells),
    )
    wide = point_grid(pts, h_min=1.5)
    wcells = (wide.origin, wide.h, wide.dims)
    labels = aot._radius_labels(wide.points, 1.5**2, wide.start, wide.order, *wcells)
    _same(labels, kernels.jit("_radius_labels")(wide.points, 1.5**2, wide.start, wide.order, *wcells))
    assert 1 < labels.max() < len(pts) - 1  # some groups, not one, not all apart


def test_depth_buffer_is_numpys_and_jits(aot: ModuleType) -> None:
    rng = np.random.default_rng(8)
    pix = rng.integers(0, 500, 20_000)
    depth = np.round(rng.normal(0, 5, len(pix)), 1)  # ties: the first of equally near entries wins
    winner, nearest = aot.zbuffer(pix, depth, 600)
    _same((winner, nearest), kernels.jit("zbuffer")(pix, depth, 600))
    top = np.full(600, -np.inf)  # the unbuffered numpy passes the loop replaced
    np.maximum.at(top, pix, depth)
    first = np.full(600, len(pix))
    front = np.flatnonzero(depth == top[pix])
    np.minimum.at(first, pix[front], front)
    assert (winner == np.where(first < len(pix), first, -1)).all()
    assert np.array_equal(nearest, np.where(first < len(pix), top, np.nan), equal_nan=True)
    assert (winner[500:] == -1).all() and (winner[:500] >= 0).all()


def _box_compare(folder: Path) -> tuple[Path, Path, np.ndarray]:
    """A 20 mm cube and 400 points off its top face and one side face by known deviations (mm, + outside),
    away from the edges: the exact signed distance is the offset. Returns the mesh, cloud and offsets."""
    folder.mkdir()
    mesh = trimesh.creation.box(extents=(20.0, 20.0, 20.0))
    nominal = folder / "cube.stl"
    mesh.export(nominal)
    rng = np.random.default_rng(11)
    u, v = rng.uniform(-8, 8, (2, 400))
    d = rng.uniform(-0.25, 0.25, 400)
    top = np.c_[u[:200], v[:200], 10.0 + d[:200]]
    side = np.c_[10.0 + d[200:], u[200:], v[200:]]
    cloud = folder / "cloud.xyz"
    np.savetxt(cloud, np.vstack([top, side]))
    return nominal, cloud, d


# `cell compare` as its script runs it, then whether the process imported numba
_RUN_COMPARE = """
import sys
from cell.cli import main
main(sys.argv[1:])
print("numba imported:", "numba" in sys.modules)
"""


def _deviations(out: Path, d: np.ndarray) -> np.ndarray:
    """cloud.ply's deviations, checked against the exact ones ``d`` (mm)."""
    ply = (out / "cloud.ply").read_bytes().split(b"end_header\n", 1)[1]  # x, y, z, deviation (float32)
    deviation = np.frombuffer(ply, "<f4").reshape(-1, 4)[:, 3]
    assert np.allclose(deviation, d, rtol=0, atol=1e-7)  # the exact signed distances (float32 in the file)
    return deviation


def test_cell_compare_runs_the_build_without_numba_and_the_jit_without_it(
    aot_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cache = tmp_path / "cache"
    cache.mkdir()
    shutil.copy(aot_file, cache / aot_file.name)
    nominal, cloud, d = _box_compare(tmp_path / "box")
    args = ["compare", str(nominal), str(cloud), "--table-z", "none", "--crop-mm", "0", "--out"]
    run = subprocess.run(  # a fresh process, as the script starts
        [sys.executable, "-c", _RUN_COMPARE, *args, str(tmp_path / "aot")],
        capture_output=True,
        text=True,
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO), "CELL_CACHE_DIR": str(cache)},
        timeout=120,
    )
    assert run.returncode == 0, run.stderr
    assert run.stdout.splitlines()[-1] == "numba imported: False"
    aot_dev = _deviations(tmp_path / "aot", d)

    from cell.cli import main  # no build: numba's jit (in this process, whose numba has the kernels already)

    monkeypatch.setenv("CELL_CACHE_DIR", str(tmp_path / "empty"))
    monkeypatch.setattr(kernels, "_aot", None)
    main([*args, str(tmp_path / "jit")])
    assert kernels._aot is None
    assert _deviations(tmp_path / "jit", d).tobytes() == aot_dev.tobytes()


@pytest.mark.parametrize(
    "error", [RuntimeError("Could not determine home directory."), PermissionError(13, "")]
)
def test_a_cache_that_cannot_be_looked_up_leaves_the_jit(
    error: Exception, monkeypatch: pytest.MonkeyPatch
) -> None:
    def cache_dir() -> Path:
        raise error

    monkeypatch.setattr(kernels, "cache_dir", cache_dir)
    monkeypatch.setattr(kernels, "_aot", None)
    monkeypatch.delenv("CELL_KERNELS", raising=False)
    assert not kernels.prefer_aot()
    assert kernels.get("zbuffer") is kernels.jit("zbuffer")


def test_a_build_removes_older_builds_and_killed_ones(tmp_path: Path) -> None:
    suffix = sysconfig.get_config_var("EXT_SUFFIX")
    kept = tmp_path / f"_cell_kernels_{'a' * 16}{suffix}"
    older = tmp_path / f"_cell_kernels_{'0123456789abcdef'}{suffix}"
    others = [
        tmp_path / "_cell_kernels_notes.txt",
        tmp_path / f"_cell_kernels_x{suffix}",
        tmp_path / "plotly.js.gz",
    ]
    for path in [kept, older, *others]:
        path.write_bytes(b"")
    killed, running = tmp_path / ".build-killed", tmp_path / ".build-running"
    for folder in (killed, running):
        folder.mkdir()
        (folder / "part.o").write_bytes(b"")
    old = killed.stat().st_mtime - kernels.STALE_BUILD_S - 1
    os.utime(killed, (old, old))
    kernels._remove_old_builds(kept)
    assert sorted(tmp_path.iterdir()) == sorted([kept, *others, running])
