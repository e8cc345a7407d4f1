"""Simulated back-imaging rig behind the :class:`cell.contracts.GlassRig` contract.

The cameras render the pane the rig holds (:mod:`fakes.sim.glass`) or, while :meth:`SimGlassRig.place_board`
has put the calibration board in, the level dot board at that height. Each grab adds fresh sensor noise from
the rig's seeded generator, so a run is reproducible.
"""

from __future__ import annotations

import time

import numpy as np
import trimesh
from numpy.typing import NDArray

from cell.contracts import CameraSettings, Frame, MarkerScreen
from cell.errors import DeviceError
from cell.glass.config import GlassCameraConfig, GlassRigConfig
from fakes.sim.glass import GlassScene, board_radiance, expose


class SimGlassCamera:
    """One rig camera; frames come from its rig's scene."""

    def __init__(self, rig: SimGlassRig, cfg: GlassCameraConfig) -> None:
        self._rig = rig
        self.cfg = cfg
        self.name = cfg.name
        self._settings = CameraSettings(exposure_ms=cfg.exposure_ms, gain_db=cfg.gain_db)
        self._connected = False
        self._frame_id = 0
        self._pending = False

    @property
    def serial(self) -> str:
        return self.cfg.serial

    @property
    def model(self) -> str:
        return self.cfg.model

    @property
    def resolution(self) -> tuple[int, int]:
        return (self.cfg.width_px, self.cfg.height_px)

    def connect(self) -> None:
        self._connected = True

    def close(self) -> None:
        self._connected = False

    def configure(self, settings: CameraSettings) -> CameraSettings:
        self._settings = settings
        return settings

    def trigger(self) -> None:
        self._pending = True

    def grab(self, timeout_ms: float) -> Frame:
        if not self._connected:
            raise DeviceError(self.name, "not connected; call connect() first")
        self._pending = False
        self._frame_id += 1
        pixels = self._rig.render(self)
        return Frame(pixels, time.monotonic(), self._frame_id, {"camera": self.name})


class SimGlassRig:
    """Cameras, screen and (simulated) pane of a back-imaging rig; the pane is the *actual* one, world mm."""

    def __init__(self, cfg: GlassRigConfig, pane_W: trimesh.Trimesh | None) -> None:
        self.cfg = cfg
        self.name = cfg.name
        self._scene = GlassScene(cfg, pane_W) if pane_W is not None else None
        self._cameras = [SimGlassCamera(self, c) for c in cfg.cameras]
        self._rng = np.random.default_rng(cfg.seed) if cfg.noise else None
        self._board_height: float | None = None
        self._screen_position = 0
        self._radiance: dict[str, NDArray[np.float64]] = {}  # noise-free signal per camera, per placement

    @property
    def cameras(self) -> list[SimGlassCamera]:
        return self._cameras

    @property
    def screen(self) -> MarkerScreen:
        """The marker screen at its current position (see :meth:`move_screen`)."""
        s = self.cfg.screen
        pose = s.T_W_S if self._screen_position == 0 else s.second_T_W_S
        assert pose is not None  # move_screen refuses position 1 without a second_T_W_S
        return MarkerScreen(pose.matrix(), s.dots_mm(), s.dot_diameter_mm)

    def move_screen(self, position: int) -> MarkerScreen:
        """Simulation of the screen's motion stage for the multi-projection method (2.4): position 0 is
        ``screen.T_W_S``, 1 is ``screen.second_T_W_S``. Returns the screen there."""
        if position not in (0, 1) or (position == 1 and self.cfg.screen.second_T_W_S is None):
            raise DeviceError(
                self.name,
                f"no screen position {position}; the rig config defines "
                "screen.T_W_S (0) and, for a second position, screen.second_T_W_S (1)",
            )
        self._screen_position = position
        if self._scene is not None:
            self._scene.T_W_S = self.screen.T_W_S
        self._radiance.clear()
        return self.screen

    def connect(self) -> None:
        for c in self._cameras:
            c.connect()

    def close(self) -> None:
        for c in self._cameras:
            c.close()

    def place_board(self, height_mm: float | None) -> None:
        """Simulation hook for the vector calibration: the level board at ``height_mm`` (None removes it)."""
        self._board_height = height_mm
        self._radiance.clear()

    def render(self, cam: SimGlassCamera) -> NDArray:
        """A frame of ``cam`` for the current placement (noise-free signal cached, fresh noise each time)."""
        if cam.name not in self._radiance:
            if self._board_height is not None:
                rate = board_radiance(cam.cfg, self.cfg.board, self._board_height, self.cfg.ambient_e_per_ms)
            elif self._scene is not None:
                rate = self._scene.radiance(self._scene.trace(cam.cfg))
            else:
                raise DeviceError(self.name, "no pane in the rig and no calibration board placed")
            self._radiance[cam.name] = rate
        s = cam._settings
        return expose(cam.cfg, self._radiance[cam.name], self._rng, s.exposure_ms, s.gain_db)

    def grab_all(self, timeout_ms: float) -> list[Frame]:
        for c in self._cameras:
            c.trigger()
        return [c.grab(timeout_ms) for c in self._cameras]
