"""Headless Chromium: the one place that finds the browser and drives it (a report's PDF, screenshots).

``cell report --pdf`` and the tests that look at pages in a real browser go through here. Chromium is
``$CELL_CHROMIUM`` or the first of :data:`NAMES` on the PATH (Debian: package ``chromium``). Each
:class:`Browser` is a fresh headless browser with a throw-away profile and the flags a locked-down machine
needs (no sandbox for root in a container, no GPU, no network chatter, no first-run dialogs), driven over
the DevTools protocol on a pipe (``--remote-debugging-pipe``: JSON messages ended by a NUL byte, the browser
reading fd 3 and writing fd 4). The protocol, unlike ``--screenshot`` or ``--print-to-pdf`` on the command
line, can wait until a page says it is ready (the report's 3D view is drawn by a script after the page
loaded). Output files are written beside their target and renamed into place, so a failed or killed call
never leaves half a PDF; a browser that does not answer in time is killed with every process it started.
"""

from __future__ import annotations

import base64
import json
import os
import secrets
import select
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path
from types import TracebackType
from typing import Any

from cell.errors import ConfigError

ENV = "CELL_CHROMIUM"
NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
    # WebGL (the report's 3D view) in software: without a GPU Chromium falls back to SwiftShader on its own,
    # a fallback it has deprecated; only the cell's own local pages are opened
    "--enable-unsafe-swiftshader",
    "--remote-debugging-pipe",
)


def find_chromium() -> Path | None:
    """The Chromium executable: ``$CELL_CHROMIUM`` if set, else the first of :data:`NAMES` on the PATH."""
    given = os.environ.get(ENV)
    if given:
        return Path(given) if Path(given).is_file() else None
    for name in NAMES:
        found = shutil.which(name)
        if found:
            return Path(found)
    return None


def require_chromium() -> Path:
    """The Chromium executable, or a ConfigError saying how to get one (before any work that needs it)."""
    exe = find_chromium()
    if exe is None:
        raise ConfigError(
            f"Chromium not found (looked for ${ENV}, then {', '.join(NAMES)} on the PATH): install it "
            f"(Debian: apt-get install chromium) or set {ENV} to the browser's path",
            field="chromium",
        )
    return exe


def write_file_atomic(path: Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` via a temporary file beside it (the umask applies)."""
    path = Path(path)
    tmp = path.parent / f".{path.name}.{os.getpid()}-{secrets.token_hex(4)}.partial"
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    except OSError as exc:
        raise ConfigError(f"cannot write {path.name} here ({exc.strerror})", path=str(path.parent)) from exc
    finally:
        tmp.unlink(missing_ok=True)
    return path


class Browser:
    """One headless Chromium with one page, for ``with Browser() as b: b.open(page); b.pdf(out)``."""

    def __init__(self, timeout_s: float = 180.0) -> None:
        self.timeout_s = timeout_s
        self._proc: subprocess.Popen[bytes] | None = None
        self._profile: tempfile.TemporaryDirectory[str] | None = None
        self._stderr: Any = None
        self._wfd = self._rfd = -1
        self._deadline = 0.0
        self._session: str | None = None
        self._buf = b""
        self._next_id = 0

    # ------------------------------------------------------------------ the process
    def __enter__(self) -> Browser:
        exe = require_chromium()
        self._profile = tempfile.TemporaryDirectory(prefix="cell-chromium-")
        self._stderr = tempfile.TemporaryFile()
        to_browser, self._wfd = os.pipe()
        self._rfd, from_browser = os.pipe()

        def fds_3_and_4() -> None:  # in the child, before exec: the pipe ends where the browser expects them
            os.dup2(to_browser, 3)
            os.dup2(from_browser, 4)

        self._proc = subprocess.Popen(
            [str(exe), *FLAGS, f"--user-data-dir={self._profile.name}", "about:blank"],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=self._stderr,
            pass_fds=(3, 4, to_browser, from_browser),
            preexec_fn=fds_3_and_4,
            start_new_session=True,  # its own process group: a timeout kills the helpers too
        )
        os.close(to_browser)
        os.close(from_browser)
        self._deadline = time.monotonic() + self.timeout_s
        return self

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        proc = self._proc
        if proc is not None:
            try:
                if kind is None:
                    self._call("Browser.close")
                    proc.wait(timeout=30)
            except (ConfigError, subprocess.TimeoutExpired):
                pass
            finally:
                if proc.poll() is None:
                    os.killpg(proc.pid, signal.SIGKILL)
                    proc.wait()
                os.close(self._wfd)
                os.close(self._rfd)
                self._stderr.close()
                if self._profile is not None:
                    self._profile.cleanup()
        self._proc = None

    def _failure(self, what: str) -> ConfigError:
        self._stderr.seek(0)
        lines = [
            ln for ln in self._stderr.read().decode(errors="replace").splitlines() if "GL Driver" not in ln
        ]
        tail = " | ".join(lines[-3:])
        return ConfigError(f"Chromium {what}{': ' + tail if tail else ''}", field="chromium")

    # ------------------------------------------------------------------ the protocol
    def _call(
        self, method: str, params: dict[str, Any] | None = None, session: bool = False
    ) -> dict[str, Any]:
        """Send one command and return its result; events in between are skipped."""
        self._next_id += 1
        msg: dict[str, Any] = {"id": self._next_id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = self._session
        try:
            os.write(self._wfd, json.dumps(msg).encode() + b"\0")
        except OSError as exc:
            raise self._failure("is not running") from exc
        while True:
            reply = self._receive()
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise self._failure(f"refused {method}: {reply['error'].get('message')}")
                return reply.get("result", {})

    def _receive(self) -> dict[str, Any]:
        while b"\0" not in self._buf:
            left = self._deadline - time.monotonic()
            ready = select.select([self._rfd], [], [], max(left, 0))[0] if left > 0 else []
            if not ready:
                raise self._failure(f"did not finish within {self.timeout_s:.0f} s")
            chunk = os.read(self._rfd, 1 << 20)
            if not chunk:
                raise self._failure("ended unexpectedly")
            self._buf += chunk
        message, self._buf = self._buf.split(b"\0", 1)
        reply: dict[str, Any] = json.loads(message)
        return reply

    # ------------------------------------------------------------------ the page
    def open(self, page: Path, width_px: int = 1200, height_px: int = 1600, fragment: str = "") -> None:
        """Load the HTML file ``page`` (with ``#fragment`` when given) in a ``width_px`` x ``height_px``
        window; wait for its load event."""
        page = Path(page).resolve()
        if not page.is_file():
            raise ConfigError("no such page to render", path=str(page))
        target = self._call("Target.createTarget", {"url": "about:blank"})["targetId"]
        self._session = self._call("Target.attachToTarget", {"targetId": target, "flatten": True})[
            "sessionId"
        ]
        metrics = {"width": width_px, "height": height_px, "deviceScaleFactor": 1, "mobile": False}
        self._call("Emulation.setDeviceMetricsOverride", metrics, session=True)
        url = page.as_uri() + (f"#{fragment}" if fragment else "")
        nav = self._call("Page.navigate", {"url": url}, session=True)
        if nav.get("errorText"):
            raise ConfigError(f"Chromium cannot open it: {nav['errorText']}", path=str(page))
        self.wait_for("document.readyState === 'complete'")

    def evaluate(self, expression: str) -> Any:
        """The value of a JavaScript expression in the page (a promise is awaited)."""
        params = {"expression": expression, "awaitPromise": True, "returnByValue": True}
        result = self._call("Runtime.evaluate", params, session=True)
        if "exceptionDetails" in result:
            raise self._failure(f"script failed: {result['exceptionDetails'].get('text')}")
        return result.get("result", {}).get("value")

    def wait_for(self, condition: str, poll_ms: int = 100) -> None:
        """Wait until the JavaScript expression ``condition`` is true in the page (or the browser's time
        runs out)."""
        self.evaluate(
            f"new Promise((done) => {{ const test = () => {{ if ({condition}) done(true); "
            f"else setTimeout(test, {poll_ms}); }}; test(); }})"
        )

    def screenshot(self, png: Path) -> Path:
        """A PNG of the window."""
        data = self._call("Page.captureScreenshot", {"format": "png"}, session=True)["data"]
        return write_file_atomic(png, base64.b64decode(data))

    def pdf(self, pdf: Path) -> Path:
        """The page printed as Chromium prints it: its print stylesheet, its ``@page`` size and margins,
        backgrounds, no header or footer line of the browser's own."""
        params = {"preferCSSPageSize": True, "printBackground": True, "displayHeaderFooter": False}
        data = self._call("Page.printToPDF", params, session=True)["data"]
        return write_file_atomic(pdf, base64.b64decode(data))


def print_pdf(
    page: Path, pdf: Path, ready: str | None = None, fragment: str = "", timeout_s: float = 180.0
) -> Path:
    """Print the HTML file ``page`` (``#fragment``) to ``pdf`` once it loaded and ``ready`` (a JavaScript
    condition) holds."""
    with Browser(timeout_s) as browser:
        browser.open(page, fragment=fragment)
        if ready:
            browser.wait_for(ready)
        return browser.pdf(pdf)


def screenshot(
    page: Path,
    png: Path,
    width_px: int = 1200,
    height_px: int = 1600,
    ready: str | None = None,
    timeout_s: float = 180.0,
) -> Path:
    """A PNG of the top ``width_px`` x ``height_px`` of ``page`` once it loaded and ``ready`` (a JavaScript
    condition, e.g. that a script drew what the page shows) holds."""
    with Browser(timeout_s) as browser:
        browser.open(page, width_px, height_px)
        if ready:
            browser.wait_for(ready)
        return browser.screenshot(png)
