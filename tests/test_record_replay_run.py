"""`cell inspect --record`: a whole inspection's device traffic recorded as fixtures replays, without the
simulator, to the identical report; a run that asks the devices for anything else stops, naming the
fixture."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import trimesh
import yaml

from cell.config import load_recipe
from cell.inspection import LambertianInspection
from cell.runs import RunFolder
from tests import cli_process
from tests.box_part import small_cell, write_box_recipe

REPO = Path(__file__).resolve().parent.parent

pytestmark = pytest.mark.slow


def cell(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "cell", *args], capture_output=True, text=True, cwd=REPO, timeout=300
    )


@pytest.fixture
def forked(tmp_path: Path) -> Iterator[Callable[..., subprocess.CompletedProcess]]:
    """`cell ARGS` in processes forked with the CLI already imported (tests/cli_process.py): the CLI's entry
    point in a process of its own, without the ~3 s of imports of `python -m cell`."""
    logs = iter(range(1000))
    with cli_process.server():
        yield lambda *args: cli_process.run(list(args), tmp_path / f"cell-{next(logs)}.log", timeout=300)


def test_recorded_inspection_replays_to_the_same_report(
    tmp_path: Path, forked: Callable[..., subprocess.CompletedProcess]
) -> None:
    recipe = write_box_recipe(tmp_path)
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(small_cell().model_dump(mode="json")))
    fx = tmp_path / "fixtures"
    rec = cell(
        "inspect",
        str(recipe),
        "--cell",
        str(tmp_path / "cell.yaml"),
        "--out",
        str(tmp_path / "a"),
        "--record",
        str(fx),
    )
    assert rec.returncode == 0, rec.stdout + rec.stderr
    replay_cell = yaml.safe_load((fx / "cell.yaml").read_text())
    assert replay_cell["robot"]["driver"] == replay_cell["sensor"]["camera"]["driver"] == "replay"
    assert replay_cell["sensor"]["projector"]["driver"] == "replay"
    rep = forked("inspect", str(recipe), "--cell", str(fx / "cell.yaml"), "--out", str(tmp_path / "b"))
    assert rep.returncode == 0, rep.stdout + rep.stderr
    recorded, replayed = (json.loads((tmp_path / r / "results" / "report.json").read_text()) for r in "ab")
    for key in ("verdict", "n_points", "deviation", "coverage", "regions"):
        assert replayed[key] == recorded[key], key
    # one frame per projected pattern of every view, each from the recording
    job = LambertianInspection(load_recipe(recipe), small_cell(), trimesh.load(tmp_path / "box.stl"))
    calls = yaml.safe_load((fx / "camera" / "fixture.yaml").read_text())["calls"]
    captured = len(list((tmp_path / "a" / "views").glob("*/view.json")))  # planned views with a clear path
    assert captured >= 5 and sum(c["method"] == "grab" for c in calls) == len(job.patterns) * captured

    # the part placed 10 mm elsewhere: the plan asks the robot for moves it never recorded
    moved = yaml.safe_load(recipe.read_text())
    x, y, z = moved["part"]["T_W_P"]["xyz_mm"]
    moved["part"]["T_W_P"] = {"xyz_mm": [x + 10.0, y, z], "rpy_deg": [0.0, 0.0, 0.0]}
    (tmp_path / "moved.yaml").write_text(yaml.safe_dump(moved))
    off = forked(
        "inspect", str(tmp_path / "moved.yaml"), "--cell", str(fx / "cell.yaml"), "--out", str(tmp_path / "c")
    )
    assert off.returncode == 3 and "paused" in off.stdout
    errors = [e for e in RunFolder.open(tmp_path / "c").journal() if e["event"] == "error"]
    assert errors and errors[0]["kind"] == "DeviceProtocolError"
    assert errors[0]["error"].startswith(f"ur5e: replay {fx / 'robot'}: call ")
    assert "was recorded as move_linear" in errors[0]["error"]

    again = forked(
        "inspect",
        str(recipe),
        "--cell",
        str(tmp_path / "cell.yaml"),
        "--out",
        str(tmp_path / "d"),
        "--record",
        str(fx),
    )
    assert again.returncode != 0 and "--record holds files already" in again.stdout + again.stderr
    assert not (tmp_path / "d").exists()
