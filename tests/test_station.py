"""The station's parts without a browser: users and PINs, the binding rules, the token gate, the time left,
the verdict's reasons, the supervisor's refusals, and abort through the controller's state machine (also
`cell abort` at the terminal). The pages themselves are tested in Chromium (tests/test_station_browser.py)."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import yaml

from cell.errors import ConfigError
from cell.inspection_run import abort_run, rebuild_report, resume, start_run
from cell.run_data import RunIdentity
from cell.runs import RunFolder
from cell.station.app import create_app
from cell.station.journal import StationJournal
from cell.station.progress import Timeline, _time_left, read_progress
from cell.station.recipes import find_recipe
from cell.station.settings import StationSettings, check_settings
from cell.station.supervisor import Supervisor
from cell.station.users import Role, add_user, authenticate, load_users
from cell.station.verdict import read_verdict
from tests.box_part import small_cell, write_box_recipe

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture
def folders(tmp_path: Path) -> StationSettings:
    """A station's folders: the box recipe, the small cell, a users file with one operator (PIN 2468)."""
    (tmp_path / "recipes").mkdir()
    (tmp_path / "runs").mkdir()
    write_box_recipe(tmp_path / "recipes")
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(small_cell().model_dump(mode="json")))
    add_user(tmp_path / "users.yaml", "olga", Role.OPERATOR, "2468")
    return StationSettings(
        cell=tmp_path / "cell.yaml",
        recipes=tmp_path / "recipes",
        runs=tmp_path / "runs",
        users=tmp_path / "users.yaml",
    )


def test_pins_are_stored_hashed_and_checked(tmp_path: Path) -> None:
    users = tmp_path / "users.yaml"
    assert add_user(users, "olga", Role.OPERATOR, "2468") is False
    assert add_user(users, "tom", Role.TECHNICIAN, "13579") is False
    text = users.read_text()
    assert "2468" not in text and "13579" not in text and "scrypt$16384$8$1$" in text
    assert users.stat().st_mode & 0o077 == 0  # readable by its owner only
    loaded = load_users(users)
    assert authenticate(loaded, "OLGA ", "2468").name == "olga"  # names compare without case
    assert authenticate(loaded, "olga", "2469") is None
    assert authenticate(loaded, "nobody", "2468") is None
    assert add_user(users, "olga", Role.TECHNICIAN, "1111") is True  # replaced, in its place
    loaded = load_users(users)
    assert [u.name for u in loaded.users] == ["olga", "tom"] and loaded.users[0].role is Role.TECHNICIAN
    assert authenticate(loaded, "olga", "2468") is None and authenticate(loaded, "olga", "1111")
    for name, pin, field in (("olga", "12a4", "PIN"), ("olga", "123", "PIN"), ("../x", "1234", "NAME")):
        with pytest.raises(ConfigError, match=f"field '{field}'"):
            add_user(users, name, Role.OPERATOR, pin)


def test_binding_beyond_loopback_needs_a_token_and_tls(folders: StationSettings, tmp_path: Path) -> None:
    check_settings(folders)  # 127.0.0.1: nothing else needed
    wide = folders.model_copy(update={"host": "0.0.0.0"})
    with pytest.raises(ConfigError, match="--token-file, --tls-cert, --tls-key") as refused:
        check_settings(wide)
    assert "field '--host'" in str(refused.value)
    (tmp_path / "token").write_text("short\n")
    for name in ("cert.pem", "key.pem"):
        (tmp_path / name).write_text("PEM")
    wide = wide.model_copy(
        update={
            "token_file": tmp_path / "token",
            "tls_cert": tmp_path / "cert.pem",
            "tls_key": tmp_path / "key.pem",
        }
    )
    with pytest.raises(ConfigError, match="at least 16 characters"):
        check_settings(wide)
    (tmp_path / "token").write_text("a-token-of-24-characters\n")
    check_settings(wide)
    with pytest.raises(ConfigError, match="field '--users'.*cell station users add"):
        check_settings(folders.model_copy(update={"users": tmp_path / "none.yaml"}))


def test_the_cli_refuses_a_wide_binding_in_one_line(folders: StationSettings) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "cell", "station", "serve", "--host", "0.0.0.0", "--cell", str(folders.cell)]
        + ["--recipes", str(folders.recipes), "--runs", str(folders.runs), "--users", str(folders.users)],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and "--token-file" in lines[0], proc.stderr


def test_a_wide_station_asks_for_its_token(folders: StationSettings, tmp_path: Path) -> None:
    with warnings.catch_warnings():  # starlette 1.x announces a move from httpx to httpx2, not yet released
        warnings.simplefilter("ignore")
        from starlette.testclient import TestClient

    token = "a-token-of-24-characters"
    (tmp_path / "token").write_text(token)
    wide = folders.model_copy(update={"host": "0.0.0.0", "token_file": tmp_path / "token"})
    with TestClient(create_app(wide), base_url="https://station") as client:
        assert client.get("/signin", follow_redirects=False).headers["location"] == "/token"
        assert client.get("/static/station.css").status_code == 200  # assets need no token
        wrong = client.post("/token", data={"token": "guess"})
        assert "Wrong station token" in wrong.text
        assert client.get("/signin", follow_redirects=False).status_code == 303
        client.post("/token", data={"token": token})
        assert client.get("/signin", follow_redirects=False).status_code == 200
    with TestClient(create_app(wide), base_url="https://station") as other:
        headers = {"Authorization": f"Bearer {token}"}
        assert other.get("/signin", headers=headers, follow_redirects=False).status_code == 200
    journal = StationJournal(folders.state_dir / "journal.jsonl").entries()
    assert [e["event"] for e in journal if e["event"].startswith("token")] == [
        "token_refused",
        "token_accepted",
    ]


def _timeline(start: float, captures: list[float], done: float) -> Timeline:
    return Timeline(start, tuple(captures), done)


def test_the_time_left_follows_the_finished_runs_of_the_part(tmp_path: Path) -> None:
    from cell.station.progress import Progress

    # two earlier runs: 4 captures 2 s apart from t=10, done 12 s after the last one (and a slower twin)
    past = [_timeline(0, [10, 12, 14, 16], 28), _timeline(0, [10, 13, 16, 19], 34)]
    p = Progress("run", state="scanning_moving", views_total=4, views_done=1)
    # this run made 2 captures, the last 1 s ago: the earlier runs needed 16 and 21 s from theirs
    left, note = _time_left(p, [100.0, 102.0], 95.0, past, now=103.0)
    assert left == pytest.approx((16 + 21) / 2 - 1) and note == ""
    # before the first capture: their whole duration, from this run's first state
    left, _ = _time_left(p, [], 95.0, past, now=100.0)
    assert left == pytest.approx((28 + 34) / 2 - 5)
    # more captures than they made: what followed their last one (12 s and 15 s)
    left, _ = _time_left(p, [100.0 + 2 * k for k in range(6)], 95.0, past, now=111.0)
    assert left == pytest.approx(13.5 - 1)
    # without history: 3 views left at this run's pace (2 s) plus half the 4 views' scanning, said as a guess
    left, note = _time_left(p, [100.0, 102.0], 95.0, [], now=103.0)
    assert left == pytest.approx(3 * 2 + 0.5 * 2 * 4) and "first estimate" in note


def test_progress_and_verdict_of_a_finished_run(tmp_path: Path) -> None:
    run = RunFolder.create(tmp_path, "box", name="box-SN-1-20260101T000000Z")
    (run.path / "inputs" / "manifest.json").write_text("{}")
    run.log("run_created", part="box", serial="SN-1", operator="olga")
    for state in ("connecting", "homing", "planning", "scanning_moving"):
        run.log("state", state=state, message="")
    run.save_checkpoint({"phase": "scanning", "views": [{"T_B_T": [[1, 0, 0, 0]] * 4}] * 3})
    run.log("capture", view=0)
    run.log("state", state="scanning_capturing", message="")
    p = read_progress(run.path)
    assert (p.words, p.view, p.views_total, p.serial, p.operator) == (
        "Measuring view 1",
        1,
        3,
        "SN-1",
        "olga",
    )
    run.log("state", state="scanning_moving", message="")
    assert read_progress(run.path).words == "Moving to view 2"
    report = {
        "verdict": "fail",
        "tolerance": {"lower_mm": -0.3, "upper_mm": 0.3},
        "deviation": {"mean_mm": 0.0, "min_mm": -0.8, "max_mm": 0.1},
        "coverage": 0.5,
        "min_coverage": 0.6,
        "regions": [
            {
                "name": "out-of-tolerance-1",
                "kind": "dent",
                "n_points": 40,
                "extreme_mm": -0.8,
                "centre_mm": [25.0, 15.0, 39.5],
                "extreme_at_mm": [25.2, 15.1, 39.2],
            },
            {
                "name": "out-of-tolerance-2",
                "kind": "excess",
                "n_points": 12,
                "extreme_mm": 0.4,
                "centre_mm": [0.0, 0.0, 0.0],
                "extreme_at_mm": [0.0, 0.0, 0.0],
            },
        ],
        "region_verdicts": [{"name": "lid", "verdict": "fail", "min_mm": -0.8, "max_mm": 0.1}],
        "incomplete_reasons": [],
    }
    (run.results_dir / "report.json").write_text(json.dumps(report))
    verdict = read_verdict(run.path, [("lid", [[-60, -45, 35], [60, 45, 41]])])
    assert verdict.verdict == "fail" and verdict.defect.kind == "dent" and verdict.defect.region == "lid"
    assert verdict.defect.at_mm == [25.2, 15.1, 39.2] and verdict.defect.value_mm == -0.8
    assert verdict.reasons == [
        "dent of -0.800 mm, beyond the tolerance -0.300 / +0.300 mm (and 1 more out-of-tolerance region(s))",
        "region 'lid' failed: -0.800 to +0.100 mm",
        "coverage 50.0 % is below the required 60.0 %",
    ]


def test_the_supervisor_refuses_what_the_cell_cannot_do(folders: StationSettings) -> None:
    journal = StationJournal(folders.state_dir / "journal.jsonl")
    supervisor = Supervisor(folders, journal)
    with pytest.raises(ConfigError, match="'SN 1/2' is not a valid serial"):
        supervisor.start_inspection(find_recipe(folders.recipes, "box"), "SN 1/2", "olga")
    with pytest.raises(ConfigError, match="scan or type the part's serial"):
        supervisor.start_inspection(find_recipe(folders.recipes, "box"), "  ", "olga")
    with pytest.raises(ConfigError, match="unknown recipe 'nope'"):
        find_recipe(folders.recipes, "nope")
    # another process (here: this one) works on a run folder under the runs root: no start
    busy = RunFolder.create(folders.runs, "box")
    busy.acquire_lock("cell inspect")
    try:
        with pytest.raises(ConfigError, match=f"run {busy.path.name} is in progress in another process"):
            supervisor.start_inspection(find_recipe(folders.recipes, "box"), "SN-1", "olga")
    finally:
        busy.release_lock()
    with pytest.raises(ConfigError, match="not running at this station"):
        supervisor.pause(busy.path.name, "olga")
    assert sorted(p.name for p in folders.runs.iterdir()) == sorted([".station", busy.path.name])  # no run


@pytest.fixture
def started(folders: StationSettings, tmp_path: Path) -> Path:
    """An inspection run folder started (inputs copied) but never executed."""
    run = start_run(
        folders.recipes / "box.yaml",
        folders.cell,
        tmp_path / "runs" / "r",
        identity=RunIdentity("SN-9", "olga"),
    )
    run.release_lock()  # start_run hands the folder over locked, for execute_run
    return run.path


def test_abort_goes_through_the_state_machine(started: Path) -> None:
    run = RunFolder.open(started)
    run.log("state", state="paused", message="pause requested: Ctrl-C")
    with pytest.raises(ConfigError, match="has not reached reporting; `cell resume` it first"):
        rebuild_report(started)  # paused: resuming it makes its report
    assert abort_run(started, "aborted by olga at the station") == "aborted"
    journal = run.journal()
    assert [e["state"] for e in journal if e["event"] in ("state", "exit")][-2:] == ["aborted", "aborted"]
    assert journal[-1]["event"] == "results_recorded"  # the runs root's database has it, status aborted
    with pytest.raises(ConfigError, match="the run is aborted already"):
        abort_run(started, "again")
    with pytest.raises(ConfigError, match="was aborted"):
        resume(started)
    with pytest.raises(ConfigError, match="was aborted before its verdict, so it has no report") as refused:
        rebuild_report(started)
    assert "cell resume` it" not in str(refused.value)
    assert not (started / "run.lock").exists()


def test_abort_refuses_a_finished_run_and_one_a_process_runs(started: Path) -> None:
    run = RunFolder.open(started)
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        lock = {"pid": holder.pid, "host": os.uname().nodename, "command": "cell inspect", "start": None}
        (started / "run.lock").write_text(json.dumps(lock))
        with pytest.raises(ConfigError, match=f"in use by PID {holder.pid}.*pause it"):
            abort_run(started, "by olga")
    finally:
        holder.kill()
        holder.wait()
    (started / "run.lock").unlink()
    run.log("state", state="done", message="")
    proc = subprocess.run(
        [sys.executable, "-m", "cell", "abort", str(started)], capture_output=True, text=True, cwd=REPO
    )
    assert proc.returncode == 2
    assert "the run is finished and its verdict stands; nothing to abort" in proc.stderr
    assert [e.get("state") for e in run.journal() if e["event"] == "state"][-1] == "done"


def test_the_live_page_offers_nothing_on_a_run_another_process_runs(
    folders: StationSettings, started: Path
) -> None:
    from cell.station.live import snapshot

    run = RunFolder.open(started)
    run.log("state", state="paused", message="")
    supervisor = Supervisor(folders, StationJournal(folders.state_dir / "journal.jsonl"))
    free = snapshot(supervisor, folders.runs, started.name, None)
    assert free["actions"] == {"pause": False, "resume": True, "abort": True}  # paused, nobody on it
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:  # a terminal's `cell resume` holds it now
        lock = {"pid": holder.pid, "host": os.uname().nodename, "command": "cell resume", "start": None}
        (started / "run.lock").write_text(json.dumps(lock))
        taken = snapshot(supervisor, folders.runs, started.name, None)
    finally:
        holder.kill()
        holder.wait()
    assert taken["actions"] == {"pause": False, "resume": False, "abort": False}
    assert f"run by another process (PID {holder.pid}, cell resume)" in taken["message"]
    assert not taken["final"]


def test_the_verdict_shows_while_the_report_page_is_written(folders: StationSettings, started: Path) -> None:
    """The controller publishes the verdict (report.json, the checkpoint's summary) before it writes the
    report's page (state ``rendering``): from then the station shows the verdict, the live page is over for
    the operator, the verdict page refreshes until the page is there, and no abort is offered (the state
    machine refuses one)."""
    with warnings.catch_warnings():  # starlette 1.x announces a move from httpx to httpx2, not yet released
        warnings.simplefilter("ignore")
        from starlette.testclient import TestClient

    from cell.station.live import snapshot

    run = RunFolder.open(started)
    run.log("state", state="rendering", message="")
    checkpoint = run.load_checkpoint() or {}
    run.save_checkpoint({**checkpoint, "phase": "rendering", "summary": {"verdict": "fail", "n_points": 7}})
    report = {"verdict": "fail", "tolerance": {"lower_mm": -0.3, "upper_mm": 0.3}, "regions": []}
    (run.results_dir / "report.json").write_text(json.dumps(report))
    progress = read_progress(started)
    assert progress.verdict == "fail" and progress.words.startswith("Verdict ready")
    supervisor = Supervisor(folders, StationJournal(folders.state_dir / "journal.jsonl"))
    snap = snapshot(supervisor, folders.runs, started.name, None)
    assert snap["final"] and snap["verdict"] == "fail" and not snap["actions"]["abort"]
    with pytest.raises(ConfigError, match="verdict is published and stands"):
        abort_run(started, "by olga")
    with TestClient(create_app(folders)) as client:
        client.post("/signin", data={"name": "olga", "pin": "2468", "next": "/start"})
        page = client.get(f"/run/{started.name}/verdict")
        assert page.status_code == 200 and 'id="word">FAIL<' in page.text
        assert 'http-equiv="refresh"' in page.text and 'id="writing"' in page.text
        assert 'id="open-report"' not in page.text  # no page yet
        run.log("state", state="done", message="")
        (run.results_dir / "report.html").write_text("<html></html>")
        done = client.get(f"/run/{started.name}/verdict").text
        assert 'http-equiv="refresh"' not in done and 'id="open-report"' in done


@pytest.mark.parametrize("bit_depth", [8, 12])
def test_the_live_page_shows_a_small_photo_of_the_last_view(
    folders: StationSettings, tmp_path: Path, bit_depth: int
) -> None:
    """The last view's photo: its fully lit raw frame (the white pattern, stored as the camera gave it),
    320 px wide, never the full-size image; the part (a bright 200 x 100 px plate on a dark table) where the
    frame has it; made once (cached); gone with the view's raw images, the map then shown alone."""
    import cv2
    import numpy as np

    from cell.sensing.patterns import gcls_patterns
    from cell.station import thumbnail
    from cell.view_files import save_raw_stack

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from starlette.testclient import TestClient

    run = RunFolder.create(folders.runs, "box", name="box-SN-5-20260101T000000Z")
    run.log("run_created", part="box", serial="SN-5", operator="olga")
    run.log("state", state="scanning_moving", message="")
    view = run.view_dir(0)
    view.mkdir()
    patterns = gcls_patterns(256, 192, 16, 8)
    full = 2**bit_depth - 1
    dtype = np.uint8 if bit_depth == 8 else np.uint16
    rng = np.random.default_rng(1)
    stack = rng.integers(0, full // 2, (len(patterns.names), 384, 512)).astype(dtype)  # any coded frames
    white = np.full((384, 512), full // 40, dtype)  # the dark table ...
    white[100:200, 200:400] = round(0.7 * full)  # ... and the lit plate
    stack[patterns.names.index("white")] = white
    save_raw_stack(view, stack, patterns, bit_depth, (256, 192))
    reasons = np.full((384, 512), 1, np.uint8)  # nothing measured but the plate
    reasons[100:200, 200:400] = 0
    cv2.imwrite(str(view / "reasons.png"), reasons)

    thumbnail._photo_jpeg.cache_clear()
    with TestClient(create_app(folders)) as client:
        client.post("/signin", data={"name": "olga", "pin": "2468"})
        page = client.get(f"/run/{run.path.name}").text
        assert f'src="/run/{run.path.name}/views/0/photo.jpg"' in page and "thumb with-photo" in page
        got = client.get(f"/run/{run.path.name}/views/0/photo.jpg")
        assert got.status_code == 200 and got.headers["content-type"] == "image/jpeg"
        assert len(got.content) < 30_000
        photo = cv2.imdecode(np.frombuffer(got.content, np.uint8), cv2.IMREAD_UNCHANGED)
        assert photo.shape == (240, 320)  # 512 x 384 camera: downscaled by 0.625, grey
        plate, table = photo[66:122, 128:247], np.delete(photo, np.s_[58:130], axis=0)
        assert plate.min() > 235 and table.max() < 110  # the plate white, the table dark (gamma 2.2)
        assert client.get(f"/run/{run.path.name}/views/0/photo.jpg").content == got.content
        assert thumbnail._photo_jpeg.cache_info().hits == 1  # the second came from memory
        inset = client.get(f"/run/{run.path.name}/views/0/thumbnail.png")
        assert cv2.imdecode(np.frombuffer(inset.content, np.uint8), cv2.IMREAD_COLOR).shape == (240, 320, 3)

        shutil.rmtree(view / "raw")  # what the retention does to a passed run's views
        from cell.station.live import snapshot

        snap = snapshot(
            Supervisor(folders, StationJournal(folders.state_dir / "j.jsonl")),
            folders.runs,
            run.path.name,
            None,
        )
        assert snap["photo"] is None and snap["thumbnail"] == f"/run/{run.path.name}/views/0/thumbnail.png"
        assert client.get(f"/run/{run.path.name}/views/0/photo.jpg").status_code == 404
        page = client.get(f"/run/{run.path.name}").text
        assert re.search(r'<img id="photo"[^>]* hidden>', page) and "with-photo" not in page
