"""Plain-text tables of the results store for ``cell history``: at most 80 columns, so they read the same
in any terminal, a log and an e-mail."""

from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime

from cell.results.spc import PART, Spc
from cell.results.store import RunRow

WIDTH = 80


def _clip(text: str | None, width: int) -> str:
    text = text or "-"
    return text if len(text) <= width else text[: width - 1] + "~"


def _mm(value: float | None) -> str:
    return "-" if value is None else f"{value:+.3f}"


def _local(t: datetime) -> str:
    return t.astimezone().strftime("%Y-%m-%d %H:%M")


def history_lines(rows: Sequence[RunRow], folders: bool = False) -> list[str]:
    """One header and one line per run (newest first): local start time, part, serial, operator, the
    verdict (or the status of a run without one), the deviation range (mm); ``folders`` adds the folder
    (the line is then longer than 80 columns)."""
    head = (
        f"{'started':<16} {'part':<10} {'serial':<12} {'operator':<9} {'result':<10} "
        f"{'dev min':>7} {'dev max':>7}"
    )
    lines = [head + ("  folder" if folders else "")]
    for r in rows:
        result = r.verdict if r.status == "done" and r.verdict else r.status
        line = (
            f"{_local(r.started):<16} {_clip(r.part, 10):<10} {_clip(r.serial, 12):<12} "
            f"{_clip(r.operator, 9):<9} {_clip(result, 10):<10} {_mm(r.dev_min):>7} {_mm(r.dev_max):>7}"
        )
        lines.append(line + (f"  {r.folder}" if folders else ""))
    return lines


def _num(value: float | None, fmt: str) -> str:
    return "-" if value is None else format(value, fmt)


def spc_lines(spc: Spc) -> list[str]:
    """The capability of each series of a recipe: runs, mean and overall spread of the per-run means, band,
    Cp/Cpk (from the moving range) and Pp/Ppk (from the overall spread), mm."""
    lines = [
        f"SPC of recipe {_clip(spc.recipe, 40)}: {spc.n_runs} runs finished with pass or fail",
        "mean deviation per run (mm); Cp/Cpk: moving range, Pp/Ppk: overall s",
        f"{'series':<14} {'n':>4} {'mean':>8} {'s':>7} {'lower':>7} {'upper':>7} "
        f"{'Cp':>6} {'Cpk':>6} {'Pp':>6} {'Ppk':>6}",
    ]
    for s in spc.series:
        c = s.capability
        name = "whole part" if s.name == PART else s.name
        lines.append(
            f"{_clip(name, 14):<14} {c.n:>4} {_num(c.mean_mm, '+.4f'):>8} {_num(c.std_mm, '.4f'):>7} "
            f"{_num(c.lower_mm, '+.3f'):>7} {_num(c.upper_mm, '+.3f'):>7} {_num(c.cp, '.2f'):>6} "
            f"{_num(c.cpk, '.2f'):>6} {_num(c.pp, '.2f'):>6} {_num(c.ppk, '.2f'):>6}"
        )
    return lines
