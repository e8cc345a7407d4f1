"""One simulated world shared by the simulated robot, projector and camera (DESIGN: fakes that share a world).

The world is not the cell config (fakes/sim/world.py): it is drawn from the config's ``world:`` section. The
robot reports its pose through the config's nominal kinematics, as a real UR does from its encoders and its
nominal DH table; the world puts the flange where the true kinematics (link lengths, joint zeros) and the
move's landing error put it, and the camera renders from

    T_W_C = T_W_B @ fk_true(q + joint_zero) @ landing @ T_T_C_true

with the true hand-eye, lenses and projector pose. The part sits where the placement error puts it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

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
from fakes.sim.world import World, build_world, place_about


@dataclass
class SimCell:
    """The simulated devices and the world they share; scene, renderer and world give tests ground truth.

    ``T_place_W`` maps the part as the recipe places it to where it really is (world points, mm):
    ``T_W_P_true = T_place_W @ T_W_P``."""

    config: CellConfig
    scene: Scene
    renderer: SceneRenderer
    clock: SimClock
    robot: Robot
    projector: SimProjector
    camera: SimCamera
    part_W: trimesh.Trimesh | None
    seed: int = 0
    world: World | None = None
    T_place_W: NDArray[np.float64] = field(default_factory=lambda: np.eye(4))
    _landing: NDArray[np.float64] = field(default_factory=lambda: np.eye(4))
    _moves_seen: int = 0
    _landing_rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(0))

    def flange_pose(self) -> NDArray[np.float64]:
        """T_B_T where the flange really is (true kinematics, the last move's landing error); mm."""
        if self.world is None:
            return self.robot.tool_pose()
        moves = self._moves_made()
        if moves != self._moves_seen:  # a new move has ended: it landed somewhere else in the ball
            self._moves_seen = moves
            self._landing = self.world.landing_error(self._landing_rng)
        return self.world.true_flange(self.robot.joints()) @ self._landing

    def _moves_made(self) -> int:
        """Moves the robot has made (refused commands and stops do not move it)."""
        log = getattr(self.robot, "command_log", ())
        return sum(1 for e in log if e["command"].startswith("move") and e["outcome"] != "refused")

    def camera_pose(self) -> NDArray[np.float64]:
        """T_W_C of the camera now (mm): world <- base <- flange <- camera, all true."""
        return self.camera.pose_source()

    def reseed(self, *key: int) -> None:
        """Restart the camera noise and the landing error of the current pose from (cell seed, *key): a
        view's images then depend only on the view, not on what was captured or how the robot got there, so
        a resumed run reproduces an uninterrupted one exactly."""
        self.camera.rng = np.random.default_rng([self.seed, *key])
        if self.world is not None:
            self._landing_rng = np.random.default_rng([self.seed, *key, 1])
            self._moves_seen = self._moves_made()
            self._landing = self.world.landing_error(self._landing_rng)


def build_sim_cell(
    cfg: CellConfig,
    part_W: trimesh.Trimesh | None,
    part_material: MaterialConfig | None = None,
    seed: int | None = None,
) -> SimCell:
    """Compose world, scene, renderer, clock, robot, projector and camera for ``cfg``; ``part_W`` is the
    (actual) part where the recipe places it, in world coordinates (mm), or None for an empty table; the
    world's placement error moves it. ``seed`` overrides ``cfg.sim.seed`` for the noise (the world is drawn
    from ``world.seed`` or ``sim.seed``)."""
    world = build_world(cfg)
    T_place_W = np.eye(4)
    if part_W is not None and len(part_W.faces):
        centre = part_W.bounds.mean(axis=0)
        T_place_W = place_about(world.placement, centre)
        part_W = part_W.copy().apply_transform(T_place_W)
    scene = Scene.from_meshes(part_W, cfg.sim, part_material)
    renderer = SceneRenderer(
        world.sensor,
        cfg.sim,
        scene,
        projector_distortion=world.projector_distortion if world.projector_distortion.any() else None,
        microstructure_seed=world.seed if world.config.microstructure else None,
    )
    clock = SimClock()
    robot = SimRobot(cfg.robot, clock=clock, obstacles_W=part_W, tool_body_T=sensor_body_points_T(cfg))
    projector = SimProjector(cfg.sensor.projector)
    T_W_B, T_T_C = cfg.robot.T_W_B.matrix(), world.sensor.T_T_C.matrix()
    seed = cfg.sim.seed if seed is None else seed
    rng = np.random.default_rng(seed)
    cell: SimCell

    def camera_pose() -> NDArray[np.float64]:
        return T_W_B @ cell.flange_pose() @ T_T_C

    camera = SimCamera(cfg.sensor.camera, renderer, projector, pose_source=camera_pose, clock=clock, rng=rng)
    cell = SimCell(
        cfg,
        scene,
        renderer,
        clock,
        robot,
        projector,
        camera,
        part_W,
        seed,
        world=world,
        T_place_W=T_place_W,
        _landing_rng=np.random.default_rng([seed, 1]),
    )
    return cell
