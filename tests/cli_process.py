"""`cell` commands in real processes that skip the interpreter's start-up: each is forked from a server
process that has already imported the CLI and the inspection's modules (multiprocessing's forkserver), so a
test that starts, kills and restarts `cell inspect` / `cell resume` twenty times pays the ~3 s of
imports once.

Each process runs the CLI's entry point (:func:`cell.cli.main`) with the given arguments and exits with its
code; SIGKILL ends it with no handler run, as it ends a `python -m cell` process. The server forks before any
of the run's threads (decode pool, numba's) exist."""

from __future__ import annotations

import multiprocessing
import os
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from multiprocessing import forkserver
from multiprocessing.process import BaseProcess
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent

# what `cell inspect` / `cell resume` of a simulated run import (a module missing here is imported by each
# process itself: slower, not wrong; a name that no longer exists is skipped by the forkserver)
PRELOAD = [
    "tests.cli_process",
    "cell.cli",
    "cell.commands.inspect",
    "cell.inspection_run",
    "cell.inspection",
    "cell.controller",
    "cell.devices",
    "cell.mesh",
    "cell.calibration",
    "cell.results",
    "cell.retention",
    "cell.analysis.alignment",
    "cell.analysis.pictures",
    "cell.analysis.report_html",
    "cell.analysis.view3d",
    "cell.verification.history",
    "fakes.sim_cell",
]


def _main(args: list[str], log: str) -> None:
    """The forked process's body: `cell ARGS` run from the repository, its output appended to ``log``."""
    fd = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)
    os.chdir(REPO)
    from cell.cli import main

    main(list(args))


@contextmanager
def server() -> Iterator[None]:
    """The forkserver of this process for a block of tests: started (with the CLI's modules imported) on the
    block's first :func:`start`, stopped and reaped at its end, so that no server outlives the tests and the
    CPU time of the processes it forked counts as this process's children's."""
    forkserver._forkserver._stop()  # one another module started (fakes/ur_controller.py) has other imports
    multiprocessing.get_context("forkserver").set_forkserver_preload(PRELOAD)
    try:
        yield
    finally:
        forkserver._forkserver._stop()  # the standard library's own tests stop it so


def start(args: list[str], log: Path) -> BaseProcess:
    """Start `cell ARGS` in a process forked from the server (its stdout and stderr appended to ``log``);
    call within :func:`server`."""
    proc = multiprocessing.get_context("forkserver").Process(target=_main, args=(list(args), str(log)))
    proc.start()
    return proc


def run(args: list[str], log: Path, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    """`cell ARGS` to its end in a forked process: its exit code and output, as :func:`subprocess.run`
    gives them."""
    proc = start(args, log)
    proc.join(timeout)
    if proc.exitcode is None:
        proc.kill()
        proc.join()
        raise subprocess.TimeoutExpired(["cell", *args], timeout)
    output = log.read_text() if log.exists() else ""
    return subprocess.CompletedProcess(["cell", *args], proc.exitcode, output, "")
