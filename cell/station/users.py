"""The station's users: a small YAML file of names, roles and PINs hashed with scrypt (hashlib, a slow KDF:
about 50 ms and 16 MiB per try, so a stolen file cannot be brute-forced like a plain hash of 4-8 digits).

Roles: ``operator`` (inspect, pause, resume, abort, read results) and ``technician`` (also calibration
routines and recipe edits). ``cell station users add NAME --role ROLE`` adds or replaces a user.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import os
import re
from enum import StrEnum
from functools import cache
from pathlib import Path

import yaml
from pydantic import Field

from cell.errors import ConfigError
from cell.schema import Strict
from cell.yaml_files import read_yaml, validate

_SCRYPT = {"n": 2**14, "r": 8, "p": 1}  # OWASP's minimum for scrypt; ~50 ms here
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9 ._-]{0,31}")
_PIN = re.compile(r"[0-9]{4,12}")


class Role(StrEnum):
    """What a user may do at the station."""

    OPERATOR = "operator"
    TECHNICIAN = "technician"


class User(Strict):
    """One user: a name, a role, and the PIN's scrypt hash (``scrypt$n$r$p$salt$hash``, base64)."""

    name: str = Field(pattern=_NAME.pattern)
    role: Role
    pin_hash: str = Field(pattern=r"^scrypt\$\d+\$\d+\$\d+\$[A-Za-z0-9+/=]+\$[A-Za-z0-9+/=]+$")


class UsersFile(Strict):
    """The users file's contents."""

    users: list[User] = Field(default_factory=list)

    def find(self, name: str) -> User | None:
        """The user of that name (names compare without regard to case), or None."""
        return next((u for u in self.users if u.name.casefold() == name.strip().casefold()), None)


def hash_pin(pin: str) -> str:
    """The scrypt hash of ``pin`` with a fresh 16-byte salt, in the users file's format."""
    salt = os.urandom(16)
    digest = hashlib.scrypt(pin.encode(), salt=salt, dklen=32, **_SCRYPT)
    b64 = base64.b64encode
    return f"scrypt${_SCRYPT['n']}${_SCRYPT['r']}${_SCRYPT['p']}${b64(salt).decode()}${b64(digest).decode()}"


def pin_matches(pin: str, pin_hash: str) -> bool:
    """True when ``pin`` hashes to ``pin_hash`` (compared in constant time)."""
    _, n, r, p, salt, digest = pin_hash.split("$")
    expected = base64.b64decode(digest)
    got = hashlib.scrypt(
        pin.encode(), salt=base64.b64decode(salt), n=int(n), r=int(r), p=int(p), dklen=len(expected)
    )
    return hmac.compare_digest(got, expected)


def load_users(path: Path) -> UsersFile:
    """The users file; ConfigError naming the file and field when it is invalid."""
    return validate(UsersFile, read_yaml(path), path)


def authenticate(users: UsersFile, name: str, pin: str) -> User | None:
    """The user when ``name`` and ``pin`` match, else None. An unknown name costs the same scrypt as a wrong
    PIN, so the answer's timing does not tell which names exist."""
    user = users.find(name)
    matches = pin_matches(pin, user.pin_hash if user else _dummy_hash())
    return user if user is not None and matches else None


def add_user(path: Path, name: str, role: Role, pin: str) -> bool:
    """Add (or replace, keeping its place) the user ``name`` in the users file, creating the file; returns
    True when a user was replaced. ConfigError for a name or PIN of the wrong form."""
    if not _NAME.fullmatch(name):
        raise ConfigError(
            "a name is 1-32 letters, digits, spaces and . _ -, starting with a letter or digit", field="NAME"
        )
    if not _PIN.fullmatch(pin):
        raise ConfigError("a PIN is 4 to 12 digits", field="PIN")
    from cell.runs import write_atomic  # here: listing the users writes nothing

    users = load_users(path) if path.exists() else UsersFile()
    user = User(name=name, role=role, pin_hash=hash_pin(pin))
    old = users.find(name)
    if old is not None:
        users.users[users.users.index(old)] = user
    else:
        users.users.append(user)
    text = "# cell station users: `cell station users add NAME --role operator|technician`\n"
    text += yaml.safe_dump(users.model_dump(mode="json"), sort_keys=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, text.encode())
    os.chmod(path, 0o600)
    return old is not None


@cache
def _dummy_hash() -> str:
    return hash_pin("0000")
