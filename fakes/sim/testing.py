"""Small simulated sensors for fast tests and contract suites (160x120 camera, 128x96 projector).

The geometry is the prototype's in miniature: camera looking down the z axis of {C}, projector 300 mm along +x
aimed at the camera axis at 400 mm (a 36.87 deg vergence), each projector pixel ~2 camera pixels wide on
a plane at 400 mm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import trimesh
from numpy.typing import NDArray

from cell.config import SensorConfig, SimConfig
from cell.geometry import look_at
from fakes.camera import SimCamera
from fakes.clock import SimClock
from fakes.projector import SimProjector
from fakes.sim.render import SceneRenderer
from fakes.sim.scene import Scene

STANDOFF_MM = 400.0
BASELINE_MM = 300.0


def small_sensor(
    *,
    bit_depth: int = 12,
    distortion: dict[str, float] | None = None,
    camera: dict[str, Any] | None = None,
    projector: dict[str, Any] | None = None,
) -> SensorConfig:
    """A small sensor config; ``camera`` / ``projector`` override fields of either."""
    cam = dict(
        width_px=160,
        height_px=120,
        fx_px=400.0,
        fy_px=400.0,
        cx_px=79.5,
        cy_px=59.5,
        pixel_pitch_um=4.65,
        f_number=8.0,
        focus_distance_mm=STANDOFF_MM,
        distortion=distortion if distortion is not None else {"k1": -0.05, "k2": 0.02, "p1": 1e-4},
        bit_depth=bit_depth,
        full_well_e=10000.0,
        read_noise_e=12.0,
        dark_offset_dn=2.0,
        exposure_ms=10.0,
        serial="SIM-SMALL-0001",
        model="simulated small camera",
    )
    cam.update(camera or {})
    slant = math.hypot(BASELINE_MM, STANDOFF_MM)
    proj = dict(
        width_px=128,
        height_px=96,
        fx_px=280.0,
        fy_px=280.0,
        cx_px=63.5,
        cy_px=47.5,
        pixel_pitch_um=13.68,
        f_number=4.0,
        focus_distance_mm=slant,
        T_C_P={
            "xyz_mm": [BASELINE_MM, 0, 0],
            "rpy_deg": [0, -math.degrees(math.atan2(BASELINE_MM, STANDOFF_MM)), 0],
        },
        irradiance_e_per_ms=700.0,
        black_level=0.002,
        gamma=1.0,
    )
    proj.update(projector or {})
    return SensorConfig.model_validate(
        dict(T_T_C={}, standoff_mm=STANDOFF_MM, depth_of_field_mm=100.0, camera=cam, projector=proj)
    )


def top_down_pose(
    height_mm: float = STANDOFF_MM, x_mm: float = 0.0, y_mm: float = 0.0
) -> NDArray[np.float64]:
    """T_W_C of a camera ``height_mm`` above (x, y) on the table, looking down, image x = world +x."""
    return look_at((x_mm, y_mm, height_mm), (x_mm, y_mm, 0.0), up=(0.0, 1.0, 0.0))


@dataclass
class SmallRig:
    sensor: SensorConfig
    sim: SimConfig
    scene: Scene
    renderer: SceneRenderer
    projector: SimProjector
    camera: SimCamera
    T_W_C: NDArray[np.float64]


def small_rig(
    *,
    part_W: trimesh.Trimesh | None = None,
    sim: SimConfig | None = None,
    T_W_C: NDArray[np.float64] | None = None,
    **sensor_kw: Any,
) -> SmallRig:
    """Scene, renderer and unconnected projector + camera of :func:`small_sensor` over the table, at a fixed
    pose (top-down at the stand-off unless ``T_W_C`` is given)."""
    sensor = small_sensor(**sensor_kw)
    sim = sim or SimConfig(seed=7)
    scene = Scene.from_meshes(part_W, sim)
    renderer = SceneRenderer(sensor, sim, scene)
    projector = SimProjector(sensor.projector)
    pose = top_down_pose() if T_W_C is None else T_W_C
    camera = SimCamera(
        sensor.camera,
        renderer,
        projector,
        pose_source=lambda: pose,
        clock=SimClock(),
        rng=np.random.default_rng(sim.seed),
    )
    return SmallRig(sensor, sim, scene, renderer, projector, camera, pose)
