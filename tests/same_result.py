"""Comparing two inspection reports that must describe the same result (a resumed or retried run against an
uninterrupted one)."""

from __future__ import annotations

import pytest


def assert_same_result(got: dict, expected: dict, context: object = "") -> None:
    """Same verdict and point count; deviation statistics equal to a nanometre.

    Not bit for bit: after a resume or a retried move the robot reaches a view from elsewhere, and the pose
    it reports there differs in the last bits (~1e-13 mm), exactly as a real robot's reported pose depends on
    its approach."""
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
