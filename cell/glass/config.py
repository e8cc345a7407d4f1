"""Schemas of the back-imaging glass rig config and of a glass recipe (until CellConfig grows a glass
section).

Units: mm, degrees in files (radians inside), ms, electrons (e), pixels (px), microradians (urad) for the
small angle thresholds of the searches.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, model_validator

from cell.config import CameraConfig, PoseConfig, ToleranceConfig, read_yaml, validate
from cell.errors import ConfigError
from cell.schema import Strict

PositiveFloat = Annotated[float, Field(gt=0)]


class GlassCameraConfig(CameraConfig):
    """A rig camera: optics and sensor as any camera, plus its fixed optical frame in the world."""

    T_W_C: PoseConfig = Field(description="camera optical frame {C} in the world {W}")


class DotGridConfig(Strict):
    """A plane carrying a rows x cols grid of black dots, centred on the plane's origin (mm)."""

    rows: Annotated[int, Field(ge=2, le=500)]
    cols: Annotated[int, Field(ge=2, le=500)]
    pitch_mm: PositiveFloat
    dot_diameter_mm: PositiveFloat
    radiance_e_per_ms: PositiveFloat = Field(description="camera signal of its white seen directly (e/ms)")
    black_level: Annotated[float, Field(ge=0, lt=1)] = 0.03

    @model_validator(mode="after")
    def _dots_apart(self) -> DotGridConfig:
        if self.dot_diameter_mm >= 0.8 * self.pitch_mm:
            raise ValueError("dot_diameter_mm must be below 0.8 * pitch_mm so that dots stay apart")
        return self

    def dots_mm(self) -> np.ndarray:
        """(rows*cols, 2) dot centres in the plane (mm), row-major."""
        x = (np.arange(self.cols) - (self.cols - 1) / 2) * self.pitch_mm
        y = (np.arange(self.rows) - (self.rows - 1) / 2) * self.pitch_mm
        gx, gy = np.meshgrid(x, y)
        return np.column_stack([gx.ravel(), gy.ravel()])


class ScreenConfig(DotGridConfig):
    """The diffuse marker screen; its plane is z=0 of {S}. ``second_T_W_S``: its second known position for
    the multi-projection method (2.4), if the rig can move it there."""

    T_W_S: PoseConfig
    second_T_W_S: PoseConfig | None = None


class BoardConfig(DotGridConfig):
    """The dot-grid board of the vector calibration, laid level (parallel to z=0 of {W}) at two heights."""

    centre_xy_mm: tuple[float, float] = (0.0, 0.0)
    heights_mm: tuple[float, float] = Field(description="the two board heights z (mm) in {W}, low then high")

    @model_validator(mode="after")
    def _ordered(self) -> BoardConfig:
        if not self.heights_mm[0] < self.heights_mm[1]:
            raise ValueError("heights_mm must be (low, high) with low < high")
        return self


class GlassMaterialConfig(Strict):
    """Optical constants of the pane (simulator): index, thickness and the tint's absorption."""

    refractive_index: Annotated[float, Field(gt=1.0, lt=3.0)] = 1.52
    thickness_mm: Annotated[float, Field(gt=0.5, lt=30)] = 4.7
    absorption_per_mm: Annotated[float, Field(ge=0, lt=5)] = Field(
        0.035, description="intensity attenuation coefficient of the tinted glass (1/mm)"
    )


class GlassRigConfig(Strict):
    """A back-imaging rig: fixed cameras, the marker screen, the calibration board, the simulated glass."""

    name: str
    description: str = ""
    driver: Literal["sim", "genicam", "replay"] = "sim"
    options: dict[str, Any] = Field(default_factory=dict)  # genicam: drivers.glass_rig.GlassRigOptions
    cameras: Annotated[list[GlassCameraConfig], Field(min_length=1, max_length=8)]
    screen: ScreenConfig
    board: BoardConfig
    glass: GlassMaterialConfig = GlassMaterialConfig()
    ambient_e_per_ms: Annotated[float, Field(ge=0)] = 0.0
    seed: int = 0
    noise: bool = True

    @model_validator(mode="after")
    def _unique_names(self) -> GlassRigConfig:
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise ValueError(f"camera names must be unique, got {names}")
        return self


class GlassSearchConfig(Strict):
    """Parameters of marker identification, the reflection search and the multi-camera feedback."""

    method: Literal["golden_section", "multi_projection"] = Field(
        "golden_section",
        description="surface point per marker: the CAD-seeded golden-section search "
        "(2.3.4) or the multi-projection method (2.4, needs screen.second_T_W_S in the rig)",
    )
    max_surface_error_mm: PositiveFloat = Field(3.0, description="Delta of eq 2.13: largest expected error")
    angle_tol_urad: PositiveFloat = Field(2.0, description="stop when the offset angle is below this")
    length_tol_mm: PositiveFloat = Field(2e-4, description="stop when the search interval is this short")
    feedback_tol_urad: PositiveFloat = Field(
        20.0, description="stop adding cameras when the normal moves less"
    )
    gate_fraction: Annotated[float, Field(gt=0, lt=0.5)] = Field(
        0.4, description="identification gate as a fraction of the screen pitch"
    )
    dark_fraction: Annotated[float, Field(gt=0.1, lt=0.9)] = Field(
        0.5, description="a pixel is a top-layer dot below this fraction of the local background"
    )
    centroid_profile_px: Annotated[int, Field(ge=0, le=5)] = Field(
        1,
        description="0: eq 2.14 weights below the threshold only; >0: the whole dot profile grown by this "
        "many pixels (cell.glass.markers.detect_dots)",
    )
    pane_thickness_mm: Annotated[float, Field(gt=0.5, lt=30)] | None = Field(
        4.7,
        description="nominal pane thickness for the geometric rejection of bottom-skin copies "
        "(cell.glass.bottom); null: rely on the intensity threshold alone",
    )
    pane_refractive_index: Annotated[float, Field(gt=1.0, lt=3.0)] = 1.52
    outlier_alpha: Annotated[float, Field(gt=0, lt=0.5)] = Field(
        1e-3, description="reject a point whose cameras' normals disagree at this chi-square tail level"
    )
    max_depth_sigma_mm: PositiveFloat = Field(
        0.05,
        description="reject a point whose depth standard error (from the cameras' geometry and the "
        "normal noise) exceeds this accuracy target (mm)",
    )


class GlassPartConfig(Strict):
    """The pane: its nominal top skin (CAD) and, for simulation, the made one. Paths relative to the
    recipe."""

    cad: Path
    actual: Path | None = None
    T_W_P: PoseConfig = PoseConfig()


class GlassRecipe(Strict):
    """A glass inspection recipe: nominal pane, tolerance, search settings and the rig it runs on."""

    name: str = ""
    rig: Path = Field(description="glass rig config YAML, relative to the recipe")
    calibration_dir: Path | None = Field(None, description="view-vector calibrations (computed if absent)")
    part: GlassPartConfig
    tolerance: ToleranceConfig
    search: GlassSearchConfig = GlassSearchConfig()


def load_glass_rig(path: str | Path) -> GlassRigConfig:
    """Load and validate a glass rig config YAML."""
    return validate(GlassRigConfig, read_yaml(path), path)


def load_glass_recipe(path: str | Path) -> GlassRecipe:
    """Load a glass recipe; paths become absolute (relative to the recipe) and files must exist."""
    p = Path(path)
    recipe = validate(GlassRecipe, read_yaml(p), p)
    base = p.resolve().parent

    def resolve(value: Path, field: str) -> Path:
        out = value if value.is_absolute() else base / value
        if not out.is_file():
            raise ConfigError(f"file not found: {out}", path=str(p), field=field)
        return out

    recipe.rig = resolve(recipe.rig, "rig")
    recipe.part.cad = resolve(recipe.part.cad, "part.cad")
    if recipe.part.actual is not None:
        recipe.part.actual = resolve(recipe.part.actual, "part.actual")
    if recipe.calibration_dir is not None and not recipe.calibration_dir.is_absolute():
        recipe.calibration_dir = base / recipe.calibration_dir
    return recipe
