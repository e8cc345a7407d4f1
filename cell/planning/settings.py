"""Task constraints of the view planner (dissertation eq 3.4, TC = {fov, S, rho, f_d, eta}) and loop settings.

The sensor part of TC (field of view, stand-off, focus range, camera/projector geometry) comes from the cell
config; what the inspection task asks for (resolution, point density, visibility thresholds, coverage and
feedback set points) lives here. Units: mm, mm^2, degrees in the schema (radians inside the code).
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from cell.schema import Fraction, Strict

Angle = Annotated[float, Field(gt=0, lt=90)]


class PlanSettings(Strict):
    """What the recipe may say about planning (its ``plan:`` section)."""

    theta_projector_deg: Angle = Field(
        75.0, description="eq 3.5 theta_th1: max angle surface normal / projector ray"
    )
    theta_camera_deg: Angle = Field(
        60.0, description="eq 3.5 theta_th2: max angle surface normal / camera ray"
    )
    patch_cone_deg: Angle = Field(
        25.0, description="eqs 3.1-3.2: max angle triangle normal / patch mean normal"
    )
    resolution_mm: Annotated[float, Field(gt=0)] = Field(
        0.5, description="rho: largest camera pixel footprint"
    )
    point_density_per_mm2: Annotated[float, Field(gt=0)] = Field(
        0.5,
        description="points per mm^2 the sensor must deliver (projector and camera) and coverage requires",
    )
    fov_margin: Annotated[float, Field(gt=0.3, le=1.0)] = Field(0.85, description="usable share of the field")
    dof_margin: Annotated[float, Field(gt=0.3, le=1.0)] = Field(
        0.9, description="usable share of the focus range"
    )
    patch_accept: Fraction = Field(0.9, description="share of a patch's area one viewpoint must measure")
    min_patch_area_mm2: Annotated[float, Field(ge=0)] = Field(
        50.0, description="smaller patches are not split"
    )
    samples: Annotated[int, Field(ge=1000, le=500000)] = Field(
        20000, description="surface samples for coverage"
    )
    clearance_mm: Annotated[float, Field(ge=0)] = Field(30.0, description="sensor body to part and table")
    coverage_radius_mm: Annotated[float, Field(gt=0)] = Field(2.0, description="disc for the density test")
    view_budget: Annotated[int, Field(ge=1, le=500)] = Field(40, description="max viewpoints incl. feedback")
    max_iterations: Annotated[int, Field(ge=0, le=50)] = 6
    q_setpoint_fraction: Fraction = Field(0.004, description="set point of Q as a share of inspectable area")
    hole_weight: Annotated[float, Field(gt=0)] = Field(
        1.0, description="w of eq 3.22: hole cost / distance cost"
    )
    accuracy_tol_mm: Annotated[float, Field(gt=0)] = Field(
        0.1, description="overlap disagreement that counts in IA"
    )
    glare_margin_deg: Annotated[float, Field(ge=0, lt=45)] = Field(8.0, description="beta - theta/2 in g_kR")
    aim: Literal["camera", "bisector"] = Field(
        "camera",
        description="camera: camera axis along the patch normal; bisector: the normal bisects the camera "
        "and projector rays (symmetric angles, but the mirror geometry that makes glare on glossy parts)",
    )
    seed: int = 0
