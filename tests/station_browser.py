"""What the station's browser tests share: a station server in a child process on a free port with a tmp runs
root, the small simulated cell and the dented box recipe; real headless Chromium (Debian's ``chromium``)
driven by Playwright; screenshots. Skipped without Chromium or Playwright unless CELL_REQUIRE_CHROMIUM=1
(CI), where their absence fails the tests."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import yaml

from cell.runs import process_alive
from cell.station.users import Role, add_user
from tests.box_part import small_cell, write_dented_box_recipe

REPO = Path(__file__).resolve().parent.parent
CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
SCREEN = {"width": 1280, "height": 800}  # a 15" industrial touch panel
USERS = {"olga": ("operator", "2468"), "tom": ("technician", "1357")}
# CELL_STATION_SCREENSHOTS=docs/station writes the pages' pictures for docs/station.md
SHOTS = os.environ.get("CELL_STATION_SCREENSHOTS")


def need_chromium() -> None:
    """Skip (or fail under CELL_REQUIRE_CHROMIUM=1) when Chromium or Playwright is missing."""
    missing = []
    if not CHROMIUM.is_file():
        missing.append(f"{CHROMIUM} (Debian package chromium)")
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        missing.append("the playwright Python package (pip install playwright)")
    if missing:
        message = "station browser tests need " + " and ".join(missing)
        if os.environ.get("CELL_REQUIRE_CHROMIUM") == "1":
            pytest.fail(message)
        pytest.skip(message)


@dataclass
class StationServer:
    """A running ``cell station serve`` (restartable with the same arguments) and its folders."""

    url: str
    root: Path
    runs: Path
    recipes: Path
    args: list[str]
    proc: subprocess.Popen[bytes] | None = None

    def journal(self) -> list[dict]:
        path = self.runs / ".station" / "journal.jsonl"
        return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []

    def run_dirs(self) -> list[Path]:
        """The inspection run folders (of the box), by name."""
        return sorted(self.runs.glob("box-*"))

    def serve(self) -> None:
        """Start the server and wait until it answers."""
        log = open(self.root / "server.log", "ab")
        self.proc = subprocess.Popen(
            self.args,
            cwd=REPO,
            stdout=log,
            stderr=subprocess.STDOUT,
            env={**os.environ, "PYTHONPATH": str(REPO)},
        )
        deadline = time.monotonic() + 60
        while True:
            try:
                urllib.request.urlopen(self.url + "/signin", timeout=2)
                return
            except OSError:
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(
                        "station did not start: " + (self.root / "server.log").read_text()
                    ) from None
                time.sleep(0.2)

    def stop(self, how: int = signal.SIGTERM) -> None:
        """Stop the server process (runs it started go on in their own processes)."""
        assert self.proc is not None
        self.proc.send_signal(how)
        try:
            self.proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()

    def children(self) -> list[dict]:
        """The records of the runs this station started that still run."""
        found = [json.loads(p.read_text()) for p in (self.runs / ".station" / "children").glob("*.json")]
        return [c for c in found if c.get("exit_code") is None and process_alive(c["pid"], c.get("start"))]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_station(root: Path, results_db: str | None = None, *extra: str) -> StationServer:
    """Recipes (the dented box without the feedback loop's extra views, for speed; a second copy,
    ``old-box``), the small cell recording into ``results_db`` (default: the runs root's SQLite file), two
    users, then the server, offering missed results to the database every second."""
    recipes, runs = root / "recipes", root / "runs"
    recipes.mkdir(parents=True)
    runs.mkdir()
    recipe = write_dented_box_recipe(recipes)
    doc = yaml.safe_load(recipe.read_text())
    doc["plan"]["max_iterations"] = 0
    recipe.write_text(yaml.safe_dump(doc))
    shutil.copy(recipe, recipes / "old-box.yaml")
    cell = small_cell().model_dump(mode="json")
    # the simulated arm's moves last a quarter of their simulated time in wall time (fakes/robot.py): ~1 s a
    # view, so a pause asked from the page lands before the last view also on a loaded machine (unpaced, the
    # box's six views took 0.2 s each, and stop 31's CI saw the run end before the pause came)
    cell["robot"]["options"]["sim_realtime_factor"] = 4.0
    if results_db:
        cell["results_db"] = results_db
    (root / "cell.yaml").write_text(yaml.safe_dump(cell))
    users = root / "users.yaml"
    for name, (role, pin) in USERS.items():
        add_user(users, name, Role(role), pin)
    port = _free_port()
    args = [sys.executable, "-m", "cell", "station", "serve", "--cell", str(root / "cell.yaml")]
    args += ["--recipes", str(recipes), "--runs", str(runs), "--users", str(users), "--port", str(port)]
    server = StationServer(
        f"http://127.0.0.1:{port}", root, runs, recipes, [*args, "--sync-every", "1", *extra]
    )
    server.serve()
    return server


def stop_station(server: StationServer) -> None:
    """Stop the server, then any inspection it started that still runs (a failed test's)."""
    server.stop(signal.SIGINT)
    for child in server.children():
        os.kill(child["pid"], signal.SIGKILL)


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    need_chromium()
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        chromium = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        yield chromium
        chromium.close()


def shot(page: Any, name: str, tmp: Path) -> None:
    """A screenshot of the page: into CELL_STATION_SCREENSHOTS (docs/station) when set, else tmp."""
    folder = Path(SHOTS) if SHOTS else tmp
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.png"
    page.screenshot(path=str(path))
    if SHOTS:  # for the docs: a 256-colour palette, a third of the bytes, the same look for flat pages
        from PIL import Image

        with Image.open(path) as image:
            small = image.convert("RGB").quantize(256, method=Image.Quantize.MEDIANCUT)
        small.save(path, optimize=True)


def sign_in(page: Any, url: str, name: str, pin: str | None = None) -> None:
    """Sign in at the station's sign-in page, typing the PIN on the page's keypad."""
    pin = USERS[name][1] if pin is None else pin
    page.goto(url + "/signin")
    page.fill("#name", name)
    for digit in pin:
        page.click(f".keypad button[data-key='{digit}']")
    page.click("#signin")
