"""The exit codes of the commands that judge a part (``inspect``, ``resume``, ``report``, ``demo``,
``compare``, ``glass``), one per outcome, so that a PLC or MES wrapper reads the verdict from the code alone
(docs/exit-codes.md). Every other command exits 0 on success, 1 on failure and 2 on bad input."""

from __future__ import annotations

from enum import IntEnum


class ExitCode(IntEnum):
    """What a judging command's exit code means."""

    PASS = 0  # the run finished and the part passed
    FAULT = 1  # a device fault, an aborted run or a failed routine: no verdict
    USAGE = 2  # bad input (unknown option, invalid recipe or config): nothing was moved or written
    PAUSED = 3  # paused at a safe point (Ctrl-C, SIGTERM, a device asking for the operator): `cell resume` it
    FAIL = 4  # the run finished and the part failed
    INCOMPLETE = 5  # the run finished without a verdict (coverage below the recipe's minimum, a datum unseen)


def for_verdict(verdict: object) -> ExitCode:
    """The exit code of a finished run's verdict (``pass``, ``fail``, ``incomplete``); anything else is a
    fault: a finished run without a verdict is a bug, never a pass."""
    return {
        "pass": ExitCode.PASS,
        "fail": ExitCode.FAIL,
        "incomplete": ExitCode.INCOMPLETE,
    }.get(str(verdict).lower(), ExitCode.FAULT)


def for_run(state: str, verdict: object) -> ExitCode:
    """The exit code of an inspection run that ended in controller state ``state`` with ``verdict``."""
    if state == "done":
        return for_verdict(verdict)
    if state == "paused":
        return ExitCode.PAUSED
    return ExitCode.FAULT
