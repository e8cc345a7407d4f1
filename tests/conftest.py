"""Suite-wide hooks: the count of the tests that need a real outside server or program (PostgreSQL, ...),
printed at the end of the run, so CI's output shows that they ran rather than skipped."""

from __future__ import annotations

from collections import Counter

import pytest

# marker -> what the tests marked with it need
COUNTED = {"postgres": "PostgreSQL server"}


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    for marker, what in COUNTED.items():
        outcomes: Counter[str] = Counter()
        for kind in ("passed", "failed", "error", "skipped"):
            for rep in terminalreporter.stats.get(kind, []):
                if marker in getattr(rep, "keywords", {}) and (rep.when == "call" or kind != "passed"):
                    outcomes[kind] += 1
        if outcomes:
            counts = ", ".join(f"{n} {kind}" for kind, n in sorted(outcomes.items()))
            terminalreporter.write_line(f"tests needing a real {what} (marker {marker}): {counts}")
