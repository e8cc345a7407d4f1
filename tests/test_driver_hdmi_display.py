"""HdmiDisplay offscreen (SDL2 from pysdl2-dll, no X server, no GPU): what the back buffer holds after each
present, read back with SDL_RenderReadPixels (glReadPixels under the OpenGL renderer), must equal the image
shown byte for byte; then SerialProjector + a pseudo-terminal ESC/VP21 peer + this display passes the
Projector contract. The truth is the image handed in (random, GCLS stripes, 1-px checkerboard)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from cell.config import ProjectorConfig
from cell.errors import DeviceFault, DeviceProtocolError, DeviceTimeout
from cell.sensing.patterns import gcls_patterns
from drivers.hdmi_display import HdmiDisplay, HdmiDisplayOptions
from drivers.serial_projector import SerialProjector
from fakes.projector_emulator import PtyProjectorEmulator
from tests.contracts.projector_contract import ProjectorContract
from tests.test_driver_serial_projector import projector_config

pytest.importorskip("sdl2", reason="pysdl2 + pysdl2-dll (PyPI) not installed: no offscreen SDL display")

pytestmark = pytest.mark.timeout(30)

# The dummy video driver needs nothing but SDL (software renderer into the window surface); the offscreen
# driver runs SDL's real OpenGL renderer on EGL pbuffers (Mesa's libEGL), which is what a GPU path does.
SOFTWARE = {"video_driver": "dummy", "renderer": "software"}
OPENGL = {"video_driver": "offscreen", "renderer": "opengl"}


def open_display(**options: object) -> HdmiDisplay:
    display = HdmiDisplay(HdmiDisplayOptions(**options))
    try:
        display.open()
    except DeviceFault as exc:
        if options.get("renderer") == "opengl":
            pytest.skip(f"no offscreen OpenGL here (needs libEGL): {exc}")
        raise
    return display


@pytest.fixture(params=[SOFTWARE, OPENGL], ids=["software", "opengl"])
def display(request: pytest.FixtureRequest):
    d = open_display(**request.param)
    yield d
    d.close()


def checkerboard(w: int, h: int) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    return (((xx + yy) % 2) * 255).astype(np.uint8)


def test_random_image_is_read_back_byte_exact_in_every_channel(display: HdmiDisplay) -> None:
    w, h = display.size
    assert (w, h) == (1024, 768)  # SDL's virtual display mode: the texture and window have the mode's size
    img = np.random.default_rng(0).integers(0, 256, size=(h, w), dtype=np.uint8)
    display.show(img)
    np.testing.assert_array_equal(display.current_rgb, np.repeat(img[:, :, None], 3, axis=2))
    np.testing.assert_array_equal(display.current_image, img)


def test_one_pixel_checkerboard_and_its_inverse_survive(display: HdmiDisplay) -> None:
    """Any resampling (scale, linear filter, half-pixel offset) blurs a 1-px checkerboard to grey."""
    board = checkerboard(*display.size)
    for img in (board, 255 - board):
        display.show(img)
        np.testing.assert_array_equal(display.current_image, img)


def test_gcls_stripe_sequence_is_byte_exact(display: HdmiDisplay) -> None:
    w, h = display.size
    patterns = gcls_patterns(w, h, stripe_px=12, n_shifts=12)
    assert len(patterns) > 20
    count0 = display.present_count
    for frame in patterns.frames:
        display.show(frame)
        np.testing.assert_array_equal(display.current_image, frame)
    assert display.present_count - count0 == len(patterns)


def test_show_returns_after_the_present_and_counts_presents() -> None:
    d = open_display(**SOFTWARE)
    try:
        w, h = d.size
        stamps = []
        for value in (0, 128, 255):
            t0 = time.monotonic()
            stamps.append(d.show(np.full((h, w), value, np.uint8)))
            assert t0 <= stamps[-1] <= time.monotonic() and d.last_present_s == stamps[-1]
            assert int(d.current_image[h // 2, w // 2]) == value
        assert d.present_count == 3 and stamps == sorted(stamps)
        assert d.vsync  # requested and granted by the renderer
    finally:
        d.close()


def test_exclusive_mode_and_missing_mode() -> None:
    d = open_display(**SOFTWARE, mode=(1024, 768))
    try:
        assert d.size == (1024, 768)
    finally:
        d.close()
    with pytest.raises(DeviceFault, match="no 640x480 mode"):
        open_display(**SOFTWARE, mode=(640, 480))


def test_wrong_image_or_display_is_refused_with_what_is_wanted() -> None:
    d = HdmiDisplay(HdmiDisplayOptions(**SOFTWARE))
    with pytest.raises(DeviceFault, match="not open"):
        d.show(np.zeros((768, 1024), np.uint8))
    d.open()
    try:
        for bad in (np.zeros((768, 1023), np.uint8), np.zeros((768, 1024), np.uint16)):
            with pytest.raises(DeviceProtocolError, match=r"\(768, 1024\)"):
                d.show(bad)
        with pytest.raises(DeviceFault, match="another HdmiDisplay"):
            HdmiDisplay(HdmiDisplayOptions(**SOFTWARE)).open()
    finally:
        d.close()
    with pytest.raises(DeviceFault, match=r"display 3 requested but SDL sees 1"):
        open_display(**SOFTWARE, display=3)


def test_a_stuck_present_raises_device_timeout_in_time() -> None:
    d = open_display(**SOFTWARE, present_timeout_s=0.1)
    real_present = d._present
    release, flipped = threading.Event(), threading.Event()

    def stuck_present(*args: object) -> float:
        release.wait(30.0)  # a compositor or driver that never flips (until the test lets it)
        stamp = real_present(*args)
        flipped.set()
        return stamp

    d._present = stuck_present  # type: ignore[method-assign]
    try:
        w, h = d.size
        with pytest.raises(DeviceTimeout, match="not presented within 0.1 s"):
            d.show(np.zeros((h, w), np.uint8))
        assert not flipped.is_set()  # show gave up on its own timeout, the present still stuck
    finally:
        release.set()
        d.close()


def test_readback_off_hides_current_image() -> None:
    d = open_display(**SOFTWARE, readback=False)
    try:
        d.show(np.zeros((768, 1024), np.uint8))
        assert not hasattr(d, "current_image")
    finally:
        d.close()


# ------------------------------------------------------------------------- SerialProjector + HDMI contract
def _status(powered: bool, muted: bool) -> list[tuple[bytes, bytes]]:
    """What an ESC/VP21 projector answers to the driver's status() queries (profile reference replies)."""
    out = [
        (b"PWR?\r", b"PWR=01\r:" if powered else b"PWR=00\r:"),
        (b"ERR?\r", b"ERR=00\r:"),
        (b"LAMP?\r", b"LAMP=1234\r:"),
    ]
    if powered:  # input and mute are not queried in standby
        out += [(b"MUTE?\r", b"MUTE=ON\r:" if muted else b"MUTE=OFF\r:"), (b"SOURCE?\r", b"SOURCE=30\r:")]
    return out


PING, OFF = (b"\r", b":"), (b"PWR OFF\r", b":")
ON = [(b"PWR ON\r", b":"), (b"PWR?\r", b"PWR=01\r:")]  # power on, then polled until it projects
HDMI = [(b"SOURCE 30\r", b":"), (b"MUTE OFF\r", b":")]
# The ESC/VP21 traffic each contract test causes, as the projector answers it.
CONTRACT_TRANSCRIPTS: dict[str, list[tuple[bytes, bytes]]] = {
    "test_is_a_projector": [],
    "test_connect_and_close_are_idempotent": [PING, PING, PING],
    "test_power_and_source_show_in_status": [
        PING,
        *ON,
        *HDMI,
        *_status(True, False),
        (b"MUTE ON\r", b":"),
        *_status(True, True),
        OFF,
        *_status(False, True),
        *_status(False, True),
    ],
    "test_show_is_pixel_exact": [PING, *ON],
    "test_show_refuses_wrong_shape_or_dtype": [PING],
    "test_sequence_steps_in_order": [PING, *ON],
    "test_switch_on_makes_it_ready_and_blank": [
        PING,
        *ON,
        *HDMI,
        *_status(True, False),
        OFF,
        *_status(False, False),
    ],
}


def contract_config(port: str) -> ProjectorConfig:
    cfg = projector_config(port)
    options = {**cfg.options, "display": SOFTWARE}
    return cfg.model_copy(update={"options": options})


class TestSerialProjectorWithHdmi(ProjectorContract):
    """The projector the cell builds from its config (SerialProjector(cfg)), with the display from
    options.display, against a pseudo-terminal ESC/VP21 peer."""

    @pytest.fixture
    def projector(self, request: pytest.FixtureRequest):
        name = request.function.__name__
        with PtyProjectorEmulator(CONTRACT_TRANSCRIPTS[name]) as emu:
            projector = SerialProjector(contract_config(emu.port))
            yield projector
            projector.close()
            emu.assert_done()


def test_projector_refuses_a_display_of_another_size() -> None:
    cfg = contract_config("unused")
    cfg = cfg.model_copy(update={"width_px": 800, "height_px": 600})
    with PtyProjectorEmulator([PING]) as emu:
        cfg = cfg.model_copy(update={"options": {**cfg.options, "port": emu.port}})
        projector = SerialProjector(cfg)
        with pytest.raises(DeviceFault, match="HDMI display mode is 1024x768 but the projector is 800x600"):
            projector.connect()
        projector.close()
        emu.assert_done()
    # the display was closed again: another one can open
    open_display(**SOFTWARE).close()
