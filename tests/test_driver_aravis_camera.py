"""AravisCamera against Aravis's GigE Vision emulator ``arv-fake-gv-camera-0.8`` on 127.0.0.1 (no hardware).

The emulator speaks the real protocols (GVCP control, GVSP streaming) and drops GVSP packets at a given ratio.
Its image is a diagonal ramp, ``((x + y + block_id) % 255) * scale`` with ``scale = 1 + GainRaw +
log10(ExposureTimeAbs / 10000 us)`` (Aravis src/arvfakecamera.c): every frame has an independent truth;
a frame that went through a lossy link must equal the ramp of its block id bit for bit.

The emulator listens on the fixed GVCP port 3956, so one runs at a time: every test here starts its own and
stops it at teardown. Without aravis-tools, gir1.2-aravis-0.8 or PyGObject the tests skip and say which;
CI (``.ci/run``) installs them and sets CELL_REQUIRE_ARAVIS=1, which turns the skip into a failure.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from cell.config import CameraConfig, load_cell_config
from cell.contracts import CameraSettings, PixelFormat, TriggerMode
from cell.errors import DeviceError, DeviceFault, DeviceTimeout
from drivers.aravis_camera import AravisCamera, load_aravis
from drivers.genicam_camera import FrameIdTracker, LostFrames
from tests.contracts.camera_contract import CameraContract
from tests.test_controller import recipe_path  # noqa: F401 - the box recipe fixture of the run test below

EMULATOR = shutil.which("arv-fake-gv-camera-0.8")


def _missing() -> str | None:
    if EMULATOR is None:
        return "arv-fake-gv-camera-0.8 not found (apt-get install aravis-tools; .ci/run installs it)"
    try:
        load_aravis()
    except ImportError as exc:
        return str(exc)
    return None


_WHY = _missing()
if _WHY and os.environ.get("CELL_REQUIRE_ARAVIS"):
    raise RuntimeError(f"CELL_REQUIRE_ARAVIS is set but the Aravis tests cannot run: {_WHY}")

# Known flake, not understood yet: on a loaded 2-core machine the clean emulator has once handed every buffer
# back as 'cleared' (block id 0) for six grabs in a row right after the stream started (CI check, 23 Nov). A
# failing test is run again up to twice; a real driver fault fails all three runs. docs/cameras.md says so.
pytestmark = [
    pytest.mark.timeout(120),
    pytest.mark.skipif(_WHY is not None, reason=_WHY or ""),
    pytest.mark.flaky(reruns=2, reruns_delay=1),
]

WIDTH, HEIGHT = 160, 120


def wait_for_device(serial: str, timeout_s: float = 5.0) -> bool:
    """True once a device with ``serial`` answers GVCP on 127.0.0.1 (opening by address skips Aravis's
    one-second discovery; an absent device costs 2.5 s of GVCP retries, so wait a little first)."""
    Aravis = load_aravis()
    from gi.repository import GLib

    deadline = time.monotonic() + timeout_s
    time.sleep(0.2)
    while time.monotonic() < deadline:
        try:
            if Aravis.Camera.new("127.0.0.1").get_device_serial_number() == serial:
                return True
        except GLib.Error:
            pass
        time.sleep(0.1)
    return False


class Emulator:
    """``arv-fake-gv-camera-0.8`` on loopback with a serial number and a GVSP lost-packet ratio (1/1000)."""

    def __init__(self, serial: str, lost_per_mille: int = 0, genicam: Path | None = None) -> None:
        self.serial, self.lost_per_mille, self.genicam = serial, lost_per_mille, genicam
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> Emulator:
        cmd = [EMULATOR, "-i", "127.0.0.1", "-s", self.serial, "-r", str(self.lost_per_mille)]
        cmd += ["-g", str(self.genicam)] if self.genicam else []
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        if not wait_for_device(self.serial, timeout_s=5.0):
            self.kill()
            out = self.proc.stdout.read().decode(errors="replace") if self.proc.stdout else ""
            raise RuntimeError(f"{' '.join(cmd)} did not come up (is another one on port 3956?): {out}")
        return self

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=5)


@pytest.fixture
def emulator() -> Iterator[Emulator]:
    emu = Emulator("ARV-TEST-0").start()
    yield emu
    emu.kill()


def camera_config(
    serial: str = "ARV-TEST-0", size: tuple[int, int] = (WIDTH, HEIGHT), **options: object
) -> CameraConfig:
    base = load_cell_config(
        Path(__file__).resolve().parent.parent / "recipes" / "cells" / "sim.yaml"
    ).sensor.camera
    return CameraConfig.model_validate(
        {
            **base.model_dump(),
            "driver": "aravis",
            "serial": serial,
            "width_px": size[0],
            "height_px": size[1],
            # the emulator's GainRaw (0..10) has no physical unit; one step per dB is this test's declaration
            "options": {"gain_raw_per_db": 1.0, **options},
        }
    )


def ramp(block_id: int, width: int = WIDTH, height: int = HEIGHT) -> np.ndarray:
    """The emulator's image at GainRaw 0 and 10 ms exposure (scale 1)."""
    y, x = np.mgrid[:height, :width]
    return ((x + y + block_id) % 255).astype(np.uint8)


CLEAN = CameraSettings(exposure_ms=10.0, gain_db=0.0, trigger=TriggerMode.SOFTWARE)


class TestAravisOnEmulator(CameraContract):
    timeout_ms = 1000.0
    refused_settings = (CameraSettings(pixel_format=PixelFormat.MONO12),)  # the emulator offers Mono8/16

    @pytest.fixture
    def camera(self, emulator: Emulator):
        cam = AravisCamera(camera_config())
        yield cam
        cam.close()


def test_exposure_and_gain_read_back_and_gain_auto_is_turned_off(emulator: Emulator) -> None:
    cam = AravisCamera(camera_config())
    cam.connect()
    try:
        cam._dev.set_string_feature_value("GainAuto", "Continuous")  # as a camera may come out of the box
        got = cam.configure(CameraSettings(exposure_ms=7.5, gain_db=3.0, trigger=TriggerMode.SOFTWARE))
        assert cam._dev.get_string_feature_value("GainAuto") == "Off"
        assert cam._dev.get_float_feature_value("ExposureTimeAbs") == pytest.approx(7500.0)
        assert cam._dev.get_integer_feature_value("GainRaw") == 3
        assert (got.exposure_ms, got.gain_db) == (pytest.approx(7.5), 3.0)
        assert cam.resolution == (WIDTH, HEIGHT) == (cam._get("Width", int), cam._get("Height", int))
    finally:
        cam.close()


def test_software_trigger_frames_are_the_emulators_image_with_its_block_ids(emulator: Emulator) -> None:
    cam = AravisCamera(camera_config())
    cam.connect()
    try:
        cam.configure(CLEAN)
        frames = []
        for _ in range(5):
            cam.trigger()
            frames.append(cam.grab(1000))
        blocks = [f.metadata["device_frame_id"] for f in frames]
        assert np.all(np.diff(blocks) == 1) and np.all(np.diff([f.frame_id for f in frames]) == 1)
        for f, block in zip(frames, blocks):
            assert np.array_equal(f.pixels, ramp(block)), f"block {block} differs from the emulator's ramp"
        gained = cam.configure(CameraSettings(exposure_ms=10.0, gain_db=1.0, trigger=TriggerMode.SOFTWARE))
        assert gained.gain_db == 1.0
        cam.trigger()
        f = cam.grab(1000)
        expected = np.minimum(ramp(f.metadata["device_frame_id"]).astype(int) * 2, 255)  # scale 1 + GainRaw
        assert np.array_equal(f.pixels, expected)
    finally:
        cam.close()


def test_pixel_formats_rgb8_and_refused_mono12(emulator: Emulator) -> None:
    cam = AravisCamera(camera_config())
    cam.connect()
    try:
        cam.configure(CameraSettings(pixel_format=PixelFormat.RGB8, trigger=TriggerMode.SOFTWARE))
        cam.trigger()
        f = cam.grab(1000)
        assert f.pixels.shape == (HEIGHT, WIDTH, 3) and f.metadata["pixel_format"] == "RGB8"
        with pytest.raises(
            DeviceFault, match=r"camera: GenApi node PixelFormat of Fake has no entry 'Mono12'"
        ):
            cam.configure(CameraSettings(pixel_format=PixelFormat.MONO12))
    finally:
        cam.close()


def test_a_mode_without_its_nodes_is_refused_naming_device_and_nodes(emulator: Emulator) -> None:
    cam = AravisCamera(camera_config())
    cam.connect()
    try:  # the emulator has TriggerActivation but no LineSelector/LineMode: no hardware trigger on it
        with pytest.raises(
            DeviceFault, match=r"^camera: hardware trigger needs GenApi node\(s\) LineSelector, "
        ):
            cam.configure(CameraSettings(trigger=TriggerMode.HARDWARE))
    finally:
        cam.close()
    raw = AravisCamera(camera_config(gain_raw_per_db=None))
    raw.connect()
    try:
        with pytest.raises(
            DeviceFault, match=r"node Gain is absent on Fake \(it has GainRaw: set .*gain_raw"
        ):
            raw.configure(CLEAN)
    finally:
        raw.close()


def test_genapi_errors_name_the_camera_and_the_node(emulator: Emulator) -> None:
    cam = AravisCamera(camera_config())
    cam.connect()
    try:
        with pytest.raises(
            DeviceFault, match=r"^camera: GenApi node ExposureTimeAbs: 1 us is outside 10\.\.1e\+07"
        ):
            cam.configure(CameraSettings(exposure_ms=1e-3))  # below the node's minimum of 10 us
        with pytest.raises(
            DeviceFault, match=r"^camera: GenApi node TriggerSelector: cannot set 'Bogus' on Fake: "
        ):
            cam._set("TriggerSelector", "Bogus")  # the GenApi error of Aravis, wrapped
    finally:
        cam.close()


def test_unknown_serial_lists_what_is_there(emulator: Emulator) -> None:
    with pytest.raises(DeviceFault, match=r"no camera with serial 'NOPE'.*serials seen: \[.*'ARV-TEST-0'"):
        AravisCamera(camera_config(serial="NOPE")).connect()


def test_stale_frames_are_flushed_before_a_software_trigger(emulator: Emulator) -> None:
    cam = AravisCamera(camera_config())
    cam.connect()
    try:
        cam.configure(CLEAN)
        cam._execute("TriggerSoftware")  # a trigger nobody grabbed: its frame waits in the stream
        time.sleep(0.3)
        cam.trigger()
        f = cam.grab(1000)
        with pytest.raises(DeviceTimeout):
            cam.grab(300)  # nothing else is waiting: the stale ones were dropped, not handed out later
        assert f.frame_id == 2  # ...and counted, so the camera's ids stay continuous
    finally:
        cam.close()


def _grab_many(cam: AravisCamera, n: int) -> list:
    frames = []
    for _ in range(n):
        cam.trigger()
        frames.append(cam.grab(1000))
    return frames


@pytest.mark.slow
def test_lost_packets_make_incomplete_frames_that_are_recaptured_never_used() -> None:
    """2 % of GVSP packets dropped: incomplete frames are detected and captured again; every frame handed
    out equals the emulator's image of its block id bit for bit, as every frame at 0 % loss does."""
    emu = Emulator("ARV-LOSSY", lost_per_mille=20).start()
    cam = AravisCamera(camera_config("ARV-LOSSY", recaptures=10))
    try:
        cam.connect()
        cam.configure(CLEAN)
        frames = _grab_many(cam, 40)
        assert cam.incomplete_frames > 0, "no packet was lost: the test shows nothing"
        for f in frames:
            assert np.array_equal(f.pixels, ramp(f.metadata["device_frame_id"]))
        ids = [f.frame_id for f in frames]
        assert ids == sorted(set(ids))
    finally:
        cam.close()
        emu.kill()


def test_incomplete_frames_beyond_the_recapture_budget_are_an_error() -> None:
    emu = Emulator("ARV-LOSSY", lost_per_mille=200).start()  # 20 %: no frame of ~10 packets gets through
    cam = AravisCamera(camera_config("ARV-LOSSY", recaptures=1))
    try:
        cam.connect()
        cam.configure(CLEAN)
        with pytest.raises(DeviceTimeout, match=r"^camera: frame incomplete \(.*2 incomplete frame"):
            _grab_many(cam, 20)
    finally:
        cam.close()
        emu.kill()


def test_emulator_killed_mid_sequence_is_a_named_device_error_and_the_sequence_resumes() -> None:
    emu = Emulator("ARV-KILL").start()
    cam = AravisCamera(camera_config("ARV-KILL"))
    try:
        cam.connect()
        cam.configure(CLEAN)
        before = _grab_many(cam, 3)
        emu.kill()
        with pytest.raises(DeviceError) as info:  # the controller pauses on a non-retryable DeviceError
            _grab_many(cam, 3)
        assert info.value.device == "camera"  # a named device error, not a hang (the test's timeout)
        assert "TriggerSoftware" in str(info.value) or isinstance(info.value, DeviceTimeout)
        emu = Emulator("ARV-KILL").start()  # the operator restarts the camera; `cell resume` reconnects
        cam.close()
        cam.connect()
        cam.configure(CLEAN)
        after = _grab_many(cam, 3)
        for f in before + after:
            assert np.array_equal(f.pixels, ramp(f.metadata["device_frame_id"]))
    finally:
        cam.close()
        emu.kill()


def test_frame_id_tracker_counts_gaps_and_the_16_bit_wrap() -> None:
    t = FrameIdTracker()
    assert [t.next(b) for b in (65533, 65534, 65535, 1, 2)] == [1, 2, 3, 4, 5]  # GEV 1.x skips id 0
    t.observe(3)  # an incomplete frame the driver dropped: seen, not lost
    assert t.next(4) == 7
    with pytest.raises(LostFrames, match="jumped from 4 to 7: 2 frame"):
        t.next(7)
    t.reset()  # acquisition restarted: the device may count from anywhere
    assert t.next(100) == 11
    t.observe(0)  # an incomplete frame whose leader (and id) was lost: one frame seen
    assert t.next(102) == 13
    t.observe(0)
    with pytest.raises(LostFrames, match="1 frame"):
        t.next(105)


class _IndexProjector:
    """The scan's projector, reduced to what capture_stack asks of it: it writes the index of the pattern it
    shows to a file, which is what the GVSP image server's camera 'sees' (tests/gvsp_image_server.py)."""

    def __init__(self, index_file: Path) -> None:
        self.index_file, self.shown = index_file, -1

    def load_sequence(self, images: list) -> None:
        self.shown = -1

    def step(self) -> int:
        self.shown += 1
        self.index_file.write_text(str(self.shown))
        return self.shown


class _StackCamera:
    """Hands out the already captured image of the pattern the projector shows: the clean reference."""

    name = "stack"

    def __init__(self, images: list, projector: _IndexProjector) -> None:
        self.images, self.projector = images, projector
        self.resolution = images[0].shape[::-1]

    def trigger(self) -> None:
        pass

    def grab(self, timeout_ms: float):
        from cell.contracts import Frame

        return Frame(self.images[self.projector.shown], 0.0, self.projector.shown)


@pytest.mark.slow
def test_a_scan_through_gvsp_at_2_percent_packet_loss_decodes_to_the_clean_cloud(tmp_path: Path) -> None:
    """The simulator's camera images of a tilted plate, streamed by Aravis's fake GV camera over GVSP with 2 %
    of the packets dropped, through AravisCamera and scan_view: the same cloud, bit for bit, as the
    images decoded directly; and packets really were lost (frames were re-captured)."""
    import sys

    import trimesh

    from cell.config import SimConfig
    from cell.geometry import make_pose
    from cell.sensing.patterns import gcls_patterns
    from cell.sensing.scan import capture_stack, scan_view
    from cell.sensing.triangulate import PinholeTriangulator
    from fakes.sim.testing import small_rig

    tilt = make_pose(trimesh.transformations.rotation_matrix(0.2, [1, 0.3, 0])[:3, :3], [0, 0, 30.0])
    rig = small_rig(
        part_W=trimesh.creation.box((400, 300, 4), transform=tilt), bit_depth=8, sim=SimConfig(seed=11)
    )
    rig.projector.connect()
    rig.projector.set_power(True)
    rig.camera.connect()
    rig.camera.configure(CameraSettings(exposure_ms=10.0, pixel_format=PixelFormat.MONO8))
    patterns = gcls_patterns(128, 96, 8, 8)
    images = capture_stack(rig.camera, rig.projector, patterns)
    np.save(tmp_path / "stack.npy", np.stack(images))
    tri = PinholeTriangulator.from_sensor(rig.sensor)
    index = tmp_path / "index"
    index.write_text("0")
    projector = _IndexProjector(index)
    clean = scan_view(_StackCamera(images, projector), projector, patterns, tri, bit_depth=8)

    server = Path(__file__).with_name("gvsp_image_server.py")
    cmd = [sys.executable, str(server), "ARV-SCAN", "20", str(tmp_path / "stack.npy"), str(index)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    cam = AravisCamera(camera_config("ARV-SCAN", rig.camera.resolution, recaptures=10))
    try:
        assert wait_for_device("ARV-SCAN"), "the GVSP image server did not come up"
        cam.connect()
        cam.configure(CLEAN)
        lossy = scan_view(cam, projector, patterns, tri, bit_depth=8)
    finally:
        cam.close()
        proc.kill()
        proc.wait(timeout=5)
    assert cam.incomplete_frames > 0, "no frame lost a packet: the test shows nothing"
    assert clean.cloud.valid.mean() > 0.9
    assert np.array_equal(lossy.cloud.reasons, clean.cloud.reasons)
    assert np.array_equal(lossy.cloud.points_C, clean.cloud.points_C, equal_nan=True)
    print(
        f"{len(patterns)} frames of {rig.camera.resolution} through GVSP at 2 % loss: "
        f"{cam.incomplete_frames} incomplete, re-captured; {int(clean.cloud.valid.sum())} points identical"
    )


def _camera_through_the_emulator(devices, aravis: AravisCamera, kill_at: int | None, emu: Emulator) -> None:
    """The simulated cell's camera, with every trigger and grab also sent through AravisCamera to the
    emulator (its frames are checked against the emulator's ramp, the simulator's are decoded): the run
    meets the real driver's errors. ``kill_at``: the trigger at which the emulator is killed."""
    sim_trigger, sim_grab = devices.camera.trigger, devices.camera.grab
    calls = {"n": 0}

    def trigger() -> None:
        calls["n"] += 1
        if calls["n"] == kill_at:
            emu.kill()
        aravis.trigger()
        sim_trigger()

    def grab(timeout_ms: float):
        frame = aravis.grab(1000)
        assert np.array_equal(frame.pixels, ramp(frame.metadata["device_frame_id"]))
        return sim_grab(timeout_ms)

    devices.camera.trigger, devices.camera.grab = trigger, grab


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_emulator_killed_mid_run_pauses_the_run_with_the_camera_named_and_it_resumes(
    recipe_path: Path,  # noqa: F811
    tmp_path: Path,
) -> None:
    """A whole (simulated) inspection whose camera calls also go through AravisCamera to the emulator: the
    emulator killed at the 40th trigger pauses the run with the camera's named error (not a fault, not a raw
    GLib error); restarted, a new controller resumes the run to the end. (That a resumed run gives the same
    result as an uninterrupted one is tests/test_controller.py's pausing-fault matrix; not repeated here.)"""
    from tests.test_controller import make_controller

    run_dir = tmp_path / "run"
    emu = Emulator("ARV-RUN").start()
    aravis = AravisCamera(camera_config("ARV-RUN"))
    try:
        aravis.connect()
        aravis.configure(CLEAN)
        ctl, devices = make_controller(recipe_path, run_dir)
        _camera_through_the_emulator(devices, aravis, kill_at=40, emu=emu)
        assert ctl.execute() == "paused", ctl.message
        assert ctl.message.startswith("camera: GenApi node TriggerSoftware"), ctl.message
        aravis.close()
        emu = Emulator("ARV-RUN").start()  # the operator powers the camera again; a new process resumes
        aravis.connect()
        aravis.configure(CLEAN)
        ctl2, devices2 = make_controller(recipe_path, run_dir)
        _camera_through_the_emulator(devices2, aravis, kill_at=None, emu=emu)
        assert ctl2.execute(resume=True) == "done", ctl2.message
    finally:
        aravis.close()
        emu.kill()
    assert (run_dir / "results" / "report.json").is_file()


def _genicam_xml(device: object) -> str:
    """The device's GenICam XML. Through ctypes with its length: the GObject binding reads the buffer as a
    NUL-terminated string, which it is not (a random tail, sometimes not UTF-8)."""
    import ctypes

    lib = ctypes.CDLL("libaravis-0.8.so.0")
    lib.arv_device_get_genicam_xml.restype = ctypes.c_void_p
    lib.arv_device_get_genicam_xml.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t)]
    get = ctypes.pythonapi.PyCapsule_GetPointer
    get.restype, get.argtypes = ctypes.c_void_p, [ctypes.py_object, ctypes.c_char_p]
    size = ctypes.c_size_t()
    data = lib.arv_device_get_genicam_xml(get(device.__gpointer__, None), ctypes.byref(size))  # type: ignore[attr-defined]
    return ctypes.string_at(data, size.value).decode()


def _enumeration(name: str, entries: list[str], address: int) -> str:
    """A GenApi enumeration over a 4-byte register of the emulator's plain memory."""
    values = "".join(f'<EnumEntry Name="{e}"><Value>{i}</Value></EnumEntry>' for i, e in enumerate(entries))
    return (
        f'<Enumeration Name="{name}" NameSpace="Standard">{values}<pValue>{name}Reg</pValue></Enumeration>'
        f'<IntReg Name="{name}Reg" NameSpace="Custom"><Address>{address:#x}</Address><Length>4</Length>'
        "<AccessMode>RW</AccessMode><pPort>Device</pPort><Sign>Unsigned</Sign>"
        "<Endianess>BigEndian</Endianess></IntReg>"
    )


@pytest.fixture
def emulator_with_lines(tmp_path: Path) -> Iterator[Emulator]:
    """The emulator with the nodes a real camera has and it lacks (LineSelector, LineMode, ExposureAuto,
    BalanceWhiteAuto, a FallingEdge activation): its own GenICam XML, read from a running one, plus these
    nodes on free registers of its memory (0x140..0x14c; plain read/write memory without behaviour)."""
    emu = Emulator("ARV-XML").start()
    try:
        xml = _genicam_xml(load_aravis().Camera.new("127.0.0.1").get_device())
    finally:
        emu.kill()
    added = (
        _enumeration("LineSelector", ["Line0", "Line1"], 0x140)
        + _enumeration("LineMode", ["Input", "Output"], 0x144)
        + _enumeration("ExposureAuto", ["Off", "Once", "Continuous"], 0x148)
        + _enumeration("BalanceWhiteAuto", ["Off", "Once", "Continuous"], 0x14C)
    )
    rising = '<EnumEntry Name="RisingEdge" NameSpace="Standard">'
    assert xml.count(rising) == 1 and "</RegisterDescription>" in xml
    xml = xml.replace(rising, '<EnumEntry Name="FallingEdge"><Value>1</Value></EnumEntry>' + rising)
    xml = xml.replace("</RegisterDescription>", added + "</RegisterDescription>")
    (tmp_path / "fake-with-lines.xml").write_text(xml)
    emu = Emulator("ARV-LINES", genicam=tmp_path / "fake-with-lines.xml").start()
    yield emu
    emu.kill()


def test_hardware_trigger_sets_line_and_activation_and_auto_features_are_turned_off(
    emulator_with_lines: Emulator,
) -> None:
    cam = AravisCamera(camera_config("ARV-LINES", trigger_source="Line0", trigger_activation="FallingEdge"))
    cam.connect()
    try:
        for auto in ("ExposureAuto", "GainAuto", "BalanceWhiteAuto"):
            cam._set(auto, "Continuous")
        cam._set("LineMode", "Output")
        got = cam.configure(CameraSettings(exposure_ms=10.0, trigger=TriggerMode.HARDWARE))
        read = {n: cam._get(n, str) for n in ("ExposureAuto", "GainAuto", "BalanceWhiteAuto")}
        assert read == dict.fromkeys(read, "Off")
        nodes = ("TriggerMode", "TriggerSource", "TriggerActivation", "LineSelector", "LineMode")
        assert {n: cam._get(n, str) for n in nodes} == {
            "TriggerMode": "On",
            "TriggerSource": "Line0",
            "TriggerActivation": "FallingEdge",
            "LineSelector": "Line0",
            "LineMode": "Input",
        }
        assert got.trigger is TriggerMode.HARDWARE
        # nothing pulses the emulator's Line0: no frame, a retryable timeout that names the trigger mode
        with pytest.raises(
            DeviceTimeout, match=r"^camera: no frame within 300 ms; check the trigger \(hardware\)"
        ):
            cam.grab(300)
        with pytest.raises(DeviceFault, match=r"trigger\(\) needs software trigger, not hardware"):
            cam.trigger()
    finally:
        cam.close()
