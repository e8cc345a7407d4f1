"""The cell controller: a declared state machine that runs a job view by view, with checkpoints.

States (``transitions`` HierarchicalGraphMachine, ``auto_transitions=False`` so no generated ``to_X``
bypasses a guard, ``queued=True``, exceptions routed to :meth:`Controller._on_exception`)::

    idle -> connecting -> homing -> planning -> scanning(moving -> capturing ... -> decoding)
         -> evaluating -> replanning -> scanning ... -> registering -> reporting -> rendering -> done
    any active state -> paused (operator), faulted (unrecoverable), aborted (not once the verdict is out)
    idle -> resuming -> connecting -> homing -> the phase the checkpoint records

Motion is only commanded while the robot is in a normal mode and the projector is ready: every trigger after
which the robot may move is guarded into ``paused`` (:func:`_transitions`).

The controller never imports a driver: it receives a :class:`cell.devices.DeviceBundle` and a job (what to
plan, capture, decode, evaluate, register and report: :class:`Job`); the projector's start-up and blanking
are its own hooks. After each completed view the view folder exists whole (see :mod:`cell.runs`); the
checkpoint (:class:`cell.run_data.Checkpoint`) records the plan and the phase, so a killed run resumes.

Pipelining: a view's work (the job's ``decode``: decoding, triangulation and the view's own analysis, all
written into its folder) runs in one worker thread, fed one view at a time, while the robot moves to the next
view; the view counts as done once its folder exists whole (the durable result). A failure there surfaces in
the main thread as that view's error (:class:`cell.errors.ViewProcessingError` for a bug), never lost. After
the last view only that view's work and the whole-cloud steps remain. ``reporting`` publishes the verdict
(the job's ``report``: report.json, a ``verdict`` journal line, the checkpoint's summary); ``rendering`` then
writes the rest of the report (the job's ``render``: pictures, page, 3D view), so the verdict never waits for
it.
"""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from transitions.extensions import HierarchicalGraphMachine

from cell.config import RobotConfig
from cell.devices import DeviceBundle
from cell.errors import (
    CalledOff,
    CellError,
    ConfigError,
    DeviceError,
    DeviceFault,
    MotionStopped,
    PlanningError,
    StorageError,
    ViewProcessingError,
)
from cell.memory import map_large_arrays, release_free_heap
from cell.planning.motion import Move
from cell.run_data import Checkpoint, Evaluation, Phase, View
from cell.runs import RunFolder
from cell.storage import is_storage_error, require_room, storage_error

ACTIVE = [
    "connecting",
    "homing",
    "planning",
    "scanning",
    "evaluating",
    "replanning",
    "registering",
    "reporting",
    "rendering",
    "resuming",
]
# the verdict is published when rendering starts: it stands, the run can pause there but not be aborted
ABORTABLE = [s for s in ACTIVE if s != "rendering"]
STATES: list[Any] = [
    "idle",
    "connecting",
    "homing",
    "planning",
    {"name": "scanning", "children": ["moving", "capturing", "decoding"]},
    "evaluating",
    "replanning",
    "registering",
    "reporting",
    "rendering",
    "done",
    "paused",
    "faulted",
    "aborted",
    "resuming",
]
TERMINAL = {"done", "paused", "faulted", "aborted"}


def _transitions() -> list[dict[str, Any]]:
    # Every trigger after which the robot may move is declared first with the ``unsafe`` guard into
    # ``paused`` (the first matching transition wins): when the robot is not in a normal mode or the projector
    # is not ready, the run stops for the operator; it never falls through to a transition that skips views.
    unsafe = {"conditions": "unsafe", "dest": "paused", "before": "_explain_unsafe"}
    moving = [
        ("connected", "connecting"),
        ("homed", "homing"),
        ("planned", "planning"),
        ("arrived", "scanning_moving"),
        ("captured", "scanning_capturing"),
        ("replanned", "replanning"),
    ]
    return [
        {"trigger": "start", "source": "idle", "dest": "connecting"},
        {"trigger": "resume", "source": ["idle", "paused"], "dest": "resuming"},
        {"trigger": "resumed", "source": "resuming", "dest": "connecting"},
        *({"trigger": trigger, "source": source, **unsafe} for trigger, source in moving),
        {"trigger": "connected", "source": "connecting", "dest": "homing"},
        # after homing, go to the phase the checkpoint records (first matching condition wins)
        {"trigger": "homed", "source": "homing", "dest": "planning", "conditions": "needs_plan"},
        {"trigger": "homed", "source": "homing", "dest": "scanning_moving", "conditions": "views_pending"},
        {"trigger": "homed", "source": "homing", "dest": "evaluating", "conditions": "phase_is_scanning"},
        {"trigger": "homed", "source": "homing", "dest": "registering", "conditions": "phase_is_registering"},
        {"trigger": "homed", "source": "homing", "dest": "reporting", "conditions": "phase_is_reporting"},
        {"trigger": "homed", "source": "homing", "dest": "rendering", "conditions": "phase_is_rendering"},
        {"trigger": "planned", "source": "planning", "dest": "scanning_moving"},
        {"trigger": "arrived", "source": "scanning_moving", "dest": "scanning_capturing"},
        {
            "trigger": "captured",
            "source": "scanning_capturing",
            "dest": "scanning_moving",
            "conditions": "views_pending",
        },
        {"trigger": "captured", "source": "scanning_capturing", "dest": "scanning_decoding"},
        {"trigger": "no_more_views", "source": "scanning_moving", "dest": "scanning_decoding"},
        {"trigger": "decoded", "source": "scanning_decoding", "dest": "evaluating"},
        {"trigger": "needs_views", "source": "evaluating", "dest": "replanning"},
        {"trigger": "qualified", "source": "evaluating", "dest": "registering"},
        {
            "trigger": "replanned",
            "source": "replanning",
            "dest": "scanning_moving",
            "conditions": "views_pending",
        },
        {"trigger": "replanned", "source": "replanning", "dest": "registering"},
        {"trigger": "registered", "source": "registering", "dest": "reporting"},
        {"trigger": "reported", "source": "reporting", "dest": "rendering", "conditions": "has_page"},
        {"trigger": "reported", "source": "reporting", "dest": "done"},
        {"trigger": "rendered", "source": "rendering", "dest": "done"},
        {"trigger": "pause", "source": ACTIVE, "dest": "paused"},
        {"trigger": "fault", "source": "*", "dest": "faulted"},
        # a published verdict stands and an aborted run stays aborted: neither can be aborted (again)
        {"trigger": "abort", "source": ["idle", *ABORTABLE, "paused", "faulted"], "dest": "aborted"},
    ]


class Job(Protocol):
    """What a job does at each step; the controller sequences it and owns motion, retries and checkpoints.

    The controller moves the robot to each view's ``T_B_T``; the rest of a :class:`View` is the job's. A job
    whose ``register`` may run in the controller's worker beside ``evaluate`` (each locks what they share)
    says so with ``register_while_evaluating = True``; its ``register`` then takes a ``stop`` event
    (``threading.Event``) and raises :class:`cell.errors.CalledOff` at its next step once it is set (the
    evaluation asked for more views: the registration would be thrown away, and the replan waits for it).

    Optional steps, looked up by name: ``prepare(devices)`` (while connecting), ``evaluations_done()`` (no
    replan follows), ``render(run)`` (the report's page after the verdict) and ``on_stop(run, state)``: the
    run loop ended short of ``done`` (``state``: paused, faulted, aborted, or the state an exception left),
    the devices are safe and the worker is idle; the job writes what it still holds in memory for the run
    folder (the inspection: the plan's last view's raw images) and returns what it wrote (``{}``: nothing),
    journalled as ``written_on_stop``. It is called once, before the process exits; an error there is
    journalled, never raised.
    """

    part_name: str

    def plan(self) -> list[View]:
        """The initial viewpoints V0."""
        ...

    def capture(self, devices: DeviceBundle, view: View, index: int, views: Sequence[View]) -> Any:
        """Project and grab at view ``index`` of ``views`` (the robot is already there); returns what
        :meth:`decode` needs. ``views`` are the views the controller runs (the stored ones on a resume)."""
        ...

    def decode(self, view: View, captured: Any, out_dir: Path) -> dict[str, Any]:
        """Decode and triangulate one view, writing its files into ``out_dir``; returns a JSON summary."""
        ...

    def evaluate(self, run: RunFolder, views: list[View], iteration: int) -> Evaluation:
        """Judge the measured views: qualified or not, and the cost Q."""
        ...

    def replan(self, run: RunFolder, views: list[View], evaluation: Evaluation) -> list[View]:
        """New viewpoints V_k from the defect maps (may be empty); ``evaluation`` is :meth:`evaluate`'s."""
        ...

    def register(self, run: RunFolder, views: list[View]) -> dict[str, Any]:
        """Bring all views into the part frame, merge and filter; ``{"n_points": int, ...}``."""
        ...

    def report(self, run: RunFolder, registration: dict[str, Any]) -> dict[str, Any]:
        """Error map and report files in ``run.results_dir``; returns the report's key figures (with its
        ``verdict`` when the job judges a part). A job with a ``render(run)`` step writes here only what the
        verdict needs; ``render`` writes the rest afterwards (its page), returning what it wrote."""
        ...


@dataclass
class ControllerSettings:
    """Limits and policies of a run. Speeds are fractions of the robot config's maxima (never above 1)."""

    max_retries: int = 3
    retry_delay_s: float = 0.2
    view_budget: int = 60
    max_iterations: int = 4
    speed_fraction: float = 0.8
    pipelining: bool = True
    grab_timeout_ms: float = 2000.0
    # captured views waiting for the worker, at most: a capture waits for room (a 5 MP stack holds 0.4 GB)
    max_views_waiting: int = 1


@dataclass(frozen=True)
class RobotLimits:
    """The robot's speed and acceleration maxima; moves are sent at a fraction of them."""

    tcp_speed_mm_s: float = 250.0
    tcp_accel_mm_s2: float = 1200.0
    joint_speed_rad_s: float = 1.0
    joint_accel_rad_s2: float = 3.0

    @classmethod
    def of(cls, robot: RobotConfig) -> RobotLimits:
        """The limits the robot config declares."""
        return cls(
            robot.max_tcp_speed_mm_s,
            robot.max_tcp_accel_mm_s2,
            robot.max_joint_speed_rad_s,
            robot.max_joint_accel_rad_s2,
        )


@dataclass
class _Progress:
    started: float = field(default_factory=time.monotonic)
    view_times: list[float] = field(default_factory=list)


class Controller:
    """Runs one job on one device bundle into one run folder."""

    # The state machine (transitions) sets ``state`` and adds one method per trigger of the transition table
    # at run time; declared here for the type checker only (a real attribute would shadow the trigger).
    state: str
    if TYPE_CHECKING:

        def start(self) -> bool: ...
        def resume(self) -> bool: ...
        def resumed(self) -> bool: ...
        def connected(self) -> bool: ...
        def homed(self) -> bool: ...
        def planned(self) -> bool: ...
        def arrived(self) -> bool: ...
        def captured(self) -> bool: ...
        def no_more_views(self) -> bool: ...
        def decoded(self) -> bool: ...
        def needs_views(self) -> bool: ...
        def qualified(self) -> bool: ...
        def replanned(self) -> bool: ...
        def registered(self) -> bool: ...
        def reported(self) -> bool: ...
        def rendered(self) -> bool: ...
        def pause(self) -> bool: ...
        def fault(self) -> bool: ...
        def abort(self) -> bool: ...

    def __init__(
        self,
        devices: DeviceBundle,
        job: Job,
        run: RunFolder,
        settings: ControllerSettings | None = None,
        *,
        robot_limits: RobotLimits | None = None,
        home_joints_rad: np.ndarray | None = None,
        motion: Any | None = None,
        on_progress: Callable[[Controller], None] | None = None,
    ) -> None:
        self.devices = devices
        self.job = job
        self.run = run
        self.settings = settings or ControllerSettings()
        self.robot_limits = robot_limits or RobotLimits()
        self.home_joints_rad = home_joints_rad
        self.motion = (
            motion  # cell.planning.motion.MotionPlanner: collision-checked paths; None: straight lines
        )
        self.on_progress = on_progress
        self.checkpoint = Checkpoint.from_json(run.load_checkpoint())
        self.message = ""
        self.pause_requested_at: float | None = None  # time.monotonic() of the last pause request
        self.progress = _Progress()
        self._pause_requested = threading.Event()
        self._executor: ThreadPoolExecutor | None = None
        self._pending: dict[int, Future[dict[str, Any]]] = {}
        self._ahead: Future[dict[str, Any]] | None = None  # the registration, started while evaluating
        self._ahead_stop = threading.Event()  # set: that registration is called off at its next step
        self._registration: dict[str, Any] | None = None
        self._attempts = 0
        self._storage_failed = False  # the run folder refused a write: the run is pausing for it
        self.current_view: int | None = None
        self.machine = HierarchicalGraphMachine(
            model=self,
            states=STATES,
            transitions=_transitions(),
            initial="idle",
            auto_transitions=False,
            queued=True,
            send_event=False,
            after_state_change="_journal_state",
            graph_engine="mermaid",
            title="Inspection cell controller",
        )

    # ------------------------------------------------------------------ conditions (guards)
    def robot_normal(self) -> bool:
        return self.devices.robot.state().normal

    def projector_ready(self) -> bool:
        return self.devices.projector.ready()

    def unsafe(self) -> bool:
        """True when motion must not be commanded: the robot is not normal or the projector is not ready."""
        return not (self.robot_normal() and self.projector_ready())

    def _explain_unsafe(self) -> None:
        robot = self.devices.robot.state()
        self.message = (
            f"stopped for the operator: robot {robot.why_not_normal or 'ok'} ({robot}), "
            f"projector {self.devices.projector.status()}; fix it, then `cell resume`"
        )

    def needs_plan(self) -> bool:
        return not self.checkpoint.views

    def views_pending(self) -> bool:
        return self._next_view() is not None

    def phase_is_scanning(self) -> bool:
        return self.checkpoint.phase in (Phase.SCANNING, Phase.EVALUATING, Phase.REPLANNING)

    def phase_is_registering(self) -> bool:
        return self.checkpoint.phase is Phase.REGISTERING

    def phase_is_reporting(self) -> bool:
        return self.checkpoint.phase is Phase.REPORTING

    def phase_is_rendering(self) -> bool:
        return self.checkpoint.phase is Phase.RENDERING

    def has_page(self) -> bool:
        """Whether the job writes its report's page after the verdict (a ``render`` step)."""
        return callable(getattr(self.job, "render", None))

    # ------------------------------------------------------------------ bookkeeping
    def _log(self, event: str, **fields: Any) -> None:
        """Journal an entry. Once the run folder refused a write (a full disk, a read-only file system), an
        entry that cannot be written is dropped: the run is pausing for that very reason, and the message
        says so; the journal's reader skips a torn last line."""
        try:
            self.run.log(event, **fields)
        except OSError as exc:
            if not (self._storage_failed and is_storage_error(exc)):
                raise

    def _journal_state(self) -> None:
        # cpu_s: this process's CPU seconds so far, so a shared machine's phases can be read in CPU time too
        self._log("state", state=self.state, message=self.message, cpu_s=round(time.process_time(), 3))
        if self.on_progress:
            self.on_progress(self)

    def _save(self) -> None:
        self.run.save_checkpoint(self.checkpoint.to_json())

    def _done_views(self) -> set[int]:
        return set(self.run.completed_views()) | set(self._pending) | set(self.checkpoint.skipped)

    def _next_view(self) -> int | None:
        done = self._done_views()
        for i in range(len(self.checkpoint.views)):
            if i not in done:
                return i
        return None

    @property
    def views_total(self) -> int:
        return len(self.checkpoint.views)

    @property
    def views_done(self) -> int:
        return len(self.run.completed_views())

    def request_pause(self, reason: str = "operator") -> None:
        """Ask for a safe pause (Ctrl-C and SIGTERM call this; safe from a signal handler or another thread).
        A move in progress is stopped at once (the robot's stop() decelerates it mid-path and the move
        raises MotionStopped); otherwise the run pauses at the next step boundary."""
        self.message = f"pause requested: {reason}"
        self._pause_requested.set()
        self.pause_requested_at = time.monotonic()
        try:
            self.devices.robot.stop()
        except Exception:  # a signal handler must not raise; _make_safe stops it again
            pass

    # ------------------------------------------------------------------ the run loop
    def execute(self, *, resume: bool = False) -> str:
        """Run until done, paused, faulted or aborted; returns the final state. Devices are made safe on
        exit."""
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="decode")
        map_large_arrays()  # whole images in mappings of their own, not in the heaps (cell.memory)
        in_main = threading.current_thread() is threading.main_thread()
        previous = {}
        if in_main:  # Ctrl-C and SIGTERM (systemd, docker stop, kill) both pause safely, mid-move too
            for signum, reason in ((signal.SIGINT, "Ctrl-C"), (signal.SIGTERM, "SIGTERM")):
                previous[signum] = signal.getsignal(signum)
                signal.signal(signum, lambda *_, r=reason: self.request_pause(r))
        try:
            self.run.discard_partial_views()
            self.resume() if resume else self.start()
            while self.state not in TERMINAL:
                if self._pause_requested.is_set():
                    self._drain_decodes()
                    self._make_safe()
                    self.pause()
                    break
                self._step()
        finally:
            for signum, handler in previous.items():
                signal.signal(signum, handler)
            self._make_safe()
            # a registration still running ahead (a fault that skipped the drain) stops at its next step
            self._ahead_stop.set()
            self._executor.shutdown(wait=True, cancel_futures=False)
            if self.state != "done":
                self._job_on_stop()
            self._close_devices()
            self._log("exit", state=self.state, message=self.message)
        return self.state

    def _step(self) -> None:
        handler = getattr(self, "_do_" + self.state)
        try:
            handler()
            self._attempts = 0
        except CellError as exc:
            self._handle_error(exc)
        except Exception as exc:
            if is_storage_error(exc, self.run.path):  # a full disk or read-only run folder: pause for room
                assert isinstance(exc, OSError)
                self._handle_error(storage_error(exc, self.run.path))
                return
            # a bug: record it, make safe, fault
            self.message = f"internal error: {type(exc).__name__}: {exc}"
            self.run.log("error", kind="internal", error=repr(exc))
            self.fault()

    def _handle_error(self, exc: CellError) -> None:
        retryable = isinstance(exc, DeviceError) and exc.retryable
        self._storage_failed = self._storage_failed or isinstance(exc, StorageError)
        self._log(
            "error", kind=type(exc).__name__, error=str(exc), attempt=self._attempts + 1, retryable=retryable
        )
        if retryable and self._attempts < self.settings.max_retries:
            self._attempts += 1
            time.sleep(self.settings.retry_delay_s)
            assert isinstance(exc, DeviceError)  # only device errors are retryable
            self._reconnect(exc.device)
            return  # same state, same handler: retry
        self._attempts = 0
        if isinstance(exc, MotionStopped) and self._pause_requested.is_set():
            self.message = f"{self.message}; {exc}"  # the operator's reason first, then where the arm stopped
        else:
            self.message = str(exc)
        self._drain_decodes()
        if isinstance(exc, (DeviceError, StorageError)):
            self.pause()  # needs the operator; `cell resume` continues from the last checkpoint
        else:
            self.fault()

    def _job_on_stop(self) -> None:
        """The job's ``on_stop(run, state)`` (:class:`Job`), if it has one: on every exit short of ``done``,
        once the worker is idle. Never raises (it runs in the run loop's ``finally``): an error is journalled,
        and a journal that cannot be written then (a full disk) is left so."""
        on_stop = getattr(self.job, "on_stop", None)
        if on_stop is None:
            return
        try:
            written = on_stop(self.run, self.state)
            if written:
                self._log("written_on_stop", state=self.state, **written)
        except Exception as exc:
            with contextlib.suppress(Exception):  # the run is stopping already; the exit line says how
                self._log("error", kind="on_stop", error=repr(exc), state=self.state)

    def _reconnect(self, name: str) -> None:
        """Close and reopen the device a timeout came from: a lost connection is the commonest cause."""
        for kind, device in self.devices.items():
            if self.devices.names.get(kind, kind) != name:
                continue
            try:
                device.close()
                device.connect()
                self.run.log("device", device=name, command="reconnect")
            except Exception as exc:  # the retry itself will report what is wrong
                self.run.log("error", kind=type(exc).__name__, error=str(exc), during="reconnect")

    def _close_devices(self) -> None:
        self.devices.close_all(lambda name, exc: self._log("close_failed", device=name, error=repr(exc)))

    def _make_safe(self) -> None:
        """Stop the robot and blank the projector; never raises (this runs on every exit path)."""
        for action in (self.devices.robot.stop, self.devices.projector.blank):
            try:
                action()
            except Exception as exc:  # a device that is gone cannot be made safer; record and go on
                self._log("safe_stop_failed", error=repr(exc))

    # ------------------------------------------------------------------ state handlers
    def _do_resuming(self) -> None:
        self.run.log("resume", checkpoint=self.checkpoint.phase.value, views_done=self.views_done)
        self.resumed()

    def _do_connecting(self) -> None:
        self.devices.bring_up(lambda name: self.run.log("device", device=name, command="connect"))
        projector = self.devices.projector
        if not self.robot_normal():
            state = self.devices.robot.state()
            raise DeviceFault(
                self.devices.names.get("robot", "robot"),
                f"not ready for motion: {state.why_not_normal} ({state})",
            )
        if not self.projector_ready():
            raise DeviceFault(
                self.devices.names.get("projector", "projector"), f"not ready: {projector.status()}"
            )
        prepare = getattr(self.job, "prepare", None)
        if prepare is not None:  # the job's device settings (camera trigger lines...): refused before motion
            prepare(self.devices)
        self.connected()

    def _do_homing(self) -> None:
        if self.home_joints_rad is not None:
            robot = self.devices.robot
            if self.motion is None:
                moves = [Move("joint", np.asarray(self.home_joints_rad, dtype=np.float64))]
            else:  # from wherever a killed run left the sensor: a checked path, never a blind joint move
                home = self.motion.kin.fk(np.asarray(self.home_joints_rad, dtype=np.float64))
                try:
                    moves, _ = self.motion.plan(robot.tool_pose(), robot.joints(), home, None)
                except PlanningError as exc:
                    raise DeviceFault(
                        self.devices.names.get("robot", "robot"),
                        f"no collision-free path home ({exc}); jog the robot clear, then resume",
                    ) from exc
            self._execute_moves(moves, view=None)
        self.homed()

    def _do_planning(self) -> None:
        views = self.job.plan()
        if not views:
            raise PlanningError(
                "no reachable viewpoint measures any of the part; check the part placement "
                "(part.T_W_P) and the robot envelope"
            )
        self.run.log("plan", n_views=len(views), views=[v.to_json() for v in views])
        self.checkpoint.phase, self.checkpoint.views, self.checkpoint.iteration = Phase.SCANNING, views, 0
        self._save()
        self.planned()

    def _do_scanning_moving(self) -> None:
        index = self._next_view()
        assert index is not None  # guarded by views_pending
        target = self.checkpoint.views[index].T_B_T
        robot = self.devices.robot
        if self.motion is None:
            moves = [Move("linear", target)]
        else:
            try:
                moves, rejected = self.motion.plan(
                    robot.tool_pose(), robot.joints(), target, self.home_joints_rad
                )
            except PlanningError as exc:  # this view cannot be reached safely: skip it, say why
                self.run.log("decision", view=index, reason=f"view skipped: {exc}")
                self.checkpoint.skipped = sorted(set(self.checkpoint.skipped) | {index})
                self._save()
                if not self.views_pending():
                    self.no_more_views()
                return
            if rejected:
                self.run.log("decision", view=index, reason="path options dropped: " + "; ".join(rejected))
        self._execute_moves(moves, view=index)
        self.current_view = index
        self.arrived()

    def _execute_moves(self, moves: list[Move], view: int | None) -> None:
        """Send the moves at the settings' fraction of the configured speeds (times each move's own scale)."""
        robot = self.devices.robot
        limits = self.robot_limits
        for move in moves:
            k = self.settings.speed_fraction * move.speed_scale
            self.run.log(
                "device",
                device="robot",
                command=f"move_{move.kind}",
                view=view,
                target=move.target,
                speed_scale=move.speed_scale,
            )
            # checked after the journal's fsync, as the last thing before the move: a stop() that comes before
            # the robot takes the move is a no-op (a UR's stopl before movel too), so a pause asked for
            # meanwhile would let the whole move run; the flag it set stays, and sends no move
            if self._pause_requested.is_set():
                raise MotionStopped(self.devices.names.get("robot", "robot"), "pause requested before a move")
            if move.kind == "linear":
                robot.move_linear(move.target, limits.tcp_speed_mm_s * k, limits.tcp_accel_mm_s2 * k)
            else:
                robot.move_joint(move.target, limits.joint_speed_rad_s * k, limits.joint_accel_rad_s2 * k)

    def _do_scanning_capturing(self) -> None:
        index = self.current_view
        assert index is not None  # set by the move to this view
        view = self.checkpoint.views[index]
        self._make_room()
        self.run.log("capture", view=index)
        captured = self.job.capture(self.devices, view, index, self.checkpoint.views)
        assert self._executor is not None
        future = self._executor.submit(self._decode_view, index, view, captured)
        self._pending[index] = future
        if not self.settings.pipelining:
            self._collect(block=True)
        else:
            self._collect(block=False)
        self.progress.view_times.append(time.monotonic())
        self.captured()

    def _make_room(self) -> None:
        """Before a capture: while one view's work runs and ``max_views_waiting`` more wait for the worker,
        wait for the oldest (the robot is at the view already; its move overlapped the work). The captured
        images in memory stay bounded when the views' work is slower than the robot and the camera (a
        loaded computer, a simulated capture); a computer that keeps up never waits here."""
        while len(self._pending) > self.settings.max_views_waiting:
            wait([self._pending[min(self._pending)]])
            self._collect(block=False)

    def _decode_view(self, index: int, view: View, captured: Any) -> dict[str, Any]:
        with self.run.writing_view(index) as tmp:
            try:
                summary = self.job.decode(view, captured, tmp)
                require_room(tmp)  # a full disk after the writes: a writer may have failed without a word
            except OSError as exc:  # judged while the half-written view still fills the disk
                if is_storage_error(exc, tmp):  # named by the view, not by its temporary folder
                    code = exc.errno or errno.ENOSPC
                    raise OSError(code, os.strerror(code), str(self.run.view_dir(index))) from exc
                raise
        # the view's images and whole-image temporaries are freed now: give their pages back, or the heap's
        # free gaps grow view by view (cell.memory)
        release_free_heap()
        return summary

    def _collect(self, *, block: bool) -> None:
        """Record finished view work in the journal; re-raise a view's error here, in the main thread: the
        cell's own errors as they are (a full disk pauses), anything else as that view's
        :class:`ViewProcessingError` (the run faults naming the view)."""
        for index in sorted(self._pending):
            future = self._pending[index]
            if not block and not future.done():
                continue
            del self._pending[index]
            try:
                summary = future.result()
            except (CellError, OSError):
                raise
            except Exception as exc:
                raise ViewProcessingError(index, exc) from exc
            self.run.log("view", view=index, summary=summary)

    def _drain_decodes(self) -> None:
        """Wait for every decode before a pause or fault: finished views are journalled, failed ones logged
        (their folders do not exist, so a resume measures them again); a registration started ahead is
        dropped (a resume registers again)."""
        self._drop_ahead()
        for index in sorted(self._pending):
            try:
                summary = self._pending[index].result()
            except Exception as exc:  # recorded here; the view is redone on resume
                self._log("error", kind="view", view=index, error=repr(exc))
            else:
                self._log("view", view=index, summary=summary)
        self._pending.clear()

    def _do_scanning_decoding(self) -> None:
        self._collect(block=True)
        self.checkpoint.phase = Phase.EVALUATING
        self._save()
        self.decoded()

    def _register_ahead(self) -> None:
        """Start the registration in the worker while this thread evaluates (when pipelining and the job says
        its ``register`` may run beside ``evaluate``: ``register_while_evaluating``): both need the views'
        refinement, then each goes its own way, on its own core. ``registering`` takes the result when the
        evaluation qualifies the views; a replan or a pause drops it."""
        if self._ahead is not None or not self.settings.pipelining:
            return
        if not getattr(self.job, "register_while_evaluating", False):
            return
        assert self._executor is not None
        self._ahead_stop = threading.Event()
        views = list(self.checkpoint.views)
        job: Any = self.job  # one that registers while evaluating takes ``stop`` (:class:`Job`)
        self._ahead = self._executor.submit(job.register, self.run, views, stop=self._ahead_stop)

    def _drop_ahead(self) -> None:
        """Call off a registration started ahead, wait for it to stop (at its next step: on the hires pillar
        the replan waited for a whole registration of its first 12 views, 33 s of replanning, 16.7 s since)
        and forget it (its error too: journalled, not raised)."""
        ahead, self._ahead = self._ahead, None
        if ahead is None:
            return
        self._ahead_stop.set()
        try:
            ahead.result()
        except CalledOff:
            self._log("registration_called_off", views=len(self.checkpoint.views))
        except Exception as exc:
            self._log("error", kind="registration ahead", error=repr(exc), used=False)

    def _do_evaluating(self) -> None:
        cp = self.checkpoint
        self._register_ahead()
        evaluation = self.job.evaluate(self.run, cp.views, cp.iteration)
        self.run.log("evaluation", **evaluation.to_json())
        spent = len(cp.views) >= self.settings.view_budget
        last = cp.iteration + 1 >= self.settings.max_iterations
        cp.evaluation = evaluation
        if evaluation.qualified or spent or last:
            # no replan follows: the round's arrays (``state``) and the job's caches for evaluations are
            # not held beside the registration (cell.memory)
            evaluation.state = None
            release = getattr(self.job, "evaluations_done", None)
            if release is not None:
                release()
            if not evaluation.qualified:
                self.run.log(
                    "decision",
                    reason="view budget or iteration limit reached before the set point",
                    Q=evaluation.q,
                )
            cp.phase = Phase.REGISTERING
            self._save()
            self.qualified()
        else:
            cp.phase = Phase.REPLANNING
            self._save()
            self.needs_views()

    def _do_replanning(self) -> None:
        self._drop_ahead()  # more views: the registration is made again when they are measured
        release_free_heap()  # the dropped registration's arrays, before the next views' scan
        cp = self.checkpoint
        assert cp.evaluation is not None  # saved with the replanning phase
        room = self.settings.view_budget - len(cp.views)
        new_views = self.job.replan(self.run, cp.views, cp.evaluation)[:room]
        cp.evaluation.state = None  # used by the replan alone: not held through the next views' scan
        self.run.log("replan", n_new=len(new_views), views=[v.to_json() for v in new_views])
        cp.views = cp.views + new_views
        cp.iteration += 1
        cp.phase = Phase.SCANNING if new_views else Phase.REGISTERING
        self._save()
        self.replanned()

    def _do_registering(self) -> None:
        ahead, self._ahead = self._ahead, None
        if ahead is not None:  # started while evaluating (a resumed run registers here)
            self._registration = ahead.result()
        else:
            self._registration = self.job.register(self.run, self.checkpoint.views)
        self.run.log("registration", **self._registration)
        if not self._registration.get("n_points", 0):
            raise CellError("registration produced no points: nothing to report")
        self.checkpoint.phase, self.checkpoint.registration = Phase.REPORTING, self._registration
        self._save()
        self.registered()

    def _do_reporting(self) -> None:
        registration = self._registration or self.checkpoint.registration or {}
        summary = self.job.report(self.run, registration)
        # the verdict is out: journalled, and in the checkpoint (what `cell inspect` exits with and what the
        # station reads), before the rest of the report is written
        self.run.log("verdict" if "verdict" in summary else "report", **summary)
        self.checkpoint.summary = summary
        self.checkpoint.phase = Phase.RENDERING if self.has_page() else Phase.DONE
        self._save()
        self.reported()

    def _do_rendering(self) -> None:
        written = self.job.render(self.run)  # type: ignore[attr-defined]  # guarded by has_page
        self.run.log("report_written", **written)
        self.checkpoint.phase = Phase.DONE
        self._save()
        self.rendered()


class _StoppedRun:
    """A run no process executes, as the state machine sees it: the state its journal last recorded
    (:func:`stopped_state`); every state change it makes is journalled like a live controller's."""

    state: str

    def __init__(self, run: RunFolder, message: str) -> None:
        self.run = run
        self.message = message

    def _journal_state(self) -> None:
        self.run.log("state", state=self.state, message=self.message)


def stopped_state(run: RunFolder) -> str:
    """The machine state of a run no process executes: ``done``, ``aborted`` or ``paused`` when its journal
    last recorded that, else ``idle`` (a run killed mid-step or faulted restarts from idle, as `cell resume`
    always did)."""
    last = next((e.get("state") for e in reversed(run.journal()) if e.get("event") == "state"), None)
    return last if last in ("done", "aborted", "paused") else "idle"


def abort_stopped(run: RunFolder, reason: str) -> str:
    """Abort a run that no process executes (the caller holds its lock) through the state machine's ``abort``
    trigger, from :func:`stopped_state`; the machine refuses a finished or an already aborted run, and a run
    whose verdict is published is refused too (ConfigError). Journals the new state with ``reason``; returns
    it."""
    from transitions import MachineError
    from transitions.extensions import HierarchicalMachine

    if Checkpoint.from_json(run.load_checkpoint()).phase is Phase.RENDERING:
        raise ConfigError(
            "the run's verdict is published and stands; nothing to abort (`cell resume` writes the rest of "
            "its report)",
            path=str(run.path),
        )
    model: Any = _StoppedRun(run, reason)
    state = stopped_state(run)
    HierarchicalMachine(
        model=model,
        states=STATES,
        transitions=_transitions(),
        initial=state,
        auto_transitions=False,
        after_state_change="_journal_state",
    )
    try:
        model.abort()
    except MachineError:
        done = state == "done"
        why = "the run is finished and its verdict stands" if done else "the run is aborted already"
        raise ConfigError(f"{why}; nothing to abort", path=str(run.path)) from None
    run.log("exit", state=model.state, message=reason)  # the run's record closed, as a controller closes it
    return str(model.state)


def mermaid_diagram() -> str:
    """The controller's state diagram in Mermaid, generated from :data:`STATES` and the transition table."""

    class _Model:
        pass

    model: Any = _Model()  # the machine adds get_graph at run time
    HierarchicalGraphMachine(
        model=model,
        states=STATES,
        transitions=_transitions(),
        initial="idle",
        auto_transitions=False,
        graph_engine="mermaid",
        show_conditions=True,
        title="Inspection cell controller",
    )
    return "```mermaid\n" + model.get_graph().draw(None) + "\n```\n"
