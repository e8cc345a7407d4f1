"""Run commands with a small or read-only tmpfs mounted: a real full disk (ENOSPC, numpy's short writes) and a
real read-only file system (EROFS), in a private mount namespace (``unshare``) that disappears with the
shell, so nothing is left mounted and no privilege outside the namespace is needed where user namespaces are
allowed."""

from __future__ import annotations

import functools
import os
import shutil
import subprocess
from pathlib import Path

import pytest


@functools.cache
def unshare_args() -> list[str] | None:
    """The unshare options that let this process mount a tmpfs (a user namespace first, then a plain mount
    namespace for root without user namespaces), or None."""
    if shutil.which("unshare") is None:
        return None
    for args in (["unshare", "-rm"], ["unshare", "-m"]):
        probe = subprocess.run(
            [*args, "sh", "-c", 'd=$(mktemp -d) && mount -t tmpfs -o size=64k tmpfs "$d" && umount "$d"'],
            capture_output=True,
            timeout=30,
        )
        if probe.returncode == 0:
            return args
    return None


def require_tmpfs() -> list[str]:
    """The unshare command, or skip: this machine lets no process mount a tmpfs."""
    args = unshare_args()
    if args is None:
        pytest.skip("no tmpfs can be mounted here (no unshare, or user and mount namespaces not allowed)")
    return args


def run_script(script: str, mount: Path, cwd: Path, timeout: float = 240) -> subprocess.CompletedProcess[str]:
    """Run the shell ``script`` in a private mount namespace; ``$M`` is ``mount`` (made here, empty)."""
    mount.mkdir(parents=True, exist_ok=True)
    return subprocess.run(
        [*require_tmpfs(), "sh", "-c", "set -u\n" + script],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=timeout,
        env={**os.environ, "M": str(mount)},
    )
