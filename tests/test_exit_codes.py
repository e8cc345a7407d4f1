"""A judging command's exit code is its outcome (docs/exit-codes.md): `cell compare` on a dented plate ends
4 (fail), within a wide band 0 (pass), with too few points for the required coverage 5 (incomplete); bad
input 2."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from cell.cli import main
from cell.exit_codes import ExitCode, for_run


@pytest.fixture(scope="module")
def plate(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A 100 x 60 mm plate and a cloud of its top with a 0.8 mm deep cone dent."""
    folder = tmp_path_factory.mktemp("plate")
    trimesh.creation.box(extents=(100.0, 60.0, 4.0)).export(folder / "nominal.stl")
    xy = np.random.default_rng(2).uniform([-45, -25], [45, 25], (3000, 2))
    z = 2.0 - 0.8 * np.clip(1 - np.hypot(xy[:, 0] - 20, xy[:, 1]) / 5.0, 0, None)
    np.savetxt(folder / "cloud.xyz", np.column_stack([xy, z]))
    return folder / "nominal.stl", folder / "cloud.xyz"


def _exit_code(*args: object) -> int:
    with pytest.raises(SystemExit) as ended:
        main([str(a) for a in args])
        raise SystemExit(0)  # main returns normally on success
    return int(ended.value.code or 0)


@pytest.mark.parametrize(
    ("options", "expected"),
    [
        (["--tolerance", "-0.3,0.3"], ExitCode.FAIL),  # the dent is 0.8 mm deep
        (["--tolerance", "-1,1"], ExitCode.PASS),
        # the cloud covers the top face only: 1/2.5 of the plate's area at most
        (["--tolerance", "-1,1", "--radius", "2", "--min-coverage", "0.9"], ExitCode.INCOMPLETE),
        (["--tolerance", "1,-1"], ExitCode.USAGE),  # lower above upper
    ],
)
def test_compare_exits_with_its_verdict(
    plate, tmp_path: Path, options: list[str], expected: ExitCode
) -> None:
    nominal, cloud = plate
    assert _exit_code("compare", nominal, cloud, "--out", tmp_path / "o", *options) == expected


def test_a_run_that_did_not_finish_never_exits_as_a_pass() -> None:
    assert for_run("paused", "pass") is ExitCode.PAUSED
    assert for_run("aborted", None) is ExitCode.FAULT
    assert for_run("fault", "pass") is ExitCode.FAULT
    assert for_run("done", None) is ExitCode.FAULT  # a finished run without a verdict is a bug, not a pass
    assert for_run("done", "FAIL") is ExitCode.FAIL
