"""A glass run's grabs on disk (cell/glass/grabs.py): the mean image each camera's measurement read comes
back bit for bit, from a 16-bit PNG of the frames' sum where that holds it, else from deflated float32. The
simulated rig's own grabs are tested in tests/test_glass_rig.py (its rendered frames are made there)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cell.glass.grabs import load_grab, save_grab


@pytest.mark.parametrize(
    "case",
    ["12-bit over 16 frames", "floats", "negative"],
)
def test_a_mean_a_png_cannot_hold_is_kept_as_float32(tmp_path: Path, case: str) -> None:
    rng = np.random.default_rng(7)
    if case == "12-bit over 16 frames":  # the sum reaches 20 x 4095, beyond 16 bits
        frames = 20
        mean = (rng.integers(0, 4096, (frames, 48, 64)).sum(axis=0) / frames).astype(np.float32)
        mean[0, 0] = 4095.0
    elif case == "floats":  # a driver that gives floats: not a sum of integers
        frames, mean = 4, rng.uniform(0, 255, (48, 64)).astype(np.float32)
    else:
        frames, mean = 4, -rng.integers(1, 255, (48, 64)).astype(np.float32)
    assert save_grab(tmp_path, "cam0", mean, frames).suffix == ".npz"
    assert np.array_equal(load_grab(tmp_path, "cam0").view(np.uint32), mean.view(np.uint32))


def test_a_run_from_before_reads_its_npy(tmp_path: Path) -> None:
    image = np.random.default_rng(2).uniform(0, 255, (12, 16)).astype(np.float32)
    np.save(tmp_path / "cam0.npy", image)
    assert np.array_equal(load_grab(tmp_path, "cam0"), image)
    with pytest.raises(FileNotFoundError):
        load_grab(tmp_path, "cam1")
