"""Schemas of the cell config and of recipes, and YAML loading with errors that name file and field.

Field names carry their unit (``_mm``, ``_deg``, ``_ms``, ``_px``) so that a unit mistake shows in review, and
bounds catch the ones a schema can (a stand-off of 0.394 is metres, not millimetres). Unknown keys are errors:
a typo must never silently fall back to a default.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from cell.defaults import DEFAULT_CELL as DEFAULT_CELL  # re-exported: where the commands' default lived
from cell.errors import ConfigError
from cell.geometry import Pose, pose_from_xyz_rpy
from cell.limits import tolerance_problem
from cell.planning.settings import PlanSettings
from cell.retention import RetentionConfig
from cell.schema import Fraction, PositiveFloat, Strict, Vec3
from cell.yaml_files import read_yaml as read_yaml  # re-exported: where every loader found them
from cell.yaml_files import validate as validate


class PoseConfig(Strict):
    """A rigid transform as written by people: translation in mm, fixed-axis roll/pitch/yaw in degrees."""

    xyz_mm: Vec3 = (0.0, 0.0, 0.0)
    rpy_deg: Vec3 = (0.0, 0.0, 0.0)

    def matrix(self) -> Pose:
        """The 4x4 float64 matrix (mm, rad inside)."""
        return pose_from_xyz_rpy(self.xyz_mm, np.deg2rad(self.rpy_deg))


class Distortion(Strict):
    """Brown-Conrady lens distortion coefficients in OpenCV order (k1, k2, p1, p2, k3)."""

    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0

    def as_array(self) -> np.ndarray:
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3], dtype=np.float64)


class PinholeConfig(Strict):
    """Pinhole intrinsics shared by camera and projector (pixels; principal point in pixel coordinates)."""

    width_px: Annotated[int, Field(gt=0, le=16384)]
    height_px: Annotated[int, Field(gt=0, le=16384)]
    fx_px: PositiveFloat
    fy_px: PositiveFloat
    cx_px: float
    cy_px: float
    pixel_pitch_um: Annotated[float, Field(gt=0.5, lt=100)]
    f_number: Annotated[float, Field(gt=0.5, lt=64)]
    focus_distance_mm: Annotated[float, Field(gt=10, lt=10000)]

    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx_px, 0, self.cx_px], [0, self.fy_px, self.cy_px], [0, 0, 1.0]])

    @property
    def focal_length_mm(self) -> float:
        return self.fx_px * self.pixel_pitch_um * 1e-3


class CameraConfig(PinholeConfig):
    """An area camera: optics, sensor noise model and the driver that talks to it."""

    driver: Literal["sim", "genicam", "aravis", "replay"] = "sim"
    name: str = "camera"
    serial: str = "SIM-CAM-0001"
    model: str = "simulated"
    distortion: Distortion = Distortion()
    bit_depth: Literal[8, 10, 12] = 8
    full_well_e: Annotated[float, Field(gt=100)]
    read_noise_e: Annotated[float, Field(ge=0)]
    dark_offset_dn: Annotated[float, Field(ge=0)] = 0.0
    exposure_ms: Annotated[float, Field(gt=0, le=10000)]
    gain_db: Annotated[float, Field(ge=0, le=48)] = 0.0
    trigger: Literal["software", "hardware"] = Field(
        "software",
        description="how a scan starts each exposure: software (wait for the display latency, then trigger) "
        "or hardware (the projector's sync or trigger output wired to a camera input line)",
    )
    options: dict[str, Any] = Field(default_factory=dict, description="driver-specific settings")


class ProjectorTiming(Strict):
    """How the projector turns input frames into light, and what the scan assumes of its latency."""

    refresh_hz: Annotated[float, Field(gt=0, le=1000)] = Field(60.0, description="input frame rate, Hz")
    modulation: Literal["none", "dlp"] = Field(
        "none",
        description="dlp: binary mirrors make grey levels by pulse width within each frame period, so camera "
        "exposures must be whole multiples of the frame period; none: steady light (LCD, LCoS)",
    )
    latency_ms: Annotated[float, Field(ge=0, le=1000)] | None = Field(
        None,
        description="delay from the display's present stamp to a fully new pattern on the part, measured by "
        "`cell calibrate latency` (the calibration file's value replaces it); None: max_latency_frames",
    )
    max_latency_frames: Annotated[float, Field(ge=0, le=20)] = Field(
        4.0, description="latency assumed until measured: an upper bound (projectors add 1-3 frames)"
    )
    max_recaptures: Annotated[int, Field(ge=0, le=10)] = Field(
        3, description="times the scan re-captures an inconsistent pattern pair, one frame later each time"
    )

    @property
    def frame_period_ms(self) -> float:
        return 1000.0 / self.refresh_hz

    def assumed_latency_s(self) -> float:
        """The wait after a present stamp before the camera may expose: measured, else the upper bound."""
        if self.latency_ms is not None:
            return self.latency_ms * 1e-3
        return self.max_latency_frames * self.frame_period_ms * 1e-3

    def check_exposure(self, exposure_ms: float, where: str) -> None:
        """ValueError unless a DLP exposure is a whole number of frame periods (to the camera's 1 us)."""
        if self.modulation != "dlp":
            return
        period = self.frame_period_ms
        n = round(exposure_ms / period)
        if n < 1 or abs(exposure_ms - n * period) > 1e-3:
            good = ", ".join(f"{k * period:.3f}" for k in (1, 2, 3))
            raise ValueError(
                f"{where} = {exposure_ms:g} ms is not a whole number of the DLP projector's frame periods "
                f"({period:.4f} ms at {self.refresh_hz:g} Hz): partial frames catch part of the grey-level "
                f"bit planes; use e.g. {good} ms or change sensor.projector.timing"
            )


class ProjectorConfig(PinholeConfig):
    """A DLP projector: optics, light output, placement in the camera frame and its control driver."""

    driver: Literal["sim", "serial", "dlpc350", "replay"] = "sim"
    name: str = "projector"
    serial: str = "SIM-PROJ-0001"
    model: str = "simulated"
    T_C_P: PoseConfig = Field(description="projector optical frame in the camera frame {C}")
    distortion: Distortion = Field(
        Distortion(),
        description="projector lens distortion, OpenCV order, projector pixels; zero: a pinhole "
        "(`cell calibrate projector` measures it, and the calibration carries it)",
    )
    irradiance_e_per_ms: PositiveFloat = Field(
        description="camera signal (electrons/ms) from a white pixel on an albedo-1 surface facing the "
        "projector at its focus distance"
    )
    black_level: Fraction = Field(0.002, description="light leaked by a black pixel: 1 / contrast ratio")
    gamma: Annotated[float, Field(gt=0.2, lt=5)] = 1.0
    timing: ProjectorTiming = ProjectorTiming()
    options: dict[str, Any] = Field(default_factory=dict, description="driver-specific settings")


class SensorConfig(Strict):
    """The structured-light area sensor on the robot flange: camera + projector, and its hand-eye pose."""

    T_T_C: PoseConfig = Field(description="camera optical frame {C} in the tool flange frame {T}")
    standoff_mm: Annotated[float, Field(gt=50, lt=5000)]
    depth_of_field_mm: Annotated[float, Field(gt=0, lt=2000)]
    camera: CameraConfig
    projector: ProjectorConfig
    max_projector_incidence_deg: Annotated[float, Field(gt=0, le=90)] = Field(
        80.0,
        description="the sensor drops points the projector lights more obliquely than this (angle of the "
        "measured normal to the projector ray): near the terminator the stripe edges blur and points land "
        "up to 0.18 mm inside the surface (docs/verification.md). The planner's eq 3.5 limit is the "
        "recipe's plan.theta_projector_deg",
    )

    @model_validator(mode="after")
    def _exposure_synchronises(self) -> SensorConfig:
        self.projector.timing.check_exposure(self.camera.exposure_ms, "sensor.camera.exposure_ms")
        return self


class RobotConfig(Strict):
    """The arm: placement in the world, workspace envelope and motion limits the cell never exceeds."""

    driver: Literal["sim", "ur_rtde", "replay"] = "sim"
    name: str = "robot"
    model: Literal["ur5e"] = "ur5e"
    host: str = "127.0.0.1"
    T_W_B: PoseConfig = PoseConfig()
    envelope_min_mm: Vec3
    envelope_max_mm: Vec3
    max_tcp_speed_mm_s: Annotated[float, Field(gt=0, le=1000)]
    max_tcp_accel_mm_s2: Annotated[float, Field(gt=0, le=5000)]
    max_joint_speed_rad_s: Annotated[float, Field(gt=0, le=math.pi)]
    max_joint_accel_rad_s2: Annotated[float, Field(gt=0, le=40)]
    home_joints_deg: tuple[float, float, float, float, float, float]
    view_pose_sigma_mm: Annotated[float, Field(gt=0, le=20)] = Field(
        1.0,
        description="1-sigma translation error of a view's camera pose through the kinematic chain (robot "
        "kinematics, repeatability, what the hand-eye calibration left), at the stand-off: the multi-view "
        "refinement's prior while the cell has no kinematic calibration",
    )
    view_pose_sigma_deg: Annotated[float, Field(gt=0, le=5)] = Field(
        0.2, description="1-sigma rotation error of a view's camera pose (as view_pose_sigma_mm)"
    )
    calibrated_view_pose_sigma_mm: Annotated[float, Field(gt=0, le=20)] = Field(
        0.2,
        description="with a kinematic calibration: the least 1-sigma translation error of a view's camera "
        "pose, under what the fit's covariance gives at the view (which counts its residuals' scatter, not "
        "the bias that imperfect lenses put into its board poses). The default is what the honest simulated "
        "world showed (docs/analysis.md); on a real cell, set it from the refinement's corrections that its "
        "runs record (registration.refinement.corrections_mm)",
    )
    calibrated_view_pose_sigma_deg: Annotated[float, Field(gt=0, le=5)] = Field(
        0.05, description="with a kinematic calibration: the least 1-sigma rotation error (as above)"
    )
    pose_uncertainty_mm: Annotated[float, Field(gt=0, le=20)] = Field(
        0.04,
        description="with a kinematic calibration: the 1-sigma translation error of a view's camera pose, at "
        "the stand-off, that the per-point uncertainty assumes (docs/uncertainty.md). Smaller than the "
        "refinement's prior floor, which errs on the large side to keep the refinement from sliding views. "
        "The default was chosen in the honest simulated world: on study seeds 1-15 the offsets of the faces "
        "no datum holds (0.052 mm rms) asked for 0.037 mm, rounded to 0.04; validated on seeds 16-30 (every "
        "u bin within 0.8-1.25). A real cell sets it from its own validation (the offsets of faces away from "
        "its datums over repeated measurements, against the pose part of u)",
    )
    pose_uncertainty_deg: Annotated[float, Field(gt=0, le=5)] = Field(
        0.01,
        description="with a kinematic calibration: the 1-sigma rotation error the per-point uncertainty "
        "assumes (as above: chosen with the translation, scaled by the same factor, 0.0094 rounded to 0.01)",
    )
    options: dict[str, Any] = Field(default_factory=dict, description="driver-specific settings")

    @model_validator(mode="after")
    def _envelope_ordered(self) -> RobotConfig:
        if any(lo >= hi for lo, hi in zip(self.envelope_min_mm, self.envelope_max_mm)):
            raise ValueError("envelope_min_mm must be below envelope_max_mm on every axis")
        return self


class MaterialConfig(Strict):
    """Surface of a material for the simulator: reflectance (ambient + Lambert + Phong specular) and its
    microstructure (rendered unless the cell's world is ideal)."""

    albedo: Fraction = 0.6
    specular: Annotated[float, Field(ge=0, le=50)] = 0.0
    shininess: Annotated[float, Field(ge=1, le=10000)] = 20.0
    roughness_um: Annotated[float, Field(ge=0, le=100)] = Field(
        1.0, description="std of the surface height about its nominal shape, on the grain's scale"
    )
    grain_mm: Annotated[float, Field(gt=0, le=100)] = Field(
        0.5, description="lateral scale of the roughness and of the albedo texture"
    )
    albedo_texture: Annotated[float, Field(ge=0, le=0.5)] = Field(
        0.03, description="relative std of the albedo across the surface"
    )


class SimConfig(Strict):
    """Everything only the simulator reads: scene lighting, table and part materials, the noise seed."""

    ambient_e_per_ms: Annotated[float, Field(ge=0)] = 5.0
    table_size_mm: Annotated[float, Field(gt=0)] = 3000.0
    table_material: MaterialConfig = MaterialConfig(albedo=0.3)
    part_material: MaterialConfig = MaterialConfig()
    seed: int = 0
    noise: bool = True


class CalibrationFiles(Strict):
    """The active calibration files (paths relative to the cell config file). Empty: the config's nominal
    geometry is used, and every result says so."""

    sensor: Path | None = Field(None, description="per-pixel d, S, alpha (cell calibrate sensor)")
    gamma: Path | None = Field(None, description="projector response LUT (cell calibrate gamma)")
    hand_eye: Path | None = Field(None, description="T_T_C; overrides sensor.T_T_C (cell calibrate handeye)")
    intrinsics: Path | None = Field(None, description="camera K and distortion (cell calibrate intrinsics)")
    projector: Path | None = Field(None, description="projector K and T_C_P (cell calibrate projector)")
    latency: Path | None = Field(None, description="display latency (cell calibrate latency)")
    kinematics: Path | None = Field(
        None,
        description="the robot's link-length and joint-zero errors (cell calibrate kinematics): the flange "
        "pose is computed from the reported joints with them instead of taken from the robot, and the fit's "
        "covariance gives each view's pose prior in the multi-view refinement",
    )


class VerificationConfig(Strict):
    """Maximum permissible errors of the VDI/VDE 2634 figures (``cell verify``), mm, and the certificate of
    the artefacts (relative to the cell config file; default recipes/artefacts/certificate.yaml)."""

    mpe_pf_mm: Annotated[float, Field(gt=0, le=10)] = Field(0.05, description="probing error, form")
    mpe_ps_mm: Annotated[float, Field(gt=0, le=10)] = Field(0.05, description="probing error, size (+-)")
    mpe_sd_mm: Annotated[float, Field(gt=0, le=10)] = Field(0.025, description="sphere-spacing error (+-)")
    mpe_f_mm: Annotated[float, Field(gt=0, le=10)] = Field(0.05, description="flatness measurement error")
    mpe_sd_multiview_mm: Annotated[float, Field(gt=0, le=10)] = Field(
        0.08,
        description="sphere-spacing error of the long ball bar across views (Part 3, robot-moved sensor)",
    )
    warn_fraction: Annotated[float, Field(gt=0, le=1)] = Field(
        0.7, description="`cell verify check` warns when a figure uses more than this share of its MPE"
    )
    certificate: Path | None = Field(None, description="artefact certificate YAML")
    block_inspections: bool = Field(
        True,
        description="`cell inspect` refuses to start while this cell's newest `cell verify check` in the "
        "runs root exceeded a maximum permissible error, until one passes again",
    )


class CellConfig(Strict):
    """A whole cell: one robot carrying one area sensor; the simulator section is used by sim devices."""

    name: str
    description: str = ""
    robot: RobotConfig
    sensor: SensorConfig
    sim: SimConfig = SimConfig()
    world: Literal["ideal"] | dict[str, Any] | None = Field(
        None,
        description="simulation only: how the simulated world differs from this config (hand-eye, lenses, "
        "robot kinematics, part placement, surface); 'ideal' is the exact model, absent or a mapping the "
        "realistic defaults. Only the simulator reads it (schema: docs/world-schema.md)",
    )
    calibration: CalibrationFiles = CalibrationFiles()
    verification: VerificationConfig = VerificationConfig()
    retention: RetentionConfig = Field(
        RetentionConfig(), description="how long runs keep their raw view images (docs/storage.md)"
    )
    results_db: str | None = Field(
        None,
        description="where runs are recorded for `cell history`, SPC and the station: a plant's "
        "PostgreSQL (postgresql://user@host/db; docs/results-db.md) or sqlite:///file; absent: "
        "results.sqlite in the runs root",
    )

    @field_validator("results_db")
    @classmethod
    def _database_url(cls, url: str | None) -> str | None:
        if url is None:
            return url
        from sqlalchemy.engine import make_url  # here: only a config that names a database pays for it
        from sqlalchemy.exc import ArgumentError

        try:
            make_url(url)
        except ArgumentError:
            url = ""
        if not re.match(r"(postgresql(\+psycopg)?|sqlite)://", url):
            raise ValueError("a postgresql://user@host/database or sqlite:///path URL")
        return url


# --------------------------------------------------------------------------------------------- recipes


class ToleranceConfig(Strict):
    """Allowed signed deviation from the nominal surface, mm (negative = into the material); limits between
    0.001 mm and 50 mm from zero."""

    lower: float = Field(lt=0)
    upper: float = Field(gt=0)

    @field_validator("lower", "upper")
    @classmethod
    def _plausible(cls, v: float) -> float:
        problem = tolerance_problem(v)
        if problem:
            raise ValueError(problem)
        return v


class RegionConfig(Strict):
    """A region of the part judged on its own (verdict, statistics, coverage): nominal faces (indices into the
    CAD mesh as loaded: file order, less any zero-area triangles the loader warns it removed) or an
    axis-aligned box in the part frame {P}, mm. ``tolerance_mm`` [lower, upper] replaces the recipe's band
    inside the region; where such regions overlap, every one of their bands must hold."""

    name: str = Field(min_length=1)
    faces: list[Annotated[int, Field(ge=0)]] | None = None
    box_mm: tuple[Vec3, Vec3] | None = None
    tolerance_mm: tuple[float, float] | None = None

    @model_validator(mode="after")
    def _one_kind(self) -> RegionConfig:
        if (self.faces is None) == (self.box_mm is None):
            raise ValueError("give exactly one of 'faces' or 'box_mm'")
        if self.faces is not None and not self.faces:
            raise ValueError("'faces' is empty: list the nominal faces of the region")
        if self.box_mm is not None and not all(a <= b for a, b in zip(*self.box_mm, strict=True)):
            raise ValueError("box_mm must be [[xmin, ymin, zmin], [xmax, ymax, zmax]]")
        if self.tolerance_mm is not None:
            lower, upper = self.tolerance_mm
            if not lower < upper:
                raise ValueError("tolerance_mm must be [lower, upper] with lower < upper")
            problem = tolerance_problem(lower, upper)
            if problem:
                raise ValueError(f"tolerance_mm {list(self.tolerance_mm)}: {problem}")
        return self


class PartConfig(Strict):
    """The part to inspect. Paths are relative to the recipe file."""

    cad: Path
    actual: Path | None = Field(None, description="simulation only: the mesh rendered as the made part")
    T_W_P: PoseConfig = PoseConfig()
    material: MaterialConfig | None = None


class DatumPoint(Strict):
    """A reference point (RPS / 3-2-1 datum) on the nominal surface, in the part frame {P} (mm). It fixes the
    part along ``normal`` (default: the nominal surface normal there), measured as the mean deviation of the
    points within ``radius_mm`` of it."""

    name: str = Field(min_length=1)
    point_mm: Vec3
    normal: Vec3 | None = None
    radius_mm: Annotated[float, Field(gt=0, le=100)] = 6.0

    @field_validator("normal")
    @classmethod
    def _unit(cls, v: Vec3 | None) -> Vec3 | None:
        if v is not None and not 0.5 < float(np.linalg.norm(v)) < 2.0:
            raise ValueError(f"{list(v)} is not a direction: give a unit vector")
        return v


AlignmentMethod = Literal["kinematic", "datums", "datum_icp", "features", "weighted", "best_fit"]
AlignmentEstimate = Literal[
    "kinematic", "datums", "datum_icp", "features"
]  # what the weighted method combines


def _default_alignment_weights() -> dict[AlignmentEstimate, float]:
    return {"kinematic": 1.0, "features": 2.0, "datums": 4.0, "datum_icp": 4.0}


class AlignmentConfig(Strict):
    """How the measured part is put into its part frame before it is judged (dissertation 4.1-4.3).

    ``kinematic``: the recipe's placement ``part.T_W_P`` through the robot and hand-eye chain (right for a
    calibrated fixture); ``datums``: the 3-2-1 / RPS points below (at least 6 constraints fixing all six
    degrees of freedom); ``datum_icp``: point-to-plane ICP on the datum regions only, started from the
    datums; ``features``: curvature-feature matching (eqs 4.16-4.20); ``weighted``: the weighted combination
    of kinematic, datums, features and datum ICP (eqs 4.21-4.22); ``best_fit``: ICP over the whole part,
    which aligns global deviations away (the report warns)."""

    method: AlignmentMethod = "kinematic"
    datums: list[DatumPoint] = Field(default_factory=list)
    weights: dict[AlignmentEstimate, Annotated[float, Field(ge=0)]] = Field(
        default_factory=_default_alignment_weights,
        description="weights of the estimates in the weighted combination (Table I of the "
        "dissertation: datums most, then features, then the kinematic chain)",
    )
    fixture_uncertainty_mm: Annotated[float, Field(ge=0, le=50)] | None = Field(
        None, description="kinematic: the stated uncertainty of the fixture's placement, for the report"
    )
    max_correction_mm: Annotated[float, Field(gt=0, le=100)] = Field(
        10.0,
        description="an alignment moving any part point farther than this from the kinematic placement "
        "is refused (wrong datums or a wrong part): the verdict becomes incomplete",
    )

    @model_validator(mode="after")
    def _datums_given(self) -> AlignmentConfig:
        names = [d.name for d in self.datums]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise ValueError(f"datum names must be unique; repeated: {', '.join(twice)}")
        if self.method in ("datums", "datum_icp") and len(self.datums) < 6:
            raise ValueError(
                f"method '{self.method}' needs at least 6 datum points (3-2-1), {len(self.datums)} given"
            )
        return self


class GuardBandConfig(Strict):
    """The guarded decision rule's guard band (ISO 14253-1): U = k u of every point (u: its standard
    uncertainty, docs/uncertainty.md); a point conforms within the tolerance shrunk by U, does not beyond the
    tolerance widened by U, and is ambiguous in between."""

    k: float = Field(2.0, ge=1.0, le=4.0, description="coverage factor of the expanded uncertainty U = k u")
    ambiguous: Literal["fail", "pass", "incomplete"] = Field(
        "incomplete",
        description="what ambiguous points make of the verdict: fail (not proven within tolerance), pass "
        "(not proven out of it) or incomplete (measure again)",
    )


class Recipe(Strict):
    """An inspection recipe: the nominal part and its tolerance; everything else has defaults."""

    name: str = ""
    part: PartConfig
    tolerance: ToleranceConfig
    min_coverage: Fraction = Field(
        0.95,
        description="share of the inspectable surface that must be measured "
        "for a pass/fail verdict; below it the verdict is 'incomplete'",
    )
    exclude_from_coverage: list[Annotated[int, Field(ge=0)]] = Field(
        default_factory=list,
        description="nominal faces (indices as for regions) that coverage leaves out: surfaces no reachable "
        "pose sees (`cell plan` names them and their faces) or that need no measurement. The planner "
        "plans no view for them; points measured on them are still judged",
    )
    plan: PlanSettings = PlanSettings()
    alignment: AlignmentConfig = AlignmentConfig()
    requires_calibration: bool = Field(
        False,
        description="the verdict is 'incomplete' unless the cell has a complete, current and good "
        "calibration (sensor or intrinsics + projector, and hand-eye), made for this cell config",
    )
    regions: list[RegionConfig] = Field(
        default_factory=list,
        description="regions judged on their own, optionally with a band of their own (in the report's "
        "region_verdicts); any failing region fails the part, any region measured below min_coverage makes "
        "it incomplete",
    )
    decision_rule: Literal["simple", "guarded"] = Field(
        "simple",
        description="simple: each deviation against its band as if exact; guarded: the band shrunk and "
        "widened by each point's expanded uncertainty (ISO 14253-1, `guard_band`)",
    )
    guard_band: GuardBandConfig = GuardBandConfig()

    @field_validator("regions")
    @classmethod
    def _unique_region_names(cls, regions: list[RegionConfig]) -> list[RegionConfig]:
        names = [r.name for r in regions]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise ValueError(f"region names must be unique; repeated: {', '.join(twice)}")
        return regions


# --------------------------------------------------------------------------------------------- loading
def load_cell_config(path: str | Path) -> CellConfig:
    """Load and validate a cell config YAML; calibration paths become absolute and must exist. A simulated
    cell's ``world:`` section is validated by the simulator (through cell.devices), never read here."""
    cfg = validate(CellConfig, read_yaml(path), path)
    from cell.devices import check_world  # late: cell.devices imports this module

    check_world(cfg, path)
    base = Path(path).resolve().parent
    for field in CalibrationFiles.model_fields:
        value = getattr(cfg.calibration, field)
        if value is None:
            continue
        resolved = value if value.is_absolute() else base / value
        if not resolved.exists():
            raise ConfigError(
                f"calibration file not found: {resolved}; run `cell calibrate` or remove the entry",
                path=str(path),
                field=f"calibration.{field}",
            )
        setattr(cfg.calibration, field, resolved)
    if cfg.calibration.latency is not None:
        from cell.calibration.latency import load_latency

        timing = cfg.sensor.projector.timing
        timing.latency_ms = load_latency(cfg.calibration.latency, cfg.sensor.projector, path)
    return cfg


def load_recipe(path: str | Path) -> Recipe:
    """Load a recipe; part paths become absolute (relative to the recipe file) and must exist."""
    p = Path(path)
    recipe = validate(Recipe, read_yaml(p), p)
    base = p.resolve().parent
    for field in ("cad", "actual"):
        value = getattr(recipe.part, field)
        if value is None:
            continue
        resolved = value if value.is_absolute() else base / value
        if not resolved.is_file():
            raise ConfigError(f"mesh file not found: {resolved}", path=str(p), field=f"part.{field}")
        setattr(recipe.part, field, resolved)
    return recipe


def config_fingerprint(cfg: CellConfig) -> str:
    """SHA-256 of the cell config as validated, without its ``calibration:`` section: what a calibration file
    records as the config it was made for (``cell_config_sha256``). Adding the file to the config does not
    change it; changing the robot, the sensor, the scene or the world does. Where results are recorded
    (``results_db``), how long raw images are kept (``retention``) and the pose prior the per-point
    uncertainty assumes (``robot.pose_uncertainty_mm/deg``: a cell sets it from its own validation, after
    calibrating) measure nothing and are left out too."""
    exclude: dict[str, Any] = {
        "calibration": True,
        "results_db": True,
        "retention": True,
        "robot": {"pose_uncertainty_mm", "pose_uncertainty_deg"},
    }
    data = cfg.model_dump(mode="json", exclude=exclude)
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()
