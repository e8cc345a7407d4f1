"""One child process at a time per station: the inspection (``cell inspect`` / ``cell resume``) or calibration
routine (``cell calibrate``) the operator started, run exactly as the terminal runs it.

The child runs in a session of its own, so the station can stop or restart without stopping a run (and a
child that ends does not take the station along). Its record (PID, kernel start time, log, exit code) is a
JSON file under ``<runs root>/.station/children/``: a restarted station finds a run still going, follows it.
Pause is SIGINT, what Ctrl-C sends: the controller decides whether and where it pauses (at once in a move,
else at the next step) and journals it. Abort pauses a running run first, then marks it aborted through the
controller's state machine (:func:`cell.inspection_run.abort_run`). Only one run at a time: the station's own
child, or any process holding a run folder's lock under the runs root, keeps a new start out.
"""

from __future__ import annotations

import json
import os
import secrets
import signal
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path

from cell.config import load_cell_config
from cell.errors import ConfigError
from cell.run_data import RunIdentity
from cell.runs import LOCK_NAME, RunFolder, process_alive, process_start, write_json_atomic
from cell.station.journal import StationJournal
from cell.station.progress import TERMINAL, read_progress
from cell.station.recipes import RecipeEntry
from cell.station.settings import StationSettings

REPO = Path(__file__).resolve().parents[2]  # the folder holding the cell package: the child imports it
ROUTINES = ("sensor", "intrinsics", "projector", "gamma", "handeye", "latency", "validate", "all")


@dataclass
class ChildRecord:
    """One child process: which run folder (by name), what it runs, who started it, how it ended."""

    run: str
    kind: str  # inspect, resume, calibrate
    pid: int
    start: str | None  # the kernel's start time of pid: a reused PID is not mistaken for the child
    user: str
    log: str
    began: float
    exit_code: int | None = None
    error: str | None = None
    ended: float | None = None


def _error_line(log: Path) -> str | None:
    """The last ``error: ...`` line of a child's log (the CLI prints one for every error a user can fix), or
    the log's last line."""
    try:
        lines = [line.strip() for line in log.read_text(errors="replace").splitlines() if line.strip()]
    except OSError:
        return None
    errors = [line.removeprefix("error:").strip() for line in lines if line.startswith("error:")]
    return errors[-1] if errors else (lines[-1] if lines else None)


class Supervisor:
    """Starts, pauses, resumes and aborts the station's runs, one at a time."""

    def __init__(self, settings: StationSettings, journal: StationJournal) -> None:
        self.settings = settings
        self.journal = journal
        self.dir = settings.state_dir / "children"
        (self.dir / "ended").mkdir(parents=True, exist_ok=True)
        (settings.state_dir / "logs").mkdir(exist_ok=True)
        self._popen: dict[int, subprocess.Popen[bytes]] = {}
        self._lock = threading.RLock()

    # ------------------------------------------------------------------ records
    def record(self, run: str) -> ChildRecord | None:
        """The latest child record of run folder ``run`` (a running child's, else the last ended one's)."""
        for path in (self.dir / f"{run}.json", self.dir / "ended" / f"{run}.json"):
            try:
                return ChildRecord(**json.loads(path.read_text()))
            except FileNotFoundError:
                continue
            except (OSError, json.JSONDecodeError, TypeError):
                return None
        return None

    def _save(self, rec: ChildRecord) -> None:
        """A running child's record in ``children/``; an ended one's in ``children/ended/`` (so that the
        station's frequent look for the running child reads only the few records of running ones)."""
        if rec.exit_code is None:
            write_json_atomic(self.dir / f"{rec.run}.json", asdict(rec))
            return
        write_json_atomic(self.dir / "ended" / f"{rec.run}.json", asdict(rec))
        (self.dir / f"{rec.run}.json").unlink(missing_ok=True)

    def _alive(self, rec: ChildRecord) -> bool:
        popen = self._popen.get(rec.pid)
        if popen is not None:
            return popen.poll() is None
        return process_alive(rec.pid, rec.start)

    def poll(self) -> None:
        """Reap children that ended: record their exit code and the error they printed."""
        with self._lock:
            for path in sorted(self.dir.glob("*.json")):
                rec = self.record(path.stem)
                if rec is None or rec.exit_code is not None or self._alive(rec):
                    continue
                popen = self._popen.pop(rec.pid, None)
                # a child of an earlier station ended while this one was not watching: its code is unknown,
                # the run folder's journal says how it ended
                rec.exit_code = popen.returncode if popen is not None else -1
                rec.ended = time.time()
                if rec.exit_code != 0:
                    rec.error = _error_line(Path(rec.log))
                self._save(rec)
                self.journal.log("child_ended", run=rec.run, kind=rec.kind, exit_code=rec.exit_code)

    def current(self) -> ChildRecord | None:
        """The station's child that is still running, if any."""
        with self._lock:
            for path in self.dir.glob("*.json"):
                rec = self.record(path.stem)
                if rec is not None and rec.exit_code is None and self._alive(rec):
                    return rec
        return None

    def busy(self) -> str | None:
        """Why no run may start now (a run of this station or any process holding a run folder's lock under
        the runs root), or None."""
        rec = self.current()
        if rec is not None:
            return f"run {rec.run} is in progress (started by {rec.user}); wait for it to end, or pause it"
        for folder in self.settings.runs.iterdir():
            if folder.name == ".station" or not (folder / LOCK_NAME).is_file():
                continue
            run = RunFolder(folder)
            holder = run.lock_holder()
            if holder is not None and run.holder_is_live(holder):
                return (
                    f"run {folder.name} is in progress in another process (PID {holder.get('pid')}, "
                    f"{holder.get('command')}); wait for it to end"
                )
        return None

    # ------------------------------------------------------------------ starting children
    def _spawn(self, run: str, kind: str, user: str, args: list[str]) -> ChildRecord:
        log = self.settings.state_dir / "logs" / f"{run}.{kind}.{int(time.time())}.log"
        env = {
            **os.environ,
            "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])),
        }
        env["PYTHONUNBUFFERED"] = "1"
        with open(log, "wb") as out:
            popen = subprocess.Popen(
                [sys.executable, "-m", "cell", *args],
                stdout=out,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                env=env,
                start_new_session=True,  # the station's end (or Ctrl-C in its terminal) does not reach it
            )
        self._popen[popen.pid] = popen
        rec = ChildRecord(run, kind, popen.pid, process_start(popen.pid), user, str(log), time.time())
        self._save(rec)
        self.journal.log("child_started", run=run, kind=kind, pid=popen.pid, user=user, args=args)
        return rec

    @staticmethod
    def check_identity(serial: str, user: str) -> None:
        """ConfigError for a missing serial or one a folder name cannot hold (the CLI's own check)."""
        if not serial.strip():
            raise ConfigError("scan or type the part's serial number first", field="serial")
        RunIdentity(serial=serial.strip(), operator=user)

    def start_inspection(self, recipe: RecipeEntry, serial: str, user: str) -> ChildRecord:
        """Start ``cell inspect`` of ``recipe`` for part ``serial`` by ``user`` into a new run folder;
        ConfigError for a serial a folder cannot hold or when a run is in progress."""
        self.check_identity(serial, user)
        with self._lock:
            why = self.busy()
            if why:
                raise ConfigError(why)
            name = RunFolder.new_name(recipe.part, serial.strip())
            out = self.settings.runs / name
            args = ["inspect", str(recipe.path), "--cell", str(self.settings.cell), "--out", str(out)]
            args += ["--serial", serial.strip(), "--operator", user]
            if load_cell_config(self.settings.cell).robot.driver == "sim":
                # each simulated part gets its own sensor noise, as each real one does (the manifest keeps
                # the seed, so a resume renders what the run would have)
                args += ["--seed", str(secrets.randbelow(2**31))]
            return self._spawn(name, "inspect", user, args)

    def start_calibration(self, routine: str, user: str) -> ChildRecord:
        """Start ``cell calibrate ROUTINE`` on the station's cell into a new folder under the runs root."""
        if routine not in ROUTINES:
            raise ConfigError(f"unknown calibration routine '{routine}'", field="routine")
        with self._lock:
            why = self.busy()
            if why:
                raise ConfigError(why)
            stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
            name = f"calibration-{routine}-{stamp}"
            out = self.settings.runs / name
            return self._spawn(
                name,
                "calibrate",
                user,
                ["calibrate", routine, "--cell", str(self.settings.cell), "--out", str(out)],
            )

    # ------------------------------------------------------------------ pause, resume, abort
    def _run_dir(self, run: str) -> Path:
        path = self.settings.runs / run
        if "/" in run or run.startswith(".") or not (path / "journal.jsonl").is_file():
            raise ConfigError(f"no run folder named '{run}' under {self.settings.runs}", field="run")
        return path

    def pause(self, run: str, user: str) -> None:
        """Ask the run's process to pause (SIGINT, as Ctrl-C); ConfigError when it is not running here or has
        not started executing yet (its controller is not listening for the request before its first state)."""
        with self._lock:
            rec = self.current()
            if rec is None or rec.run != run:
                raise ConfigError(f"run {run} is not running at this station: nothing to pause")
            state = read_progress(self._run_dir(run)).state
            if state is None or state in TERMINAL:
                why = "still starting" if state is None else state
                raise ConfigError(f"run {run} cannot be paused now: it is {why}; try again in a moment")
            os.kill(rec.pid, signal.SIGINT)
            RunFolder(self.settings.runs / run).log("operator", action="pause", by=user, via="station")
            self.journal.log("pause_requested", run=run, user=user, pid=rec.pid)

    def resume(self, run: str, user: str) -> ChildRecord:
        """Start ``cell resume`` of a stopped run (the library refuses a finished or an aborted one)."""
        with self._lock:
            run_dir = self._run_dir(run)
            why = self.busy()
            if why:
                raise ConfigError(why)
            state = read_progress(run_dir).state
            if state in ("done", "aborted"):
                raise ConfigError(f"run {run} is {state}: it cannot be resumed; start a new run of the part")
            RunFolder(run_dir).log("operator", action="resume", by=user, via="station")
            return self._spawn(run, "resume", user, ["resume", str(run_dir)])

    def abort(self, run: str, user: str, wait_s: float = 120.0) -> str:
        """Abort the run: pause it first if it runs here (and wait up to ``wait_s`` for its process to end),
        then :func:`cell.inspection_run.abort_run`; returns the new state (``aborted``). Blocks: call it from
        a worker thread."""
        from cell.inspection_run import abort_run

        run_dir = self._run_dir(run)
        rec = self.current()
        if rec is not None and rec.run == run:
            self.pause(run, user)
            deadline = time.monotonic() + wait_s
            while self._alive(rec):
                if time.monotonic() > deadline:
                    raise ConfigError(f"run {run} did not pause within {wait_s:.0f} s; try again")
                time.sleep(0.1)
            self.poll()
        with self._lock:
            state = abort_run(run_dir, f"aborted by {user} at the station")
        self.journal.log("aborted", run=run, user=user)
        return state
