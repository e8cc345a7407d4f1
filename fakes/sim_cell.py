"""One simulated world shared by the simulated robot, projector and camera (DESIGN: fakes that share a world).

Moving the robot moves the camera: the camera renders from T_W_C = T_W_B @ T_B_T @ T_T_C, with T_B_T the
robot's current flange pose and T_T_C the configured hand-eye transform.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from numpy.typing import NDArray

from cell.config import CellConfig, MaterialConfig
from cell.contracts import Robot
from cell.planning.reach import sensor_body_points_T
from fakes.camera import SimCamera
from fakes.clock import SimClock
from fakes.projector import SimProjector
from fakes.robot import SimRobot
from fakes.sim.render import SceneRenderer
from fakes.sim.scene import Scene


@dataclass
class SimCell:
    """The simulated devices and the world they share; scene and renderer give tests ground truth."""

    config: CellConfig
    scene: Scene
    renderer: SceneRenderer
    clock: SimClock
    robot: Robot
    projector: SimProjector
    camera: SimCamera
    part_W: trimesh.Trimesh | None
    seed: int = 0

    def camera_pose(self) -> NDArray[np.float64]:
        """T_W_C of the camera now (mm): world <- base <- flange <- camera."""
        return self.camera.pose_source()

    def reseed(self, *key: int) -> None:
        """Restart the camera noise from (cell seed, *key): a view's images then depend only on the view,
        not on what was captured before, so a resumed run reproduces an uninterrupted one exactly."""
        self.camera.rng = np.random.default_rng([self.seed, *key])


def build_sim_cell(
    cfg: CellConfig,
    part_W: trimesh.Trimesh | None,
    part_material: MaterialConfig | None = None,
    seed: int | None = None,
) -> SimCell:
    """Compose scene, renderer, clock, robot, projector and camera for ``cfg``; ``part_W`` is the (actual)
    part in world coordinates (mm) or None for an empty table; ``seed`` overrides ``cfg.sim.seed``."""
    scene = Scene.from_meshes(part_W, cfg.sim, part_material)
    renderer = SceneRenderer(cfg.sensor, cfg.sim, scene)
    clock = SimClock()
    robot = SimRobot(cfg.robot, clock=clock, obstacles_W=part_W, tool_body_T=sensor_body_points_T(cfg))
    projector = SimProjector(cfg.sensor.projector)
    T_W_B, T_T_C = cfg.robot.T_W_B.matrix(), cfg.sensor.T_T_C.matrix()

    def camera_pose() -> NDArray[np.float64]:
        return T_W_B @ robot.tool_pose() @ T_T_C

    seed = cfg.sim.seed if seed is None else seed
    rng = np.random.default_rng(seed)
    camera = SimCamera(cfg.sensor.camera, renderer, projector, pose_source=camera_pose, clock=clock, rng=rng)
    return SimCell(cfg, scene, renderer, clock, robot, projector, camera, part_W, seed)
