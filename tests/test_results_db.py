"""The results database (cell/results): record, query, filter and SPC on SQLite and on a real PostgreSQL
server (tests/postgres_server.py), two cells writing at once, a lost database, a damaged SQLite file, an old
index.sqlite, `cell history`, and one real simulated inspection landing in it with its serial and operator.

Run folders are synthetic but made by the real writers (RunFolder, write_report): each run's deviations are
chosen here, so the expected figures (means, extremes, Cp/Cpk) are computed from them, not from the store.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import multiprocessing
import socket
import sqlite3
import subprocess
import sys
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cell.analysis.regions import Region, Tolerance
from cell.analysis.report import ReportInput, write_report
from cell.cli import main
from cell.results import ResultsDamaged, ResultsStore, ResultsUnavailable, migrate, open_results
from cell.results.folder import PENDING_NAME
from cell.results.migrate import HEAD, current
from cell.run_data import RunIdentity
from cell.runs import RunFolder, write_json_atomic
from cell.verification.history import VerificationHistory, inspection_block
from cell.verification.procedure import AcceptanceResult
from tests.postgres_server import PostgresServer, require_postgres

T0 = datetime(2026, 11, 20, 8, 0, tzinfo=UTC)
N_POINTS = 40  # points 0..39 along x; x < 10: region "left" (the recipe's band), x >= 30: "right" (its own)
BAND = (-0.3, 0.3)
RIGHT_BAND = (-0.1, 0.2)
MPE = {"PF": 0.05, "PS": 0.05, "SD": 0.025, "F": 0.05}


# ---------------------------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def pg_server() -> Iterator[PostgresServer]:
    server = PostgresServer(require_postgres())
    server.start()
    yield server
    server.destroy()


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def db_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """A fresh, empty database of each backend (the PostgreSQL server starts once per module)."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'results.sqlite'}"
    return request.getfixturevalue("pg_server").create_database()


def deviations(offset: float, spread: float = 0.02) -> np.ndarray:
    """A run's deviations (mm): a fixed pattern of +-spread around ``offset``; the right end 0.05 higher."""
    dev = offset + spread * np.sin(np.arange(N_POINTS) * 1.7)
    dev[30:] += 0.05
    return dev


def make_run(
    root: Path,
    name: str,
    dev: np.ndarray,
    *,
    started: datetime = T0,
    part: str = "box",
    cell: str = "cell-a",
    identity: RunIdentity = RunIdentity(),
    state: str | None = "done",
) -> Path:
    """A finished inspection run folder as inspection_run writes one: inputs (recipe, cell config, manifest
    with identity), journal (created, exit), report.json from write_report with ``dev`` (mm) on points
    0..N-1 along x; the journal's times put its start at ``started``."""
    run = RunFolder.create(root, part, name=name)
    (run.path / "inputs" / "recipe.yaml").write_text(
        f"name: {part}\ntolerance: {{lower: -0.3, upper: 0.3}}\n"
    )
    (run.path / "inputs" / "cell.yaml").write_text(f"name: {cell}\n")
    manifest = {
        "recipe": "recipe.yaml",
        "cell": "cell.yaml",
        "identity": identity.to_json(),
        "sources": {"recipe": f"/recipes/{part}.yaml", "cad": f"/recipes/parts/{part}.stl"},
    }
    write_json_atomic(run.path / "inputs" / "manifest.json", manifest)
    run.log("run_created", part=part, **identity.to_json())
    if state is not None:
        points = np.column_stack([np.arange(N_POINTS, dtype=float), np.zeros(N_POINTS), np.zeros(N_POINTS)])
        regions = [
            Region("left", box_mm=((-1, -1, -1), (9.5, 1, 1))),
            Region("right", box_mm=((29.5, -1, -1), (50, 1, 1)), tolerance=Tolerance(*RIGHT_BAND)),
        ]
        inp = ReportInput(points, dev, Tolerance(*BAND), N_POINTS, regions=regions, metadata={"part": part})
        write_report(run.results_dir, inp, pictures=False, csv=False)
        run.log("exit", state=state, message="")
    lines = [json.loads(x) for x in run.journal_path.read_text().splitlines()]
    for k, entry in enumerate(lines):
        entry["t"] = (started + timedelta(seconds=60 * k)).timestamp()
    run.journal_path.write_text("".join(json.dumps(e) + "\n" for e in lines))
    return run.path


def report(run: Path) -> dict:
    return json.loads((run / "results" / "report.json").read_text())


# ---------------------------------------------------------------------------------------------- record, query
def test_record_query_and_filter(db_url: str, tmp_path: Path) -> None:
    root = tmp_path / "runs"
    specs = [  # name, offset, part, serial, operator, day
        ("r0", 0.00, "box", "SN-1", "ann", 0),
        ("r1", 0.40, "box", "SN-2", "bob", 1),  # beyond the band: fail
        ("r2", 0.05, "lid", "SN-3", "ann", 2),
        ("r3", -0.02, "box", "SN-4", "ann", 3),
    ]
    runs = {
        name: make_run(
            root,
            name,
            deviations(off),
            part=part,
            identity=RunIdentity(serial, op),
            started=T0 + timedelta(days=d),
        )
        for name, off, part, serial, op, d in specs
    }
    store = ResultsStore(db_url, root, "cell-a")
    for path in runs.values():
        store.record_run(path)
        store.record_run(path)  # idempotent
    assert current(store.engine) == HEAD

    rows = store.runs()
    assert [r.folder for r in rows] == [
        str(runs[n].resolve()) for n in ("r3", "r2", "r1", "r0")
    ]  # newest first
    r1 = next(r for r in rows if r.serial == "SN-2")
    dev = deviations(0.40)
    assert (r1.cell, r1.part, r1.recipe, r1.operator, r1.status) == ("cell-a", "box", "box", "bob", "done")
    assert r1.verdict == "fail" and report(runs["r1"])["verdict"] == "fail"
    assert (
        r1.recipe_sha256 == hashlib.sha256((runs["r1"] / "inputs" / "recipe.yaml").read_bytes()).hexdigest()
    )
    assert r1.n_points == N_POINTS
    assert r1.dev_min == pytest.approx(dev.min()) and r1.dev_max == pytest.approx(dev.max())
    assert r1.dev_mean == pytest.approx(dev.mean()) and r1.dev_std == pytest.approx(dev.std(), rel=1e-6)
    assert r1.started == T0 + timedelta(days=1) and r1.finished == T0 + timedelta(days=1, minutes=1)

    assert {r.serial for r in store.runs(part="box")} == {"SN-1", "SN-2", "SN-4"}
    assert [r.serial for r in store.runs(serial="SN-3")] == ["SN-3"]
    assert [r.serial for r in store.runs(verdict="fail")] == ["SN-2"]
    assert [r.serial for r in store.runs(operator="ann", part="box")] == ["SN-4", "SN-1"]
    assert [r.serial for r in store.runs(since=T0 + timedelta(days=1), until=T0 + timedelta(days=3))] == [
        "SN-3",
        "SN-2",
    ]
    assert [r.serial for r in store.runs(limit=2)] == ["SN-4", "SN-3"]
    assert [r.serial for r in store.runs(limit=2, offset=2)] == ["SN-2", "SN-1"]
    assert store.distinct("part") == ["box", "lid"] and store.distinct("operator") == ["ann", "bob"]
    assert store.runs(operator="nobody") == []

    # a re-recorded folder updates its row, never adds one
    make_report = report(runs["r0"])
    make_report["verdict"] = "incomplete"
    (runs["r0"] / "results" / "report.json").write_text(json.dumps(make_report))
    store.record_run(runs["r0"])
    assert len(store.runs()) == 4 and store.runs(serial="SN-1")[0].verdict == "incomplete"
    store.close()


def _hand_capability(values: list[float], lower: float, upper: float) -> tuple[float, float, float, float]:
    """Cp, Cpk (sigma from the mean moving range / 1.128, an individuals chart's) and Pp, Ppk (sample s)."""
    n = len(values)
    mean = sum(values) / n
    s = math.sqrt(sum((v - mean) ** 2 for v in values) / (n - 1))
    within = sum(abs(values[i] - values[i - 1]) for i in range(1, n)) / (n - 1) / 1.128
    return (
        (upper - lower) / (6 * within),
        min(upper - mean, mean - lower) / (3 * within),
        (upper - lower) / (6 * s),
        min(upper - mean, mean - lower) / (3 * s),
    )


def test_capability_of_a_drifting_process_shows_pp_below_cp() -> None:
    """Means drifting 0.01 mm a run: from one run to the next the spread is small (Cp high), over the
    series it is large (Pp low), as AIAG's individuals chart tells them apart; shuffled, Pp is unchanged."""
    from cell.results.spc import capability

    drift = [0.01 * k for k in range(10)]
    c = capability(drift, -0.3, 0.3)
    cp, cpk, pp, ppk = _hand_capability(drift, -0.3, 0.3)
    assert (c.cp, c.cpk, c.pp, c.ppk) == pytest.approx((cp, cpk, pp, ppk))
    assert c.cp == pytest.approx(0.6 / (6 * 0.01 / 1.128)) and c.pp < c.cp / 2
    shuffled = capability([drift[k] for k in (3, 8, 0, 6, 1, 9, 4, 7, 2, 5)], -0.3, 0.3)
    assert shuffled.pp == pytest.approx(c.pp) and shuffled.cp < c.cp / 2


def test_spc_figures_against_hand_computation(db_url: str, tmp_path: Path) -> None:
    root = tmp_path / "runs"
    offsets = [0.010, -0.015, 0.030, 0.005, -0.020, 0.012]
    runs = [
        make_run(
            root, f"r{k}", deviations(off), started=T0 + timedelta(hours=k), identity=RunIdentity(f"S{k}")
        )
        for k, off in enumerate(offsets)
    ]
    # not counted: an incomplete run, a running one, another recipe's
    make_run(root, "running", deviations(0.5), started=T0 + timedelta(hours=9), state=None)
    other = make_run(root, "lid", deviations(0.1), part="lid", started=T0)
    bad = make_run(root, "inc", deviations(0.2), started=T0 + timedelta(hours=10))
    doc = report(bad)
    doc["verdict"] = "incomplete"
    (bad / "results" / "report.json").write_text(json.dumps(doc))
    store = ResultsStore(db_url, root)
    for path in [*runs, other, bad, root / "running"]:
        store.record_run(path)

    spc = store.spc("box")
    assert spc.n_runs == len(offsets)
    devs = [deviations(off) for off in offsets]
    expected = {
        "": ([d.mean() for d in devs], [d for d in devs], BAND),
        "left": ([d[:10].mean() for d in devs], [d[:10] for d in devs], BAND),
        "right": ([d[30:].mean() for d in devs], [d[30:] for d in devs], RIGHT_BAND),
    }
    assert [s.name for s in spc.series] == ["", "left", "right"]
    for s in spc.series:
        means, points, band = expected[s.name]
        assert [p.serial for p in s.trend] == [f"S{k}" for k in range(len(offsets))]  # time order
        assert [p.mean_mm for p in s.trend] == pytest.approx(means)
        extremes = [float(p[np.argmax(np.abs(p))]) for p in points]
        assert [p.extreme_mm for p in s.trend] == pytest.approx(extremes)
        cp, cpk, pp, ppk = _hand_capability(means, *band)
        c = s.capability
        assert (c.n, c.lower_mm, c.upper_mm) == (len(offsets), *band)
        assert (c.cp, c.cpk, c.pp, c.ppk) == pytest.approx((cp, cpk, pp, ppk))

    table = list(csv.DictReader(io.StringIO(store.spc_csv("box"))))
    assert len(table) == 3 * len(offsets)
    right = [r for r in table if r["series"] == "region:right"]
    assert [float(r["mean_mm"]) for r in right] == pytest.approx(expected["right"][0], rel=1e-5)
    cap = {r["series"]: r for r in csv.DictReader(io.StringIO(store.spc_csv("box", "capability")))}
    hand = _hand_capability(*expected[""][0:1], *BAND)
    assert float(cap["part"]["cpk"]) == pytest.approx(hand[1], rel=1e-5)
    assert float(cap["part"]["ppk"]) == pytest.approx(hand[3], rel=1e-5)
    one = store.spc("lid")  # one run: no spread, no Cp
    assert one.n_runs == 1 and one.part.capability.cp is None and one.part.capability.mean_mm is not None
    assert store.spc("nothing").n_runs == 0
    store.close()


# ---------------------------------------------------------------------------------------------- two cells
def _record_all(url: str, root: str, folders: list[str], barrier: Any) -> None:
    store = ResultsStore(url, Path(root))
    barrier.wait()  # both processes open a fresh database (migrations) and write at the same moment
    for folder in folders:
        store.record_run(Path(folder))
    store.close()


@pytest.mark.parametrize("backend", [pytest.param("postgresql", marks=pytest.mark.postgres), "sqlite"])
def test_two_cells_write_one_database_at_once(
    backend: str, request: pytest.FixtureRequest, tmp_path: Path
) -> None:
    """Two processes (two cells, each with its runs root) record 50 runs each into one fresh database at
    once: all 100 runs and their 200 region rows arrive."""
    if backend == "postgresql":
        url = request.getfixturevalue("pg_server").create_database()
    else:
        url = f"sqlite:///{tmp_path / 'shared.sqlite'}"
    roots = {cell: tmp_path / cell for cell in ("cell-a", "cell-b")}
    folders = {
        cell: [
            str(
                make_run(
                    root,
                    f"{cell}-{k:02d}",
                    deviations(0.001 * k),
                    cell=cell,
                    identity=RunIdentity(f"{cell}-{k}"),
                )
            )
            for k in range(50)
        ]
        for cell, root in roots.items()
    }
    ctx = multiprocessing.get_context("fork")
    barrier = ctx.Barrier(2)
    procs = [
        ctx.Process(target=_record_all, args=(url, str(roots[cell]), folders[cell], barrier))
        for cell in roots
    ]
    for p in procs:
        p.start()
    for p in procs:
        p.join(timeout=120)
    assert [p.exitcode for p in procs] == [0, 0]
    store = ResultsStore(url, tmp_path)
    rows = store.runs()
    assert len(rows) == 100
    for cell in roots:
        assert sorted(r.serial or "" for r in store.runs(cell=cell)) == sorted(
            f"{cell}-{k}" for k in range(50)
        )
    assert sum(len(s.trend) for s in store.spc("box").regions) == 200
    store.close()


# ---------------------------------------------------------------------------------------------- lost database
@pytest.mark.postgres
def test_lost_postgresql_connection_records_the_run_later(pg_server: PostgresServer, tmp_path: Path) -> None:
    """The server goes down between two runs: the second run's recording says why it failed (journalled,
    a pending marker in its folder), and the next sync, once the server is back, records it."""
    from cell.inspection_run import _record_results

    root = tmp_path / "runs"
    store = ResultsStore(pg_server.create_database(), root)
    first = make_run(root, "first", deviations(0.0), identity=RunIdentity("SN-1"))
    store.record_run(first)
    second = make_run(root, "second", deviations(0.01), identity=RunIdentity("SN-2", "ann"))
    said: list[str] = []
    pg_server.stop()
    try:
        _record_results(RunFolder.open(second), store, said.append)
        with pytest.raises(ResultsUnavailable, match="unavailable while .*cell history --sync"):
            store.runs()
    finally:
        pg_server.start()
    (entry,) = [e for e in RunFolder.open(second).journal() if e["event"] == "results_not_recorded"]
    assert "unavailable" in entry["reason"] and "postgresql://cell@" in entry["database"]
    assert len(said) == 1 and "not recorded" in said[0]
    assert "unavailable" in json.loads((second / PENDING_NAME).read_text())["reason"]
    assert report(second)["verdict"] == "pass"  # the run itself is whole

    assert store.sync() == 1
    assert not (second / PENDING_NAME).exists()
    assert [r.serial for r in store.runs()] == ["SN-2", "SN-1"]  # the same times: by id, newest first
    assert store.runs(serial="SN-2")[0].operator == "ann"
    store.close()


def test_a_killed_run_stays_pending_and_is_recorded_interrupted(tmp_path: Path) -> None:
    """A run records itself as running with its marker kept; killed (its lock left by a dead process), the
    next sync records it as interrupted and removes the marker."""
    root = tmp_path / "runs"
    run = make_run(root, "r", deviations(0.0), state=None)
    folder = RunFolder.open(run)
    folder.acquire_lock("cell inspect")
    store = open_results(None, root)
    assert store.record_or_defer(run) is None
    assert [r.status for r in store.runs()] == ["running"] and (run / PENDING_NAME).is_file()
    folder.release_lock()
    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
    )
    lock = {"pid": int(dead.stdout), "host": socket.gethostname(), "command": "cell inspect"}
    (run / "run.lock").write_text(json.dumps(lock))  # what a SIGKILLed process leaves
    assert store.sync() == 1
    assert [r.status for r in store.runs()] == ["interrupted"] and not (run / PENDING_NAME).exists()


def test_unwritable_sqlite_defers_and_syncs(tmp_path: Path) -> None:
    root = tmp_path / "runs"
    run = make_run(root, "r", deviations(0.0))
    (root / "results.sqlite").mkdir()  # where the file should be, a folder: SQLite cannot open it
    store = open_results(None, root)
    reason = store.record_or_defer(run)
    assert reason is not None and "unavailable" in reason and "results.sqlite" in reason
    assert (run / PENDING_NAME).is_file()
    (root / "results.sqlite").rmdir()
    elsewhere = make_run(root, "pg", deviations(0.0))
    ResultsStore("postgresql://cell@db.plant/results", root).mark_pending(elsewhere, "server down")
    store = open_results(None, root)
    assert len(store.runs()) == 2  # the first open reads the root's folders in
    assert store.sync() == 1 and not (run / PENDING_NAME).exists()
    assert (elsewhere / PENDING_NAME).is_file()  # waits for its own database, not this one


# ---------------------------------------------------------------------------------------------- damaged, old
def test_damaged_sqlite_says_so_and_rebuilds(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = tmp_path / "runs"
    for k in range(3):
        make_run(root, f"r{k}", deviations(0.01 * k), identity=RunIdentity(f"SN-{k}"))
    garbage = b"this is not an SQLite database" * 50
    (root / "results.sqlite").write_bytes(garbage)
    with pytest.raises(ResultsDamaged):
        open_results(None, root).runs()

    with pytest.raises(SystemExit) as exit_:
        main(["history", "--runs", str(root)])
    err = capsys.readouterr().err
    assert exit_.value.code == 1
    assert len(err.strip().splitlines()) == 1 and "damaged" in err and "cell history --rebuild" in err
    assert "Traceback" not in err

    main(["history", "--runs", str(root), "--rebuild"])
    out = capsys.readouterr().out
    assert "rebuilt" in out and "from 3 run folders" in out
    (aside,) = root.glob("results.sqlite.damaged-*")
    assert aside.read_bytes() == garbage  # moved aside, never deleted
    assert sorted(r.serial or "" for r in open_results(None, root).runs()) == ["SN-0", "SN-1", "SN-2"]


def test_old_index_sqlite_is_read_in(tmp_path: Path) -> None:
    """An index.sqlite of RunIndex (runs table) with a verification table: the store reads its rows in
    (a folder still there from the folder itself, a deleted one from the old row) and leaves the file as it
    was."""
    root = tmp_path / "runs"
    kept = make_run(root, "kept", deviations(0.0), identity=RunIdentity("SN-9", "eve"))
    index = root / "index.sqlite"
    with sqlite3.connect(index) as db:
        db.execute(
            "CREATE TABLE runs (folder TEXT PRIMARY KEY, part TEXT, started TEXT, status TEXT, verdict TEXT, "
            "n_points INTEGER, coverage REAL, dev_min REAL, dev_max REAL, updated TEXT)"
        )
        db.execute(  # the verification history's table as cell/verification/history.py made it
            "CREATE TABLE verification (folder TEXT PRIMARY KEY, time TEXT, kind TEXT, cell TEXT, pf REAL, "
            "ps REAL, sd REAL, f REAL, verdict TEXT)"
        )
        db.execute(
            "INSERT INTO verification VALUES ('/old/check', '2026-11-02T06:00:00+00:00', 'check', 'cell-a', "
            "0.01, NULL, 0.031, 0.02, 'fail')"
        )
        for folder, started, verdict in (
            (str(kept), "2026-11-20T08:00:00+00:00", "pass"),
            (str(root / "gone"), "2026-11-01T08:00:00+00:00", "fail"),
        ):
            db.execute(
                "INSERT INTO runs VALUES (?, 'box', ?, 'done', ?, 1000, 0.9, -0.6, 0.1, ?)",
                (folder, started, verdict, started),
            )
    before = index.read_bytes()
    rows = open_results(None, root).runs()
    assert [(r.folder, r.verdict, r.serial) for r in rows] == [
        (str(kept.resolve()), "pass", "SN-9"),
        (str(root / "gone"), "fail", None),
    ]
    assert rows[1].dev_min == pytest.approx(-0.6) and rows[1].started == datetime(2026, 11, 1, 8, tzinfo=UTC)
    (check,) = VerificationHistory(root).entries("cell-a")
    assert (check.folder, check.time, check.verdict) == ("/old/check", "2026-11-02T06:00:00+00:00", "fail")
    assert check.figures_mm == {"PF": 0.01, "PS": None, "SD": 0.031, "F": 0.02}
    assert index.read_bytes() == before


def make_check(root: Path, name: str, cell: str, sd_mm: float, verdict: str) -> Path:
    """A verification folder as `cell verify check` leaves it: verification.json by the real writer."""
    from cell.verification.certificate import load_certificate
    from cell.verification.report import write_json

    result = AcceptanceResult(
        cell, "nominal", {}, MPE, [], figures_mm={"PF": 0.01, "PS": 0.002, "SD": sd_mm, "F": 0.02}
    )
    result.verdict, result.interim = verdict, True
    folder = root / name
    folder.mkdir(parents=True)
    write_json(folder / "verification.json", result, load_certificate(), "Interim check.")
    return folder


@pytest.mark.postgres
def test_verification_history_in_postgresql_follows_the_cell(
    pg_server: PostgresServer, tmp_path: Path
) -> None:
    """With results_db set, a cell's failed check blocks its inspections from any runs root; with the server
    down the block comes from the check folders of the runs root itself, a check made meanwhile is marked
    pending, and the next sync records it."""
    import yaml

    from cell.config import load_cell_config
    from tests.box_part import small_cell

    data = small_cell().model_dump(mode="json")
    cell_file = tmp_path / "cell.yaml"
    cell_file.write_text(yaml.safe_dump({**data, "results_db": pg_server.create_database()}))
    cfg = load_cell_config(cell_file)
    a, b = tmp_path / "a", tmp_path / "b"
    b.mkdir()
    failed = make_check(a, "verify-check-1", cfg.name, 0.031, "fail")
    history = VerificationHistory(a, cfg)
    assert [e.verdict for e in history.entries(cfg.name)] == ["fail"]  # read in from root a's folders
    assert "SD 31.0 um" in (inspection_block(b, cfg.name, True, cfg) or "")  # from another root too
    assert inspection_block(b, "another-cell", True, cfg) is None

    pg_server.stop()
    try:
        assert "SD 31.0 um" in (inspection_block(a, cfg.name, True, cfg) or "")  # the folders say so
        assert inspection_block(b, cfg.name, True, cfg) is None  # b holds no check of this cell
        with pytest.raises(ResultsUnavailable):
            history.entries()
        passed = make_check(a, "verify-check-2", cfg.name, 0.004, "pass")
        history.store.mark_pending(
            passed, "server down"
        )  # as interim_check does when the database refuses it
    finally:
        pg_server.start()
    store = open_results(cfg, a)
    assert store.sync() == 1
    assert [e.folder for e in VerificationHistory(a, cfg).entries(cfg.name)] == [str(failed), str(passed)]
    assert inspection_block(b, cfg.name, True, cfg) is None


def test_the_schema_is_migrated_when_behind_and_only_read_when_up_to_date(
    db_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An up-to-date schema is told from Alembic's version table without running Alembic; the revision
    read is the one Alembic reads, and the known head is Alembic's head of migrations/versions."""
    from alembic.runtime.migration import MigrationContext

    def alembics(engine: Any) -> str | None:
        with engine.connect() as conn:
            return MigrationContext.configure(conn).get_current_revision()

    assert HEAD == migrate.alembic_head()
    engine = ResultsStore(db_url, tmp_path).engine
    assert current(engine) is None and alembics(engine) is None  # empty: no schema yet
    assert migrate.upgrade(engine) is True  # behind: Alembic migrates
    assert current(engine) == alembics(engine) == HEAD

    def no_migration(*_: Any) -> bool:
        raise AssertionError("an up-to-date schema was migrated")

    monkeypatch.setattr(migrate, "_migrate", no_migration)
    assert migrate.upgrade(engine) is False
    store = ResultsStore(db_url, tmp_path)  # a later process: opens and reads without migrating
    assert store.runs() == [] and store.verifications() == []
    engine.dispose()
    store.close()


def test_a_schema_newer_than_the_software_is_refused_untouched(tmp_path: Path) -> None:
    store = ResultsStore(f"sqlite:///{tmp_path / 'results.sqlite'}", tmp_path)
    assert store.runs() == [] and current(store.engine) == HEAD
    store.close()
    with sqlite3.connect(tmp_path / "results.sqlite") as db:
        db.execute("UPDATE alembic_version SET version_num = 'f00d'")
    with pytest.raises(ResultsUnavailable, match=r"revision f00d\) is newer than this software"):
        ResultsStore(f"sqlite:///{tmp_path / 'results.sqlite'}", tmp_path).runs()


def test_a_bad_results_db_url_names_the_field(tmp_path: Path) -> None:
    from cell.config import CellConfig, load_cell_config
    from cell.errors import ConfigError
    from tests.box_part import small_cell

    data = small_cell().model_dump(mode="json")
    path = tmp_path / "cell.yaml"
    import yaml

    path.write_text(yaml.safe_dump({**data, "results_db": "mysql://x@y/z"}))
    with pytest.raises(ConfigError, match="results_db"):
        load_cell_config(path)
    cfg = CellConfig.model_validate({**data, "results_db": "postgresql://cell@db.plant/results"})
    assert open_results(cfg, tmp_path).where == "postgresql://cell@db.plant/results"


# ---------------------------------------------------------------------------------------------- cell history
def test_history_fits_80_columns_filters_and_says_when_empty(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = tmp_path / "runs"
    main(["history", "--runs", str(root)])
    empty = capsys.readouterr().out
    assert "no runs" in empty and "cell inspect" in empty
    long = RunIdentity("SN-" + "7" * 40, "Maximiliane Mustermann-Schmidt")
    make_run(root, "a", deviations(0.0), part="a-very-long-part-name-indeed", identity=long)
    make_run(root, "b", deviations(0.4), identity=RunIdentity("SN-2", "bob"), started=T0 + timedelta(days=1))
    main(["history", "--runs", str(root)])
    said, *lines = capsys.readouterr().out.splitlines()  # first what it reads (a path: as long as it is)
    assert said == f"past runs in {root / 'results.sqlite'}, newest first"
    assert len(lines) == 3 and all(len(line) <= 80 for line in lines)
    dev = deviations(0.4)
    assert "fail" in lines[1] and "SN-2" in lines[1] and f"{dev.min():+.3f}  {dev.max():+.3f}" in lines[1]
    main(["history", "--runs", str(root), "--verdict", "fail"])
    assert len(capsys.readouterr().out.splitlines()) == 3
    main(["history", "--runs", str(root), "--since", "2026-11-21T00:00+00:00", "--operator", "bob"])
    assert len(capsys.readouterr().out.splitlines()) == 3
    main(["history", "--runs", str(root), "--serial", "SN-404"])
    assert "no runs with serial SN-404 in" in capsys.readouterr().out
    main(["history", "--runs", str(root), "--spc", "box", "--csv", str(tmp_path / "box.csv")])
    out = capsys.readouterr().out.splitlines()
    table = [line for line in out if str(tmp_path) not in line]  # the paths are as long as they are
    assert out[0] == f"SPC of recipe 'box' from {root / 'results.sqlite'}"
    assert len(table) == 6 and all(len(line) <= 80 for line in table) and table[4].startswith("left ")
    assert (tmp_path / "box.csv").is_file() and (tmp_path / "box-capability.csv").is_file()
    with pytest.raises(SystemExit) as exit_:
        main(["history", "--runs", str(root), "--since", "last week"])
    assert exit_.value.code == 2 and "--since" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------- a real run
@pytest.mark.slow
def test_a_simulated_inspection_lands_in_the_database(tmp_path: Path) -> None:
    """The box inspected in the simulated cell with a serial and an operator: its row in the runs root's
    database carries them and the verdict and figures of its report."""
    import yaml

    from cell.inspection_run import inspect
    from tests.box_part import small_cell, write_box_recipe

    recipe = write_box_recipe(tmp_path)
    cell = tmp_path / "cell.yaml"
    cell.write_text(yaml.safe_dump(small_cell().model_dump(mode="json")))
    outcome = inspect(
        recipe, cell, tmp_path / "runs" / "box-1", identity=RunIdentity("SN-42", "Ann"), say=lambda _: None
    )
    assert outcome.state == "done"
    (row,) = open_results(None, tmp_path / "runs").runs(serial="SN-42")
    doc = report(outcome.run.path)
    assert (row.operator, row.status, row.verdict, row.part) == ("Ann", "done", doc["verdict"], "box")
    assert row.n_points == doc["n_points"] and row.dev_max == pytest.approx(doc["deviation"]["max_mm"])
    assert not (outcome.run.path / PENDING_NAME).exists()
    assert any(e["event"] == "results_recorded" for e in outcome.run.journal())
