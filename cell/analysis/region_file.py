"""The schema of a region file (``cell compare --regions``): a recipe's ``regions:`` alone. A module of its
own so that :mod:`cell.analysis.regions` loads the config schemas only when a region file is read."""

from __future__ import annotations

from cell.config import RegionConfig
from cell.schema import Strict


class RegionFile(Strict):
    """A region file: ``regions: [{name, faces | box_mm, tolerance_mm}]`` as in a recipe."""

    regions: list[RegionConfig]
