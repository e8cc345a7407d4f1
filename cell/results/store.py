"""The results store: every inspection run's summary, per-region statistics and identity, in an SQLite file
in the runs root (the default) or in a plant's PostgreSQL (the cell config's ``results_db``).

The run folders stay the truth: a row is a copy of what a folder holds (:mod:`cell.results.folder`), so a
lost database is never a lost run. A run whose results could not be written keeps a pending marker in its
folder and is recorded by the next :meth:`ResultsStore.sync`; a damaged SQLite file is moved aside and the
store rebuilt from the folders (:meth:`ResultsStore.rebuild`).
"""

from __future__ import annotations

import socket
import sqlite3
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

from sqlalchemy import Connection, Engine, and_, create_engine, delete, event, exc, select
from sqlalchemy.engine import make_url

from cell.results import folder as fold
from cell.results.errors import ResultsDamaged, ResultsUnavailable
from cell.results.migrate import upgrade
from cell.results.schema import imported_roots, regions, runs, verifications
from cell.results.spc import PART, Spc, TrendPoint, series, to_csv

SQLITE_NAME = "results.sqlite"
LEGACY_INDEX = "index.sqlite"  # the runs table of the index before this store (cell.runs.RunIndex)
CONNECT_TIMEOUT_S = 5
FINISHED = ("pass", "fail")  # the verdicts SPC counts


@dataclass(frozen=True)
class RunRow:
    """One run as the store lists it. Times are aware UTC; deviations are signed, mm."""

    folder: str
    cell: str
    recipe: str
    recipe_sha256: str | None
    part: str
    serial: str | None
    operator: str | None
    order: str | None
    started: datetime
    finished: datetime | None
    status: str
    verdict: str | None
    n_points: int | None
    coverage: float | None
    dev_min: float | None
    dev_max: float | None
    dev_mean: float | None
    dev_std: float | None


@dataclass(frozen=True)
class VerificationRow:
    """One stored verification (``cell verify check`` or an acceptance test): figures in mm."""

    cell: str
    folder: str
    kind: str
    time: datetime
    figures_mm: dict[str, float | None]
    verdict: str


def _row(r: Any) -> RunRow:
    m = r._mapping
    return RunRow(
        **{k: m[k] for k in RunRow.__dataclass_fields__ if k != "order"}, order=m["production_order"]
    )


def _short(error: BaseException) -> str:
    orig = getattr(error, "orig", None) or error
    text = str(orig).strip().splitlines()
    return text[0] if text else type(orig).__name__


class ResultsStore:
    """One results database. Cheap to open: it connects (and creates or upgrades the schema, and reads in
    the runs root's folders the first time it meets them) on first use. Every method raises
    ResultsUnavailable or ResultsDamaged, never a driver's exception."""

    def __init__(self, url: str, runs_root: Path, cell: str = "") -> None:
        self.url = make_url(url)
        self.runs_root = Path(runs_root).resolve()
        self.cell = cell
        self._engine: Engine | None = None
        self._migrated = False
        self._imported = False

    # ------------------------------------------------------------------ connection
    @property
    def where(self) -> str:
        """The database for messages, password hidden."""
        if self.is_sqlite:
            return str(self.sqlite_path)
        from urllib.parse import unquote

        return unquote(self.url.render_as_string(hide_password=True))

    @property
    def is_sqlite(self) -> bool:
        return self.url.get_backend_name() == "sqlite"

    @property
    def sqlite_path(self) -> Path | None:
        return Path(self.url.database) if self.is_sqlite and self.url.database else None

    @property
    def engine(self) -> Engine:
        if self._engine is None:
            if self.is_sqlite:
                engine = create_engine(self.url, connect_args={"timeout": 30})
                event.listen(engine, "connect", _sqlite_connect)
                event.listen(engine, "begin", _sqlite_begin)
            else:
                url = self.url.set(drivername="postgresql+psycopg")
                engine = create_engine(
                    url, pool_pre_ping=True, connect_args={"connect_timeout": CONNECT_TIMEOUT_S}
                )
            self._engine = engine
        return self._engine

    def close(self) -> None:
        if self._engine is not None:
            self._engine.dispose()
            self._engine = None
        self._migrated = self._imported = False

    @contextmanager
    def _guard(self, doing: str) -> Iterator[None]:
        """Driver errors as ResultsUnavailable (cannot reach or write) or ResultsDamaged (SQLite corrupt)."""
        try:
            yield
        except (exc.OperationalError, exc.InterfaceError) as e:
            raise ResultsUnavailable(
                f"results database {self.where} unavailable while {doing} ({_short(e)}); the run folders "
                "keep everything: `cell history --sync` records what is missing once it is back"
            ) from e
        except exc.DatabaseError as e:
            if not self.is_sqlite:
                raise ResultsUnavailable(
                    f"results database {self.where}: {doing} failed ({_short(e)})"
                ) from e
            raise ResultsDamaged(
                f"results database {self.where} is damaged ({_short(e)}): `cell history --rebuild` rebuilds "
                "it from the run folders (the damaged file is kept beside it)"
            ) from e

    @contextmanager
    def _write(self, doing: str) -> Iterator[Connection]:
        """One write transaction (on SQLite, BEGIN IMMEDIATE: writers queue instead of deadlocking)."""
        self._open()
        with self._guard(doing), self.engine.connect() as conn:
            conn.execution_options(write=True)
            with conn.begin():
                yield conn

    @property
    def absent(self) -> bool:
        """An SQLite store whose folder does not exist: nothing recorded, and reading creates nothing."""
        path = self.sqlite_path
        return path is not None and not path.parent.is_dir()

    @contextmanager
    def _read(self, doing: str) -> Iterator[Connection]:
        self._open()
        with self._guard(doing), self.engine.connect() as conn:
            yield conn

    def _open(self) -> None:
        """Connect, create or upgrade the schema, read in the runs root the first time (once each)."""
        if not self._migrated:
            path = self.sqlite_path
            if path is not None and not path.parent.is_dir():
                raise ResultsUnavailable(f"results database {path}: its folder does not exist")
            with self._guard("opening it"):
                upgrade(self.engine)
            self._migrated = True
        if not self._imported:
            self._imported = True  # before: the import itself reads and writes through _open
            try:
                self._import_root()
            except BaseException:
                self._imported = False
                raise

    # ------------------------------------------------------------------ writing
    def record_run(self, run_dir: Path) -> None:
        """Read the run folder and insert or update its row and region rows (idempotent)."""
        record = fold.read_run(run_dir)
        with self._write(f"recording {Path(run_dir).name}") as conn:
            _upsert(conn, record)

    def record_or_defer(self, run_dir: Path) -> str | None:
        """:meth:`record_run`, or when the database cannot take it, the reason (a pending marker in the
        folder has it, and :meth:`sync` records the run later). The marker is written first and removed
        once a finished run is in: a run killed meanwhile is recorded by the next sync too."""
        self.mark_pending(run_dir, "being recorded")
        try:
            self.record_run(run_dir)
        except Exception as e:  # whatever the database did, the run goes on; the reason is kept
            reason = (
                str(e) if isinstance(e, (ResultsUnavailable, ResultsDamaged)) else f"{type(e).__name__}: {e}"
            )
            self.mark_pending(run_dir, reason)
            return reason
        if fold.read_run(run_dir).run["status"] != "running":
            (Path(run_dir) / fold.PENDING_NAME).unlink(missing_ok=True)
        return None

    def mark_pending(self, folder: Path, reason: str) -> None:
        """Note in a run or verification folder that it is not in this database yet, and why: the next
        :meth:`sync` of this database records it."""
        fold.mark_pending(folder, reason, self.where)

    def sync(self) -> int:
        """Record every run (or verification) of the runs root that has a pending marker; how many."""
        n = 0
        for path in fold.pending_folders(self.runs_root, self.where):
            with self._write(f"recording {path.name}") as conn:
                running = _record_folder(conn, path)
            if not running:
                (path / fold.PENDING_NAME).unlink(missing_ok=True)
            n += 1
        return n

    def rebuild(self, runs_root: Path | None = None, *, say: Callable[[str], None] | None = None) -> int:
        """Record every inspection and verification folder under ``runs_root`` (default: the store's)
        again; a damaged SQLite file is first moved aside (``results.sqlite.damaged-<UTC time>``, said
        through ``say``), never deleted. The number of inspection runs recorded."""
        if self.is_sqlite and self._damaged():
            moved = self._move_aside()
            if say is not None:
                say(f"the damaged database was moved aside: {moved}")
        root = Path(runs_root or self.runs_root)
        folders = fold.inspection_folders(root)
        running = set()
        with self._write("rebuilding it from the run folders") as conn:
            for path in [*folders, *fold.verification_folders(root)]:
                if _record_folder(conn, path):
                    running.add(path)
        for path in fold.pending_folders(root, self.where):
            if path not in running:
                (path / fold.PENDING_NAME).unlink(missing_ok=True)
        return len(folders)

    def _damaged(self) -> bool:
        path = self.sqlite_path
        if path is None or not path.exists():
            return False
        try:
            with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as db:
                return db.execute("PRAGMA quick_check").fetchone()[0] != "ok"
        except sqlite3.DatabaseError:
            return True

    def _move_aside(self) -> Path:
        """Rename the SQLite file (and its journal) to ``<name>.damaged-<UTC time>``; the new name."""
        path = self.sqlite_path
        assert path is not None
        self.close()
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S%fZ")
        for suffix in ("", "-journal", "-wal", "-shm"):
            part = path.with_name(path.name + suffix)
            if part.exists():
                part.rename(path.with_name(f"{path.name}.damaged-{stamp}{suffix}"))
        return path.with_name(f"{path.name}.damaged-{stamp}")

    def _import_root(self) -> None:
        """Once per runs root and database: record the root's run and verification folders, and the rows
        of a legacy ``index.sqlite`` whose folders are gone, so that switching databases loses no history."""
        key = f"{socket.gethostname()}:{self.runs_root}"
        with self._read("reading it") as conn:
            if conn.execute(select(imported_roots).where(imported_roots.c.root == key)).first():
                return
        folders = [*fold.inspection_folders(self.runs_root), *fold.verification_folders(self.runs_root)]
        legacy_runs, legacy_checks = _legacy_rows(self.runs_root / LEGACY_INDEX, self.cell)
        with self._write("reading in the runs root") as conn:
            for path in folders:
                _record_folder(conn, path)
            for row in legacy_runs:
                _upsert(conn, fold.RunRecord(row), replace=False)
            for row in legacy_checks:
                _upsert_verification(conn, row, replace=False)
            stmt = _insert(conn)(imported_roots).values(root=key, time=datetime.now(UTC))
            conn.execute(stmt.on_conflict_do_nothing())

    def record_verification(
        self,
        folder: Path,
        kind: str,
        cell: str,
        figures_mm: dict[str, float | None],
        verdict: str,
        time: datetime | None = None,
    ) -> None:
        """Store one verification's figures (PF, PS, SD, F in mm); replaces an earlier one of the folder."""
        row = {
            "cell": cell,
            "folder": str(Path(folder).resolve()),
            "kind": kind,
            "time": time or datetime.now(UTC),
            "verdict": verdict,
            **{k.lower(): figures_mm.get(k) for k in ("PF", "PS", "SD", "F")},
        }
        with self._write("recording a verification") as conn:
            _upsert_verification(conn, row)

    # ------------------------------------------------------------------ reading
    def runs(
        self,
        *,
        part: str | None = None,
        recipe: str | None = None,
        serial: str | None = None,
        verdict: str | None = None,
        operator: str | None = None,
        cell: str | None = None,
        since: datetime | None = None,
        until: datetime | None = None,
        limit: int | None = None,
        offset: int = 0,
    ) -> list[RunRow]:
        """The runs matching every filter given (exact matches; ``since`` <= started < ``until``), newest
        first, at most ``limit`` after skipping ``offset`` (a page)."""
        c = runs.c
        wanted = [
            col == value
            for col, value in (
                (c.part, part),
                (c.recipe, recipe),
                (c.serial, serial),
                (c.verdict, verdict),
                (c.operator, operator),
                (c.cell, cell),
            )
            if value is not None
        ]
        if since is not None:
            wanted.append(c.started >= since)
        if until is not None:
            wanted.append(c.started < until)
        query = select(runs).where(and_(True, *wanted)).order_by(c.started.desc(), c.id.desc())
        query = query.limit(limit).offset(offset or None)
        if self.absent:
            return []
        with self._read("listing runs") as conn:
            return [_row(r) for r in conn.execute(query)]

    def distinct(
        self, column: Literal["cell", "recipe", "part", "operator", "verdict", "status"]
    ) -> list[str]:
        """The values of ``column`` that recorded runs have (for a filter's choices), sorted."""
        if self.absent:
            return []
        col = runs.c[column]
        with self._read(f"listing {column}s") as conn:
            return [v for (v,) in conn.execute(select(col).where(col.is_not(None)).distinct().order_by(col))]

    def verifications(self, cell: str | None = None) -> list[VerificationRow]:
        """Every stored verification of ``cell`` (all cells when None), oldest first."""
        v = verifications.c
        query = select(verifications).order_by(v.time, v.id)
        if cell is not None:
            query = query.where(v.cell == cell)
        if self.absent:
            return []
        with self._read("listing verifications") as conn:
            return [
                VerificationRow(
                    r.cell,
                    r.folder,
                    r.kind,
                    r.time,
                    {"PF": r.pf, "PS": r.ps, "SD": r.sd, "F": r.f},
                    r.verdict,
                )
                for r in conn.execute(query)
            ]

    def spc(self, recipe: str) -> Spc:
        """SPC of ``recipe`` (:mod:`cell.results.spc`): trends and Cp/Cpk of the whole part and per region
        over its runs that finished with a pass or fail verdict."""
        c = runs.c
        counted = and_(c.recipe == recipe, c.status == "done", c.verdict.in_(FINISHED))
        if self.absent:
            return Spc(recipe, 0, series(PART, [], None, None), [])
        with self._read("reading SPC figures") as conn:
            rows = list(conn.execute(select(runs).where(counted).order_by(c.started, c.id)))
            by_run: dict[int, list[Any]] = {}
            joined = select(regions).join(runs, regions.c.run_id == c.id).where(counted)
            for reg in conn.execute(joined):
                by_run.setdefault(reg.run_id, []).append(reg)
        part = [
            TrendPoint(r.folder, r.started, r.serial, r.verdict, r.dev_mean, r.dev_min, r.dev_max)
            for r in rows
        ]
        band: tuple[float | None, float | None] = (
            (rows[-1].tol_lower, rows[-1].tol_upper) if rows else (None, None)
        )
        out = [series(PART, part, *band)]
        for name in sorted({reg.name for regs in by_run.values() for reg in regs}):
            trend, band = [], (None, None)
            for r in rows:
                for reg in by_run.get(r.id, []):
                    if reg.name == name:
                        trend.append(
                            TrendPoint(r.folder, r.started, r.serial, reg.verdict, reg.mean, reg.min, reg.max)
                        )
                        band = (reg.tol_lower, reg.tol_upper)
            out.append(series(name, trend, *band))
        return Spc(recipe, len(rows), out[0], out[1:])

    def spc_csv(self, recipe: str, table: str = "trend") -> str:
        """:meth:`spc` as CSV: ``trend`` (one row per run and series) or ``capability`` (one per series)."""
        return to_csv(self.spc(recipe), table)


# ---------------------------------------------------------------------------------------------- helpers
def _sqlite_connect(dbapi_conn: Any, _record: Any) -> None:
    dbapi_conn.isolation_level = None  # the driver leaves transactions to the "begin" listener below
    dbapi_conn.execute("PRAGMA foreign_keys=ON")


def _sqlite_begin(conn: Connection) -> None:
    conn.exec_driver_sql("BEGIN IMMEDIATE" if conn.get_execution_options().get("write") else "BEGIN")


def _insert(conn: Connection) -> Any:
    """The dialect's INSERT (both have ON CONFLICT ... DO UPDATE / DO NOTHING)."""
    from sqlalchemy.dialects import postgresql, sqlite

    return postgresql.insert if conn.dialect.name == "postgresql" else sqlite.insert


def _upsert(conn: Connection, record: fold.RunRecord, *, replace: bool = True) -> None:
    """Insert or update one run (by cell and folder) and replace its region rows; with ``replace`` False
    an existing row is left alone (legacy rows never overwrite a folder's own record)."""
    values = {**record.run, "recorded": datetime.now(UTC)}
    stmt = _insert(conn)(runs).values(**values)
    keys = ["cell", "folder"]
    if replace:
        stmt = stmt.on_conflict_do_update(
            index_elements=keys, set_={k: v for k, v in values.items() if k not in keys}
        )
    else:
        stmt = stmt.on_conflict_do_nothing(index_elements=keys)
    run_id = conn.execute(stmt.returning(runs.c.id)).scalar()
    if run_id is None or not replace:
        return
    conn.execute(delete(regions).where(regions.c.run_id == run_id))
    if record.regions:
        conn.execute(regions.insert(), [{**r, "run_id": run_id} for r in record.regions])


def _record_folder(conn: Connection, path: Path) -> bool:
    """Record an inspection or a verification folder; True if it is an inspection still running."""
    if fold.is_inspection_folder(path):
        record = fold.read_run(path)
        _upsert(conn, record)
        return record.run["status"] == "running"
    row = fold.read_verification(path)
    if row is not None:
        _upsert_verification(conn, row)
    return False


def _upsert_verification(conn: Connection, row: dict[str, Any], *, replace: bool = True) -> None:
    stmt = _insert(conn)(verifications).values(**row)
    keys = ["cell", "folder"]
    if replace:
        conn.execute(stmt.on_conflict_do_update(index_elements=keys, set_=row))
    else:
        conn.execute(stmt.on_conflict_do_nothing(index_elements=keys))


def _legacy_tables(path: Path) -> dict[str, list[dict[str, Any]]]:
    """The ``runs`` and ``verification`` tables of an old ``index.sqlite``, as far as they can be read."""
    out: dict[str, list[dict[str, Any]]] = {"runs": [], "verification": []}
    if not path.is_file():
        return out
    try:
        with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as db:
            db.row_factory = sqlite3.Row
            tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='table'")}
            for name in out:
                if name in tables:
                    out[name] = [dict(r) for r in db.execute(f"SELECT * FROM {name}")]
    except sqlite3.DatabaseError:
        pass
    return out


def _utc(text: Any) -> datetime | None:
    try:
        t = datetime.fromisoformat(str(text))
    except ValueError:
        return None
    return t if t.tzinfo else t.replace(tzinfo=UTC)


def _legacy_rows(path: Path, cell: str) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The rows of an old ``index.sqlite``: RunIndex's ``runs`` whose folders are gone (as ``runs`` rows of
    ``cell``; a folder still there is read itself) and the verification history's ``verification`` rows."""
    tables = _legacy_tables(path)
    checks = []
    for r in tables["verification"]:
        time = _utc(r.get("time"))
        if time is None or not r.get("cell") or not r.get("folder"):
            continue
        figures = {k: r.get(k) for k in ("pf", "ps", "sd", "f")}
        checks.append(
            {"cell": r["cell"], "folder": r["folder"], "kind": r.get("kind") or "check", "time": time}
            | figures
            | {"verdict": r.get("verdict") or "incomplete"}
        )
    runs_ = []
    for r in tables["runs"]:
        started = _utc(r.get("started"))
        if started is None or not r.get("folder") or fold.is_inspection_folder(Path(r["folder"])):
            continue
        kept = {k: r.get(k) for k in ("verdict", "n_points", "coverage", "dev_min", "dev_max")}
        unknown = dict.fromkeys(
            ("recipe_sha256", "serial", "operator", "production_order", "finished", "dev_mean", "dev_std")
        )
        runs_.append(
            {"cell": cell, "folder": r["folder"], "recipe": r.get("part") or "", "part": r.get("part") or ""}
            | {
                "started": started,
                "status": r.get("status") or "unknown",
                "tol_lower": None,
                "tol_upper": None,
            }
            | kept
            | unknown
        )
    return runs_, checks
