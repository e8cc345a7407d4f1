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


class EscVp21Projector:
    """A stateful ESC/VP21 projector behind the Transport interface (write/read/discard_input/close), strict
    where the real one is: commands end with CR; set commands answer ':' or ``ERR`` CR ':'; queries
    ``KEY=VALUE`` CR ':'.

    Behaviour, on ``clock`` (a :class:`fakes.clock.SimClock` shared with the driver, so tests do not wait):

    * ``PWR ON`` from standby answers ':' at once and warms up (``PWR?`` = 02) for ``warmup_s``, then projects
      (01). With ``lamp_failure`` the ignition fails after ``ignition_s``: ``PWR?`` = 05 (abnormal standby),
      ``ERR?`` = 03 (lamp failure at power on), and ``PWR ON`` is refused until the lamp is replaced.
    * ``SOURCE``, ``MUTE`` and their queries are refused (``ERR``) unless projecting; ``SOURCE 30`` is also
      refused until the HDMI signal has been stable for ``signal_settle_s`` (:meth:`signal_on` when the
      pattern display opens; a signal present from the start counts from time 0).
    * Anything else is refused: an unknown or malformed command never gets a ':' alone.
    """

    def __init__(
        self,
        clock: Any,
        *,
        warmup_s: float = 20.0,
        ignition_s: float = 4.0,
        signal_settle_s: float = 3.0,
        lamp_failure: bool = False,
        lamp_hours: int = 1234,
        signal: bool = True,
    ) -> None:
        self.clock = clock
        self.warmup_s, self.ignition_s, self.signal_settle_s = warmup_s, ignition_s, signal_settle_s
        self.lamp_failure = lamp_failure
        self.lamp_hours = lamp_hours
        self.power = "00"
        self.error = "00"
        self.source = "30"
        self.mute = "OFF"
        self._power_on_at = 0.0
        self._signal_since: float | None = 0.0 if signal else None
        self._pending = b""
        self._buffer = b""
        self.commands: list[str] = []

    def signal_on(self) -> None:
        """The HDMI signal appears now (the pattern display opened)."""
        self._signal_since = self.clock.now()

    def _advance(self) -> None:
        if self.power == "02":
            elapsed = self.clock.now() - self._power_on_at
            if self.lamp_failure and elapsed >= self.ignition_s:
                self.power, self.error = "05", "03"
            elif not self.lamp_failure and elapsed >= self.warmup_s:
                self.power = "01"

    def _answer(self, command: str) -> bytes:
        self._advance()
        ok, err = b":", b"ERR\r:"
        projecting = self.power == "01"
        if command == "":
            return ok
        if command == "PWR ON":
            if self.power in ("00", "04"):
                self.power, self._power_on_at = "02", self.clock.now()
                return ok
            return ok if self.power in ("01", "02") else err
        if command == "PWR OFF":
            if self.power != "05":  # abnormal standby stays until the lamp is replaced
                self.power = "00"
            return ok
        queries = {
            "PWR?": f"PWR={self.power}",
            "ERR?": f"ERR={self.error}",
            "LAMP?": f"LAMP={self.lamp_hours}",
        }
        if command in queries:
            return queries[command].encode() + b"\r:"
        if command == "SOURCE?" and projecting:
            return f"SOURCE={self.source}".encode() + b"\r:"
        if command == "MUTE?" and projecting:
            return f"MUTE={self.mute}".encode() + b"\r:"
        if command in ("MUTE ON", "MUTE OFF") and projecting:
            self.mute = command.split()[1]
            return ok
        if command.startswith("SOURCE ") and projecting:
            stable = (
                self._signal_since is not None
                and self.clock.now() - self._signal_since >= self.signal_settle_s
            )
            code = command.split()[1]
            if code == "30" and not stable:
                return err  # no stable signal on the input yet
            if len(code) == 2:
                self.source = code
                return ok
        return err

    # ----------------------------------------------------------------------------------------- transport
    def write(self, data: bytes) -> None:
        self._buffer += data
        while b"\r" in self._buffer:
            line, self._buffer = self._buffer.split(b"\r", 1)
            command = line.decode("ascii", errors="replace")
            self.commands.append(command)
            self._pending += self._answer(command)

    def read(self, timeout_s: float) -> bytes:
        if not self._pending:
            time.sleep(min(timeout_s, 0.002))  # a silent line: let the caller's deadline pass
            return b""
        data, self._pending = self._pending, b""
        return data

    def discard_input(self) -> None:
        self._pending = b""

    def close(self) -> None:
        pass
