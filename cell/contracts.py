"""What a device of each kind is: runtime-checkable Protocols and the value types they exchange.

Every device kind has up to three implementations side by side: a real driver (``drivers/``), a simulated one
(``fakes/``, backed by the scene simulator) and a replay one (``fakes/``, backed by a recorded fixture). The
controller only ever sees these Protocols; the cell config decides which implementation it gets.

Units: mm, rad, ms for exposure and timeouts, seconds for timestamps. Poses are 4x4 float64 ``T_<to>_<from>``.
"""

from __future__ import annotations

import time
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

    def switch_on(self) -> None:
        """Make the projector ready to show patterns (power, video input) and blank it."""
        ...

    def ready(self) -> bool:
        """Whether it can show patterns now (:attr:`ProjectorStatus.ready`)."""
        ...

    def blank(self) -> None:
        """Light nothing: between stacks, and whenever the run stops."""
        ...


class ProjectorHooks:
    """:meth:`Projector.switch_on`, :meth:`~Projector.ready` and :meth:`~Projector.blank` over the
    Protocol's primitives, written once: the projector classes inherit them (one whose start-up differs
    overrides them)."""

    def switch_on(self: Projector) -> None:
        self.set_power(True)
        self.set_source(ProjectorSource.HDMI)
        self.blank()

    def ready(self: Projector) -> bool:
        return self.status().ready

    def blank(self: Projector) -> None:
        w, h = self.resolution
        self.show(np.zeros((h, w), np.uint8))


class Clock(Protocol):
    """Time in seconds as a device sees it: ``time.monotonic`` on a real cell, the simulated clock in
    fakes."""

    def now(self) -> float: ...

    def sleep(self, dt_s: float) -> None: ...


class SystemClock:
    """The host's monotonic clock (what :class:`drivers.hdmi_display.HdmiDisplay` stamps presents with)."""

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, dt_s: float) -> None:
        if dt_s > 0:
            time.sleep(dt_s)


@runtime_checkable
class TimedProjector(Protocol):
    """A projector that says when its last frame was presented at its input (vsync flip), on ``clock``.

    ``timing`` is the cell's knowledge of the link (``cell.config.ProjectorTiming``: refresh rate, DLP or not,
    measured or assumed latency). The scan waits from ``last_present_s`` for the latency before a software
    trigger; without this capability (replay) it cannot wait and triggers at once."""

    @property
    def clock(self) -> Clock: ...

    @property
    def timing(self) -> Any: ...

    @property
    def last_present_s(self) -> float: ...


@runtime_checkable
class SequenceProjector(Protocol):
    """A projector that runs its loaded pattern sequence by itself (DLP pattern mode) and fires its trigger
    output once per pattern into a camera in hardware-trigger mode."""

    def run_sequence(self, camera: Camera, count: int, timeout_ms: float) -> list[Frame | None]:
        """Flush the camera, start the sequence, grab ``count`` frames and stop. The result is indexed by
        pattern (position in the sequence), placed by the camera's frame ids; None where a frame was lost
        (an id skipped, or fewer frames than patterns). Refuses a camera not in hardware-trigger mode."""
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
    """The robot's operating mode, as a UR controller reports it (simplified). Only IDLE and RUNNING may
    move: UR robot_mode 7 (RUNNING: powered, brakes released). UR mode 5 (IDLE) has the brakes on."""

    DISCONNECTED = "disconnected"
    BOOTING = "booting"  # UR modes 1 (confirm safety), 2 (booting)
    POWER_OFF = "power_off"  # UR mode 3
    BRAKES_ON = "brakes_on"  # UR modes 4 (power on, brakes not yet released), 5 (idle), 6 (backdrive)
    IDLE = "idle"  # powered, brakes released, no program
    RUNNING = "running"  # a motion program is executing


@dataclass(frozen=True)
class RobotState:
    """Safety and program state of a robot (the UR RTDE safety status bits: reduced mode 1, protective stop 2,
    safeguard stop 4 (a guard, door or light curtain), emergency stop 5-7, violation 8, fault 9)."""

    mode: RobotMode
    protective_stop: bool = False
    emergency_stop: bool = False
    program_running: bool = False
    safeguard_stop: bool = False
    fault: bool = False
    violation: bool = False
    reduced: bool = False  # reduced speed limits active: motion allowed, but slower than commanded

    @property
    def normal(self) -> bool:
        """True when motion may be commanded: powered with brakes released, no stop, fault or violation."""
        return self.mode in (RobotMode.IDLE, RobotMode.RUNNING) and not (
            self.protective_stop or self.emergency_stop or self.safeguard_stop or self.fault or self.violation
        )

    @property
    def why_not_normal(self) -> str:
        """What keeps the robot from moving, in words for the operator ('' when normal)."""
        reasons = [
            name
            for flag, name in (
                (self.emergency_stop, "emergency stop"),
                (self.protective_stop, "protective stop"),
                (self.safeguard_stop, "safeguard stop (a guard is open)"),
                (self.fault, "fault"),
                (self.violation, "safety violation"),
            )
            if flag
        ]
        if self.mode not in (RobotMode.IDLE, RobotMode.RUNNING):
            reasons.insert(0, f"mode {self.mode.value} (needs power on and brakes released)")
        return ", ".join(reasons)


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
        """Move the flange along a straight line to ``T_B_T``; blocks until there, polling the motion (it
        runs asynchronously on the device) so that :meth:`stop` can end it. Raises on refusal/stop
        (MotionStopped when :meth:`stop` ended it)."""
        ...

    def move_joint(self, joints_rad: NDArray[np.float64], speed_rad_s: float, accel_rad_s2: float) -> None:
        """Move in joint space to ``joints_rad``; blocks until there like :meth:`move_linear`."""
        ...

    def stop(self) -> None:
        """Decelerate and stop any motion now. Safe to call from a signal handler or another thread while
        a move blocks: the arm starts to decelerate within one poll period and the move raises
        MotionStopped."""
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


def expected_frame_id(camera: Camera) -> int | None:
    """The id the camera's next frame will carry (``next_frame_id``), when the camera can tell; read right
    after a flush, it lets :func:`frames_by_id` see a lost *first* frame of a sequence."""
    value = getattr(camera, "next_frame_id", None)
    return None if value is None else int(value)


def grab_ready(camera: Camera) -> list[Frame]:
    """Every frame the camera already holds (a grab that does not wait). A real driver keeps only a few
    buffers (4-8), so a sequence longer than that must be fetched while it runs, as a host thread would."""
    from cell.errors import DeviceTimeout

    out: list[Frame] = []
    while True:
        try:
            out.append(camera.grab(0.0))
        except DeviceTimeout:
            return out


def frames_by_id(
    camera: Camera,
    count: int,
    timeout_ms: float,
    *,
    first_id: int | None = None,
    received: Sequence[Frame] = (),
) -> list[Frame | None]:
    """Grab the rest of one sequence run (after the frames already ``received`` during it) and place every
    frame by the camera's frame id: pattern 0 is ``first_id`` (the camera's expected id when the run began;
    without it, the first frame received). A skipped id is a lost frame (None), so are missing frames at the
    end; without ``first_id`` a short run is all None (a lost first frame and a lost last one look alike).
    A frame id beyond the sequence is a DeviceProtocolError: the trigger fired more often than there are
    patterns."""
    from cell.errors import DeviceProtocolError, DeviceTimeout

    frames: list[Frame] = list(received)

    def first() -> int:
        return first_id if first_id is not None else frames[0].frame_id

    while not frames or frames[-1].frame_id - first() < count - 1:
        try:
            frames.append(camera.grab(timeout_ms))
        except DeviceTimeout:
            break
    out: list[Frame | None] = [None] * count
    if first_id is None and frames and frames[-1].frame_id - frames[0].frame_id < count - 1:
        return out  # frames missing and no known first id: a lost first frame would shift them all
    for f in frames:
        k = f.frame_id - first()
        if not 0 <= k < count:
            raise DeviceProtocolError(camera.name, f"frame id {f.frame_id} beyond the sequence of {count}")
        out[k] = f
    return out


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
