"""A serial projector's command set as data: a YAML profile validated here (see drivers/profiles/).

The profile says what bytes to send for each action, what ends a command and a reply, how replies look
(regular expressions with a ``value`` group), how long to wait and how often to retry. The driver
(:mod:`drivers.serial_projector`) knows none of this, so another command set is a new YAML file, not code.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, field_validator

from cell.config import Strict, read_yaml, validate

PROFILE_DIR = Path(__file__).resolve().parent / "profiles"


class SerialSettings(Strict):
    """Line settings, e.g. 9600 8N1."""

    baudrate: Annotated[int, Field(gt=0)] = 9600
    bytesize: Literal[5, 6, 7, 8] = 8
    parity: Literal["N", "E", "O", "M", "S"] = "N"
    stopbits: Literal[1, 2] = 1


class Timing(Strict):
    """Seconds to wait for a reply, extra attempts after a timeout/garbled reply, pause before a command, and
    how power-up and refused commands are waited for."""

    reply_timeout_s: Annotated[float, Field(gt=0, le=600)] = 5.0
    retries: Annotated[int, Field(ge=0, le=10)] = 2
    settle_s: Annotated[float, Field(ge=0, le=10)] = 0.0
    refused_retry_interval_s: Annotated[float, Field(gt=0, le=10)] = 0.5
    power_poll_s: Annotated[float, Field(gt=0, le=10)] = 1.0
    power_on_s: Annotated[float, Field(gt=0, le=600)] = 100.0


class Command(Strict):
    """One command: the text to send (``str.format`` fields allowed) and, for queries, the reply grammar."""

    send: str
    reply: str | None = Field(None, description="regex a query's reply line must match; group 'value'")
    timeout_s: Annotated[float, Field(gt=0, le=600)] | None = None
    retry_refused_s: Annotated[float, Field(ge=0, le=600)] = Field(
        0.0, description="a refusal is retried for this long (e.g. SOURCE while the input signal settles)"
    )

    @field_validator("reply")
    @classmethod
    def _has_value_group(cls, v: str | None) -> str | None:
        if v is not None and "value" not in re.compile(v).groupindex:
            raise ValueError(f"reply pattern {v!r} needs a named group 'value'")
        return v


COMMAND_NAMES = (
    "ping",
    "power_on",
    "power_off",
    "power_query",
    "source_set",
    "source_query",
    "mute_set",
    "mute_query",
    "lamp_query",
    "error_query",
    "temperature_query",
)


class ProjectorProfile(Strict):
    """A whole command set. ``commands`` maps each action of :data:`COMMAND_NAMES` to a Command or null."""

    format: Literal[1]
    name: str
    serial: SerialSettings = SerialSettings()
    encoding: str = "ascii"
    terminator: str
    prompt: str
    error_reply: str
    timing: Timing = Timing()
    commands: dict[str, Command | None]
    power_states: dict[str, str]
    powered_states: list[str]
    warming_states: list[str] = Field(default_factory=list, description="power states to wait through")
    sources: dict[Literal["hdmi"], str]
    error_codes: dict[str, str] = Field(default_factory=dict)

    @field_validator("commands")
    @classmethod
    def _known_commands(cls, v: dict[str, Command | None]) -> dict[str, Command | None]:
        unknown = set(v) - set(COMMAND_NAMES)
        if unknown:
            raise ValueError(f"unknown command name(s) {sorted(unknown)}; known: {list(COMMAND_NAMES)}")
        for required in ("ping", "power_on", "power_off", "power_query", "source_set"):
            if v.get(required) is None:
                raise ValueError(f"command '{required}' is required")
        return v

    def command(self, name: str) -> Command | None:
        return self.commands.get(name)


def load_profile(name_or_path: str | Path) -> ProjectorProfile:
    """Load a profile by bare name or by path; ConfigError if invalid."""
    p = Path(name_or_path)
    if p.suffix not in (".yaml", ".yml"):
        p = PROFILE_DIR / f"{name_or_path}.yaml"
    return validate(ProjectorProfile, read_yaml(p), p)
