"""The report's files on disk: the cloud stored once (PLY with the deviation field, every measured point in
order, CSV on request), written as one set (a failure mid-write leaves the previous report whole, or none),
and an unwritable folder as one ConfigError naming it."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import trimesh

from cell.analysis import report_files
from cell.analysis.compare import load_cloud
from cell.analysis.report import ReportInput, Tolerance, write_report
from cell.analysis.report_files import read_ply_points, stored_points, write_ply
from cell.errors import ConfigError, StorageError
from cell.inspection_run import rebuild_report
from tests.synthetic_report import SPIKES, synthetic_input
from tests.tmpfs import run_script

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def inp():
    """The synthetic box with isolated outliers set aside (min_defect_points 10)."""
    return synthetic_input(n_points=8_000)


def snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_cloud_ply_holds_every_measured_point_once(inp, tmp_path: Path) -> None:
    write_report(tmp_path, inp, pictures=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cloud.ply", "report.html", "report.json"]
    stored = inp.stored
    assert stored is not None and stored.isolated is not None
    assert stored.isolated.sum() == SPIKES == inp.excluded["isolated_out_of_tolerance_points"]
    points = read_ply_points(tmp_path / "cloud.ply")
    # in order, each coordinate as float32 keeps it: within half a step of 2^-23 of its power of two
    assert np.array_equal(points, stored_points(stored.points_mm))
    half_step = np.exp2(np.floor(np.log2(np.abs(stored.points_mm))) - 24)
    assert np.all(np.abs(points - stored.points_mm) <= half_step)
    ply = trimesh.load(tmp_path / "cloud.ply", process=False)  # an independent reader sees the fields
    raw = ply.metadata["_ply_raw"]["vertex"]["data"]
    assert raw.dtype["x"] == np.float32 and raw.dtype["deviation"] == np.float32
    assert np.array_equal(load_cloud(tmp_path / "cloud.ply"), points)  # what `cell compare` reads of it
    assert np.allclose(raw["deviation"], stored.deviation_mm, atol=1e-6)
    assert np.array_equal(raw["isolated"].astype(bool), stored.isolated)
    assert np.array_equal(points[raw["isolated"] == 0], stored_points(inp.points_mm))  # the judged ones
    # 12 bytes of coordinates, 4 of deviation and 1 of the isolated flag a point, after the header
    data = (tmp_path / "cloud.ply").read_bytes()
    assert len(data) - data.index(b"end_header\n") - len(b"end_header\n") == 17 * len(points)


def test_a_cloud_without_isolated_outliers_has_no_isolated_column(tmp_path: Path) -> None:
    """An inspection's cloud judged with nothing set aside: no column of zeros (2 MB on the pillar)."""
    from cell.analysis.errormap import NominalMesh
    from cell.analysis.judge import judge
    from tests.synthetic_report import box_mesh

    mesh = box_mesh()
    pts = trimesh.sample.sample_surface_even(mesh, 3000, seed=4)[0]
    inp = judge(NominalMesh.from_trimesh(mesh), pts, Tolerance(-0.3, 0.3), min_defect_points=10)
    assert inp.stored is not None and inp.stored.isolated is not None and not inp.stored.isolated.any()
    write_report(tmp_path, inp, pictures=False)
    data = (tmp_path / "cloud.ply").read_bytes()
    head = data[: data.index(b"end_header\n")].decode()
    assert "isolated" not in head and "property float deviation" in head
    assert len(data) - len(head) - len(b"end_header\n") == 16 * len(pts)
    assert np.array_equal(read_ply_points(tmp_path / "cloud.ply"), stored_points(pts))


def test_a_float64_cloud_from_before_reads_as_it_was_stored(tmp_path: Path) -> None:
    """A cloud.ply written with double coordinates (before float32) reads back exactly as stored."""
    pts = np.random.default_rng(3).uniform(-300, 300, (500, 3))
    rec = np.empty(len(pts), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("deviation", "<f4")])
    rec["x"], rec["y"], rec["z"], rec["deviation"] = pts[:, 0], pts[:, 1], pts[:, 2], 0.0
    header = (
        "ply\nformat binary_little_endian 1.0\nelement vertex 500\nproperty double x\nproperty double y\n"
        "property double z\nproperty float deviation\nend_header\n"
    )
    (tmp_path / "old.ply").write_bytes(header.encode() + rec.tobytes())
    assert np.array_equal(read_ply_points(tmp_path / "old.ply"), pts)


def test_csv_on_request_and_gone_with_the_next_report(inp, tmp_path: Path) -> None:
    write_report(tmp_path, inp, pictures=False, csv=True)
    csv = np.loadtxt(tmp_path / "deviations.csv", delimiter=",", skiprows=1)
    assert np.allclose(csv[:, :3], inp.points_mm, atol=1e-5) and np.allclose(
        csv[:, 3], inp.deviation_mm, atol=1e-5
    )
    (tmp_path / "report.pdf").write_bytes(b"%PDF an older print")
    write_report(tmp_path, inp, pictures=False)  # a report without CSV: the older CSV and print would lie
    assert not (tmp_path / "deviations.csv").exists() and not (tmp_path / "report.pdf").exists()


def test_a_failure_mid_write_leaves_no_half_set(inp, tmp_path: Path, monkeypatch) -> None:
    """The CSV writer dies half way: a fresh folder stays empty; a folder with a report keeps it byte for
    byte (no report.json beside a half CSV, no temporary files)."""

    def dying_csv(path: Path, points, deviation) -> None:
        path.write_text("x_mm,y_mm,z_mm,deviation_mm\n1.0,2.0,")
        raise RuntimeError("killed while writing the CSV")

    monkeypatch.setattr(report_files, "write_csv", dying_csv)
    fresh = tmp_path / "fresh"
    with pytest.raises(RuntimeError, match="killed"):
        write_report(fresh, inp, pictures=False, csv=True)
    assert list(fresh.iterdir()) == []
    old = tmp_path / "old"
    write_report(old, inp, pictures=False)
    before = snapshot(old)
    inp.tolerance = type(inp.tolerance)(-0.1, 0.1)  # the new report would differ
    try:
        with pytest.raises(RuntimeError, match="killed"):
            write_report(old, inp, pictures=False, csv=True)
    finally:
        inp.tolerance = type(inp.tolerance)(-0.3, 0.3)
    assert snapshot(old) == before


def test_a_report_killed_mid_write_leaves_no_half_set(tmp_path: Path) -> None:
    """SIGKILL while the CSV is being written (no handler runs): no report.json, no CSV, no cloud; only
    hidden partial files, which the next report removes."""
    out = tmp_path / "results"
    script = (
        "import sys, numpy as np\n"
        "from cell.analysis.report import ReportInput, Tolerance, write_report\n"
        "n = 600_000\n"
        "pts = np.c_[np.random.default_rng(0).uniform(0, 300, (n, 2)), np.zeros(n)]\n"
        "write_report(sys.argv[1], ReportInput(pts, np.zeros(n), Tolerance(-0.3, 0.3), n), pictures=False, "
        "csv=True)\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", script, str(out)], cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}
    )
    deadline = time.monotonic() + 120
    while not any(p.stat().st_size > 100_000 for p in out.glob(".deviations.csv.*.partial")):
        assert proc.poll() is None and time.monotonic() < deadline, "the writer ended before it was killed"
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=60)
    left = sorted(p.name for p in out.iterdir())
    assert left and all(name.startswith(".") and name.endswith(".partial") for name in left), left
    pts = np.zeros((10, 3))
    write_report(out, ReportInput(pts, np.zeros(10), Tolerance(-0.3, 0.3), 10), pictures=False)
    assert sorted(p.name for p in out.iterdir()) == ["cloud.ply", "report.html", "report.json"]


def test_a_full_disk_is_one_clear_error_and_leaves_nothing(inp, tmp_path: Path, monkeypatch) -> None:
    """ENOSPC while the cloud is written: a StorageError naming the folder and the file (a run under way
    pauses on it, cell.controller), and nothing of the report left."""

    def full(path: Path, *args, **kwargs) -> None:
        path.write_bytes(b"ply\n")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    monkeypatch.setattr(report_files, "write_ply", full)
    with pytest.raises(StorageError) as err:
        write_report(tmp_path, inp, pictures=False)
    text = str(err.value)
    assert f"cannot write {tmp_path}: the disk is full ({tmp_path / 'cloud.ply'})" in text
    assert err.value.path == str(tmp_path) and list(tmp_path.iterdir()) == []


def test_a_disk_filling_up_while_the_report_is_written(tmp_path: Path) -> None:
    """A real full disk (a 1.5 MB tmpfs): cell compare writes the cloud, then the page does not fit; one line
    naming the folder and the file, no traceback, and no report file left (tests/tmpfs.py)."""
    folder = tmp_path / "in"
    folder.mkdir()
    trimesh.creation.box(extents=(100.0, 60.0, 4.0)).export(folder / "plate.stl")
    xy = np.random.default_rng(0).uniform((-45, -25), (45, 25), (20_000, 2))
    np.savetxt(folder / "cloud.xyz", np.c_[xy, np.full(len(xy), 2.0)])
    out = tmp_path / "out"
    out.mkdir()
    script = (
        'mount -t tmpfs -o size=1536k tmpfs "$M" || exit 99\n'
        f'PYTHONPATH={REPO} "{sys.executable}" -m cell compare plate.stl cloud.xyz --out "$M/cmp" '
        f"> {out}/out 2> {out}/err; echo $? > {out}/rc\n"
        f'ls -A "$M/cmp" > {out}/left\n'
    )
    proc = run_script(script, tmp_path / "mnt", folder)
    assert proc.returncode == 0, proc.stderr
    code, err = int((out / "rc").read_text()), (out / "err").read_text()
    assert code == 1 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    cmp_dir = tmp_path / "mnt" / "cmp"
    assert "".join(
        f"error: cannot write {cmp_dir}: the disk is full ({cmp_dir / 'report.html'})".split()
    ) in ("".join(err.split()))
    assert (out / "left").read_text().split() == []  # the cloud written before is not kept either


@contextmanager
def read_only(folder: Path) -> Iterator[None]:
    """``folder`` read-only for this process: mode 555, and as root (who writes anyway) run as nobody."""
    folder.chmod(0o555)
    root = os.geteuid() == 0
    try:
        if root:
            os.seteuid(65534)
        yield
    finally:
        if root:
            os.seteuid(0)
        folder.chmod(0o755)


def test_a_read_only_folder_is_one_clear_error(inp) -> None:
    """The report into a folder it may not write: a StorageError naming it, nothing left; `cell report` of a
    run whose results folder is read-only: refused before any work, a ConfigError (exit 2) naming it."""
    with tempfile.TemporaryDirectory() as parent:  # under /tmp: every user may pass through it
        Path(parent).chmod(0o755)
        out = Path(parent) / "results"
        out.mkdir()
        with read_only(out), pytest.raises(StorageError) as err:
            write_report(out, inp, pictures=False)
        assert f"cannot write {out}: permission denied" in str(err.value) and list(out.iterdir()) == []
        run = Path(parent) / "run"  # a finished inspection run, as far as `cell report` looks first
        (run / "inputs").mkdir(parents=True)
        (run / "inputs" / "manifest.json").write_text("{}")
        (run / "journal.jsonl").write_text("")
        (run / "journal.jsonl").chmod(0o666)  # the run's own files stay writable to whoever runs the test
        (run / "checkpoint.json").write_text(json.dumps({"phase": "done", "views": [], "iteration": 0}))
        (run / "results").mkdir()
        with read_only(run / "results"), pytest.raises(ConfigError) as err:
            rebuild_report(run)
        assert f"cannot write {run / 'results'}: permission denied" in str(err.value)
        assert err.value.exit_code == 2


def test_a_truncated_cloud_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "cloud.ply"
    write_ply(path, np.arange(30.0).reshape(10, 3), np.zeros(10))
    path.write_bytes(path.read_bytes()[:-20])
    with pytest.raises(ConfigError, match="truncated"):
        read_ply_points(path)
