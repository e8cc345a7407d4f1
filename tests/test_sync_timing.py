"""Camera-projector synchronisation in the simulator: display latency, exposure integration, DLP frame
modulation, the scan's waits and re-captures, and the latency calibration.

Truth is the simulated world (``SimProjector.latency_s``, its vblank grid); the scan only knows what the cell
config or a calibration says. A stack re-captured after a fault is compared bit for bit with an undisturbed
one: the simulated noise is keyed per pattern (fakes/camera.py), so any difference is a wrong frame.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
import yaml

from cell.calibration.latency import KIND, latency_meta, measure_latency
from cell.calibration.store import save_calibration
from cell.config import DEFAULT_CELL, CellConfig, SimConfig, load_cell_config, read_yaml, validate
from cell.contracts import CameraSettings, PixelFormat, TriggerMode
from cell.errors import ConfigError, DeviceProtocolError, DeviceTimeout
from cell.geometry import make_pose
from cell.sensing.patterns import gcls_patterns
from cell.sensing.scan import CaptureLog, capture_stack
from fakes.sim.testing import small_rig, small_sensor

GCLS = gcls_patterns(128, 96, 8, 8)
T = 1 / 60.0  # the default refresh period (s)
PLATE = trimesh.creation.box(
    (400, 300, 4),
    transform=make_pose(trimesh.transformations.rotation_matrix(0.25, [0, 1, 0])[:3, :3], [0, 0, 20]),
)


def _rig(
    trigger: TriggerMode = TriggerMode.SOFTWARE, *, noise: bool = True, exposure_ms: float = 10.0, **proj
):
    rig = small_rig(
        part_W=PLATE,
        bit_depth=8,
        sim=SimConfig(seed=3, noise=noise),
        camera={"exposure_ms": exposure_ms},
        projector=proj or None,
    )
    rig.projector.connect()
    rig.projector.set_power(True)
    rig.camera.connect()
    rig.camera.configure(
        CameraSettings(exposure_ms=exposure_ms, pixel_format=PixelFormat.MONO8, trigger=trigger)
    )
    rig.camera.rng = np.random.default_rng([3, 1])  # per-view keyed noise, as SimCell.reseed sets it
    return rig


def _stack(rig) -> tuple[np.ndarray, CaptureLog]:
    log = CaptureLog()
    return np.stack(capture_stack(rig.camera, rig.projector, GCLS, log=log)), log


def _after(rig, value: int, delay_s: float) -> float:
    """Mean of the lit pixels of a frame triggered ``delay_s`` after ``value`` was presented (after black)."""
    h, w = 96, 128
    rig.projector.show(np.zeros((h, w), np.uint8))
    rig.projector.clock.sleep(0.2)
    rig.projector.show(np.full((h, w), value, np.uint8))
    clock = rig.projector.clock
    clock.sleep(rig.projector.last_present_s + delay_s - clock.now())
    rig.camera.trigger()
    return float(rig.camera.grab(100).pixels[rig.renderer.view(rig.T_W_C).lit].mean())


def test_present_waits_for_the_vblank_and_light_follows_after_the_latency() -> None:
    rig = _rig(noise=False)
    clock = rig.projector.clock
    clock.sleep(0.005)
    rig.projector.show(np.zeros((96, 128), np.uint8))
    assert rig.projector.last_present_s == pytest.approx(T) and clock.now() == pytest.approx(T)
    assert rig.projector.latency_s == pytest.approx(2 * T)  # the default: 2 refresh periods at 60 Hz
    dark, bright = _after(rig, 255, 0.0), _after(rig, 255, 2 * T)
    assert bright > 5 * dark  # triggered at the present: the old (black) frame
    half = _after(rig, 255, 2 * T - 0.005)  # 5 of 10 ms before the light: half old, half new
    assert (half - dark) / (bright - dark) == pytest.approx(0.5, abs=0.02)


def test_latency_is_configurable_in_the_simulated_world() -> None:
    rig = _rig(noise=False, options={"latency_frames": 3.5})
    dark, bright = _after(rig, 255, 0.0), _after(rig, 255, 3.5 * T)
    assert _after(rig, 255, 3.5 * T - 0.0025) == pytest.approx(
        dark + 0.75 * (bright - dark), abs=0.02 * bright
    )


def test_dlp_partial_frames_distort_grey_levels_whole_frames_do_not() -> None:
    rig = _rig(noise=False, exposure_ms=16.667, timing={"modulation": "dlp"})
    clock = rig.projector.clock

    def grey(level: int, exposure_s: float) -> float:
        rig.camera.configure(CameraSettings(exposure_ms=exposure_s * 1e3, trigger=TriggerMode.SOFTWARE))
        rig.projector.show(np.full((96, 128), level, np.uint8))
        start = (
            rig.projector.frame_start(clock.now() + rig.projector.latency_s) + 2 * T
        )  # a mirror frame start
        clock.sleep(start - clock.now())
        rig.camera.trigger()
        return float(rig.camera.grab(100).pixels[rig.renderer.view(rig.T_W_C).lit].mean())

    black = grey(0, T)
    one = {v: grey(v, T) - black for v in (127, 128, 255)}
    assert one[128] / one[127] == pytest.approx(128 / 127, rel=0.02)  # whole frame: every bit plane counted
    assert (grey(128, 2 * T) - 2 * black) / one[128] == pytest.approx(2.0, rel=0.02)
    half_black = grey(0, T / 2)
    half = {v: grey(v, T / 2) - half_black for v in (127, 128)}
    assert half[128] < 0.02 * one[255] and half[127] > 0.9 * one[127]  # the MSB plane is in the second half


def test_dlp_profile_refuses_exposures_that_are_not_whole_frames() -> None:
    with pytest.raises(ValueError, match="whole number .* frame periods"):
        small_sensor(projector={"timing": {"modulation": "dlp"}})  # its camera exposes 10 ms at 60 Hz
    small_sensor(camera={"exposure_ms": 33.333}, projector={"timing": {"modulation": "dlp"}})
    data = read_yaml(DEFAULT_CELL)
    data["sensor"]["projector"]["timing"] = {"modulation": "dlp", "refresh_hz": 120.0}
    with pytest.raises(
        ConfigError, match=r"sensor\.camera\.exposure_ms = 16 ms .*8\.3333 ms at 120 Hz"
    ) as err:
        validate(CellConfig, data, "cell.yaml")
    assert "cell.yaml" in str(err.value)


def test_software_trigger_waits_for_the_latency_and_decodes_like_the_truth() -> None:
    rig = _rig()
    stack, log = _stack(rig)
    assert not log.recaptured and log.extra_wait_s == 0
    assert rig.projector.timing.assumed_latency_s() == pytest.approx(4 * T)  # uncalibrated: the upper bound


def test_an_underestimated_latency_is_caught_by_the_pair_check_and_recaptured_exactly() -> None:
    reference, _ = _stack(_rig())
    stack, log = _stack(_rig(timing={"latency_ms": 0.0}))  # believes the light comes at the present
    assert log.recaptured and log.extra_wait_s == pytest.approx(2 * T)
    np.testing.assert_array_equal(stack, reference)


def test_a_latency_beyond_the_recaptures_fails_naming_the_projector() -> None:
    rig = _rig(timing={"latency_ms": 0.0, "max_recaptures": 1})
    with pytest.raises(DeviceProtocolError, match="projector.*inconsistent.*calibrate latency"):
        _stack(rig)


@pytest.mark.parametrize("trigger", [TriggerMode.SOFTWARE, TriggerMode.HARDWARE])
def test_a_mixed_frame_is_recaptured_and_the_stack_is_unchanged(trigger: TriggerMode) -> None:
    calibrated = {"timing": {"latency_ms": 2000 * T + 0.5}}
    reference, _ = _stack(_rig(trigger, **calibrated))
    rig = _rig(trigger, **calibrated)
    presents = {"n": 0}
    original = rig.projector._present

    def present(image: np.ndarray) -> None:
        presents["n"] += 1
        if presents["n"] == 7:
            rig.projector.faults.late_presents = 1  # a missed vblank: light one refresh after the stamp
        original(image)

    rig.projector._present = present
    stack, log = _stack(rig)
    assert GCLS.names[6] in log.recaptured
    np.testing.assert_array_equal(stack, reference)


def test_hardware_trigger_places_frames_by_id_and_recaptures_a_lost_one() -> None:
    reference, _ = _stack(_rig(TriggerMode.HARDWARE))
    rig = _rig(TriggerMode.HARDWARE)
    steps = {"n": 0}
    original = rig.projector.step

    def step() -> int:
        steps["n"] += 1
        if steps["n"] == 5:
            rig.camera.faults.drop_frames = 1  # lost in transport: its frame id is skipped
        return original()

    rig.projector.step = step
    stack, log = _stack(rig)
    assert log.recaptured[0] == GCLS.names[4]
    np.testing.assert_array_equal(stack, reference)


def test_latency_calibration_measures_the_simulated_latency(tmp_path) -> None:
    for frames in (2.0, 3.3):
        rig = _rig(options={"latency_frames": frames})
        m = measure_latency(rig.camera, rig.projector, exposure_ms=10.0)
        assert m.latency_s == pytest.approx(frames * T, abs=2e-4), m.white_share
        assert m.latency_ms > frames * T * 1e3  # what the scan waits includes the margin
    cfg = load_cell_config(DEFAULT_CELL)
    path = save_calibration(tmp_path / "latency", KIND, {}, latency_meta(m, cfg.sensor.projector))
    cell = yaml.safe_load(DEFAULT_CELL.read_text())
    cell["calibration"] = {"latency": str(path)}
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(cell))
    loaded = load_cell_config(tmp_path / "cell.yaml")
    assert loaded.sensor.projector.timing.latency_ms == pytest.approx(m.latency_ms, abs=1e-3)
    cell["sensor"]["projector"]["timing"] = {"refresh_hz": 120.0}
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(cell))
    with pytest.raises(ConfigError, match="120 Hz.*calibrate latency"):
        load_cell_config(tmp_path / "cell.yaml")


def test_calibrate_latency_command_measures_the_default_cell(tmp_path) -> None:
    from cell.cli import main

    out = tmp_path / "latency"
    main(["calibrate", "latency", "--out", str(out), "--max-frames", "4", "--steps-per-frame", "2"])
    meta = yaml.safe_load((out / "latency.yaml").read_text())
    assert meta["kind"] == KIND and meta["projector"]["refresh_hz"] == 60.0
    assert meta["figures"]["measured_ms"] == pytest.approx(2000 * T, abs=0.2)  # the world's 2 frames


def test_serial_projector_path_waits_from_the_hdmi_displays_present_stamp() -> None:
    from cell.config import ProjectorConfig
    from cell.contracts import Frame
    from drivers.serial_projector import SerialProjector
    from fakes.clock import SimClock

    clock = SimClock(0.004)

    class StampingDisplay:  # presents at the next vblank, like HdmiDisplay with vsync
        size = (128, 96)
        last_present_s = float("nan")

        def open(self) -> None: ...

        def close(self) -> None: ...

        def show(self, image: np.ndarray) -> float:
            self.last_present_s = (int(clock.now() / T) + 1) * T
            clock.advance(self.last_present_s - clock.now())
            return self.last_present_s

    class RecordingCamera:
        name, resolution = "camera", (160, 120)

        def __init__(self) -> None:
            self.triggers: list[float] = []

        def trigger(self) -> None:
            self.triggers.append(clock.now())
            clock.advance(0.010)

        def grab(self, timeout_ms: float) -> Frame:
            return Frame(np.zeros((120, 160), np.uint8), self.triggers[-1], len(self.triggers) - 1)

    base = small_sensor().projector.model_dump()
    cfg = ProjectorConfig.model_validate(
        {**base, "driver": "serial", "options": {"port": "unused"}, "timing": {"latency_ms": 30.0}}
    )
    display = StampingDisplay()
    projector = SerialProjector(cfg, display=display, clock=clock)
    camera = RecordingCamera()
    presents: list[float] = []
    show = display.show
    display.show = lambda image: presents.append(show(image)) or presents[-1]  # type: ignore[method-assign]
    capture_stack(camera, projector, GCLS)
    assert len(camera.triggers) == len(presents) == len(GCLS)
    np.testing.assert_allclose(np.array(camera.triggers) - np.array(presents), 0.030, atol=1e-12)


def test_a_camera_with_four_buffers_takes_a_long_hardware_sequence_exactly() -> None:
    """A real driver keeps 4-8 frame buffers: the 26-frame sequence is fetched while it runs, not after."""
    reference, _ = _stack(_rig(TriggerMode.HARDWARE))
    rig = _rig(TriggerMode.HARDWARE)
    rig.camera.buffers = 4
    stack, log = _stack(rig)
    assert log.recaptured == []
    np.testing.assert_array_equal(stack, reference)


def test_frames_left_in_the_camera_beyond_its_buffers_are_lost_and_leave_an_id_gap() -> None:
    rig = _rig()
    rig.camera.buffers = 4
    for _ in range(6):
        rig.camera.trigger()
    ids = [rig.camera.grab(100).frame_id for _ in range(4)]
    with pytest.raises(DeviceTimeout):
        rig.camera.grab(100)
    rig.camera.trigger()
    assert ids == [0, 1, 2, 3] and rig.camera.grab(100).frame_id == 6


def test_a_lost_first_frame_of_a_hardware_sequence_is_placed_by_the_expected_id_and_recaptured() -> None:
    reference, _ = _stack(_rig(TriggerMode.HARDWARE))
    rig = _rig(TriggerMode.HARDWARE)
    original = rig.projector.step

    def step() -> int:
        if rig.projector._index == -1 and rig.camera.faults.drop_frames == 0 and not step.done:
            rig.camera.faults.drop_frames, step.done = 1, True  # the very first exposure never arrives
        return original()

    step.done = False
    rig.projector.step = step
    stack, log = _stack(rig)
    assert log.recaptured == [GCLS.names[0]]
    np.testing.assert_array_equal(stack, reference)


def test_the_camera_buffer_count_is_validated() -> None:
    with pytest.raises(ConfigError, match="options.buffers"):
        small_rig(part_W=PLATE, camera={"options": {"buffers": 0}})
