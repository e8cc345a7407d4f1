"""The artefacts' calibration certificate: the calibrated values the figures are measured against (YAML,
edited by the technician from the calibration laboratory's certificate of each real artefact).

Lengths in mm. The simulator builds its artefacts from the same file (cell/verification/artefacts.py): in
simulation the artefact is exactly as certified, so the certificate's own uncertainty is not simulated.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from pydantic import Field, model_validator

from cell.config import MaterialConfig, read_yaml, validate
from cell.schema import Strict

Length = Annotated[float, Field(gt=0, lt=5000)]
Small = Annotated[float, Field(ge=0, lt=1)]

# A matte, coated artefact (sprayed or sand-blasted ceramic/steel): bright, diffuse, no grain visible at the
# sensor's resolution. The simulator renders it; the pipeline never reads it.
MATTE = MaterialConfig(
    albedo=0.8, specular=0.0, shininess=10.0, roughness_um=0.5, grain_mm=0.5, albedo_texture=0.01
)


class Calibration(Strict):
    """Who calibrated the artefact, when, and with what expanded uncertainty (k=2, mm)."""

    serial: str = Field(min_length=1)
    laboratory: str = ""
    date: str = Field("", description="calibration date, ISO 8601")
    uncertainty_mm: Small = Field(0.0, description="expanded uncertainty (k=2) of the certified lengths")


class SphereArtefact(Calibration):
    """A single sphere: its certified diameter and form deviation."""

    diameter_mm: Length
    form_mm: Small = Field(0.0, description="certified form deviation (range of radii)")


class BallBarArtefact(Calibration):
    """Two spheres on a bar: both certified diameters and the centre distance."""

    sphere_diameters_mm: tuple[Length, Length]
    centre_distance_mm: Length
    bar_diameter_mm: Length = Field(description="the bar between the spheres (excluded from the sphere fits)")

    @model_validator(mode="after")
    def _spheres_apart(self) -> BallBarArtefact:
        if self.centre_distance_mm <= sum(self.sphere_diameters_mm) / 2:
            raise ValueError("centre_distance_mm must exceed the sum of the sphere radii")
        if self.bar_diameter_mm >= min(self.sphere_diameters_mm):
            raise ValueError("bar_diameter_mm must be smaller than the spheres")
        return self


class PlaneArtefact(Calibration):
    """A flat rectangular standard: its measured face (length x width) and certified flatness."""

    length_mm: Length
    width_mm: Length
    thickness_mm: Length
    flatness_mm: Small = Field(0.0, description="certified flatness of the measured face")


class Certificate(Strict):
    """Every artefact the verification uses. ``ball_bar`` is the short bar for one view, ``ball_bar_long``
    (about 300 mm) the one that spans several views (Part 3). ``material`` is for the simulator only."""

    sphere: SphereArtefact
    ball_bar: BallBarArtefact
    ball_bar_long: BallBarArtefact | None = None
    plane: PlaneArtefact
    material: MaterialConfig = Field(MATTE, description="simulation only: the artefacts' coating")


DEFAULT_CERTIFICATE = Path(__file__).resolve().parents[2] / "recipes" / "artefacts" / "certificate.yaml"


def load_certificate(path: str | Path = DEFAULT_CERTIFICATE) -> Certificate:
    """Load and validate a certificate YAML; ConfigError names the file and field."""
    return validate(Certificate, read_yaml(path), path)
