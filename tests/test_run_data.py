"""Typed run data: checkpoints written by earlier controllers load, and save the same JSON."""

from __future__ import annotations

import numpy as np

from cell.run_data import Checkpoint, Phase


def test_checkpoint_written_before_the_typed_run_data_loads_and_saves_the_same() -> None:
    """A run folder's checkpoint.json as the controller wrote it with plain dicts: an inspection view, a
    calibration view (job-specific keys), a skipped view, the evaluation and the registration."""
    T = np.eye(4).tolist()
    doc = {
        "phase": "replanning",
        "views": [
            {"T_W_C": T, "T_B_T": T, "patch": "P0", "source": "f0", "iteration": 0},
            {"T_B_T": T, "index": 1, "board": "charuco 11x8 15 mm", "T_W_Bd": T},
        ],
        "iteration": 1,
        "skipped": [1],
        "evaluation": {"qualified": False, "coverage": 0.9, "Q": 12.5, "setpoint": 3.0, "iteration": 1},
        "registration": {"n_points": 10},
    }
    cp = Checkpoint.from_json(doc)
    assert cp.phase is Phase.REPLANNING and cp.skipped == [1]
    assert cp.views[0].patch == "P0" and cp.views[1].data["board"] == "charuco 11x8 15 mm"
    assert cp.evaluation is not None and not cp.evaluation.qualified and cp.evaluation.q == 12.5
    assert cp.to_json() == doc
    assert Checkpoint.from_json(None).to_json() == {"phase": "new", "views": [], "iteration": 0}
