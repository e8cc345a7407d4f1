"""The inspection's views in memory (cell/inspection_views.py): each read once, the full points held within a
byte budget (the oldest dropped and read again from the folder, identical; big views' dropped once the next
comes), the local planes as stored."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from cell.analysis.view_refinement import estimate_normals
from cell.inspection_views import (
    PLANES_FILE,
    ViewResult,
    ViewStore,
    load_regions,
    load_view_result,
    remove_planes,
    save_planes,
    save_regions,
    stored_regions,
)
from cell.planning.measured import DefectRegion
from cell.runs import RunFolder
from cell.view_files import STEP_MM, ViewPoints, save_view_points


def _write_view(run: RunFolder, index: int, rng: np.random.Generator) -> ViewResult:
    """A view folder as the decode writes it (a noisy plane patch) and the result the decode keeps."""
    folder = run.view_dir(index)
    folder.mkdir(parents=True)
    xy = rng.uniform(0, 40, (3000, 2)) + 30 * index
    points = np.column_stack([xy, 0.01 * rng.normal(size=len(xy))])
    quality = rng.uniform(10, 200, len(points)).astype(np.float32)
    oblique = rng.random(len(points)) < 0.1
    sub = np.arange(0, len(points), 4)
    stored = save_view_points(folder, points, quality, oblique, sub)
    planes = estimate_normals(stored[sub])
    save_planes(folder, planes)
    save_regions(folder / "defects.npz", [])
    summary = {"T_W_C": np.eye(4).tolist(), "points": len(points), "excluded": {"table": index}}
    (folder / "view.json").write_text(json.dumps(summary))
    return ViewResult(index, ViewPoints(stored, quality, oblique), stored[sub], planes, [], summary, folder)


def test_the_store_holds_full_points_within_its_budget_and_reads_the_rest(tmp_path: Path) -> None:
    run = RunFolder.create(tmp_path, "plate")
    rng = np.random.default_rng(4)
    made = [_write_view(run, i, rng) for i in range(3)]
    one = made[0].held_bytes
    store = ViewStore(points_budget_bytes=int(1.5 * one))
    for view in made[:2]:
        store.add(view)
    assert made[0].held is None and made[1].held is not None  # the older one dropped, the newest kept
    views = store.completed(run)
    assert [v.index for v in views] == [0, 1, 2]
    assert views[2] is not made[2] and views[2].held is not None  # read from its folder, once
    assert store.get(run, 2) is views[2]
    assert views[1].held is None  # dropped when view 2 came in over the budget
    for kept, original in zip(views, made, strict=True):
        back = kept.points()  # from memory or from the folder: the same numbers
        assert np.array_equal(back.points_W, made[original.index].points().points_W)
        assert np.array_equal(back.quality, original.points().quality)
        assert np.array_equal(back.oblique, original.points().oblique)
        assert np.array_equal(kept.eval_W, original.eval_W)
        assert np.array_equal(kept.planes.normal, original.planes.normal)
        assert kept.summary == original.summary
    # a folder written before the planes were stored, or a finished run (remove_planes): computed from its
    # evaluation points, the same
    assert remove_planes(run) > 0 and not list(run.path.glob(f"views/*/{PLANES_FILE}"))
    for i in range(3):
        again = ViewStore().get(run, i)
        assert np.array_equal(again.planes.normal, made[i].planes.normal)
        assert np.array_equal(again.planes.centroid, made[i].planes.centroid)
        assert np.array_equal(again.planes.ok, made[i].planes.ok)
    d, _ = again.eval_tree.query(again.eval_W[:5])
    assert np.all(d == 0)
    # views bigger than the store's limit for one view: no points are held, the newest one's neither, whatever
    # room
    fresh = [load_view_result(run.view_dir(i), i) for i in range(3)]
    big = ViewStore(points_budget_bytes=10 * one, held_view_max_bytes=one - 1)
    for view in fresh:
        assert view.held is not None
        big.add(view)
        assert view.held is None
    assert np.array_equal(big.get(run, 2).points().points_W, made[2].points().points_W)
    assert np.array_equal(big.get(run, 0).points().points_W, made[0].points().points_W)  # from its folder


def test_the_hole_regions_are_stored_in_steps_and_old_files_still_read(tmp_path: Path) -> None:
    """defects.npz format 2: the regions' nominal points in 0.1 um steps, read back exactly as
    stored_regions gives them (within half a step of the originals), smaller than the float64 of format 1,
    which is still read."""
    rng = np.random.default_rng(2)
    line = np.cumsum(rng.normal(0, 0.05, (4000, 3)), axis=0) + [120.0, -80.0, 35.0]  # neighbouring pixels
    regions = [
        DefectRegion("shadow", line[:300], line, 4000),
        DefectRegion("glare", line[:0], line[:0], 0),
        DefectRegion("low_contrast", line[5:9], line[5:60], 55),
    ]
    save_regions(tmp_path / "defects.npz", regions)
    back = load_regions(tmp_path / "defects.npz")
    kept = stored_regions(regions)
    for mine, original, stored in zip(back, regions, kept, strict=True):
        assert (mine.reason, mine.pixels) == (original.reason, original.pixels)
        for name in ("boundary_W", "points_W"):
            a, b = getattr(mine, name), getattr(original, name)
            assert a.shape == b.shape and a.dtype == np.float64
            assert np.array_equal(a, getattr(stored, name))  # what an uninterrupted run keeps
            assert len(a) == 0 or np.abs(a - b).max() <= 0.51 * STEP_MM
    old = tmp_path / "old.npz"  # format 1, as runs before wrote it
    arrays = {
        "reasons": np.array([r.reason for r in regions], "U16"),
        "pixels": np.array([r.pixels for r in regions]),
    }
    for k, r in enumerate(regions):
        arrays[f"boundary_{k}"], arrays[f"points_{k}"] = r.boundary_W, r.points_W
    np.savez_compressed(old, **arrays)
    for mine, original in zip(load_regions(old), regions, strict=True):
        assert mine.reason == original.reason and np.array_equal(mine.points_W, original.points_W)
    assert (tmp_path / "defects.npz").stat().st_size < 0.5 * old.stat().st_size
