"""Serial projector peers for tests: a transcript served over a real pseudo-terminal, and a strict transcript.

A transcript is an ordered list of (bytes the host writes, bytes the projector answers) pairs, kept as a
versioned YAML fixture (``fakes/fixtures/projector/*.yaml``, format in docs/fixtures.md). ``None`` as an
answer means the projector stays silent.

* :class:`PtyProjectorEmulator` opens ``os.openpty()``; the driver opens the slave path with pyserial, so the
  real transport, termios settings and byte timing are exercised. It serves the transcript from a thread and
  records every deviation (unexpected write, write past the end) for :meth:`assert_done`.
* :class:`ExpectedProtocol` is an in-process transport in the style of pymeasure's ``expected_protocol``:
  it fails at once on an unexpected write or on a read with nothing pending, and at exit on unused pairs.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from pathlib import Path
from typing import Any

import yaml

Exchange = tuple[bytes, bytes | None]
TRANSCRIPT_FORMAT = 1


def _text(b: bytes) -> str:
    return b.decode("latin-1")  # latin-1 maps every byte to one code point, so any byte string round-trips


def load_transcript(path: str | Path) -> list[Exchange]:
    """Read a transcript fixture; strings are latin-1 so that any byte (garbage included) round-trips."""
    data = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    if data.get("format") != TRANSCRIPT_FORMAT or data.get("kind") != "serial-transcript":
        raise ValueError(f"{path}: not a serial transcript of format {TRANSCRIPT_FORMAT}")
    return [
        (e["write"].encode("latin-1"), None if e["reply"] is None else e["reply"].encode("latin-1"))
        for e in data["exchanges"]
    ]


def save_transcript(path: str | Path, exchanges: list[Exchange], *, device: str, source: str) -> None:
    """Write a transcript fixture (e.g. from :class:`drivers.serial_transport.RecordingTransport`)."""
    doc: dict[str, Any] = {
        "format": TRANSCRIPT_FORMAT,
        "kind": "serial-transcript",
        "device": device,
        "source": source,
        "exchanges": [{"write": _text(w), "reply": None if r is None else _text(r)} for w, r in exchanges],
    }
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(yaml.safe_dump(doc, sort_keys=False, allow_unicode=False), encoding="utf-8")


class PtyProjectorEmulator:
    """Serve a transcript on a pseudo-terminal. ``chunk`` > 0 sends each reply in pieces of that many bytes,
    ``chunk_delay_s`` apart, so the driver sees partial reads."""

    def __init__(self, exchanges: list[Exchange], *, chunk: int = 0, chunk_delay_s: float = 0.0) -> None:
        self._exchanges = list(exchanges)
        self._chunk = chunk
        self._chunk_delay_s = chunk_delay_s
        self.errors: list[str] = []
        self.served = 0
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo or line editing before pyserial configures the port
        self.port = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="projector-emulator", daemon=True)

    def __enter__(self) -> PtyProjectorEmulator:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        os.close(self._master)
        os.close(self._slave)

    def _send(self, reply: bytes) -> None:
        step = self._chunk or len(reply)
        for i in range(0, len(reply), step):
            os.write(self._master, reply[i : i + step])
            if self._chunk_delay_s and i + step < len(reply):
                time.sleep(self._chunk_delay_s)

    def _run(self) -> None:
        buf = b""
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master], [], [], 0.01)
            if not ready:
                continue
            try:
                buf += os.read(self._master, 4096)
            except OSError:
                return
            while buf:
                if self.served >= len(self._exchanges):
                    self.errors.append(f"write {buf!r} after the transcript ended")
                    buf = b""
                    break
                expected, reply = self._exchanges[self.served]
                if buf.startswith(expected):
                    buf = buf[len(expected) :]
                    self.served += 1
                    if reply is not None:
                        self._send(reply)
                elif expected.startswith(buf):
                    break  # wait for the rest of the command
                else:
                    self.errors.append(f"exchange {self.served}: expected {expected!r}, got {buf!r}")
                    buf = b""

    def assert_done(self) -> None:
        """Fail if any write deviated from the transcript or any exchange was left unused."""
        problems = list(self.errors)
        if self.served < len(self._exchanges):
            problems.append(
                f"{len(self._exchanges) - self.served} exchange(s) unused, next "
                f"{self._exchanges[self.served][0]!r}"
            )
        assert not problems, "; ".join(problems)


class ExpectedProtocol:
    """A strict transcript transport: every write must be the next expected one, byte for byte."""

    def __init__(self, exchanges: list[Exchange]) -> None:
        self._exchanges = list(exchanges)
        self._index = 0
        self._pending = b""

    def write(self, data: bytes) -> None:
        assert self._index < len(self._exchanges), f"unexpected write {data!r}: transcript exhausted"
        expected, reply = self._exchanges[self._index]
        assert data == expected, f"exchange {self._index}: expected write {expected!r}, got {data!r}"
        assert not self._pending, f"write {data!r} while reply {self._pending!r} was still unread"
        self._index += 1
        self._pending = reply or b""

    def read(self, timeout_s: float) -> bytes:
        assert self._pending, "read with nothing pending"
        data, self._pending = self._pending, b""
        return data

    def discard_input(self) -> None:
        """Nothing is ever stale here: the driver reads each reply fully."""

    def close(self) -> None:
        pass

    def __enter__(self) -> ExpectedProtocol:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        if exc_type is None:
            left = len(self._exchanges) - self._index
            assert left == 0 and not self._pending, (
                f"{left} exchange(s) unused, reply unread: {self._pending!r}"
            )
