"""Suite-wide hooks: the longest test files first (see LONGEST_FIRST), and the count of the tests that need
a real outside server or program (PostgreSQL, ...), printed at the end of the run, so CI's output shows that
they ran rather than skipped."""

from __future__ import annotations

from collections import Counter

import pytest

# marker -> what the tests marked with it need
COUNTED = {"postgres": "PostgreSQL server", "chromium": "headless Chromium browser"}

# The longest test files, longest first (CPU time, user+sys, measured on the shared 2-core machine with a warm
# numba cache, nice 10, load stated). `make test` runs `pytest -n 2 --dist loadfile --no-loadscope-reorder`:
# the two workers take whole files in collection order, so these start first and the short files fill in
# around them (xdist's default order, most tests first, would start these few-test files last, where one of
# them may run alone at the end). The box reference runs that several files compare against are made once per
# session by whichever file asks first (tests/shared_runs.py); the figures include them.
LONGEST_FIRST = (
    "test_inspect_e2e.py",  # 131 s (load 7.5-9): a pillar inspection 64 s, the kill-and-resume test 65 s
    "test_inspect_alignment.py",  # 97 s (load 10): a pillar inspection, its kinematic report
    "test_station_browser.py",  # ~70 s, more wall time: it waits on a browser and a live run
    "test_controller_safety.py",  # 57-62 s alone (load 7), both box references included
    "test_calib_procedures.py",  # 56 s (commit edb3b19)
    "test_sync_faults.py",  # 45 s (commit 7c95bd3)
    "test_glass_rig.py",
    "test_driver_ur_robot.py",  # 31 s, 106 s wall (load 6-7): real-time moves of the fake controller
    "test_feedback_glare.py",  # 29.5 s (load 10; 83-96 s before the batched planning IK)
    "test_verification_acceptance.py",
    "test_calib_cli.py",
    "test_safety_storage.py",
    "test_record_replay_run.py",
    "test_calib_active.py",
    "test_controller_overlap.py",  # 16-17 s (load 10-11.5)
    "test_planning_sim.py",
    "test_controller.py",  # 12 s (load 11.5; 39 s before its faults shared two runs)
    "test_results_db.py",
    "test_storage_run.py",
)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The files of :data:`LONGEST_FIRST` first, in its order; every other file after them, as collected
    (a stable sort: the tests of a file stay together and in their order)."""
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


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
