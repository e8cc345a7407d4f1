"""Byte transport for serial devices (pyserial) and reply framing with deadlines.

The transport only moves bytes; the command set lives in a profile (:mod:`drivers.projector_profile`).
Tests swap the transport for a pseudo-terminal peer or a strict transcript (``fakes/projector_emulator.py``).
"""

from __future__ import annotations

import time
from typing import Any, Protocol

from cell.errors import DeviceProtocolError, DeviceTimeout


class Transport(Protocol):
    """What a serial-like link offers: write bytes, read what arrives within a timeout, drop stale input."""

    def write(self, data: bytes) -> None: ...

    def read(self, timeout_s: float) -> bytes:
        """Bytes available now, or the first ones to arrive within ``timeout_s``; b'' if none came."""
        ...

    def discard_input(self) -> None: ...

    def close(self) -> None: ...


class PySerialTransport:
    """A pyserial port: device path or any pyserial URL (``spy://``, ``loop://``, ``rfc2217://``)."""

    def __init__(
        self, url: str, *, baudrate: int = 9600, bytesize: int = 8, parity: str = "N", stopbits: int = 1
    ) -> None:
        import serial  # lazily: pyserial is only needed when a serial device is configured

        self._port: Any = serial.serial_for_url(
            url,
            baudrate=baudrate,
            bytesize=bytesize,
            parity=parity,
            stopbits=stopbits,
            timeout=0,
            write_timeout=2.0,
            exclusive=True,
        )

    def write(self, data: bytes) -> None:
        self._port.write(data)
        self._port.flush()

    def read(self, timeout_s: float) -> bytes:
        self._port.timeout = max(timeout_s, 0.0)
        first = self._port.read(1)
        if not first:
            return b""
        self._port.timeout = 0
        return first + self._port.read(self._port.in_waiting or 0)

    def discard_input(self) -> None:
        self._port.reset_input_buffer()

    def close(self) -> None:
        self._port.close()


class RecordingTransport:
    """Wraps a transport and keeps the traffic as a transcript: [(bytes written, bytes read after it), ...].

    The transcript is what ``fakes/projector_emulator.py`` serves back (saved by :func:`save_transcript`).
    """

    def __init__(self, inner: Transport) -> None:
        self.inner = inner
        self.transcript: list[tuple[bytes, bytes]] = []

    def write(self, data: bytes) -> None:
        self.inner.write(data)
        self.transcript.append((data, b""))

    def read(self, timeout_s: float) -> bytes:
        data = self.inner.read(timeout_s)
        if data and self.transcript:
            w, r = self.transcript[-1]
            self.transcript[-1] = (w, r + data)
        return data

    def discard_input(self) -> None:
        self.inner.discard_input()

    def close(self) -> None:
        self.inner.close()


def read_frame(transport: Transport, prompt: bytes, timeout_s: float, device: str, what: str) -> bytes:
    """Read until the buffer ends with ``prompt`` (partial reads accumulate); return the frame without it.

    Raises DeviceTimeout if nothing arrived within ``timeout_s`` and DeviceProtocolError if bytes arrived
    but never a complete frame (garbage, a cut reply).
    """
    deadline = time.monotonic() + timeout_s
    buf = b""
    while True:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            if buf:
                raise DeviceProtocolError(
                    device,
                    f"{what}: incomplete reply {buf!r} (no {prompt!r} within {timeout_s:g} s); "
                    "check baud rate and cable",
                )
            raise DeviceTimeout(
                device, f"{what}: no reply within {timeout_s:g} s; check power, cable and port settings"
            )
        buf += transport.read(remaining)
        if buf.endswith(prompt):
            return buf[: -len(prompt)]
