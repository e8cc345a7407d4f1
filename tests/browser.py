"""Tests in a real browser: headless Chromium found by :func:`cell.chromium.find_chromium`.

Without Chromium such a test is skipped, unless ``CELL_REQUIRE_CHROMIUM`` is set (CI, ``.ci/run``), which
makes it fail instead: in CI a browser test must never pass by not running. Mark such tests
``@pytest.mark.chromium``: the end of the run counts them (tests/conftest.py).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from cell.chromium import find_chromium


def require_chromium() -> Path:
    """The Chromium executable; skips the test without one (fails it when CELL_REQUIRE_CHROMIUM is set)."""
    exe = find_chromium()
    if exe is None:
        why = "Chromium not found (Debian: apt-get install chromium; or set CELL_CHROMIUM)"
        if os.environ.get("CELL_REQUIRE_CHROMIUM"):
            pytest.fail(f"CELL_REQUIRE_CHROMIUM is set but {why}")
        pytest.skip(why)
    return exe
