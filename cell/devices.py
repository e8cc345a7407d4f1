"""Build the cell's devices from its config: the only place that knows which class implements which driver.

The controller receives a :class:`DeviceBundle` and sees only the Protocols of ``cell.contracts``; switching a
simulated cell for a real one is a config change. Driver modules are imported here lazily, by name, so that a
missing or broken hardware library only matters when its driver is configured.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cell.config import CameraConfig, CellConfig, MaterialConfig
from cell.contracts import (
    BoardStage,
    Camera,
    CameraSettings,
    MarkerScreen,
    PixelFormat,
    Projector,
    Robot,
    TriggerMode,
)
from cell.errors import ConfigError

if TYPE_CHECKING:
    import trimesh

# (device kind, driver name) -> "module:Class". Sim devices are not listed: they share one simulated world
# and are built together by fakes.sim_cell.build_sim_cell.
REAL_DRIVERS: dict[tuple[str, str], str] = {
    ("robot", "ur_rtde"): "drivers.ur_robot:URRobot",
    ("camera", "genicam"): "drivers.genicam_camera:GenICamCamera",
    ("camera", "aravis"): "drivers.aravis_camera:AravisCamera",
    ("projector", "serial"): "drivers.serial_projector:SerialProjector",
    ("projector", "dlpc350"): "drivers.dlpc350:Dlpc350Projector",
    ("robot", "replay"): "fakes.replay:ReplayRobot",
    ("camera", "replay"): "fakes.replay:ReplayCamera",
    ("projector", "replay"): "fakes.replay:ReplayProjector",
    ("glass_rig", "genicam"): "drivers.glass_rig:GenICamGlassRig",
    ("glass_rig", "replay"): "fakes.replay:ReplayGlassRig",
}


@dataclass
class DeviceBundle:
    """The devices of one cell. ``sim`` is the simulated world when the cell is simulated (ground truth)."""

    robot: Robot
    camera: Camera
    projector: Projector
    sim: Any | None = None
    names: dict[str, str] = field(default_factory=dict)
    stage: BoardStage | None = None  # calibration targets (cell calibrate); None for inspections

    def items(self) -> list[tuple[str, Any]]:
        """(kind, device) pairs in connection order."""
        kinds: list[tuple[str, Any]] = [
            ("robot", self.robot),
            ("projector", self.projector),
            ("camera", self.camera),
        ]
        return kinds + ([("stage", self.stage)] if self.stage is not None else [])

    @property
    def simulated(self) -> bool:
        """Whether these devices are the simulator's (a job may record it; it never reads the world)."""
        return self.sim is not None

    def bring_up(self, on_connect: Callable[[str], None] | None = None) -> None:
        """Connect every device in order (``on_connect`` hears each one's name) and switch the projector on
        at its HDMI input, blank: the one start-up of the controller and of the commands that capture
        outside it."""
        for kind, device in self.items():
            device.connect()
            if on_connect is not None:
                on_connect(self.names.get(kind, kind))
        self.projector.switch_on()

    def close_all(self, on_error: Callable[[str, Exception], None] | None = None) -> None:
        """Close every device in connection order; a device that fails to close is reported to ``on_error``
        (its name and the error) and the others are closed still: closing must not hide how a run ended."""
        for kind, device in self.items():
            try:
                device.close()
            except Exception as exc:  # reported, never raised
                if on_error is not None:
                    on_error(self.names.get(kind, kind), exc)

    def begin_view(self, key: int, arrived: int | None = None) -> None:
        """Called by a job before it captures a view, ``key`` naming the view the same way on a resumed run,
        ``arrived`` the key of the view for which the robot came to the pose it holds (default ``key``: it
        came for this one). A simulated cell restarts its noise from them (a view's images then depend on the
        view alone, and a held pose keeps its landing error on a resumed run too); real devices need
        nothing."""
        if self.sim is not None:
            self.sim.reseed(key, arrived=None if arrived is None else (arrived,))

    def end_view(self) -> None:
        """Called by a job once it has captured a view's frames: a simulated cell drops what it rendered the
        view's pose with (a 5 MP camera's ~0.3 GB, else held through the evaluation and the registration
        after the last view; issue 16, item 5); real devices need nothing."""
        if self.sim is not None:
            self.sim.end_view()


def _drivers(cfg: CellConfig) -> dict[str, str]:
    """The driver the cell config names for each device kind."""
    return {
        "robot": cfg.robot.driver,
        "camera": cfg.sensor.camera.driver,
        "projector": cfg.sensor.projector.driver,
    }


def _import_driver(kind: str, driver: str, where: str) -> type:
    target = REAL_DRIVERS.get((kind, driver))
    if target is None:
        raise ConfigError(f"no '{driver}' driver for a {kind}", field=where)
    module_name, class_name = target.split(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ConfigError(
            f"the '{driver}' {kind} driver needs {exc.name or 'a library'} which cannot be imported ({exc}); "
            "install it or use driver: sim",
            field=where,
        ) from exc
    return getattr(module, class_name)


def check_world(cfg: CellConfig, path: str | Path) -> None:
    """Validate a simulated cell's ``world:`` section with the simulator's schema (fakes.sim.world): a bad
    key or value is a ConfigError naming the file and field at load time. Cells without sim drivers skip."""
    if cfg.world is None or cfg.world == "ideal" or cfg.robot.driver != "sim":
        return
    from pydantic import ValidationError

    from cell.schema_errors import unknown_key_message
    from fakes.sim.world import WorldConfig, world_config

    try:
        world_config(cfg.world)
    except ValidationError as exc:
        err = exc.errors()[0]
        msg = err["msg"]
        if err["type"] == "extra_forbidden":
            msg = f"{unknown_key_message(WorldConfig, err['loc'])} (docs/world-schema.md)"
        raise ConfigError(msg, path=str(path), field=".".join(["world", *map(str, err["loc"])])) from exc


def build_devices(
    cfg: CellConfig,
    *,
    part_W: trimesh.Trimesh | None = None,
    part_material: MaterialConfig | None = None,
    seed: int | None = None,
    stream: tuple[int | str, ...] = (),
    with_stage: bool = False,
) -> DeviceBundle:
    """Devices for ``cfg``. ``part_W`` (world coordinates, mm) is what a simulated cell renders; real
    cells ignore it, and ``seed`` and ``stream``: a simulated cell's noise is drawn from ``seed`` (default
    its ``sim.seed``) with ``stream`` mixed in (fakes.sim_cell.noise_seed). ``with_stage`` adds the board
    stage the calibration routines need: a simulated motorised stage on a simulated cell, else the operator,
    asked on the console to place each target and confirm."""
    drivers = _drivers(cfg)
    sim_kinds = [k for k, d in drivers.items() if d == "sim"]
    if sim_kinds and len(sim_kinds) != len(drivers):
        raise ConfigError(
            f"simulated devices ({', '.join(sim_kinds)}) cannot be mixed with real ones: they share one "
            "simulated world; make every driver 'sim' or none",
            field="driver",
        )
    names = {
        "robot": cfg.robot.name,
        "camera": cfg.sensor.camera.name,
        "projector": cfg.sensor.projector.name,
    }
    if sim_kinds:
        from fakes.sim_cell import build_sim_cell

        sim = build_sim_cell(cfg, part_W, part_material=part_material, seed=seed, stream=stream)
        stage: BoardStage | None = None
        if with_stage:
            from fakes.stage import SimBoardStage

            stage = SimBoardStage(sim)
            names["stage"] = stage.name
        return DeviceBundle(
            robot=sim.robot, camera=sim.camera, projector=sim.projector, sim=sim, names=names, stage=stage
        )
    robot = _import_driver("robot", cfg.robot.driver, "robot.driver")(cfg.robot)
    camera = _import_driver("camera", cfg.sensor.camera.driver, "sensor.camera.driver")(cfg.sensor.camera)
    projector = _import_driver("projector", cfg.sensor.projector.driver, "sensor.projector.driver")(
        cfg.sensor.projector
    )
    stage = None
    if with_stage:
        from cell.calibration.operator_stage import OperatorBoardStage

        operator = OperatorBoardStage()
        names["stage"], stage = operator.name, operator
    return DeviceBundle(robot=robot, camera=camera, projector=projector, names=names, stage=stage)


@dataclass
class DeviceCheck:
    """One device of :func:`check_devices`: its name, kind, driver, and a line of status (connected) or the
    error that stopped it."""

    name: str
    kind: str
    driver: str
    status: str = ""
    error: Exception | None = None


def describe(device: Any) -> str:
    """One line of status for a connected device, read through its contract."""
    if isinstance(device, Robot):
        state = device.state()
        x, y, z = device.tool_pose()[:3, 3]
        stops = [
            n
            for n, on in (("protective stop", state.protective_stop), ("E-stop", state.emergency_stop))
            if on
        ]
        return f"mode {state.mode.value}; flange at ({x:.1f}, {y:.1f}, {z:.1f}) mm" + (
            f"; {', '.join(stops)}" if stops else ""
        )
    if isinstance(device, Projector):
        s = device.status()
        w, h = device.resolution
        errors = f"; errors: {', '.join(s.errors)}" if s.errors else ""
        return (
            f"{w}x{h}; power {'on' if s.powered else 'off'}; source {s.source.value}; "
            f"lamp {s.lamp_hours:.0f} h; {s.temperature_c:.0f} C{errors}"
        )
    if isinstance(device, Camera):
        w, h = device.resolution
        return f"{device.model}, serial {device.serial}, {w}x{h}"
    return type(device).__name__


def check_devices(cfg: CellConfig) -> list[DeviceCheck]:
    """Connect each device of ``cfg``, describe it, close them all: a failing device is reported, not
    raised, so that one check shows every device."""
    bundle = build_devices(cfg)
    drivers = _drivers(cfg)
    checks = []
    for kind, device in bundle.items():
        check = DeviceCheck(bundle.names[kind], kind, drivers[kind])
        try:
            device.connect()
            check.status = describe(device)
        except Exception as exc:  # any failure is reported per device
            check.error = exc
        checks.append(check)
    bundle.close_all()  # a device that failed to connect may fail to close too: the report says enough
    return checks


@contextmanager
def ready_to_capture(devices: DeviceBundle, camera: CameraConfig) -> Iterator[CameraSettings]:
    """Every device connected, the projector on at its HDMI input and the camera set to ``camera``'s exposure,
    gain and bit depth with a software trigger, for a command that captures outside the controller (a
    scan, a latency measurement). Yields the settings the camera took; closes every device on the way out."""
    try:
        devices.bring_up()
        yield devices.camera.configure(
            CameraSettings(
                camera.exposure_ms,
                camera.gain_db,
                PixelFormat(f"Mono{camera.bit_depth}"),
                TriggerMode.SOFTWARE,
            )
        )
    finally:
        failed: list[Exception] = []
        devices.close_all(lambda _, exc: failed.append(exc))
        if failed:  # every device is closed first; then the command hears what went wrong
            raise failed[0]


def record_devices(devices: DeviceBundle) -> DeviceBundle:
    """The same cell with every device call recorded (drivers.recording), for :func:`save_recording`."""
    from drivers.recording import record_bundle

    return record_bundle(devices)


def save_recording(devices: DeviceBundle, out: Path, cell_config: dict[str, Any]) -> Path:
    """Write the calls :func:`record_devices` recorded as replay fixtures under ``out``, with a ``cell.yaml``
    (``cell_config`` with every driver set to ``replay``) that runs them again; returns the folder."""
    from drivers.recording import save_bundle

    return save_bundle(devices, out, cell_config)


# artefact stages for verification (cell.verification.stage.ArtefactStage): a simulated cell's stage puts the
# artefact into the simulated scene; a real cell's technician places it by hand.
ARTEFACT_STAGES: dict[str, str] = {
    "sim": "fakes.artefact_stage:SimArtefactStage",
    "operator": "cell.verification.stage:OperatorStage",
}


def build_artefact_stage(devices: DeviceBundle, certificate: Any) -> Any:
    """The artefact stage of ``devices``' cell: the simulated one (rendering ``certificate``'s artefacts)
    when the cell is simulated, else the technician's hands (cell.verification.stage.OperatorStage)."""
    kind = "sim" if devices.sim is not None else "operator"
    module_name, class_name = ARTEFACT_STAGES[kind].split(":")
    cls = getattr(importlib.import_module(module_name), class_name)
    return cls(devices.sim, certificate) if kind == "sim" else cls()


def build_glass_rig(
    cfg: Any, actual_W: trimesh.Trimesh, operator_places_board: Callable[[float | None], None]
) -> tuple[Any, Callable[[float | None], None], Callable[[int], MarkerScreen] | None]:
    """The glass rig of ``cfg`` (cell.glass.config.GlassRigConfig), how its dot-grid board gets placed and how
    its screen moves (None: it cannot). A simulated rig renders ``actual_W`` (world, mm) and places its board
    and screen itself; a real or replayed rig asks the operator to place the board."""
    if cfg.driver == "sim":
        from fakes.glass_rig import SimGlassRig

        rig = SimGlassRig(cfg, actual_W)
        return rig, rig.place_board, rig.move_screen
    if cfg.driver == "genicam":  # the real rig takes its cameras' options beside the config
        return _import_driver("glass_rig", "genicam", "driver")(cfg, cfg.options), operator_places_board, None
    return _import_driver("glass_rig", cfg.driver, "driver")(cfg), operator_places_board, None
