"""``cell scan`` end to end on the simulated cell: outputs exist, the cloud lies on the scanned part."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
import yaml
from typer.testing import CliRunner

from cell.cli import app
from cell.config import DEFAULT_CELL

PARTS = Path(__file__).resolve().parent.parent / "recipes" / "parts"


@pytest.mark.skipif(not (PARTS / "gauge.stl").is_file(), reason="gauge block not built")
def test_scan_writes_cloud_masks_and_summary(tmp_path: Path) -> None:
    # the ideal world (the simulator renders the config's geometry): the points are checked to 0.1 mm
    ideal = tmp_path / "cell.yaml"
    ideal.write_text(yaml.safe_dump({**yaml.safe_load(DEFAULT_CELL.read_text()), "world": "ideal"}))
    out = tmp_path / "scan"
    res = CliRunner().invoke(
        app, ["scan", "--cell", str(ideal), "--part", str(PARTS / "gauge.stl"), "--out", str(out)]
    )
    assert res.exit_code == 0, res.output
    summary = json.loads((out / "scan.json").read_text())
    assert "simulator" in summary["geometry_source"] and summary["n_images"] == 38
    counts = summary["counts"]
    pts = np.asarray(trimesh.load(out / "cloud.ply").vertices)
    assert len(pts) == counts["valid"] > 100_000
    # Points on the gauge top (z = 30) or the table (z = 0), in world mm; the camera looked down at the
    # centre.
    top = np.abs(pts[:, 2] - 30.0) < 0.1
    table = np.abs(pts[:, 2]) < 0.1
    assert np.mean(top | table) > 0.995 and top.sum() > 0.5 * len(pts)
    T_W_C = np.array(summary["pose"]["T_W_C"])
    np.testing.assert_allclose(T_W_C[:3, 3], [0, 0, 15.0 + 393.7], atol=1e-6)
    assert counts["dark"] > 0  # the block shadows the table on the side away from the projector
    masks = cv2.imread(str(out / "masks.png"))
    assert masks.shape == (768, 1024, 3)


def test_scan_rejects_a_bad_pose(tmp_path: Path) -> None:
    res = CliRunner().invoke(app, ["scan", "--pose", "1,2,3", "--out", str(tmp_path / "x")])
    assert res.exit_code != 0 and "--pose" in str(res.exception)
    assert not (tmp_path / "x").exists()
