"""Comparing two inspection reports that must describe the same result (a resumed or retried run against an
uninterrupted one)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from cell.exit_codes import ExitCode, for_verdict


def assert_same_result(got: dict, expected: dict, context: object = "") -> None:
    """Same verdict and point count; deviation statistics equal to a nanometre.

    Not bit for bit: after a resume or a retried move the robot reaches a view from elsewhere, and the pose
    it reports there differs in the last bits (~1e-13 mm), exactly as a real robot's reported pose depends on
    its approach. The report judges the cloud as cloud.ply stores it, rounded to float32 (docs/storage.md):
    a coordinate that close to a rounding boundary may land one float32 step away (3.8 nm on the test box),
    once in some hundred runs; that moves a mean by 1e-10 mm, within the tolerance (an extreme or percentile
    only if that very point is the one, not seen)."""
    assert got["verdict"] == expected["verdict"], context
    assert got["n_points"] == expected["n_points"], context
    flat_got, flat_expected = _flatten(got["deviation"]), _flatten(expected["deviation"])
    assert flat_got.keys() == flat_expected.keys(), context
    for name, value in flat_expected.items():
        assert flat_got[name] == pytest.approx(value, abs=1e-9, rel=0), f"{context}: {name}"


def _flatten(stats: dict, prefix: str = "") -> dict[str, float]:
    out: dict[str, float] = {}
    for key, value in stats.items():
        if isinstance(value, dict):
            out.update(_flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def judged_report(proc: subprocess.CompletedProcess[str], run: Path) -> dict:
    """The report of a run a `cell inspect` / `cell resume` process finished, after checking that the
    process exited with the code of the report's verdict (pass 0, fail 4, incomplete 5)."""
    assert proc.returncode in (ExitCode.PASS, ExitCode.FAIL, ExitCode.INCOMPLETE), proc.stdout + proc.stderr
    doc = json.loads((run / "results" / "report.json").read_text())
    assert proc.returncode == for_verdict(doc["verdict"]), (doc["verdict"], proc.stdout + proc.stderr)
    return doc
