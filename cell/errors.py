"""One small error hierarchy for the whole cell.

The controller decides what to do with an error by its class: device timeouts and protocol errors are
retryable, device faults pause for the operator, configuration/calibration/planning errors stop a job before
it moves anything. Every message names the file, field or device and says what to do.
"""

from __future__ import annotations


class CellError(Exception):
    """Base class of every error the cell raises on purpose."""

    exit_code = 1


class ConfigError(CellError):
    """A config, recipe or input file is missing or invalid. Nothing has been written or moved."""

    exit_code = 2

    def __init__(self, message: str, *, path: str | None = None, field: str | None = None) -> None:
        self.path = path
        self.field = field
        named = [part for part in (path, f"field '{field}'" if field else None) if part]
        where = "".join(f"{part}: " for part in named)
        super().__init__(f"{where}{message}")


class DeviceError(CellError):
    """Base of the errors a device raises; ``device`` names it as the cell config does."""

    retryable = False

    def __init__(self, device: str, message: str) -> None:
        self.device = device
        super().__init__(f"{device}: {message}")


class DeviceTimeout(DeviceError):
    """The device did not answer in time. Retrying may help."""

    retryable = True


class DeviceProtocolError(DeviceError):
    """The device answered something the driver cannot parse (garbled reply, wrong echo)."""

    retryable = True


class DeviceFault(DeviceError):
    """The device reports a fault (lamp error, protective stop, refused motion). Needs the operator."""


class MotionStopped(DeviceFault):
    """A move was stopped on request (a pause, Ctrl-C, SIGTERM) before it reached its target; the arm
    decelerated along its path and stands wherever that ended."""


class DeviceLibraryError(DeviceFault):
    """The device's own library raised an error of its own kind (ur_rtde's RuntimeError, a GenApi error);
    wrapped with the device's name so that the run pauses for the operator instead of faulting."""


class StorageError(CellError):
    """A folder the cell writes cannot take a write: the disk is full, the file system read-only, or the
    folder not ours. ``path`` names the folder; the message says what to do. A run under way pauses on it
    (its views on disk are whole); elsewhere it ends the command with exit code 1."""

    def __init__(self, message: str, *, path: str | None = None) -> None:
        self.path = path
        super().__init__(message)


class ViewProcessingError(CellError):
    """A view's background work (its decode and own analysis, run while the robot moves on) failed with an
    error of no kind the cell handles: the view is not measured, and the run stops, naming the view and the
    cause, instead of carrying on without it."""

    def __init__(self, view: int, cause: BaseException) -> None:
        self.view = view
        super().__init__(
            f"view {view}: its processing failed ({type(cause).__name__}: {cause}); the view is not counted "
            "as measured (`cell resume` measures it again once the cause is fixed)"
        )


class CalibrationError(CellError):
    """A calibration routine failed or would be worse than the active calibration."""


class RoutinePaused(CalibrationError):
    """A calibration or verification routine paused safely (Ctrl-C, a device asking for the operator): not a
    failure; the same command on the same folder resumes it. Exit code 3, as a paused inspection's."""

    exit_code = 3


class PlanningError(CellError):
    """No viewpoint plan satisfies the constraints, or a pose is unreachable."""


class CalledOff(Exception):
    """Work started ahead stopped at its next step because its result is no longer wanted (a registration
    begun beside an evaluation that then asked for more views, or a run that pauses): not a fault, and nothing
    of that work is kept."""
