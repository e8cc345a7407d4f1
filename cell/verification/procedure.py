"""The VDI/VDE 2634 Part 2 acceptance test's pieces: where the artefacts go in the single-view measuring
volume, how each position's points are evaluated (sphere: PF, PS; ball bar: SD, and PF and PS of its two
spheres; plane: F) and the result against the maximum permissible errors. The procedure that measures them
runs as a controller job (cell/verification/job.py).

Single-view points are in the camera frame {C}: the figures are lengths and forms, which no rigid transform
changes, so they do not depend on the hand-eye or the robot. The commanded artefact pose only seeds the
segmentation (gates of several mm absorb placement and hand-eye errors).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.config import CellConfig
from cell.geometry import invert, look_at, transform_points
from cell.verification.certificate import BallBarArtefact, Certificate, PlaneArtefact, SphereArtefact
from cell.verification.figures import (
    OUTLIER_FRACTION,
    SphereFit,
    fit_plane,
    fit_sphere,
    flatness,
    probing_form,
    probing_size,
    sphere_spacing,
)
from cell.verification.positions import (
    Position,
    Volume,
    ball_bar_positions,
    plane_positions,
    sphere_positions,
)

COARSE_GATE_MM = 8.0  # first selection around the commanded artefact: placement + hand-eye errors
FINE_GATE_MM = 1.0  # points farther than this from the first fit do not belong to the artefact surface
BAR_CLEARANCE_MM = 1.5  # sphere points this close to the bar (beyond its radius) are left out
PLANE_EDGE_MM = 5.0  # the plane's edge zone left out (mixed pixels where the face ends)
VOLUME_CENTRE_HEIGHT_MM = 80.0  # the measuring volume's centre above the table (its far end clears it)


@dataclass
class PositionResult:
    """One position's figures (mm; None where they do not apply or the fit failed)."""

    label: str
    artefact: str
    n_points: int = 0
    pf_mm: list[float] = field(default_factory=list)  # one per sphere
    ps_mm: list[float] = field(default_factory=list)
    sd_mm: float | None = None
    f_mm: float | None = None
    rms_mm: list[float] = field(default_factory=list)  # RMS residual of each fit: the noise under PF and F
    excluded_points: int = 0
    error: str | None = None


@dataclass
class AcceptanceResult:
    """The acceptance test: every position, the worst figure of each kind and the verdict against the MPEs."""

    cell: str
    geometry_source: str
    volume_mm: dict[str, float]
    mpe_mm: dict[str, float]
    positions: list[PositionResult]
    figures_mm: dict[str, float | None] = field(default_factory=dict)
    passed: dict[str, bool | None] = field(default_factory=dict)
    verdict: str = "incomplete"
    simulated: bool = False
    kind: str = "VDI/VDE 2634 Part 2, single view"
    required: tuple[str, ...] = ("PF", "PS", "SD", "F")
    interim: bool = False  # a start-of-shift check on a few positions, not the whole acceptance test

    def summarise(self) -> None:
        """Worst value (largest magnitude) per figure, pass/fail per figure and overall. PF and PS are the
        sphere's, as the guideline takes them; without sphere positions (the interim check, Part 3) the ball
        bar's spheres give them."""

        def worst(values: list[float]) -> float | None:
            return max(values, key=abs) if values else None

        p = self.positions
        probed = [r for r in p if r.artefact == "sphere"] or p
        self.figures_mm = {
            "PF": worst([v for r in probed for v in r.pf_mm]),
            "PS": worst([v for r in probed for v in r.ps_mm]),
            "SD": worst([r.sd_mm for r in p if r.sd_mm is not None]),
            "F": worst([r.f_mm for r in p if r.f_mm is not None]),
        }
        self.passed = {
            k: (None if v is None else abs(v) <= self.mpe_mm[k]) for k, v in self.figures_mm.items()
        }
        if any(r.error for r in p) or any(self.passed[k] is None for k in self.required):
            self.verdict = "incomplete"
        else:
            self.verdict = "pass" if all(v for v in self.passed.values() if v is not None) else "fail"

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> AcceptanceResult:
        """The result back from :meth:`to_dict` (a run's results/fit.json)."""
        names = {f.name for f in fields(cls)}
        positions = [PositionResult(**p) for p in d["positions"]]
        kept = {k: v for k, v in d.items() if k in names}  # a report's extra keys (note, certificate) go
        return cls(**{**kept, "positions": positions, "required": tuple(d["required"])})


# ------------------------------------------------------------------------------------------ evaluation
def evaluate_sphere(
    points_C: NDArray[np.float64], T_C_A: NDArray[np.float64], sphere: SphereArtefact
) -> PositionResult:
    """PF and PS of the single sphere from its view's points (camera frame, mm); ``T_C_A`` is where it is
    expected, which only seeds the segmentation (a wide gate around it, then a narrow one around the first
    fit, the final fit with the guideline's 0.3 % exclusion)."""
    res = PositionResult("", "sphere")
    centre, r = T_C_A[:3, 3], sphere.diameter_mm / 2
    for gate in (COARSE_GATE_MM, FINE_GATE_MM):
        sel = np.abs(np.linalg.norm(points_C - centre, axis=1) - r) < gate
        fit = fit_sphere(points_C[sel], outlier_fraction=0.0 if gate > FINE_GATE_MM else OUTLIER_FRACTION)
        centre = fit.centre
    res.pf_mm.append(probing_form(fit))
    res.ps_mm.append(probing_size(fit, sphere.diameter_mm))
    res.rms_mm.append(fit.rms)
    res.n_points, res.excluded_points = fit.n_used, fit.n_excluded
    return res


def evaluate_ball_bar(
    points_C: NDArray[np.float64], T_C_A: NDArray[np.float64], bar: BallBarArtefact
) -> PositionResult:
    """PF and PS of both spheres and SD of a ball bar from its view's points (camera frame, mm); ``T_C_A``
    is where the bar is expected (model), which only seeds the segmentation."""
    res = PositionResult("", "ball_bar", n_points=0)
    L = bar.centre_distance_mm
    centres = transform_points(T_C_A, np.array([[-L / 2, 0, 0], [L / 2, 0, 0]]))
    fits: list[SphereFit] = []
    # twice: first around the expected centres with a wide gate, then around the first fit with a narrow one
    for gate, clearance in ((COARSE_GATE_MM, COARSE_GATE_MM / 2), (FINE_GATE_MM, BAR_CLEARANCE_MM)):
        axis = (centres[1] - centres[0]) / np.linalg.norm(centres[1] - centres[0])
        fits = []
        for i, (c, d) in enumerate(zip(centres, bar.sphere_diameters_mm, strict=True)):
            rel = points_C - c
            dist = np.linalg.norm(rel, axis=1)
            toward_other = rel @ (axis if i == 0 else -axis)
            off_axis = np.linalg.norm(rel - np.outer(rel @ axis, axis), axis=1)
            on_bar = (toward_other > 0) & (off_axis < bar.bar_diameter_mm / 2 + clearance)
            sel = (np.abs(dist - d / 2) < gate) & ~on_bar
            fits.append(
                fit_sphere(points_C[sel], outlier_fraction=0.0 if gate > FINE_GATE_MM else OUTLIER_FRACTION)
            )
        centres = np.array([f.centre for f in fits])
    for fit, d in zip(fits, bar.sphere_diameters_mm, strict=True):
        res.pf_mm.append(probing_form(fit))
        res.ps_mm.append(probing_size(fit, d))
        res.rms_mm.append(fit.rms)
        res.n_points += fit.n_used
        res.excluded_points += fit.n_excluded
    res.sd_mm = sphere_spacing(fits[0], fits[1], L)
    return res


def evaluate_plane(
    points_C: NDArray[np.float64], T_C_A: NDArray[np.float64], plate: PlaneArtefact
) -> PositionResult:
    """F of the plane standard from its view's points (camera frame, mm); ``T_C_A`` seeds the segmentation.
    The face's extent is found from the points themselves and its edge zone left out."""
    res = PositionResult("", "plane")
    p_A = transform_points(invert(T_C_A), points_C)
    hl, hw = plate.length_mm / 2 + COARSE_GATE_MM, plate.width_mm / 2 + COARSE_GATE_MM
    near = (np.abs(p_A[:, 0]) < hl) & (np.abs(p_A[:, 1]) < hw) & (np.abs(p_A[:, 2]) < COARSE_GATE_MM)
    coarse = fit_plane(points_C[near], outlier_fraction=0.0)
    on_face = near & (np.abs((points_C - coarse.point) @ coarse.normal) < FINE_GATE_MM)
    # in-plane coordinates along the artefact's nominal axes, projected onto the fitted plane
    u = T_C_A[:3, 0] - (T_C_A[:3, 0] @ coarse.normal) * coarse.normal
    u /= np.linalg.norm(u)
    v = np.cross(coarse.normal, u)
    rel = points_C[on_face] - coarse.point
    cu, cv = rel @ u, rel @ v
    inner = (
        (cu > cu.min() + PLANE_EDGE_MM)
        & (cu < cu.max() - PLANE_EDGE_MM)
        & (cv > cv.min() + PLANE_EDGE_MM)
        & (cv < cv.max() - PLANE_EDGE_MM)
    )
    fit = fit_plane(points_C[on_face][inner])
    res.f_mm = flatness(fit)
    res.rms_mm.append(fit.rms)
    res.n_points, res.excluded_points = fit.n_used, fit.n_excluded
    return res


# ------------------------------------------------------------------------------------------ the procedure
def single_view_pose(cfg: CellConfig) -> NDArray[np.float64]:
    """T_W_C (mm) of the single-view test: looking straight down at the measuring volume's centre, which
    sits :data:`VOLUME_CENTRE_HEIGHT_MM` above the table at the world origin."""
    centre = np.array([0.0, 0.0, VOLUME_CENTRE_HEIGHT_MM])
    return look_at(centre + (0.0, 0.0, cfg.sensor.standoff_mm), centre, up=(0.0, 1.0, 0.0))


def acceptance_positions(cfg: CellConfig, certificate: Certificate) -> list[Position]:
    """The Part 2 positions for this cell's measuring volume and these artefacts: the sphere's, the ball
    bar's, the plane's."""
    vol = Volume.of(cfg.sensor)
    bar = certificate.ball_bar
    return (
        sphere_positions(vol, certificate.sphere.diameter_mm)
        + ball_bar_positions(vol, bar.centre_distance_mm, max(bar.sphere_diameters_mm))
        + plane_positions(vol, certificate.plane.length_mm)
    )


def check_positions(cfg: CellConfig, certificate: Certificate) -> list[Position]:
    """The interim check's two positions: the ball bar along the first space diagonal (it spans the depth
    and the field) and the plane flat in the middle."""
    every = {p.label: p for p in acceptance_positions(cfg, certificate)}
    return [every["ball bar, space diagonal 1"], every["plane, flat middle"]]
