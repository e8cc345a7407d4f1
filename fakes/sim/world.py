"""How the simulated world differs from the cell config's nominal model (simulation only).

A real cell never matches its drawings: the sensor sits on the flange a little off the mounting drawing, the
projector a little off the camera, the lenses are not the data sheet's, the arm's links and joint zeros are
off by fractions of a millimetre and a hundredth of a degree, the robot lands within its repeatability, the
part sits on its fixture a millimetre off, and its surface is not a perfect mathematical plane. The
``world:`` section of a simulated cell config says by how much; :func:`build_world` draws one seeded world
from it, and the simulator renders that world while the pipeline under ``cell/`` measures with the config.
Nothing under ``cell/`` reads this module or the section (tests/test_world_isolation.py).

Sizes. Rigid errors (hand-eye, camera-projector, part placement) have exactly the stated size, in a seeded
random direction (translation) and about a seeded random axis (rotation): the size in the docs is the size in
the world. Per-parameter errors (link lengths, joint zeros) are seeded normal draws with the stated standard
deviation. Intrinsics: both focal lengths scaled by ``1 +- focal_fraction`` (one seeded sign), the principal
point moved ``principal_point_px`` in a seeded direction, the lens distortion is the config's plus
``distortion_delta``. Pose repeatability: each move's landing error is a seeded draw, uniform in a ball of
radius ``repeatability_mm`` (UR5e data sheet: +-0.03 mm).

``world: ideal`` is the exact model (every error zero, no surface microstructure): a figure measured there is
a noise floor.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from cell.config import CellConfig, Distortion, PoseConfig, SensorConfig
from cell.geometry import Pose, make_pose
from cell.planning.kinematics import UR5E, DHParams, URKinematics
from cell.schema import Strict

NonNegative = Annotated[float, Field(ge=0)]


class RigidError(Strict):
    """A rigid pose error of exactly this size: translation (mm) in a seeded direction, rotation (deg) about
    a seeded axis."""

    translation_mm: Annotated[float, Field(ge=0, le=50)]
    rotation_deg: Annotated[float, Field(ge=0, le=10)]


class IntrinsicsError(Strict):
    """How a lens differs from its config: focal lengths scaled by 1 +- ``focal_fraction``, the principal
    point moved by ``principal_point_px``, the distortion coefficients the config's plus
    ``distortion_delta`` (OpenCV order)."""

    focal_fraction: Annotated[float, Field(ge=0, le=0.1)] = 0.005
    principal_point_px: Annotated[float, Field(ge=0, le=100)] = 3.0
    distortion_delta: Distortion = Distortion()


class RobotError(Strict):
    """Kinematic errors of the arm (standard deviations of seeded normal draws) and its repeatability."""

    link_length_mm: Annotated[float, Field(ge=0, le=5)] = Field(
        0.2, description="std of each non-zero DH length (d1, a2, a3, d4, d5, d6)"
    )
    joint_zero_deg: Annotated[float, Field(ge=0, le=1)] = Field(0.02, description="std of each joint's zero")
    repeatability_mm: Annotated[float, Field(ge=0, le=1)] = Field(
        0.03, description="radius of the ball each move lands in (UR5e: +-0.03 mm)"
    )


class PlacementError(Strict):
    """Where the part really sits on its fixture: shifted ``translation_mm`` in the table plane (seeded
    direction) and turned ``rotation_deg`` about the vertical through its centre (seeded sign); it still rests
    on the table."""

    translation_mm: Annotated[float, Field(ge=0, le=50)] = 1.0
    rotation_deg: Annotated[float, Field(ge=0, le=10)] = 0.5


class WorldConfig(Strict):
    """The ``world:`` section of a simulated cell config. Defaults are realistic for the prototype cell; each
    error is independent of the others. ``seed`` (default: ``sim.seed``) draws the directions and signs."""

    base: Literal["realistic", "ideal"] = Field(
        "realistic",
        description="what the errors not written in the section are: the realistic defaults, or zero "
        "('ideal': e.g. only a placement error)",
    )
    seed: int | None = Field(None, description="draws every error's direction and sign; default sim.seed")
    hand_eye: RigidError = Field(
        RigidError(translation_mm=1.5, rotation_deg=0.4),
        description="camera on the flange (T_T_C) vs the mounting drawing; default 1.5 mm, 0.4 deg",
    )
    camera_projector: RigidError = Field(
        RigidError(translation_mm=0.3, rotation_deg=0.05),
        description="projector pose T_C_P relative to the camera; default 0.3 mm, 0.05 deg",
    )
    camera: IntrinsicsError = Field(
        IntrinsicsError(distortion_delta=Distortion(k1=0.01, k2=-0.02, p1=1e-4, p2=-1e-4, k3=0.0)),
        description="camera lens; default focal 0.5 %, principal point 3 px, dk1 0.01, dk2 -0.02, "
        "dp1 1e-4, dp2 -1e-4",
    )
    projector: IntrinsicsError = Field(
        IntrinsicsError(focal_fraction=0.005, principal_point_px=3.0),
        description="projector lens (its distortion_delta is unused: see projector_distortion); "
        "default focal 0.5 %, principal point 3 px",
    )
    projector_distortion: Distortion = Field(
        Distortion(k1=-0.02, k2=0.01),
        description="the projector lens's distortion (the config models the projector as a pinhole); "
        "default k1 -0.02, k2 0.01",
    )
    robot: RobotError = Field(RobotError(), description="arm kinematics and repeatability")
    placement: PlacementError = Field(PlacementError(), description="the part on its fixture; 1 mm, 0.5 deg")
    microstructure: bool = Field(
        True, description="surface roughness and albedo texture as the part's and table's materials set them"
    )


IDEAL = WorldConfig(
    base="ideal",
    hand_eye=RigidError(translation_mm=0, rotation_deg=0),
    camera_projector=RigidError(translation_mm=0, rotation_deg=0),
    camera=IntrinsicsError(focal_fraction=0, principal_point_px=0),
    projector=IntrinsicsError(focal_fraction=0, principal_point_px=0),
    projector_distortion=Distortion(),
    robot=RobotError(link_length_mm=0, joint_zero_deg=0, repeatability_mm=0),
    placement=PlacementError(translation_mm=0, rotation_deg=0),
    microstructure=False,
)


def world_config(section: Literal["ideal"] | dict[str, Any] | None) -> WorldConfig:
    """The validated ``world:`` section: ``'ideal'``, a mapping (missing keys take the realistic defaults,
    or zero with ``base: ideal``), or None (absent: the realistic defaults). Raises pydantic's
    ValidationError on bad keys or values."""
    if section == "ideal":
        return IDEAL
    wc = WorldConfig.model_validate(section or {})
    if wc.base == "ideal":
        return WorldConfig.model_validate(_deep_update(IDEAL.model_dump(), section or {}))
    return wc


def _deep_update(base: dict[str, Any], update: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in update.items():
        out[key] = _deep_update(out[key], value) if isinstance(value, dict) and key in out else value
    return out


def _rotation() -> Any:
    """scipy's Rotation, imported when a world is built (cell.devices.check_world only validates one)."""
    from scipy.spatial.transform import Rotation

    return Rotation


def _unit(rng: np.random.Generator) -> NDArray[np.float64]:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def rigid_error(spec: RigidError, rng: np.random.Generator) -> Pose:
    """A pose of exactly the spec's size: translation along a random unit vector, rotation about another."""
    R = _rotation().from_rotvec(_unit(rng) * np.deg2rad(spec.rotation_deg)).as_matrix()
    return make_pose(R, _unit(rng) * spec.translation_mm)


@dataclass(frozen=True)
class World:
    """One drawn world. ``sensor`` is the true sensor (hand-eye, lenses, projector pose) in the config's
    schema; ``projector_distortion`` the projector lens (OpenCV order); ``kinematics`` and
    ``joint_zero_rad`` the true arm (flange = ``kinematics.fk(q + joint_zero_rad)``); ``placement`` the part's
    placement error (a yaw and an in-plane shift; :func:`place_about` makes it a map of world points)."""

    config: WorldConfig
    seed: int
    sensor: SensorConfig
    projector_distortion: NDArray[np.float64]
    kinematics: URKinematics
    joint_zero_rad: NDArray[np.float64]
    placement: Pose

    @property
    def ideal(self) -> bool:
        return self.config == IDEAL

    def true_flange(self, joints_rad: NDArray[np.float64]) -> Pose:
        """``T_B_T`` where the flange really is for joint readings ``joints_rad``."""
        return self.kinematics.fk(np.asarray(joints_rad, dtype=np.float64) + self.joint_zero_rad)

    def landing_error(self, rng: np.random.Generator) -> Pose:
        """One move's landing error: a translation uniform in the repeatability ball."""
        r = self.config.robot.repeatability_mm
        if r == 0:
            return np.eye(4)
        return make_pose(np.eye(3), _unit(rng) * r * rng.uniform() ** (1 / 3))


def _lens(cfg: Any, spec: IntrinsicsError, rng: np.random.Generator, distortion: bool) -> dict[str, Any]:
    """Field updates of a camera or projector config for its true lens."""
    scale = 1.0 + spec.focal_fraction * rng.choice((-1.0, 1.0))
    angle = rng.uniform(0, 2 * np.pi)
    update: dict[str, Any] = {
        "fx_px": cfg.fx_px * scale,
        "fy_px": cfg.fy_px * scale,
        "cx_px": cfg.cx_px + spec.principal_point_px * np.cos(angle),
        "cy_px": cfg.cy_px + spec.principal_point_px * np.sin(angle),
    }
    if distortion:
        true = cfg.distortion.as_array() + spec.distortion_delta.as_array()
        update["distortion"] = Distortion(**dict(zip(Distortion.model_fields, true.tolist(), strict=True)))
    return update


def build_world(cfg: CellConfig, config: WorldConfig | None = None) -> World:
    """Draw the world of ``cfg`` (its ``world:`` section unless ``config`` is given), seeded by
    ``world.seed`` or else ``sim.seed``. Each error draws from its own stream, so changing one size does not
    move the others."""
    wc = config if config is not None else world_config(cfg.world)
    seed = cfg.sim.seed if wc.seed is None else wc.seed

    def rng(stream: int) -> np.random.Generator:
        return np.random.default_rng([seed, stream])

    s = cfg.sensor

    def pose_config(T: Pose) -> PoseConfig:
        rpy = np.degrees(_rotation().from_matrix(T[:3, :3]).as_euler("xyz"))
        return PoseConfig(xyz_mm=tuple(T[:3, 3].tolist()), rpy_deg=tuple(rpy.tolist()))

    def moved(pose: PoseConfig, spec: RigidError, stream: int) -> PoseConfig:
        if spec.translation_mm == 0 and spec.rotation_deg == 0:
            return pose  # exactly the config's (no round trip through a matrix)
        return pose_config(pose.matrix() @ rigid_error(spec, rng(stream)))

    camera = s.camera.model_copy(update=_lens(s.camera, wc.camera, rng(3), distortion=True))
    projector = s.projector.model_copy(
        update={
            **_lens(s.projector, wc.projector, rng(4), distortion=False),
            "T_C_P": moved(s.projector.T_C_P, wc.camera_projector, 2),
        }
    )
    sensor = s.model_copy(
        update={"T_T_C": moved(s.T_T_C, wc.hand_eye, 1), "camera": camera, "projector": projector}
    )

    r = rng(5)
    dh = UR5E.dh
    dd = np.where(np.asarray(dh.d) != 0, r.normal(0, wc.robot.link_length_mm, 6), 0.0)
    da = np.where(np.asarray(dh.a) != 0, r.normal(0, wc.robot.link_length_mm, 6), 0.0)
    true_dh = DHParams(
        d=tuple((np.asarray(dh.d) + dd).tolist()), a=tuple((np.asarray(dh.a) + da).tolist()), alpha=dh.alpha
    )
    zero = np.deg2rad(r.normal(0, wc.robot.joint_zero_deg, 6))

    p = rng(6)
    angle = p.uniform(0, 2 * np.pi)
    shift = wc.placement.translation_mm * np.array([np.cos(angle), np.sin(angle), 0.0])
    yaw = np.deg2rad(wc.placement.rotation_deg) * p.choice((-1.0, 1.0))
    placement = make_pose(_rotation().from_rotvec([0, 0, yaw]).as_matrix(), shift)
    return World(
        config=wc,
        seed=seed,
        sensor=sensor,
        projector_distortion=wc.projector_distortion.as_array(),
        kinematics=URKinematics(dh=true_dh),
        joint_zero_rad=zero,
        placement=placement,
    )


def place_about(placement: Pose, centre_W: NDArray[np.float64]) -> Pose:
    """The placement error as a rigid map of world points: its rotation about the vertical through
    ``centre_W`` (the part's footprint centre), then its translation."""
    c = np.asarray(centre_W, dtype=np.float64).copy()
    c[2] = 0.0
    return make_pose(placement[:3, :3], c - placement[:3, :3] @ c + placement[:3, 3])


def value_noise(points_mm: NDArray[np.float64], grain_mm: float, seed: int) -> NDArray[np.float64]:
    """A smooth random field of unit standard deviation (on average) at world points (N, 3): seeded values
    on a cubic lattice of spacing ``grain_mm``, trilinearly interpolated. A function of the position only, so
    every view sees the same surface. Hand-written (a numba kernel): no library offers seeded lattice noise
    on numpy arrays fast enough for a million pixels per view."""
    from fakes.sim.noise import lattice_noise  # numba: loaded by the renderer, not by a config's check

    p = np.ascontiguousarray(points_mm, dtype=np.float64).reshape(-1, 3)
    return lattice_noise(p, 1.0 / grain_mm, np.uint64(seed & 0xFFFFFFFF))


def schema_page() -> str:
    """docs/world-schema.md (tests/test_sim_world.py checks it is fresh; regenerate with
    ``python -m fakes.sim.world``)."""
    from cell.docgen import schema_page as page

    return page(
        "World schema (simulation only)",
        WorldConfig,
        "The `world:` section of a simulated cell config: how the simulated world differs from the config's "
        "nominal model (fakes/sim/world.py, docs/simulator.md). `world: ideal` is the exact model; absent, "
        "the defaults below. Nothing under `cell/` reads it. Surface microstructure is set by the materials "
        "(`roughness_um`, `grain_mm`, `albedo_texture` in the cell config's and the recipe's materials).\n",
    )


if __name__ == "__main__":
    from pathlib import Path

    (Path(__file__).resolve().parents[2] / "docs" / "world-schema.md").write_text(schema_page())
