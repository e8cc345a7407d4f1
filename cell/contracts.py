"""What a device of each kind is: runtime-checkable Protocols and the value types they exchange.

Every device kind has up to three implementations side by side: a real driver (``drivers/``), a simulated one
(``fakes/``, backed by the scene simulator) and a replay one (``fakes/``, backed by a recorded fixture). The
controller only ever sees these Protocols; the cell config decides which implementation it gets.

Units: mm, rad, ms for exposure and timeouts, seconds for timestamps. Poses are 4x4 float64 ``T_<to>_<from>``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray


# --------------------------------------------------------------------------------------------- projector
class ProjectorSource(StrEnum):
    """Which input the projector shows: the HDMI pattern stream or its internal test/black screen."""

    HDMI = "hdmi"
    INTERNAL = "internal"


@dataclass(frozen=True)
class ProjectorStatus:
    """A projector's health as its control port reports it."""

    powered: bool
    source: ProjectorSource
    lamp_hours: float
    temperature_c: float
    errors: tuple[str, ...] = ()

    @property
    def ready(self) -> bool:
        """True when the projector can show patterns: powered, on HDMI, no error."""
        return self.powered and self.source is ProjectorSource.HDMI and not self.errors


@runtime_checkable
class Projector(Protocol):
    """A DLP projector: control over serial, pixel-exact images over HDMI."""

    name: str

    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) in projector pixels."""
        ...

    def connect(self) -> None: ...

    def close(self) -> None: ...

    def set_power(self, on: bool) -> None: ...

    def set_source(self, source: ProjectorSource) -> None: ...

    def status(self) -> ProjectorStatus: ...

    def show(self, image: NDArray[np.uint8]) -> None:
        """Show an (H, W) uint8 image pixel-exact: no scaling, no colour management."""
        ...

    def load_sequence(self, images: Sequence[NDArray[np.uint8]]) -> None:
        """Hold a pattern sequence; :meth:`step` shows the next one. Loading shows nothing yet."""
        ...

    def step(self) -> int:
        """Show the next image of the loaded sequence and return its index (0-based)."""
        ...


# --------------------------------------------------------------------------------------------- camera
class TriggerMode(StrEnum):
    """How a camera starts an exposure."""

    FREE_RUN = "free_run"
    SOFTWARE = "software"
    HARDWARE = "hardware"  # an external line, e.g. the projector's frame sync


class PixelFormat(StrEnum):
    """Pixel formats the cell uses. MonoN frames arrive as uint8 (N=8) or uint16 (N=10, 12)."""

    MONO8 = "Mono8"
    MONO10 = "Mono10"
    MONO12 = "Mono12"
    RGB8 = "RGB8"

    @property
    def bit_depth(self) -> int:
        return {"Mono8": 8, "Mono10": 10, "Mono12": 12, "RGB8": 8}[self.value]


@dataclass(frozen=True)
class CameraSettings:
    """What :meth:`Camera.configure` sets. Exposure in ms, gain in dB."""

    exposure_ms: float = 10.0
    gain_db: float = 0.0
    pixel_format: PixelFormat = PixelFormat.MONO8
    trigger: TriggerMode = TriggerMode.SOFTWARE


@dataclass(frozen=True)
class Frame:
    """One grabbed image: pixels, when it was exposed (s, device clock) and what the device said of it."""

    pixels: NDArray[Any]
    timestamp_s: float
    frame_id: int
    metadata: dict[str, Any] = field(default_factory=dict)


@runtime_checkable
class Camera(Protocol):
    """An area camera (GenICam in the real cell)."""

    name: str

    @property
    def serial(self) -> str: ...

    @property
    def model(self) -> str: ...

    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        ...

    def connect(self) -> None: ...

    def close(self) -> None: ...

    def configure(self, settings: CameraSettings) -> CameraSettings:
        """Apply settings; returns what the device actually accepted (it may round exposure, say)."""
        ...

    def trigger(self) -> None:
        """Issue a software trigger (TriggerMode.SOFTWARE)."""
        ...

    def grab(self, timeout_ms: float) -> Frame:
        """Return the next frame or raise DeviceTimeout after ``timeout_ms``."""
        ...


# --------------------------------------------------------------------------------------------- robot
class RobotMode(StrEnum):
    """The robot's operating mode, as a UR controller reports it (simplified)."""

    DISCONNECTED = "disconnected"
    POWER_OFF = "power_off"
    IDLE = "idle"  # powered, brakes released, no program
    RUNNING = "running"  # a motion program is executing


@dataclass(frozen=True)
class RobotState:
    """Safety and program state of a robot."""

    mode: RobotMode
    protective_stop: bool = False
    emergency_stop: bool = False
    program_running: bool = False

    @property
    def normal(self) -> bool:
        """True when motion may be commanded: powered, no stop of any kind."""
        return self.mode in (RobotMode.IDLE, RobotMode.RUNNING) and not (
            self.protective_stop or self.emergency_stop
        )


@dataclass(frozen=True)
class Envelope:
    """Axis-aligned box in the base frame {B} (mm) that the tool flange must stay inside."""

    min_mm: tuple[float, float, float]
    max_mm: tuple[float, float, float]

    def contains(self, point_mm: NDArray[np.float64], tol_mm: float = 1e-9) -> bool:
        p = np.asarray(point_mm, dtype=np.float64)
        return bool(
            np.all(p >= np.asarray(self.min_mm) - tol_mm) and np.all(p <= np.asarray(self.max_mm) + tol_mm)
        )


@runtime_checkable
class Robot(Protocol):
    """A 6-axis arm that carries the sensor. Poses are ``T_B_T`` (tool flange in base), mm."""

    name: str

    @property
    def envelope(self) -> Envelope: ...

    def connect(self) -> None: ...

    def close(self) -> None: ...

    def state(self) -> RobotState: ...

    def tool_pose(self) -> NDArray[np.float64]:
        """Current ``T_B_T`` (4x4, mm)."""
        ...

    def joints(self) -> NDArray[np.float64]:
        """Current joint angles (rad), base to wrist 3."""
        ...

    def move_linear(self, T_B_T: NDArray[np.float64], speed_mm_s: float, accel_mm_s2: float) -> None:
        """Move the flange along a straight line to ``T_B_T``; blocks until there. Raises on refusal/stop."""
        ...

    def move_joint(self, joints_rad: NDArray[np.float64], speed_rad_s: float, accel_rad_s2: float) -> None:
        """Move in joint space to ``joints_rad``; blocks until there."""
        ...

    def stop(self) -> None:
        """Decelerate and stop any motion now."""
        ...


# --------------------------------------------------------------------------------------------- glass rig
@dataclass(frozen=True)
class MarkerScreen:
    """A diffuse screen with black marker dots at known world positions (mm)."""

    T_W_S: NDArray[np.float64]  # screen frame in world; the screen is the plane z=0 of {S}
    dots_mm: NDArray[np.float64]  # (N, 2) dot centres in the screen plane
    dot_diameter_mm: float


@runtime_checkable
class GlassRig(Protocol):
    """Several cameras triggered together looking at a marker screen reflected in a glass pane."""

    name: str

    @property
    def cameras(self) -> Sequence[Camera]: ...

    @property
    def screen(self) -> MarkerScreen: ...

    def connect(self) -> None: ...

    def close(self) -> None: ...

    def grab_all(self, timeout_ms: float) -> list[Frame]:
        """Trigger every camera together and return one frame per camera, in camera order."""
        ...


# --------------------------------------------------------------------------------------------- board stage
class BoardKind(StrEnum):
    """What a calibration target is: a flat white board, a printed ChArUco board, or a solid artefact (gauge,
    sphere) given by its mesh."""

    FLAT = "flat"
    CHARUCO = "charuco"
    MESH = "mesh"


@dataclass(frozen=True)
class CalibrationBoard:
    """A calibration target and its frame {Bd} (mm).

    FLAT: the top face is the plane z = 0 of {Bd}, centred on its origin, ``size_mm`` wide. CHARUCO: the
    printed face is z = 0, origin at the print's top-left corner, x right and y down along the print (OpenCV's
    board frame); ``squares``, ``square_mm``, ``marker_mm`` and the ArUco ``dictionary`` name describe it.
    MESH: ``mesh_path`` is the artefact's STL in its own frame {Bd} (its mounting drawing)."""

    name: str
    kind: BoardKind
    size_mm: tuple[float, float] = (600.0, 450.0)
    squares: tuple[int, int] = (11, 8)
    square_mm: float = 15.0
    marker_mm: float = 11.0
    dictionary: str = "DICT_5X5_100"
    mesh_path: str | None = None


@runtime_checkable
class BoardStage(Protocol):
    """Whatever puts a calibration target where a routine needs it: a motorised (linear or multi-axis) stage,
    or the operator asked on the console to place the target and confirm. Poses are ``T_W_Bd`` (target
    frame in the world, mm): the routine's request; where the target really ends up is for the routine to
    measure, never to assume beyond the stage's accuracy."""

    name: str

    def connect(self) -> None: ...

    def close(self) -> None: ...

    def place(self, board: CalibrationBoard, T_W_Bd: NDArray[np.float64]) -> None:
        """Put ``board`` at ``T_W_Bd``; blocks until it is there. Raises DeviceFault naming the stage when the
        pose is outside its travel (e.g. a height it does not reach) or the operator declines."""
        ...

    def clear(self) -> None:
        """Take the target out of the sensor's view."""
        ...
