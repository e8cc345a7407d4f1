"""Simulated motorised board stage: puts calibration targets into the simulated world.

It implements :class:`cell.contracts.BoardStage` for a simulated cell. Placing a target changes what the
simulated camera renders (the cell's camera is given a renderer of the target in the world), so a calibration
routine sees the target only through camera images, exactly as on a real cell. The stage has a travel box
around its station (world mm); a pose outside it is refused with a DeviceFault naming the stage, like a real
stage's soft limits. ``pose_error`` (4x4, applied in the target frame) models where the stage really puts a
target relative to where it was asked to; the routines must not rely on it being identity.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import trimesh
from numpy.typing import NDArray

from cell.contracts import BoardKind, CalibrationBoard
from cell.errors import DeviceFault
from fakes.sim.board import WHITE_BOARD, TexturedBoardRenderer, board_texture, reference_board_mesh
from fakes.sim.render import SceneRenderer
from fakes.sim.scene import Scene


@dataclass
class SimBoardStage:
    """A motorised stage at ``station_W`` (world mm) that reaches targets within ``reach_xy_mm`` sideways and
    ``travel_z_mm`` (low, high) in height above the table. ``sim`` is the simulated cell (fakes.sim_cell)."""

    sim: Any
    name: str = "board-stage"
    station_W: tuple[float, float, float] = (-130.0, 90.0, 0.0)
    reach_xy_mm: float = 300.0
    travel_z_mm: tuple[float, float] = (0.0, 320.0)
    pose_error: NDArray[np.float64] = field(default_factory=lambda: np.eye(4))
    placed: tuple[CalibrationBoard, NDArray[np.float64]] | None = None  # what the world holds now (truth)
    _base: Any = None
    _connected: bool = False

    def connect(self) -> None:
        self._connected = True
        if self._base is None:
            self._base = self.sim.camera.renderer

    def close(self) -> None:
        self._connected = False

    def _check_reach(self, T_W_Bd: NDArray[np.float64]) -> None:
        p = np.asarray(T_W_Bd, dtype=np.float64)[:3, 3] - np.asarray(self.station_W)
        lo, hi = self.travel_z_mm
        if not lo <= p[2] <= hi:
            raise DeviceFault(
                self.name,
                f"cannot reach height {p[2]:.1f} mm above the table (travel {lo:g}..{hi:g} mm); "
                "choose heights within the stage's travel",
            )
        if float(np.hypot(p[0], p[1])) > self.reach_xy_mm:
            raise DeviceFault(
                self.name,
                f"cannot reach {np.hypot(p[0], p[1]):.0f} mm from its station "
                f"(reach {self.reach_xy_mm:g} mm)",
            )

    def place(self, board: CalibrationBoard, T_W_Bd: NDArray[np.float64]) -> None:
        if not self._connected:
            raise DeviceFault(self.name, "not connected; call connect() first")
        self._check_reach(T_W_Bd)
        actual = np.asarray(T_W_Bd, dtype=np.float64) @ self.pose_error
        base: SceneRenderer = self._base
        if board.kind is BoardKind.CHARUCO:
            printed = cv2.aruco.CharucoBoard(
                board.squares,
                board.square_mm,
                board.marker_mm,
                cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary)),
            )
            tex, ppm = board_texture(printed)
            renderer: Any = TexturedBoardRenderer(base, actual, tex, ppm)
        else:
            if board.kind is BoardKind.FLAT:
                mesh = reference_board_mesh(0.0, board.size_mm)
                material = WHITE_BOARD
            else:
                if board.mesh_path is None:
                    raise DeviceFault(self.name, f"target '{board.name}' has no mesh")
                mesh = trimesh.load_mesh(board.mesh_path)
                material = None
            renderer = SceneRenderer(
                base.sensor,
                base.sim,
                Scene.from_meshes(mesh.copy().apply_transform(actual), base.sim, material),
                projector_distortion=base.projector_distortion,
                microstructure_seed=base.microstructure_seed,
            )
        self.sim.camera.renderer = renderer
        self.placed = (board, actual)

    def clear(self) -> None:
        if self._base is not None:
            self.sim.camera.renderer = self._base
        self.placed = None
