"""Expensive runs that several test files compare against, made once per test session.

`make test` runs the files on two pytest-xdist workers (whole files each): an uninterrupted reference run
that three files need was made three times. :func:`once_per_session` makes it once: the first worker to ask
makes it in a folder both workers share (the session's base temporary folder), under a file lock; a worker
that asks meanwhile waits for it, and any later one reads it. Outside xdist (one process) it is made on the
spot and kept for the session's other files. pytest-xdist documents this pattern ("Making session-scoped
fixtures execute only once"); the lock is `fcntl.flock` (Linux, the suite's platform).

The runs are made from the same inputs, seed and settings as before; each file's tests only read them (a
test that changes a run folder copies it first)."""

from __future__ import annotations

import fcntl
import os
import pickle
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import pytest
import yaml

from tests.box_part import small_cell, write_box_recipe

T = TypeVar("T")
REPO = Path(__file__).resolve().parent.parent


def once_per_session(tmp_path_factory: pytest.TempPathFactory, name: str, make: Callable[[Path], T]) -> T:
    """``make(folder)``'s value, made once in the test session: ``folder`` is a new empty folder that the
    value may point into (it stays for the session); the value must pickle."""
    if name not in _made:
        _made[name] = pickle.dumps(_make_or_read(tmp_path_factory, name, make))
    return pickle.loads(_made[name])  # a copy for each file: one that changes it changes no other's


_made: dict[str, bytes] = {}  # this process's values, by name


def _make_or_read(tmp_path_factory: pytest.TempPathFactory, name: str, make: Callable[[Path], T]) -> T:
    if "PYTEST_XDIST_WORKER" not in os.environ:
        return make(tmp_path_factory.mktemp(name))
    shared = tmp_path_factory.getbasetemp().parent / "shared-runs"  # the session's, common to its workers
    shared.mkdir(exist_ok=True)
    value_file = shared / f"{name}.pickle"
    with open(shared / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes, also if make() raises
        if value_file.exists():
            return pickle.loads(value_file.read_bytes())
        folder = shared / name
        shutil.rmtree(folder, ignore_errors=True)  # a worker whose make() failed left it half made
        folder.mkdir()
        value = make(folder)
        partial = value_file.with_suffix(".partial")
        partial.write_bytes(pickle.dumps(value))
        partial.replace(value_file)
        return value


OPERATOR = "<script>alert(1)</script>"  # a valid operator name (printable) that must reach the page escaped


def box_cli_reference(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """The box recipe and the small cell as files, and the run folder of an uninterrupted `cell inspect` of
    them (a `python -m cell` process, the part's serial SN-7 and :data:`OPERATOR` given): the truth of the
    kill-and-resume test (tests/test_inspect_e2e.py) and of the CLI fault tests
    (tests/test_controller_safety.py). Returns (recipe, cell file, run folder)."""

    def make(folder: Path) -> tuple[Path, Path, Path]:
        recipe = write_box_recipe(folder)  # where the robot reaches every face (tests/box_part.py)
        cell_file = folder / "cell.yaml"
        cell_file.write_text(yaml.safe_dump(small_cell().model_dump(mode="json")))
        out = folder / "ref"
        args = ["inspect", str(recipe), "--cell", str(cell_file), "--out", str(out)]
        proc = subprocess.run(
            [sys.executable, "-m", "cell", *args, "--serial", "SN-7", "--operator", OPERATOR],
            capture_output=True,
            text=True,
            cwd=REPO,
            timeout=600,
        )
        from tests.same_result import judged_report

        judged_report(proc, out)
        return recipe, cell_file, out

    return once_per_session(tmp_path_factory, "box-cli-reference", make)
