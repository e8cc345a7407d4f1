"""`cell inspect` end to end through the CLI: the pillar's dent is found where it is; a killed run resumes.

The binned simulated cell (recipes/cells/sim_binned.yaml: the prototype with its camera binned 2x2) keeps a
full pillar inspection to about half a minute. The kill test uses a small box part for speed.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.box_part import small_cell, write_box_recipe
from tests.same_result import assert_same_result

REPO = Path(__file__).resolve().parent.parent
BINNED = REPO / "recipes" / "cells" / "sim_binned.yaml"
PILLAR = REPO / "recipes" / "pillar.yaml"

pytestmark = pytest.mark.slow


def cell(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "cell", *args], capture_output=True, text=True, cwd=REPO, timeout=timeout
    )


def report(run: Path) -> dict:
    return json.loads((run / "results" / "report.json").read_text())


def test_dented_pillar_fails_with_the_dent_located(tmp_path: Path) -> None:
    proc = cell("inspect", str(PILLAR), "--cell", str(BINNED), "--out", str(tmp_path / "run"))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    doc = report(tmp_path / "run")
    truth = json.loads((REPO / "recipes" / "parts" / "pillar_actual.truth.json").read_text())
    assert doc["verdict"] == "fail"
    dent = doc["regions"][0]
    assert dent["kind"] == "dent"
    assert np.linalg.norm(np.subtract(dent["centre_mm"], truth["centre_mm"])) < 2.0
    assert abs(dent["extreme_mm"] - truth["signed_deviation_mm"]) < 0.05
    assert doc["coverage"] >= 0.95
    # nothing else fails: every other out-of-tolerance cluster would be a false alarm
    assert len(doc["regions"]) == 1
    assert "verdict: FAIL" in proc.stdout


def test_undented_pillar_passes(tmp_path: Path) -> None:
    ok = REPO / "recipes" / "parts" / "pillar_actual_ok.stl"
    proc = cell(
        "inspect", str(PILLAR), "--cell", str(BINNED), "--sim-actual", str(ok), "--out", str(tmp_path / "r")
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    doc = report(tmp_path / "r")
    assert doc["verdict"] == "pass", doc["regions"]
    # the undented actual has a 0.05 mm springback bow: the measured deviations must show it, not hide it
    truth = json.loads((REPO / "recipes" / "parts" / "pillar_actual_ok.truth.json").read_text())
    assert truth["max_deviation_mm"] == pytest.approx(0.05, abs=1e-6)
    assert 0.03 < max(
        abs(doc["deviation"]["percentiles_mm"]["p1"]), abs(doc["deviation"]["percentiles_mm"]["p99"])
    )


@pytest.fixture(scope="module")
def box_inputs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A small box recipe and a cell config with the 160x120 test sensor, written as files for the CLI.

    The box stands where the robot reaches all its faces: a run takes about 8 s on the shared 2-core machine,
    against 37 s at the origin, where the planner splits the unreachable face into tiny patches."""
    folder = tmp_path_factory.mktemp("boxcli")
    recipe = write_box_recipe(folder, at_mm=(0.0, -60.0, 0.0))
    (folder / "cell.yaml").write_text(yaml.safe_dump(small_cell().model_dump(mode="json")))
    return recipe, folder / "cell.yaml"


@pytest.mark.timeout(900)  # 20 kills and resumes of a ~8 s run, on a shared 2-core machine
def test_killed_runs_resume_to_the_same_result(box_inputs: tuple[Path, Path], tmp_path: Path) -> None:
    recipe, cell_file = box_inputs
    t0 = time.monotonic()
    ref = cell("inspect", str(recipe), "--cell", str(cell_file), "--out", str(tmp_path / "ref"))
    duration = time.monotonic() - t0
    assert ref.returncode == 0, ref.stdout + ref.stderr
    expected = report(tmp_path / "ref")
    rng = np.random.default_rng(7)
    kills = 0
    for k, instant in enumerate(rng.uniform(0.3, 0.9 * duration, size=30)):
        if kills == 20:
            break
        run = tmp_path / f"k{k}"
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "cell",
                "inspect",
                str(recipe),
                "--cell",
                str(cell_file),
                "--out",
                str(run),
            ],
            cwd=REPO,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        time.sleep(instant)
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
            kills += 1
        proc.wait(timeout=60)
        if not run.exists():  # killed before the run folder was complete: the run never started
            done = cell("inspect", str(recipe), "--cell", str(cell_file), "--out", str(run))
        elif (run / "results" / "report.json").exists() and json.loads(
            (run / "checkpoint.json").read_text()
        ).get("phase") == "done":
            done = ref
        else:
            done = cell("resume", str(run))
        assert done.returncode == 0, f"kill {k} at {instant:.2f} s: {done.stdout}{done.stderr}"
        assert_same_result(report(run), expected, f"kill {k} at {instant:.2f} s")
    assert kills == 20
