"""The ahead-of-time build of the compare path's kernels (numba.pycc, cell.analysis.kernels) gives the same
bits as numba's jit functions: error map (grid, point order, signed closest point, face, feature), point grid
(binning, nearest other point, radius groups) and the pictures' depth buffer (also checked against the numpy
passes it replaced), on a mesh whose points fall on faces, edges and vertices, inside and outside, near and
far."""

from __future__ import annotations

from types import ModuleType

import numpy as np
import pytest
import trimesh

from cell.analysis import kernels
from cell.analysis._point_grid import point_grid
from cell.analysis.errormap import NominalMesh


@pytest.fixture(scope="module")
def aot() -> ModuleType:
    """The build `make venv` made; built here (once per source change, ~10 s of CPU) when it is missing."""
    module = kernels.load_aot()
    if module is None:
        kernels.build()
        module = kernels.load_aot()
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
    order = kernels.jit("cell_order")(pts, *grid)
    _same(aot.cell_order(pts, *grid), order)
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
