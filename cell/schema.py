"""Base pieces of every YAML schema (cell config, recipes, plan settings), kept apart so that feature modules
can define their own sections without importing cell.config (which imports them back for the Recipe)."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

PositiveFloat = Annotated[float, Field(gt=0)]
Fraction = Annotated[float, Field(ge=0, le=1)]
Vec3 = tuple[float, float, float]


class Strict(BaseModel):
    """Base of every schema: unknown keys are errors, values are validated on assignment too."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, frozen=False)
