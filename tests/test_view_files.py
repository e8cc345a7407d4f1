"""A view folder's stored points and raw images (cell.view_files): format 2 round trips within its stated
step, raw stacks come back bit for bit through the capture-folder reader, and format-1 folders still load."""

from __future__ import annotations

import numpy as np
import pytest

from cell.calibration.capture_folder import CodeSpec, ProjectorSpec, code_spec
from cell.config import load_cell_config
from cell.inspection_run import REPO
from cell.sensing.patterns import gcps_patterns, measuring_patterns, sensor_calibration_patterns
from cell.view_files import (
    STEP_MM,
    load_eval_points,
    load_eval_uncertainty,
    load_raw_stack,
    load_view_points,
    save_raw_stack,
    save_view_points,
)


def _surface_points(n: int, rng: np.random.Generator) -> np.ndarray:
    """A scan-like cloud: a tilted, wavy surface sampled in pixel order 400-600 mm from the origin, with
    20 um of noise (float64 to the last bit)."""
    u, v = np.meshgrid(np.linspace(-80, 80, n), np.linspace(-60, 60, n))
    z = 40 + 0.2 * u + 3 * np.sin(v / 7)
    p = np.column_stack([u.ravel() + 450.0, v.ravel() - 120.0, z.ravel() + 300.0])
    return p + rng.normal(0, 0.02, p.shape)


def test_points_round_trip_within_the_step_and_flags_exactly(tmp_path):
    rng = np.random.default_rng(1)
    p = _surface_points(300, rng)
    quality = rng.uniform(0.4, 1.0, len(p)).astype(np.float32)
    oblique = rng.random(len(p)) < 0.1
    sub = np.sort(rng.choice(len(p), 5000, replace=False))
    stored = save_view_points(tmp_path, p, quality, oblique, sub)
    back = load_view_points(tmp_path)
    assert np.abs(back.points_W - p).max() <= STEP_MM / 2 * (1 + 1e-6)  # 0.05 um
    assert np.array_equal(back.points_W, stored)  # what the writer said it stored is what is read
    assert np.array_equal(back.quality, quality) and np.array_equal(back.oblique, oblique)
    assert np.array_equal(load_eval_points(tmp_path), stored[sub])


def test_format_3_holds_format_2s_numbers_in_fewer_bytes_and_format_2_still_loads(tmp_path):
    """Format 3 stores the same int32 step differences as format 2, as byte planes: a format 2 file of the
    same view (``delta``) reads back to the same points, and is larger."""
    rng = np.random.default_rng(6)
    p = _surface_points(300, rng)
    quality = rng.uniform(0.4, 1.0, len(p)).astype(np.float32)
    oblique = rng.random(len(p)) < 0.1
    sub = np.sort(rng.choice(len(p), 5000, replace=False))
    (tmp_path / "new").mkdir()
    stored = save_view_points(tmp_path / "new", p, quality, oblique, sub)
    with np.load(tmp_path / "new" / "points.npz") as z:
        arrays = {k: z[k] for k in z.files if k != "delta_planes"}
        assert int(z["format"]) == 3 and "delta" not in z.files
    steps = np.round(p / STEP_MM).astype(np.int64)  # format 2 as main wrote it
    arrays |= {
        "format": np.asarray(2, np.int32),
        "delta": np.diff(steps, axis=0, prepend=0 * steps[:1]).astype(np.int32),
    }
    (tmp_path / "old").mkdir()
    np.savez_compressed(tmp_path / "old" / "points.npz", **arrays)
    old = load_view_points(tmp_path / "old")
    assert np.array_equal(old.points_W, stored) and np.array_equal(
        load_view_points(tmp_path / "new").points_W, stored
    )
    assert np.array_equal(load_eval_points(tmp_path / "old"), stored[sub])
    assert (tmp_path / "new" / "points.npz").stat().st_size < (tmp_path / "old" / "points.npz").stat().st_size


def test_an_empty_view_round_trips(tmp_path):
    stored = save_view_points(tmp_path, np.zeros((0, 3)), np.zeros(0), np.zeros(0, bool), np.zeros(0, int))
    assert stored.shape == (0, 3) and load_view_points(tmp_path).points_W.shape == (0, 3)
    assert load_eval_points(tmp_path).shape == (0, 3)


def test_points_too_far_out_are_refused(tmp_path):
    with pytest.raises(ValueError, match="beyond"):
        save_view_points(tmp_path, np.array([[2.0e8, 0.0, 0.0]]), np.ones(1), np.zeros(1, bool), [0])


def test_format_1_view_folders_still_load(tmp_path):
    """A view written before format 2 (float64 .npy files; the oldest without oblique.npy)."""
    rng = np.random.default_rng(2)
    p = _surface_points(50, rng)
    q = rng.uniform(0.4, 1.0, len(p)).astype(np.float32)
    np.save(tmp_path / "points_W.npy", p)
    np.save(tmp_path / "quality.npy", q)
    np.save(tmp_path / "points_eval_W.npy", p[::7])
    old = load_view_points(tmp_path)
    assert np.array_equal(old.points_W, p) and np.array_equal(old.quality, q) and not old.oblique.any()
    assert np.array_equal(load_eval_points(tmp_path), p[::7])
    oblique = rng.random(len(p)) < 0.3
    np.save(tmp_path / "oblique.npy", oblique)
    assert np.array_equal(load_view_points(tmp_path).oblique, oblique)


@pytest.mark.parametrize("bit_depth", [8, 12])
def test_raw_stack_round_trips_bit_for_bit(tmp_path, bit_depth):
    """Noisy frames of an 8-bit and a 12-bit camera (16-bit PNG files) come back exactly, in code order,
    through the capture-folder reader, which also checks the stack (black and white frames, sizes)."""
    ps = measuring_patterns(load_cell_config(REPO / "recipes" / "cells" / "sim_binned.yaml").sensor.projector)
    rng = np.random.default_rng(bit_depth)
    top = (1 << bit_depth) - 1
    dtype = np.uint8 if bit_depth == 8 else np.uint16
    h, w = 48, 64
    base = rng.integers(0, top // 8, (h, w))
    stack = np.stack(
        [np.clip(base + (top // 2) * (f[:h, :w] > 0) + rng.integers(0, 9, (h, w)), 0, top) for f in ps.frames]
    ).astype(dtype)
    stack[ps.index("white")] = np.clip(base + top // 2 + 40, 0, top).astype(dtype)
    stack[ps.index("black")] = base.astype(dtype)
    written = save_raw_stack(tmp_path, stack, ps, bit_depth, (ps.width_px, ps.height_px))
    assert written == sum(f.stat().st_size for f in (tmp_path / "raw").rglob("*") if f.is_file())
    back = load_raw_stack(tmp_path)
    assert back is not None and back.dtype == dtype and np.array_equal(back, stack)


def test_no_raw_images_reads_as_none(tmp_path):
    assert load_raw_stack(tmp_path) is None


def test_a_durable_write_replaces_a_raw_folder_cut_short(tmp_path):
    """A ``raw/`` a cut write left in a committed view folder (frames, one of them truncated, and no manifest)
    reads as no raw stack, and the durable write (the plan's last view's, after its commit) replaces it whole:
    the new stack comes back bit for bit and nothing of the cut write stays."""
    ps = measuring_patterns(load_cell_config(REPO / "recipes" / "cells" / "sim_binned.yaml").sensor.projector)
    rng = np.random.default_rng(3)
    stack = rng.integers(0, 40, (len(ps), 48, 64)).astype(np.uint8)
    stack[ps.index("white")] += 200
    (tmp_path / "view.json").write_text("{}")  # committed
    frames = tmp_path / "raw" / "frames"
    frames.mkdir(parents=True)
    (frames / "00_black.png").write_bytes(b"\x89PNG\r\n")  # cut mid-file
    (frames / "99_stale.png").write_bytes(b"stale")  # a name this stack does not write
    assert load_raw_stack(tmp_path) is None
    written = save_raw_stack(tmp_path, stack, ps, 8, (ps.width_px, ps.height_px), durable=True)
    files = [f for f in (tmp_path / "raw").rglob("*") if f.is_file()]
    assert written == sum(f.stat().st_size for f in files) and len(files) == len(ps) + 1  # frames, manifest
    back = load_raw_stack(tmp_path)
    assert back is not None and np.array_equal(back, stack)


@pytest.mark.parametrize(
    "patterns",
    [
        measuring_patterns(load_cell_config(REPO / "recipes" / "cells" / "sim.yaml").sensor.projector),
        sensor_calibration_patterns(
            load_cell_config(REPO / "recipes" / "cells" / "sim.yaml").sensor.projector
        ),
        gcps_patterns(640, 480, 16, 4, "both"),
    ],
    ids=["measuring", "sensor-both", "gcps"],
)
def test_code_spec_names_the_same_patterns(patterns):
    """The manifest's code section regenerates the very frames the projector showed."""
    again = CodeSpec.model_validate(code_spec(patterns)).patterns(
        ProjectorSpec(width_px=patterns.width_px, height_px=patterns.height_px)
    )
    assert again.names == patterns.names and np.array_equal(again.frames, patterns.frames)


def test_uncertainty_round_trips_within_its_code_step(tmp_path):
    rng = np.random.default_rng(2)
    p = _surface_points(100, rng)
    u = rng.uniform(0.006, 0.3, len(p))
    u[:3] = [np.nan, 0.0, 1e-9]
    save_view_points(tmp_path, p, np.ones(len(p)), np.zeros(len(p), bool), [0, 5], uncertainty=u)
    back = load_view_points(tmp_path).uncertainty
    assert back is not None and np.isnan(back[0]) and not np.isnan(back[1:]).any()
    assert np.abs(back[3:] / u[3:] - 1).max() <= 2 ** (1 / 64) - 1 + 1e-6  # 1.09 %
    assert np.array_equal(load_eval_uncertainty(tmp_path), back[[0, 5]], equal_nan=True)
