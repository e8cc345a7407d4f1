"""Replay devices: serve a fixture written by :class:`drivers.recording.RecordingProxy` (docs/fixtures.md).

Replay is strict, like a transcript: each call must be the next recorded one with equal arguments (arrays
compared exactly); it returns the recorded result or raises the recorded error. A call out of order or past
the end raises DeviceProtocolError naming the fixture, so a replay never answers something it did not see.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
import yaml

from cell.contracts import (
    CameraSettings,
    Envelope,
    Frame,
    MarkerScreen,
    ProjectorHooks,
    ProjectorSource,
    ProjectorStatus,
    RobotState,
)
from cell.errors import ConfigError, DeviceProtocolError
from cell.glass.config import GlassCameraConfig, GlassRigConfig
from drivers.recording import FIXTURE_FORMAT, decode

DEFAULT_DIR = Path(__file__).resolve().parent / "fixtures" / "replay"


def _equal(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (
            isinstance(a, np.ndarray)
            and isinstance(b, np.ndarray)
            and a.shape == b.shape
            and bool(np.array_equal(a, b))
        )
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b))
    return a == b


class ReplayDevice:
    """The common part: load a fixture directory and serve its calls in order."""

    kind = ""

    def __init__(self, config: Any = None, *, fixture: str | Path | None = None) -> None:
        opts = getattr(config, "options", {}) or {}
        path = Path(fixture or opts.get("fixture") or DEFAULT_DIR / getattr(config, "name", ""))
        spec = path / "fixture.yaml"
        if not spec.is_file():
            raise ConfigError(
                "replay fixture not found; record one with drivers.recording.RecordingProxy", path=str(spec)
            )
        doc = yaml.safe_load(spec.read_text(encoding="utf-8"))
        if doc.get("format") != FIXTURE_FORMAT or doc.get("kind") != self.kind:
            raise ConfigError(f"not a format-{FIXTURE_FORMAT} {self.kind} fixture", path=str(spec))
        with np.load(path / "arrays.npz") as arrays:
            self._properties = {k: decode(v, arrays) for k, v in doc["properties"].items()}
            self._calls = [
                (
                    c["method"],
                    decode(c["args"], arrays),
                    c.get("kwargs", {}),
                    decode(c.get("result"), arrays),
                    decode(c.get("error"), arrays),
                )
                for c in doc["calls"]
            ]
        self._path = path
        self._index = 0
        self.name = self._properties["name"]

    def _replay(self, method: str, *args: Any) -> Any:
        if self._index >= len(self._calls):
            raise DeviceProtocolError(
                self.name,
                f"replay {self._path}: call {method}{args!r} past the end "
                f"of the {len(self._calls)} recorded calls",
            )
        rec_method, rec_args, _, result, error = self._calls[self._index]
        if rec_method != method or not _equal(tuple(rec_args), tuple(args)):
            raise DeviceProtocolError(
                self.name,
                f"replay {self._path}: call {self._index} was recorded as "
                f"{rec_method}{tuple(rec_args)!r}, got {method}{args!r}",
            )
        self._index += 1
        if error is not None:
            raise error
        return result

    @property
    def remaining(self) -> int:
        """Recorded calls not yet replayed."""
        return len(self._calls) - self._index

    def connect(self) -> None:
        self._replay("connect")

    def close(self) -> None:
        self._replay("close")


class ReplayCamera(ReplayDevice):
    kind = "camera"

    @property
    def serial(self) -> str:
        return self._properties["serial"]

    @property
    def model(self) -> str:
        return self._properties["model"]

    @property
    def resolution(self) -> tuple[int, int]:
        return tuple(self._properties["resolution"])

    def configure(self, settings: CameraSettings) -> CameraSettings:
        return self._replay("configure", settings)

    def trigger(self) -> None:
        self._replay("trigger")

    def grab(self, timeout_ms: float) -> Frame:
        return self._replay("grab", timeout_ms)


class ReplayProjector(ProjectorHooks, ReplayDevice):
    kind = "projector"

    @property
    def resolution(self) -> tuple[int, int]:
        return tuple(self._properties["resolution"])

    def set_power(self, on: bool) -> None:
        self._replay("set_power", on)

    def set_source(self, source: ProjectorSource) -> None:
        self._replay("set_source", source)

    def status(self) -> ProjectorStatus:
        return self._replay("status")

    def show(self, image: np.ndarray) -> None:
        self._replay("show", np.asarray(image))

    def load_sequence(self, images: Sequence[np.ndarray]) -> None:
        self._replay("load_sequence", tuple(np.asarray(i) for i in images))

    def step(self) -> int:
        return self._replay("step")


class ReplayRobot(ReplayDevice):
    kind = "robot"

    @property
    def envelope(self) -> Envelope:
        return self._properties["envelope"]

    def state(self) -> RobotState:
        return self._replay("state")

    def tool_pose(self) -> np.ndarray:
        return self._replay("tool_pose")

    def joints(self) -> np.ndarray:
        return self._replay("joints")

    def move_linear(self, T_B_T: np.ndarray, speed_mm_s: float, accel_mm_s2: float) -> None:
        self._replay("move_linear", np.asarray(T_B_T, dtype=np.float64), speed_mm_s, accel_mm_s2)

    def move_joint(self, joints_rad: np.ndarray, speed_rad_s: float, accel_rad_s2: float) -> None:
        self._replay("move_joint", np.asarray(joints_rad, dtype=np.float64), speed_rad_s, accel_rad_s2)

    def stop(self) -> None:
        self._replay("stop")


class ReplayRigCamera:
    """A camera of a replayed glass rig: its identity comes from the rig config, since the fixture holds the
    rig's own calls only (connect, close, grab_all). Driving the camera directly was never recorded, so every
    call on it raises DeviceProtocolError."""

    def __init__(self, rig: str, cfg: GlassCameraConfig) -> None:
        self.name = cfg.name
        self._rig = rig
        self._cfg = cfg

    @property
    def serial(self) -> str:
        return self._cfg.serial

    @property
    def model(self) -> str:
        return self._cfg.model

    @property
    def resolution(self) -> tuple[int, int]:
        return (self._cfg.width_px, self._cfg.height_px)

    def _unrecorded(self, method: str) -> NoReturn:
        raise DeviceProtocolError(
            self.name,
            f"{method}() on a camera of the replayed rig '{self._rig}' was not recorded; "
            "the rig fixture replays connect, close and grab_all only",
        )

    def connect(self) -> None:
        self._unrecorded("connect")

    def close(self) -> None:
        self._unrecorded("close")

    def configure(self, settings: CameraSettings) -> CameraSettings:
        self._unrecorded("configure")

    def trigger(self) -> None:
        self._unrecorded("trigger")

    def grab(self, timeout_ms: float) -> Frame:
        self._unrecorded("grab")


class ReplayGlassRig(ReplayDevice):
    """A GlassRig served from a ``glass_rig`` fixture; cameras and screen from ``config`` (the rig config the
    fixture was recorded with: fixture format 1 stores only the rig's name among its properties)."""

    kind = "glass_rig"

    def __init__(self, config: GlassRigConfig, *, fixture: str | Path | None = None) -> None:
        super().__init__(config, fixture=fixture)
        if self.name != config.name:
            raise ConfigError(
                f"fixture recorded rig '{self.name}' but the config is rig '{config.name}'",
                path=str(self._path / "fixture.yaml"),
            )
        self._cameras = [ReplayRigCamera(config.name, c) for c in config.cameras]
        s = config.screen
        self._screen = MarkerScreen(s.T_W_S.matrix(), s.dots_mm(), s.dot_diameter_mm)

    @property
    def cameras(self) -> list[ReplayRigCamera]:
        return self._cameras

    @property
    def screen(self) -> MarkerScreen:
        return self._screen

    def grab_all(self, timeout_ms: float) -> list[Frame]:
        return list(self._replay("grab_all", timeout_ms))
