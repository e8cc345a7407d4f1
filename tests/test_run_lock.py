"""One process per run folder (cell/runs.py): the lock names its holder, refuses a second live process and
takes over the lock of a dead one. Truth: real processes (a live sleeper, an exited child)."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from cell.errors import ConfigError
from cell.runs import RunFolder


def _run(tmp_path: Path) -> RunFolder:
    run = RunFolder.create(tmp_path, "box", name="run")
    run.log("run_created")
    return run


def test_lock_names_this_process_and_is_released(tmp_path: Path) -> None:
    run = _run(tmp_path)
    run.acquire_lock("cell resume")
    holder = run.lock_holder()
    assert holder["pid"] == os.getpid() and holder["host"] == socket.gethostname()
    assert holder["command"] == "cell resume"
    run.acquire_lock("cell resume")  # the holder may take it again
    run.release_lock()
    assert run.lock_holder() is None


def test_a_live_holder_is_refused_by_name(tmp_path: Path) -> None:
    run = _run(tmp_path)
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        live = {"pid": sleeper.pid, "host": socket.gethostname(), "command": "cell inspect", "since": "now"}
        run.lock_path.write_text(json.dumps(live))
        with pytest.raises(ConfigError, match=f"in use by PID {sleeper.pid} on host {socket.gethostname()}"):
            run.acquire_lock("cell resume")
        run.release_lock()  # not ours: left alone
        assert run.lock_holder()["pid"] == sleeper.pid
    finally:
        sleeper.kill()
        sleeper.wait()


def test_a_lock_of_another_host_is_never_taken_over(tmp_path: Path) -> None:
    run = _run(tmp_path)
    run.lock_path.write_text(json.dumps({"pid": 1, "host": "other-pc", "command": "cell resume"}))
    with pytest.raises(ConfigError, match="other-pc"):
        run.acquire_lock("cell resume")


def test_a_stale_lock_is_taken_over_and_journalled(tmp_path: Path) -> None:
    run = _run(tmp_path)
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    stale = {"pid": child.pid, "host": socket.gethostname(), "command": "cell inspect", "since": "then"}
    run.lock_path.write_text(json.dumps(stale))
    run.acquire_lock("cell resume")
    assert run.lock_holder()["pid"] == os.getpid()
    entry = [e for e in run.journal() if e["event"] == "lock"][0]
    assert entry["action"] == "stale lock taken over" and entry["stale_holder"]["pid"] == child.pid


def test_a_reused_pid_does_not_keep_a_lock_alive(tmp_path: Path) -> None:
    """The holder's PID now belongs to another process (this one), started at another time: stale."""
    run = _run(tmp_path)
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        reused = {"pid": sleeper.pid, "host": socket.gethostname(), "start": "1", "command": "cell inspect"}
        run.lock_path.write_text(json.dumps(reused))
        run.acquire_lock("cell resume")
        assert run.lock_holder()["pid"] == os.getpid()
    finally:
        sleeper.kill()
        sleeper.wait()
