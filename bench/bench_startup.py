"""Start-up of the `cell` command: `cell --help`, and for every command its help, a usage error and the first
line of real work, each as a fresh process, wall and CPU time.

Every command line runs ROUNDS times, interleaved (all lines once, then again), so that all see the same load;
the median and best wall time and the median CPU time (user + system) are printed with the load average.

- help: `cell CMD --help` to its end (CPU from the child's rusage);
- usage: `cell CMD --bogus-option` (one line, exit code 2) to its end;
- first line: `cell CMD ...` with real inputs in a scratch folder until its first line of output arrives
  (stdout or stderr, unbuffered); the CPU time is the child's at that moment (/proc/PID/stat, 10 ms ticks),
  then the process group is killed unless it ended first. Heavy commands (inspect, calibrate, ...) are
  killed right after their first line: the figure is how long a user waits to see what the command does.
  The query commands run twice: on a missing runs root (nothing to read) and on a kept one (K/runs, made
  once) whose results database is up to date and whose station users file holds two users, as on a cell PC.
  With ``--history-run RUN`` (a finished inspection's folder; by default the newest in runs/ that has a
  report) K/runs also holds HISTORY_COPIES copies of that run (its inputs, journal, checkpoint and
  report.json), recorded in the database, so `cell history` prints a page of real rows.

With `--base DIR` (an older tree, e.g. `git archive f94ac49 | tar -x -C /tmp/base`) the same lines run from
that tree too, side by side. `--only help,usage` limits the kinds; `--match compare` the command lines.

    .venv/bin/python bench/bench_startup.py [--rounds 3] [--base /tmp/base] [--only first] [--match calib]
"""

from __future__ import annotations

import argparse
import os
import select
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
TICK = os.sysconf("SC_CLK_TCK")
SIM = "recipes/cells/sim_binned.yaml"

# the commands and sub-commands, each with the arguments of one real job (T: the scratch folder)
JOBS: list[tuple[str, list[str]]] = [
    ("inspect", ["recipes/pillar.yaml", "--cell", SIM, "--out", "T/inspect"]),
    ("resume", ["T/inspect"]),
    ("report", ["T/inspect"]),
    ("abort", ["T/inspect"]),
    ("demo", ["--runs", "T/demo", "--cell", SIM, "--no-calibrate"]),
    ("history", ["--runs", "T/runs"]),
    ("prune", ["--runs", "T/runs", "--dry-run"]),
    ("plan", ["recipes/pillar.yaml", "--cell", SIM, "--out", "T/plan"]),
    ("scan", ["--cell", SIM, "--out", "T/scan"]),
    ("compare", ["T/nominal.stl", "T/cloud.ply", "--out", "T/compare", "--table-z", "none"]),
    ("glass", ["recipes/glass/pane.yaml", "--out", "T/glass"]),
    *[
        (f"calibrate {r}", ["--cell", SIM, "--out", f"T/cal-{r}"])
        for r in (
            "sensor",
            "intrinsics",
            "projector",
            "gamma",
            "handeye",
            "kinematics",
            "latency",
            "validate",
        )
    ],
    ("calibrate all", ["--cell", SIM, "--out", "T/cal-all"]),
    ("verify acceptance", ["--cell", SIM, "--out", "T/acceptance"]),
    ("verify check", ["--cell", SIM, "--runs", "T/runs"]),
    ("verify history", ["--runs", "T/runs"]),
    ("sensor error-table", []),
    ("devices", ["--cell", SIM]),
    ("docs", ["--out", "T/docs"]),
    ("station serve", ["--runs", "T/runs", "--port", "18473", "--cell", SIM]),
    ("station users list", ["--runs", "T/runs"]),
]
# first lines only: the query commands on K/runs, a runs root with an up-to-date results.sqlite (with
# --history-run, a hundred runs in it; their answer is read from the database, not skipped because the root
# is missing) and a users file
ON_DATABASE: list[tuple[str, list[str]]] = [
    ("history", ["--runs", "K/runs"]),
    ("verify history", ["--runs", "K/runs"]),
    ("station users list", ["--runs", "K/runs"]),
]
KEPT = "kept"  # the scratch folder of K/, not emptied between rounds
HISTORY_COPIES = 100  # runs recorded in K/runs's database with --history-run: `cell history` prints 50


@dataclass(frozen=True)
class Line:
    kind: str  # "help", "usage", "first"
    args: tuple[str, ...]

    def label(self) -> str:
        return "cell " + " ".join(a if a[:2] not in ("T/", "K/") else a[0] + "/" + a[2:] for a in self.args)


def lines() -> list[Line]:
    out = [Line("help", ("--help",))]
    for name, job in JOBS:
        words = tuple(name.split())
        out.append(Line("help", (*words, "--help")))
        out.append(Line("usage", (*words, "--bogus-option")))
        out.append(Line("first", (*words, *job)))
    out += [Line("first", (*name.split(), *job)) for name, job in ON_DATABASE]
    return out


def _path_args(args: tuple[str, ...], scratch: Path) -> list[str]:
    """T/x: scratch/x (emptied every round); K/x: scratch/kept/x (made once)."""
    roots = {"T/": scratch, "K/": scratch / KEPT}
    return [str(roots[a[:2]] / a[2:]) if a[:2] in roots else a for a in args]


def _cpu_of(pid: int) -> float:
    """utime + stime of a live process (s)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK


def _first_line(proc: subprocess.Popen, timeout_s: float) -> bytes | None:
    """The first line the process writes (or all it wrote before it ended), None after ``timeout_s``."""
    assert proc.stdout is not None
    fd, got, end = proc.stdout.fileno(), b"", time.monotonic() + timeout_s
    while b"\n" not in got:
        ready, _, _ = select.select([fd], [], [], max(0.0, end - time.monotonic()))
        if not ready:
            return None
        chunk = os.read(fd, 4096)
        if not chunk:
            break
        got += chunk
    return got.split(b"\n")[0]


def run_line(tree: Path, line: Line, scratch: Path, timeout_s: float) -> tuple[float, float, str]:
    """Wall and CPU seconds of one run of ``line`` from ``tree``; and the line it printed first. A first
    line that takes longer than ``timeout_s`` counts as inf (the process is killed)."""
    args = _path_args(line.args, scratch)
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONPATH": str(tree), "COLUMNS": "100"}
    t = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "cell", *args],
        cwd=tree,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        stdin=subprocess.DEVNULL,
        start_new_session=True,
    )
    assert proc.stdout is not None
    if line.kind != "first":
        out = proc.stdout.read()
        _, _, ru = os.wait4(proc.pid, 0)
        proc.returncode = 0
        wall = time.perf_counter() - t
        return wall, ru.ru_utime + ru.ru_stime, out.decode(errors="replace").strip().split("\n")[0]
    first = _first_line(proc, timeout_s)
    wall = time.perf_counter() - t if first is not None else float("inf")
    try:
        cpu = _cpu_of(proc.pid)
    except (FileNotFoundError, ProcessLookupError, IndexError):
        cpu = float("nan")  # it ended with that line: use its rusage below
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
    _, _, ru = os.wait4(proc.pid, 0)
    proc.returncode = 0
    if cpu != cpu:
        cpu = ru.ru_utime + ru.ru_stime
    if first is None:
        return wall, float("inf"), f"(no line within {timeout_s:g} s)"
    return wall, cpu, first.decode(errors="replace").strip()


def make_compare_inputs(scratch: Path) -> None:
    """A small nominal and cloud for `cell compare` (bench_compare's sphere, 20k points)."""
    sys.path.insert(0, str(REPO / "bench"))
    from bench_compare import make_inputs

    nominal, cloud = make_inputs(scratch, 20_000)
    shutil.move(cloud, scratch / "cloud.ply")


def newest_reported_run(root: Path = REPO / "runs") -> Path | None:
    """The newest run folder under ``root`` with a results/report.json (None if there is none)."""
    found = sorted(p.parent.parent for p in root.glob("*/results/report.json"))
    return found[-1] if found else None


def copy_run_record(run: Path, runs: Path, copies: int) -> None:
    """``copies`` copies of finished run ``run`` under ``runs`` (what the results database records from a
    run folder: inputs, journal, checkpoint, results/report.json; not the cloud or the pictures)."""
    for k in range(copies):
        dest = runs / f"{run.name}-copy{k:03d}"
        shutil.copytree(run / "inputs", dest / "inputs")
        for name in ("journal.jsonl", "checkpoint.json"):
            shutil.copy2(run / name, dest / name)
        (dest / "results").mkdir()
        shutil.copy2(run / "results" / "report.json", dest / "results" / "report.json")


def make_kept_root(scratch: Path, history_run: Path | None) -> None:
    """K/runs: a runs root whose results.sqlite is created and migrated (by `cell history`), holding
    HISTORY_COPIES records of ``history_run`` when given (`cell history --rebuild`), and whose station users
    file holds two users (`cell station users add`), made once with this tree's `cell`."""
    runs = scratch / KEPT / "runs"
    runs.mkdir(parents=True)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    cell = [sys.executable, "-m", "cell"]
    if history_run is not None:
        copy_run_record(history_run, runs, HISTORY_COPIES)
    make_db = ["history", "--runs", str(runs)] + (["--rebuild"] if history_run is not None else [])
    subprocess.run([*cell, *make_db], cwd=REPO, env=env, check=True, capture_output=True)
    for name in ("anna", "ben"):
        add = [*cell, "station", "users", "add", name, "--pin-stdin", "--runs", str(runs)]
        subprocess.run(add, cwd=REPO, env=env, input=b"1234\n", check=True, capture_output=True)


def reset(scratch: Path) -> None:
    """Empty the output folders of the previous round (commands refuse an --out that holds files)."""
    for child in scratch.iterdir():
        if child.is_dir() and child.name != KEPT:
            shutil.rmtree(child, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--base", type=Path, default=None, help="an older tree to compare with")
    ap.add_argument("--only", default="help,usage,first", help="kinds of line: help, usage, first")
    ap.add_argument("--match", default="", help="only command lines containing this text")
    ap.add_argument("--timeout", type=float, default=60.0, help="seconds to wait for a first line")
    ap.add_argument(
        "--history-run",
        type=Path,
        default=newest_reported_run(),
        help="a finished run folder whose record fills K/runs's database (default: newest in runs/)",
    )
    ap.add_argument("--empty-history", action="store_true", help="K/runs's database holds no runs")
    args = ap.parse_args()
    history_run = None if args.empty_history else args.history_run
    trees = {"now": REPO} | ({"base": args.base} if args.base else {})
    kinds = args.only.split(",")
    todo = [ln for ln in lines() if ln.kind in kinds and args.match in " ".join(ln.args)]
    print(f"nproc {os.cpu_count()}, load average {os.getloadavg()}, {args.rounds} rounds, {len(todo)} lines")
    print(
        f"K/runs's database: {HISTORY_COPIES} copies of {history_run}" if history_run else "K/runs: no runs"
    )
    times: dict[tuple[str, Line], list[tuple[float, float]]] = {(n, ln): [] for n in trees for ln in todo}
    said: dict[tuple[str, Line], str] = {}
    with tempfile.TemporaryDirectory(prefix="bench_startup_") as tmp:
        scratch = Path(tmp)
        make_compare_inputs(scratch)
        make_kept_root(scratch, history_run)
        for _ in range(args.rounds):
            for ln in todo:
                for name, tree in trees.items():
                    reset(scratch)
                    wall, cpu, first = run_line(tree, ln, scratch, args.timeout)
                    times[(name, ln)].append((wall, cpu))
                    said[(name, ln)] = first
    width = max(len(ln.label()) for ln in todo) + 2
    head = "".join(f"{name + ': wall median / best, CPU median (s)':>44s}" for name in trees)
    print(f"{'':7s}{'command line':{width}s}{head}")
    for ln in todo:
        cols = ""
        for n in trees:
            walls, cpus = zip(*times[(n, ln)], strict=True)
            cols += f"{statistics.median(walls):>24.3f} / {min(walls):.3f}, {statistics.median(cpus):.3f}"
        print(f"{ln.kind:7s}{ln.label():{width}s}{cols}")
    if "first" in kinds:
        print("\nfirst line printed (now):")
        for ln in todo:
            if ln.kind == "first":
                print(f"  {ln.label():{width}s}{said[('now', ln)][:110]}")
    print(f"load average after {os.getloadavg()}")


if __name__ == "__main__":
    main()
