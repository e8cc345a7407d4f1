"""The run folder: every input, state change, view and result of one job, written as it happens.

Layout of a run folder::

    inputs/          copies of the recipe, the cell config, the CAD files and calibration files the run read
    journal.jsonl    one JSON object per line: state changes, device commands, decisions (append + fsync)
    checkpoint.json  what is done: the plan, the completed views, the current step (atomic replace)
    views/NNN/       one folder per measured view (pose, points, masks; raw/ its raw images while the cell's
                     retention keeps them), written atomically (a dir rename); docs/storage.md
    results/         report.json, report.html, cloud.ply, deviations.csv
    run.lock         while a process works on the run: its PID, host and command (one process per folder)

Killing the process at any instant leaves a folder from which the job resumes: a view folder exists whole or
not at all, the checkpoint is replaced atomically, and a torn last journal line is ignored when reading.
What a run's results were is recorded in the results database (``cell.results``: results.sqlite in the runs
root, or the cell's PostgreSQL), a copy of the folders that ``cell history --rebuild`` can make again.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from cell.defaults import RUNS_ROOT as RUNS_ROOT  # re-exported: where the library found it
from cell.errors import ConfigError
from cell.storage import fsync_path, require_writable

INDEX_NAME = "index.sqlite"  # the verification history (cell.verification.history)
LOCK_NAME = "run.lock"
RAW_IMAGES = "raw"  # views/NNN/raw/: a view's raw pattern stack (cell.view_files), what `cell prune` removes


def process_start(pid: int) -> str | None:
    """The kernel's start time of ``pid`` (field 22 of /proc/PID/stat), or None where /proc is missing:
    with the PID it tells a live holder from a new process that reuses a dead holder's PID."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat.rsplit(")", 1)[1].split()[19]


def process_alive(pid: int, start: str | None) -> bool:
    """True while process ``pid`` of this host runs and is the one that started at ``start`` (see
    :func:`process_start`; None: any process of that PID)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process: it exists
        pass
    try:  # a zombie (ended, its parent has not collected it yet) no longer runs
        if Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z":
            return False
    except OSError:
        pass
    now = process_start(pid)
    return start is None or now is None or now == start


def _json_default(value: Any) -> Any:
    import numpy as np  # here, not at the top: a command that only names the runs root stays light

    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that a reader sees the old file or the new one, never a torn one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    fsync_path(path.parent)


def write_json_atomic(path: Path, obj: Any) -> None:
    write_atomic(path, json.dumps(obj, indent=2, default=_json_default).encode())


RESUME_OR_ANOTHER = "choose another --out, or `cell resume` the run that is there"
_UNSAFE = re.compile(r"[^A-Za-z0-9._+-]+")


def folder_safe(text: str) -> str:
    """``text`` as one folder-name component: characters other than letters, digits and ``._+-`` become
    ``_``, leading dots go (no hidden folders, no ``..``), at most 64 characters; never empty."""
    safe = _UNSAFE.sub("_", text).lstrip(".")[:64]
    return safe or "run"


@dataclass
class RunFolder:
    """One run's folder. Create with :meth:`create`, reopen with :meth:`open`."""

    path: Path

    # ------------------------------------------------------------------ creation
    @staticmethod
    def new_name(*parts: str) -> str:
        """``<part>[-<serial>...]-<UTC time>``: the name :meth:`create` gives a run folder. Each part is made
        safe for a folder name first (:func:`folder_safe`): a recipe named ``../x`` names no other folder."""
        stem = "-".join(folder_safe(p) for p in parts if p)
        return f"{stem}-{datetime.now(UTC).strftime('%Y%m%dT%H%M%S%fZ')}"

    @classmethod
    def create(cls, root: Path, part_name: str, *, name: str | None = None) -> RunFolder:
        """A new, empty run folder under ``root`` named :meth:`new_name` unless ``name`` is given."""
        path = require_empty_output(Path(root) / (name or cls.new_name(part_name)), then=RESUME_OR_ANOTHER)
        (path / "inputs").mkdir(parents=True, exist_ok=True)
        (path / "views").mkdir(exist_ok=True)
        (path / "results").mkdir(exist_ok=True)
        return cls(path)

    @property
    def kind(self) -> str | None:
        """What ran in this folder: ``inspection`` (its inputs hold the manifest), the routine's kind that
        :meth:`mark_kind` recorded (a calibration or verification routine), or None (an older routine)."""
        marker = self.path / "inputs" / "routine.txt"
        if marker.is_file():
            return marker.read_text().strip()
        return "inspection" if (self.path / "inputs" / "manifest.json").is_file() else None

    def mark_kind(self, kind: str) -> None:
        """Record that a routine of ``kind`` runs in this folder (see :attr:`kind`)."""
        (self.path / "inputs" / "routine.txt").write_text(kind + "\n")

    @classmethod
    def open(cls, path: Path) -> RunFolder:
        """An existing run folder; ConfigError if it is not one."""
        path = Path(path)
        if not (path / "inputs").is_dir() or not (path / "journal.jsonl").exists():
            raise ConfigError("not a run folder (no inputs/ or journal.jsonl)", path=str(path))
        run = cls(path)
        run._drop_torn_journal_line()
        return run

    def _drop_torn_journal_line(self) -> None:
        """A process killed mid-write leaves a last line without its newline; cut it off so that the next
        entry starts on a line of its own (journal() skips torn lines, but not one glued to a good one)."""
        with open(self.journal_path, "rb+") as f:
            data = f.read()
            if data and not data.endswith(b"\n"):
                f.truncate(data.rfind(b"\n") + 1)

    # ------------------------------------------------------------------ inputs
    def copy_input(self, source: Path, name: str | None = None) -> Path:
        """Copy a file the run reads into inputs/ (once) and return the copy's path."""
        target = self.path / "inputs" / (name or Path(source).name)
        if not target.exists():
            write_atomic(target, Path(source).read_bytes())
        return target

    # ------------------------------------------------------------------ journal
    @property
    def journal_path(self) -> Path:
        return self.path / "journal.jsonl"

    def log(self, event: str, **fields: Any) -> None:
        """Append one journal entry (time, event, fields) and fsync it."""
        entry = {"t": time.time(), "event": event, **fields}
        line = json.dumps(entry, default=_json_default) + "\n"
        with open(self.journal_path, "a", encoding="utf-8") as f:
            f.write(line)
            f.flush()
            os.fsync(f.fileno())

    def started(self) -> datetime | None:
        """When the run was created (UTC): the time of its journal's ``run_created`` entry (the first line of
        a run's journal); in a journal without one (a folder from before that entry), its first entry's;
        without a journal, when ``inputs/manifest.json`` was written; None when there is neither. What the
        report (:mod:`cell.run_record`) and the results database (:mod:`cell.results.folder`) both state."""
        first: float | None = None
        try:
            with open(self.journal_path, encoding="utf-8") as fh:
                for line in fh:
                    try:
                        entry = json.loads(line)
                        t = float(entry["t"])
                    except (ValueError, KeyError, TypeError):
                        continue  # a torn last line
                    if entry.get("event") == "run_created":
                        return datetime.fromtimestamp(t, UTC)
                    first = t if first is None else first
        except OSError:
            pass
        if first is None:
            try:
                first = (self.path / "inputs" / "manifest.json").stat().st_mtime
            except OSError:
                return None
        return datetime.fromtimestamp(first, UTC)

    def journal(self) -> list[dict[str, Any]]:
        """All complete journal entries; a torn last line (the process died mid-write) is skipped."""
        if not self.journal_path.exists():
            return []
        entries = []
        for line in self.journal_path.read_text(encoding="utf-8").splitlines():
            try:
                entries.append(json.loads(line))
            except json.JSONDecodeError:
                continue
        return entries

    # ------------------------------------------------------------------ checkpoint
    @property
    def checkpoint_path(self) -> Path:
        return self.path / "checkpoint.json"

    def save_checkpoint(self, state: dict[str, Any]) -> None:
        write_json_atomic(self.checkpoint_path, state)

    def load_checkpoint(self) -> dict[str, Any] | None:
        if not self.checkpoint_path.exists():
            return None
        return json.loads(self.checkpoint_path.read_text())

    # ------------------------------------------------------------------ views
    def view_dir(self, index: int) -> Path:
        return self.path / "views" / f"{index:03d}"

    @contextmanager
    def writing_view(self, index: int) -> Iterator[Path]:
        """Yield a temporary folder to fill; on success it becomes views/NNN in one rename."""
        final = self.view_dir(index)
        tmp = Path(tempfile.mkdtemp(dir=self.path / "views", prefix=f".{index:03d}."))
        try:
            yield tmp
            for child in sorted(tmp.rglob("*"), reverse=True):  # files before the folders holding them
                if child.is_dir():
                    fsync_path(child)
                    continue
                with open(child, "rb") as f:
                    os.fsync(f.fileno())
            if final.exists():
                shutil.rmtree(final)
            os.replace(tmp, final)
            fsync_path(final.parent)
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)

    def completed_views(self) -> list[int]:
        """Indices of the view folders that exist whole (temp folders of a killed write are ignored)."""
        views = self.path / "views"
        return sorted(int(p.name) for p in views.iterdir() if p.is_dir() and p.name.isdigit())

    def discard_partial_views(self) -> None:
        """Remove temp view folders left by a process that died mid-write."""
        for p in (self.path / "views").iterdir():
            if p.name.startswith("."):
                shutil.rmtree(p, ignore_errors=True)

    @property
    def results_dir(self) -> Path:
        return self.path / "results"

    # ------------------------------------------------------------------ one process per folder
    @property
    def lock_path(self) -> Path:
        return self.path / LOCK_NAME

    def lock_holder(self) -> dict[str, Any] | None:
        """Who holds the run folder (pid, host, command, since), or None when no lock file exists."""
        try:
            return json.loads(self.lock_path.read_text())
        except FileNotFoundError:
            return None
        except (json.JSONDecodeError, OSError):  # torn by a crash while it was written: nobody holds it
            return {"pid": -1, "host": socket.gethostname(), "command": "?", "torn": True}

    def holder_is_live(self, holder: dict[str, Any]) -> bool:
        """True unless the holder is a process of this host that no longer runs (a stale lock)."""
        if holder.get("host") != socket.gethostname():
            return True  # another machine's process cannot be checked from here: assume it runs
        pid = int(holder.get("pid", -1))
        if pid == os.getpid():
            return True
        return pid > 0 and process_alive(pid, holder.get("start"))

    def acquire_lock(self, command: str) -> None:
        """Make this process the only one working on the folder; ConfigError naming the holder if another
        live process has it. A stale lock (its process is gone) is taken over and journalled."""
        me = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "start": process_start(os.getpid()),
            "command": command,
            "since": datetime.now(UTC).isoformat(timespec="seconds"),
        }
        for _ in range(3):
            # the lock appears with its content at once (written aside, then hard-linked into place), so a
            # racing process never reads an empty lock and mistakes it for a torn, stale one
            mine = self.lock_path.with_name(f".{LOCK_NAME}.new-{os.getpid()}")
            with open(mine, "w") as f:
                f.write(json.dumps(me))
                f.flush()
                os.fsync(f.fileno())
            try:
                os.link(mine, self.lock_path)
            except FileExistsError:
                holder = self.lock_holder()
                if holder is None:
                    continue  # released meanwhile: try again
                if holder.get("pid") == me["pid"] and holder.get("host") == me["host"]:
                    return  # this process holds it already
                if self.holder_is_live(holder):
                    raise ConfigError(
                        f"run folder in use by PID {holder.get('pid')} on host {holder.get('host')} "
                        f"({holder.get('command')}, since {holder.get('since')}); wait for it to end or "
                        "pause it (Ctrl-C or SIGTERM). If that process is surely gone, delete "
                        f"{LOCK_NAME} in the folder",
                        path=str(self.path),
                    ) from None
                # stale: rename it away (only one of two racing processes can), then create ours
                stale = self.lock_path.with_name(f".{LOCK_NAME}.stale-{os.getpid()}")
                try:
                    os.replace(self.lock_path, stale)
                except FileNotFoundError:
                    continue
                stale.unlink(missing_ok=True)
                if (self.path / "journal.jsonl").exists():
                    self.log("lock", action="stale lock taken over", stale_holder=holder, holder=me)
                continue
            finally:
                mine.unlink(missing_ok=True)
            return
        raise ConfigError(
            "could not take the run folder's lock (another process races for it)", path=str(self.path)
        )

    def release_lock(self) -> None:
        """Remove the lock if this process holds it (a lock of another process is left alone)."""
        holder = self.lock_holder()
        if holder and holder.get("pid") == os.getpid() and holder.get("host") == socket.gethostname():
            self.lock_path.unlink(missing_ok=True)


def require_empty_output(
    out: Path, *, field: str = "--out", then: str = "choose another folder (results are never written over)"
) -> Path:
    """``out`` as a folder a command may write into: absent or empty, else a ConfigError naming ``field`` and
    saying what to do (``then``); and writable (not on a full disk or a read-only file system: probed, see
    :func:`cell.storage.require_writable`). Results are never written over earlier ones (a compare into a
    scan's folder would replace its cloud.ply; an inspection into a run's folder would mix two runs)."""
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ConfigError(f"{field} holds files already; {then}", path=str(out), field=field)
    require_writable(out, field=field)  # refused before any work: a full disk or read-only folder
    return out
