"""The default files the commands name in their options, in a module that imports nothing.

``cell inspect --help`` prints ``--cell``'s and ``--runs``' defaults; importing them from :mod:`cell.config`
or :mod:`cell.runs` would load the config schemas (pydantic, numpy) or the run folder's machinery just to
print a path. :mod:`cell.config`, :mod:`cell.runs` and :mod:`cell.inspection_run` take their defaults from
here.
"""

from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
DEFAULT_CELL = REPO / "recipes" / "cells" / "sim.yaml"  # the cell config a command uses without --cell
DEMO_CELL = REPO / "recipes" / "cells" / "sim.yaml"  # the honest simulated world: it differs from the config
RUNS_ROOT = REPO / "runs"  # the default runs root: runs/ in the repository
