"""One simulated world shared by the simulated robot, projector and camera (DESIGN: fakes that share a world).

The world is not the cell config (fakes/sim/world.py): it is drawn from the config's ``world:`` section. The
robot reports its pose through the config's nominal kinematics, as a real UR does from its encoders and its
nominal DH table; the world puts the flange where the true kinematics (link lengths, joint zeros) and the
move's landing error put it, and the camera renders from

    T_W_C = T_W_B @ fk_true(q + joint_zero) @ landing @ T_T_C_true

with the true hand-eye, lenses and projector pose. The part sits where the placement error puts it.
"""

from __future__ import annotations

import zlib
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

HELD_RAD = 1e-9  # a move that changes no joint by more (rad, 6e-8 deg) leaves the arm where it landed


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
    world: World
    seed: int = 0
    T_place_W: NDArray[np.float64] = field(default_factory=lambda: np.eye(4))
    _landing: NDArray[np.float64] = field(default_factory=lambda: np.eye(4))
    _moves_seen: int = 0  # moves made when the flange last landed
    _moves_at_reseed: int = 0  # moves made at the last reseed
    _landing_rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(0))

    def flange_pose(self) -> NDArray[np.float64]:
        """T_B_T where the flange really is (true kinematics, the last move's landing error); mm."""
        moves = self._moves_made()
        if moves != self._moves_seen:  # the arm has gone somewhere since: it landed elsewhere in the ball
            self._moves_seen = moves
            self._landing = self.world.landing_error(self._landing_rng)
        return self.world.true_flange(self.robot.joints()) @ self._landing

    def _moves_made(self) -> int:
        """Moves the robot has made that took it somewhere. Refused commands and stops do not move it, and
        a move to where it stands (a calibration routine's joint move to the pose it holds while the stage
        moves the board) leaves the arm where it landed: a real arm that does not move does not land again.
        Judged by how far the move took the joints (the command log's ``moved_rad``, end against start), not
        by its duration: an IK solution of the pose it holds differs from its joints by round-off (~1e-15
        rad), which takes a tiny but non-zero time."""
        log = getattr(self.robot, "command_log", ())
        return sum(
            1
            for e in log
            if e["command"].startswith("move") and e["outcome"] != "refused" and e["moved_rad"] > HELD_RAD
        )

    def camera_pose(self) -> NDArray[np.float64]:
        """T_W_C of the camera now (mm): world <- base <- flange <- camera, all true."""
        return self.camera.pose_source()

    def end_view(self) -> None:
        """A view's frames are all taken: the camera's renderer drops the pose's geometry, which no later view
        reuses (each is at a pose of its own; a view taken again computes it anew, the same)."""
        self.camera.renderer.forget_poses()

    def reseed(self, *key: int, arrived: tuple[int, ...] | None = None) -> None:
        """Restart the camera noise from (cell seed, *key), and the landing error from (cell seed, *arrived)
        when the arm has moved since the last reseed (``arrived``: the key of the view for which it came to
        the pose it holds, default ``key``; a held pose keeps its landing). A view's images then depend only
        on the view, not on what was captured or how the robot got there, so a resumed run reproduces an
        uninterrupted one exactly, also when it resumes at a view of a held pose: there the arm comes from
        home, and the draw of the view it arrived for gives it the landing the uninterrupted run kept."""
        self.camera.rng = np.random.default_rng([self.seed, *key])
        rng = np.random.default_rng([self.seed, *(key if arrived is None else arrived), 1])
        landing = self.world.landing_error(rng)  # drawn either way: the same stream after it
        moves = self._moves_made()
        if moves != self._moves_at_reseed:  # it came here since the last view (from home on a resumed run)
            self._moves_seen, self._landing = moves, landing
        self._moves_at_reseed, self._landing_rng = moves, rng


def noise_seed(cfg: CellConfig, seed: int | None = None, stream: tuple[int | str, ...] = ()) -> int:
    """The seed of a simulated cell's camera noise and robot landing errors: ``seed`` (default the cell's
    ``sim.seed``), or, with a ``stream``, one drawn from it and the stream together (a text by its CRC-32,
    stable across processes, unlike ``hash``). A calibration routine passes (its --seed, its kind), so that
    every routine of one world and every world of one routine seed draw their own noise; an inspection's
    --seed is the seed itself."""
    base = cfg.sim.seed if seed is None else seed
    if not stream:
        return base
    keys = [zlib.crc32(k.encode()) if isinstance(k, str) else k for k in stream]
    return int(np.random.SeedSequence([base, *keys]).generate_state(1)[0])


def build_sim_cell(
    cfg: CellConfig,
    part_W: trimesh.Trimesh | None,
    part_material: MaterialConfig | None = None,
    seed: int | None = None,
    stream: tuple[int | str, ...] = (),
) -> SimCell:
    """Compose world, scene, renderer, clock, robot, projector and camera for ``cfg``; ``part_W`` is the
    (actual) part where the recipe places it, in world coordinates (mm), or None for an empty table; the
    world's placement error moves it. ``seed`` overrides ``cfg.sim.seed`` for the noise and ``stream`` is
    mixed into it (:func:`noise_seed`; the world is drawn from ``world.seed`` or ``sim.seed``)."""
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
    seed = noise_seed(cfg, seed, stream)
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
        world,
        seed,
        T_place_W=T_place_W,
        _landing_rng=np.random.default_rng([seed, 1]),
    )
    return cell
