"""SerialProjector (Epson ESC/VP21 profile) against transcripts: byte-exact in process, and through a real
pseudo-terminal with pyserial. Expected values come from the transcript fixture, i.e. from what the
projector says, never from the driver."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from cell.config import ProjectorConfig, load_cell_config
from cell.contracts import Projector, ProjectorSource
from cell.errors import ConfigError, DeviceFault, DeviceProtocolError, DeviceTimeout
from drivers.projector_profile import load_profile
from drivers.serial_projector import SerialProjector
from drivers.serial_transport import PySerialTransport, RecordingTransport
from fakes.clock import SimClock
from fakes.projector_emulator import (
    EscVp21Projector,
    ExpectedProtocol,
    PtyProjectorEmulator,
    load_transcript,
    save_transcript,
)

pytestmark = pytest.mark.timeout(10)

ROOT = Path(__file__).resolve().parent.parent
SESSION = ROOT / "fakes" / "fixtures" / "projector" / "escvp21_session.yaml"
TIMEOUT_S = 0.2
RETRIES = 1


def projector_config(port: str = "unused", **options: object) -> ProjectorConfig:
    base = load_cell_config(ROOT / "recipes" / "cells" / "sim.yaml").sensor.projector
    opts = {
        "port": port,
        "profile": "epson_escvp21",
        "reply_timeout_s": TIMEOUT_S,
        "retries": RETRIES,
        **options,
    }
    return ProjectorConfig.model_validate({**base.model_dump(), "driver": "serial", "options": opts})


def run_session(projector: SerialProjector) -> object:
    projector.connect()
    projector.set_power(True)
    projector.set_source(ProjectorSource.HDMI)
    status = projector.status()
    projector.set_power(False)
    return status


def check_session_status(status: object) -> None:
    # PWR=01 (projecting), ERR=00, LAMP=1234, MUTE=OFF, SOURCE=30 (HDMI) in the transcript
    assert status.powered and status.source is ProjectorSource.HDMI
    assert status.lamp_hours == 1234.0 and status.errors == () and status.ready
    assert math.isnan(status.temperature_c)  # ESC/VP21 has no temperature query


def test_session_byte_exact() -> None:
    with ExpectedProtocol(load_transcript(SESSION)) as transport:
        projector = SerialProjector(projector_config(), transport=transport)
        assert isinstance(projector, Projector)
        check_session_status(run_session(projector))


def test_expected_protocol_catches_a_wrong_write() -> None:
    with pytest.raises(AssertionError, match="expected write"):
        with ExpectedProtocol([(b"PWR OFF\r", b":")]) as transport:
            SerialProjector(projector_config(), transport=transport).set_power(True)


def test_expected_protocol_catches_unused_pairs() -> None:
    with pytest.raises(AssertionError, match="unused"):
        with ExpectedProtocol([(b"\r", b":"), (b"PWR OFF\r", b":")]) as transport:
            SerialProjector(projector_config(), transport=transport).connect()


@pytest.mark.parametrize("chunk", [0, 1])
def test_session_over_pty(chunk: int) -> None:
    """The real pyserial transport on a pseudo-terminal; chunk=1 delivers replies byte by byte."""
    with PtyProjectorEmulator(load_transcript(SESSION), chunk=chunk, chunk_delay_s=0.002) as emu:
        projector = SerialProjector(projector_config(emu.port))
        try:
            check_session_status(run_session(projector))
        finally:
            projector.close()
        emu.assert_done()


def test_recorded_transcript_round_trips(tmp_path: Path) -> None:
    """Recording the session through RecordingTransport gives back the served transcript, byte for byte."""
    served = load_transcript(SESSION)
    with PtyProjectorEmulator(served, chunk=3, chunk_delay_s=0.002) as emu:
        recorder = RecordingTransport(PySerialTransport(emu.port))
        projector = SerialProjector(projector_config(emu.port), transport=recorder)
        run_session(projector)
        recorder.close()
    save_transcript(tmp_path / "t.yaml", recorder.transcript, device="test", source="recorded over a pty")
    assert load_transcript(tmp_path / "t.yaml") == served


FAULTS = [
    # (name, served exchanges, expected error, attempts used: the exchanges, all served and no more, as
    # assert_done checks)
    ("silent", [(b"PWR?\r", None)] * 2, DeviceTimeout, 2),
    ("garbage-no-prompt", [(b"PWR?\r", b"\x8f\x03zz\x00")] * 2, DeviceProtocolError, 2),
    ("garbage-framed", [(b"PWR?\r", b"#$%\r:")] * 2, DeviceProtocolError, 2),
    ("wrong-echo", [(b"PWR?\r", b"LAMP=1234\r:")] * 2, DeviceProtocolError, 2),
    ("refused", [(b"PWR?\r", b"ERR\r:")], DeviceFault, 1),
]


@pytest.mark.parametrize("name,served,error,attempts", FAULTS, ids=[f[0] for f in FAULTS])
def test_fault_gives_typed_error_within_timeout(name: str, served: list, error: type, attempts: int) -> None:
    with PtyProjectorEmulator(served) as emu:
        projector = SerialProjector(projector_config(emu.port))
        projector._transport = PySerialTransport(emu.port)  # skip the ping: the fault is on the query
        with pytest.raises(error) as info:
            projector.status()
        projector._transport.close()
        emu.assert_done()  # the refusal is not retried; timeouts and garbage are retried exactly once
    assert info.value.device == "projector" and "PWR?" in str(info.value)
    if error is DeviceTimeout:  # each attempt waited the configured timeout, not a default
        assert f"no reply within {TIMEOUT_S:g} s" in str(info.value)


def test_retry_recovers_after_one_silent_attempt() -> None:
    with PtyProjectorEmulator(
        [(b"PWR?\r", None), (b"PWR?\r", b"PWR=00\r:"), (b"ERR?\r", b"ERR=04\r:"), (b"LAMP?\r", b"LAMP=7\r:")]
    ) as emu:
        projector = SerialProjector(projector_config(emu.port))
        projector._transport = PySerialTransport(emu.port)
        status = projector.status()
        projector._transport.close()
        emu.assert_done()
    # PWR=00 standby: input not queried; ERR=04 is the high-temperature code of the profile
    assert not status.powered and status.source is ProjectorSource.INTERNAL and status.lamp_hours == 7.0
    assert status.errors == ("high internal temperature",) and not status.ready


def test_missing_port_is_a_device_fault() -> None:
    projector = SerialProjector(projector_config("/dev/does-not-exist-ttyUSB9"))
    with pytest.raises(DeviceFault, match="cannot open serial port"):
        projector.connect()


def test_show_checks_shape_and_needs_a_display() -> None:
    import numpy as np

    projector = SerialProjector(projector_config())
    w, h = projector.resolution
    with pytest.raises(DeviceProtocolError, match="uint8 of shape"):
        projector.show(np.zeros((h, w + 1), np.uint8))
    with pytest.raises(DeviceFault, match="no HDMI pattern display"):
        projector.show(np.zeros((h, w), np.uint8))


def test_profile_errors_name_the_problem(tmp_path: Path) -> None:
    text = (ROOT / "drivers" / "profiles" / "epson_escvp21.yaml").read_text()
    bad = tmp_path / "bad.yaml"
    bad.write_text(text.replace("lamp_query:", "lamp_hours_query:"))
    with pytest.raises(ConfigError, match="unknown command name"):
        load_profile(bad)
    assert load_profile("epson_escvp21").serial.baudrate == 9600


# ------------------------------------------------------------------------ behaviour against a stateful peer
class _SignalDisplay:
    """A pattern display whose opening starts the HDMI signal on the emulated projector."""

    def __init__(self, peer: EscVp21Projector, size: tuple[int, int]) -> None:
        self.peer, self.size = peer, size

    def open(self) -> None:
        self.peer.signal_on()

    def show(self, image: object) -> None:
        pass

    def close(self) -> None:
        pass


def _stateful(**behaviour: object) -> tuple[SerialProjector, EscVp21Projector, SimClock]:
    clock = SimClock()
    peer = EscVp21Projector(clock, signal=False, **behaviour)
    cfg = projector_config()
    display = _SignalDisplay(peer, (cfg.width_px, cfg.height_px))
    return SerialProjector(cfg, transport=peer, display=display, clock=clock), peer, clock


def test_source_is_retried_while_the_signal_settles_after_the_display_opens() -> None:
    projector, peer, clock = _stateful(warmup_s=1.0, signal_settle_s=3.0)
    projector.connect()  # opens the display: the signal starts now
    projector.set_power(True)
    assert 1.0 <= clock.now() < 2.0  # returned after the warm-up, polling PWR?
    projector.set_source(ProjectorSource.HDMI)
    assert 3.0 <= clock.now() < 3.6
    assert peer.commands.count("SOURCE 30") > 2  # refused (ERR) while the signal settled, then accepted
    assert projector.status().ready


def test_source_without_a_signal_fails_after_the_retry_window() -> None:
    projector, peer, clock = _stateful(warmup_s=1.0)
    projector._display = None  # nothing ever drives the input
    projector.connect()
    projector.set_power(True)
    start = clock.now()
    with pytest.raises(DeviceFault, match="refused 'SOURCE 30'.*10 s"):
        projector.set_source(ProjectorSource.HDMI)
    assert clock.now() - start == pytest.approx(10.0, abs=0.6)


def test_lamp_failure_is_reported_within_ten_seconds() -> None:
    projector, peer, clock = _stateful(lamp_failure=True, ignition_s=4.0)
    projector.connect()
    with pytest.raises(DeviceFault, match="lamp failure at power on") as err:
        projector.set_power(True)
    assert not err.value.retryable and clock.now() < 10.0
    status = projector.status()
    assert "lamp failure at power on" in status.errors and not status.ready


def test_a_normal_warm_up_is_waited_for() -> None:
    projector, peer, clock = _stateful(warmup_s=20.0)
    projector.connect()
    projector.set_power(True)
    assert 20.0 <= clock.now() <= 21.0 and peer.power == "01"


def test_the_stateful_peer_refuses_what_the_projector_refuses() -> None:
    peer = EscVp21Projector(SimClock())
    for command, reply in (
        (b"SOURCE 30\r", b"ERR\r:"),  # in standby
        (b"MUTE?\r", b"ERR\r:"),
        (b"FOO\r", b"ERR\r:"),
        (b"PWR?\r", b"PWR=00\r:"),
        (b"\r", b":"),
    ):
        peer.write(command)
        assert peer.read(0.1) == reply, command
