"""The user's cache folder for files derived from installed ones (compressed plotly.js, compiled kernels)."""

from __future__ import annotations

import os
from pathlib import Path


def cache_dir() -> Path:
    """Where derived files are kept between runs: $CELL_CACHE_DIR, else $XDG_CACHE_HOME/inspection-cell,
    else ~/.cache/inspection-cell."""
    if os.environ.get("CELL_CACHE_DIR"):
        return Path(os.environ["CELL_CACHE_DIR"])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "inspection-cell"
