"""The station end to end in real headless Chromium (Debian's chromium, driven by Playwright; no mocked
browser) and a real PostgreSQL results database: sign in, scan a serial (typed, then Enter, as a
keyboard-wedge reader does), start a simulated inspection of a dented box, follow it live, pause and resume it
from the page, read the verdict and its reasons; lose the database while the run is paused and see it
recorded once the database is back; read the runs list and the SPC table; abort a run from the page. And the
refusals: a wrong PIN, a serial a folder cannot hold, a recipe gone since the page was loaded, a start while a
run is in progress, an operator at the technician's pages. What the pages say is checked against the run
folders' journals and reports, the dent the simulated part carries, and Cp/Cpk and Pp/Ppk computed here
from the reports.

The tests of this module share one station and run in order: the runs of the early ones are the history of
the later ones (two finished runs make the SPC)."""

from __future__ import annotations

import json
import re
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from playwright.sync_api import expect

from cell.errors import ConfigError
from cell.inspection_run import resume
from cell.runs import process_alive
from tests.box_part import DENT
from tests.postgres_server import PostgresServer, require_postgres
from tests.station_browser import SCREEN, StationServer, browser, shot, sign_in, start_station, stop_station

pytestmark = [pytest.mark.slow, pytest.mark.chromium, pytest.mark.postgres]
__all__ = ["browser"]  # the fixture, imported for the tests of this module


@pytest.fixture(scope="module")
def database() -> Iterator[PostgresServer]:
    server = PostgresServer(require_postgres())
    server.start()
    yield server
    server.destroy()


@pytest.fixture(scope="module")
def station(
    tmp_path_factory: pytest.TempPathFactory, browser: object, database: PostgresServer
) -> Iterator[StationServer]:
    server = start_station(tmp_path_factory.mktemp("station"), database.create_database())
    yield server
    stop_station(server)


@pytest.fixture
def page(browser, station: StationServer):  # noqa: ANN001, ANN201 (Playwright's types)
    context = browser.new_context(viewport=SCREEN)
    page = context.new_page()
    page.set_default_timeout(20_000)
    yield page
    context.close()


def _events(station: StationServer, event: str) -> list[dict]:
    return [e for e in station.journal() if e["event"] == event]


def test_a_wrong_pin_is_refused_and_journalled(page, station: StationServer, tmp_path: Path) -> None:
    sign_in(page, station.url, "olga", "1111")
    assert page.locator(".msg.error").inner_text().startswith("Wrong name or PIN")
    assert "/signin" in page.url
    assert _events(station, "sign_in_failed")[-1]["name"] == "olga"
    shot(page, "signin", tmp_path)
    sign_in(page, station.url, "olga")
    page.wait_for_url("**/start")
    assert page.locator("#who").inner_text().startswith("olga")


def test_a_bad_serial_and_a_vanished_recipe_start_nothing(page, station: StationServer) -> None:
    sign_in(page, station.url, "olga")
    page.fill("#serial", "SN/01 ?")
    page.press("#serial", "Enter")  # the barcode reader's Enter submits
    message = page.locator(".msg.error").inner_text()
    assert "Not started" in message and "'SN/01 ?' is not a valid serial" in message
    assert page.locator("#serial").input_value() == "SN/01 ?"  # kept for the operator to see
    # the recipe list was read when the page loaded; the file goes away before Start is pressed
    page.goto(station.url + "/start")
    page.check("input[value='old-box']", force=True)
    (station.recipes / "old-box.yaml").unlink()
    page.fill("#serial", "SN-0002")
    page.click("#start")
    assert "unknown recipe 'old-box'" in page.locator(".msg.error").inner_text()
    assert station.run_dirs() == []  # nothing started, no folder made
    refused = [e["why"] for e in _events(station, "start_refused")]
    assert any("not a valid serial" in why for why in refused)
    assert any("unknown recipe 'old-box'" in why for why in refused)


def test_an_operator_may_not_calibrate_or_edit_recipes(page, station: StationServer, tmp_path: Path) -> None:
    sign_in(page, station.url, "olga")
    page.wait_for_url("**/start")
    assert page.locator("nav a[href='/calibrate']").count() == 0
    for path in ("/calibrate", "/recipes", "/recipes/box"):
        response = page.goto(station.url + path)
        assert response.status == 403
        assert "only a technician may run calibration routines or edit recipes" in page.inner_text("#text")
    assert {e["path"] for e in _events(station, "refused") if e["user"] == "olga"} >= {"/calibrate"}
    # a technician gets the routines, and a recipe edit that breaks the schema is refused, the file unchanged
    page.click("text=Sign out")
    sign_in(page, station.url, "tom")
    page.goto(station.url + "/calibrate")
    assert page.locator("button[name='routine']").count() == 8
    shot(page, "calibrate", tmp_path)
    page.click("button[value='gamma']")  # the projector's response: a short routine, run like an inspection
    page.wait_for_url("**/run/calibration-gamma-*")
    page.wait_for_url("**/verdict", timeout=90_000)
    assert page.inner_text("#word") == "DONE"
    folder = station.runs / page.url.split("/")[-2]
    assert f"gamma: {folder / 'gamma.yaml'}" in page.inner_text("#output")  # the config line to use it
    assert (folder / "gamma.yaml").is_file()
    before = (station.recipes / "box.yaml").read_text()
    page.goto(station.url + "/recipes/box")
    page.fill("#text", before.replace("min_coverage", "min_coverag"))
    page.click("#save")
    assert "Not saved" in page.locator(".msg.error").inner_text()
    assert "min_coverag" in page.locator(".msg.error").inner_text()
    assert (station.recipes / "box.yaml").read_text() == before


def _journal(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "journal.jsonl").read_text().splitlines()]


def _start(page, station: StationServer, serial: str) -> Path:  # noqa: ANN001
    """Sign in as olga, scan ``serial`` (typed, then Enter), start; the run folder the live page follows."""
    sign_in(page, station.url, "olga")
    page.wait_for_url("**/start")
    page.check("input[value='box']", force=True)
    page.locator("#serial").press_sequentially(serial)
    page.press("#serial", "Enter")
    page.wait_for_url(f"**/run/box-{serial}-*")
    return station.runs / page.url.rsplit("/", 1)[1]


def test_an_inspection_started_paused_and_resumed_from_the_page(
    page, station: StationServer, database: PostgresServer, tmp_path: Path
) -> None:
    """The run loses its database while paused: it finishes all the same, and the verdict page says its
    results wait for the database (the next test brings the database back)."""
    sign_in(page, station.url, "olga")
    page.wait_for_url("**/start")
    page.check("input[value='box']", force=True)
    page.fill("#serial", "SN-1001")
    shot(page, "start", tmp_path)
    page.fill("#serial", "")
    run = _start(page, station, "SN-1001")
    # live: the progress comes by server-sent events as the run goes; read in one go in the page (the events
    # change it between two reads) and the pause asked at once: the station paces the arm (~1 s a view), and
    # the box run's last four views and its tail take a few seconds, so a pause asked later could find the
    # run done (it did, under load)
    seen = page.wait_for_function(
        """() => {
            const text = (id) => document.getElementById(id).textContent;
            const state = document.getElementById('live').dataset.state || '';
            if (!(+text('done') >= 2 && state.startsWith('scanning'))) return null;
            return {words: text('words'), view: text('view'), total: text('total'), left: text('left')};
        }""",
        timeout=90_000,
    ).json_value()
    shot(page, "live", tmp_path)
    page.click("#pause")
    assert re.fullmatch(r"(Moving to|Measuring) view \d+", seen["words"])
    view, total = int(seen["view"]), int(seen["total"])
    assert 2 <= view <= total
    assert re.fullmatch(r"\d+ (min \d\d )?s", seen["left"])
    page.wait_for_function("() => document.getElementById('live').dataset.state === 'paused'", timeout=60_000)
    assert page.inner_text("#words") == "Paused by olga"
    # the last measured view's picture (read once loaded, in one go: a new view would change its source) and
    # its photo (the run keeps its raw images until it ends), the map its inset; never full size
    loaded = "(i) => (i.getAttribute('src') && i.complete) ? [i.naturalWidth, i.naturalHeight] : null"
    thumb = page.wait_for_function(f"() => ({loaded})(document.getElementById('thumb'))").json_value()
    if thumb != [320, 240]:  # a broken image is complete and 0 px wide: say what the station answered
        src = page.locator("#thumb").get_attribute("src")
        answer = page.request.get(station.url + src)
        said = f"HTTP {answer.status} {answer.text()[:200]!r}"
        pytest.fail(f"the view's picture {src} did not load ({thumb}); the station answered {said}")
    photo = page.wait_for_function(
        f"() => {{ const p = document.getElementById('photo'); return p.hidden ? null : ({loaded})(p); }}"
    ).json_value()
    assert photo == [320, 240]
    assert page.locator("#pictures").evaluate("f => f.classList.contains('with-photo')")
    expect(page.locator("#resume")).to_be_enabled(timeout=60_000)  # once the paused process has ended
    assert page.locator("#pause").is_disabled()
    shot(page, "paused", tmp_path)
    journal = _journal(run)
    asked = next(i for i, e in enumerate(journal) if e["event"] == "operator" and e["action"] == "pause")
    assert journal[asked]["by"] == "olga"
    assert any(e.get("state") == "paused" for e in journal[asked:])  # the controller paused it, after
    measured = len(list((run / "views").iterdir()))
    database.stop()  # the plant's database goes away while the run waits
    page.click("#resume")
    page.wait_for_url("**/verdict", timeout=120_000)
    # the verdict against the dent the simulated part carries (part frame)
    assert page.inner_text("#word") == "FAIL"
    assert page.inner_text("#serial") == "SN-1001"
    assert page.inner_text("#defect-kind") == "dent"
    value = float(page.inner_text("#defect-value").split()[0])
    assert value == pytest.approx(-DENT["depth_mm"], abs=0.08)
    at = [float(v) for v in re.findall(r"-?\d+\.\d", page.inner_text("#defect-at"))]
    assert np.linalg.norm(np.subtract(at[:2], DENT["centre_mm"][:2])) < 0.6 * DENT["radius_mm"]
    assert page.inner_text("#defect-region").startswith("lid")
    assert "region 'lid' failed" in page.inner_text("#reasons")
    report = json.loads((run / "results" / "report.json").read_text())
    assert value == pytest.approx(report["regions"][0]["extreme_mm"], abs=5e-4)
    # the run's own report, embedded once written: the verdict page shows as soon as the verdict is published
    # and refreshes until the report's page is there
    expect(page.locator("#report")).to_have_count(1, timeout=60_000)
    # the database was away: said on the page and in the run's journal; the run is whole all the same
    assert "Not yet in the results database" in page.inner_text("#unsynced")
    shot(page, "verdict", tmp_path)
    journal = _journal(run)
    assert [e["state"] for e in journal if e["event"] == "exit"] == ["paused", "done"]
    assert any(e["event"] == "results_not_recorded" for e in journal)
    assert measured >= 2 and (run / "results" / "cloud.ply").is_file()


def test_the_database_back_the_run_is_recorded_and_listed(
    page, station: StationServer, database: PostgresServer, tmp_path: Path
) -> None:
    database.start()
    (run,) = station.run_dirs()
    deadline = time.monotonic() + 60
    while not any(e["event"] == "results_recorded" and e.get("later") for e in _journal(run)):
        assert time.monotonic() < deadline, "the station did not record the run once the database was back"
        time.sleep(0.5)
    events = [e["event"] for e in _journal(run)]
    assert events.index("results_not_recorded") < len(events) - 1 - events[::-1].index("results_recorded")
    assert any(e["event"] == "results_recorded_later" for e in station.journal())
    sign_in(page, station.url, "olga")
    page.goto(station.url + "/runs")
    page.fill("#f-serial", "SN-1001")
    page.select_option("#f-operator", "olga")  # the choices are what the database holds
    assert page.locator("#f-part option").all_inner_texts() == ["any", "box"]
    page.click("#filter")
    rows = page.locator("#runs tbody tr")
    expect(rows).to_have_count(1)
    assert "FAIL" in rows.inner_text().upper() and "olga" in rows.inner_text()
    page.goto(station.url + "/runs?verdict=pass")
    assert page.inner_text("#runs tbody") == "No run matches."


def test_a_start_while_running_is_refused_and_a_station_restart_leaves_the_run_alone(
    page, station: StationServer, tmp_path: Path
) -> None:
    run = _start(page, station, "SN-1002")
    page.wait_for_function(
        "() => (document.getElementById('live').dataset.state || '').startsWith('scanning')", timeout=90_000
    )
    # a second operator tab: the start page says a run is in progress, and a start is refused
    other = page.context.new_page()
    other.goto(station.url + "/start")
    assert "A run is in progress" in other.inner_text(".banner")
    other.fill("#serial", "SN-1003")
    other.press("#serial", "Enter")
    assert "Not started: run box-SN-1002-" in other.locator(".msg.error").inner_text()
    shot(other, "refused", tmp_path)
    other.close()
    assert not list(station.runs.glob("box-SN-1003-*"))
    assert any("in progress" in e["why"] for e in _events(station, "start_refused"))
    # the station stops (an update, a crash) and comes back: the run goes on meanwhile, the page follows it
    (child,) = station.children()
    station.stop()
    assert process_alive(child["pid"], child["start"])
    station.serve()
    assert station.children() == [child]
    page.wait_for_url("**/verdict", timeout=120_000)  # this one runs to its end: the SPC's second run
    assert page.inner_text("#word") == "FAIL"
    # its end (the verdict page refreshes until the report's page is written): recorded in the database
    expect(page.locator("#report")).to_have_count(1, timeout=60_000)
    assert page.locator("#unsynced").count() == 0
    assert run.is_dir()


def _extreme(report: dict) -> float:
    low, high = report["deviation"]["min_mm"], report["deviation"]["max_mm"]
    return high if abs(high) >= abs(low) else low


def test_the_spc_table_agrees_with_the_runs_reports(page, station: StationServer, tmp_path: Path) -> None:
    runs = sorted(station.run_dirs(), key=lambda r: _journal(r)[0]["t"])  # oldest first, as the page
    reports = [json.loads((r / "results" / "report.json").read_text()) for r in runs]
    sign_in(page, station.url, "olga")
    page.goto(station.url + "/runs")
    shot(page, "runs", tmp_path)
    page.goto(station.url + "/spc")
    page.click("a.tile[href='/spc/box']")
    rows = page.locator("#trend tbody tr")
    expect(rows).to_have_count(2)
    for row, report in zip(rows.all(), reports):
        assert float(row.locator(".mean").inner_text()) == pytest.approx(
            report["deviation"]["mean_mm"], abs=6e-5
        )
        assert float(row.locator(".extreme").inner_text()) == pytest.approx(_extreme(report), abs=6e-5)
    # Cp/Cpk (moving range of consecutive runs / 1.128) and Pp/Ppk (sample s) of the per-run means against
    # the band, computed here from the reports
    means = np.array([r["deviation"]["mean_mm"] for r in reports])
    s, xbar = means.std(ddof=1), means.mean()
    within = np.abs(np.diff(means)).mean() / 1.128
    lower, upper = reports[-1]["tolerance"]["lower_mm"], reports[-1]["tolerance"]["upper_mm"]
    part = page.locator("#capability tr[data-series='part']")
    for cls, sigma in (("cp", within), ("pp", s)):
        assert float(part.locator(f".{cls}").inner_text()) == pytest.approx(
            (upper - lower) / (6 * sigma), rel=0.01
        )
        assert float(part.locator(f".{cls}k").inner_text()) == pytest.approx(
            min(upper - xbar, xbar - lower) / (3 * sigma), rel=0.01
        )
    lid = [next(v for v in r["region_verdicts"] if v["name"] == "lid")["mean_mm"] for r in reports]
    expected = (upper - lower) / (6 * np.std(lid, ddof=1))
    assert float(page.locator("#capability tr[data-series='lid'] .pp").inner_text()) == pytest.approx(
        expected, rel=0.01
    )
    assert page.locator("figure.chart svg").count() == 2  # the trends of the part and of the region
    shot(page, "spc", tmp_path)
    with page.expect_download() as download:
        page.click("#csv")
    text = Path(download.value.path()).read_text()
    part_rows = [line.split(",") for line in text.splitlines()[1:] if line.startswith("part,")]
    assert [float(r[5]) for r in part_rows] == pytest.approx(list(means), abs=1e-5)


def test_a_run_aborted_from_the_page(page, station: StationServer) -> None:
    run = _start(page, station, "SN-1004")
    page.wait_for_function(
        "() => (document.getElementById('live').dataset.state || '').startsWith('scanning')", timeout=90_000
    )
    page.click("#abort")
    page.click("#confirm-yes")  # asked on the page itself
    page.wait_for_url("**/verdict", timeout=90_000)
    assert page.inner_text("#word") == "ABORTED"
    assert "aborted by olga at the station" in page.inner_text("#reasons")
    journal = _journal(run)
    states = [e["state"] for e in journal if e["event"] == "state"]
    assert states[-2:] == ["paused", "aborted"]  # paused safely first, then aborted by the state machine
    assert [e["state"] for e in journal if e["event"] == "exit"] == ["paused", "aborted"]
    with pytest.raises(ConfigError, match="was aborted"):
        resume(run)  # the terminal's `cell resume` refuses it too
    # the runs list is the results database's, which learns the end from the run's folder a moment later (the
    # verdict page reads the folder): it said "paused" once, read right after the abort (CI, 2026-11-27)
    deadline = time.monotonic() + 30
    while True:
        page.goto(station.url + "/runs?serial=SN-1004")
        listed = page.inner_text("#runs tbody").lower()
        if "aborted" in listed or time.monotonic() > deadline:
            break
        time.sleep(0.5)
    assert "aborted" in listed, f"the runs list still says {listed!r} 30 s after the abort"
