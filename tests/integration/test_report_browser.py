"""report.html in a real browser: headless Chromium loads the report of a small simulated survey,
every plot (a base64 PNG) must decode and the page must log no error; a screenshot is saved.

Chromium is driven over the DevTools protocol on a pipe (``--remote-debugging-pipe``: JSON
messages ending in a NUL byte on file descriptors 3 and 4), so no websocket library, driver or
browser download is needed; only the Debian package ``chromium`` (scripts/setup.sh installs it
when apt-get can). ``RAILTRAJ_UPDATE_DOCS=1`` also copies the screenshot to docs/report.png.
"""

from __future__ import annotations

import base64
import fcntl
import json
import os
import select
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow
REPO = Path(__file__).resolve().parents[2]
BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def find_chromium() -> str:
    """The Chromium binary, or a failure saying how to install it (CI must not skip this)."""
    for name in (os.environ.get("RAILTRAJ_CHROMIUM", ""), *BROWSERS):
        path = shutil.which(name) if name else None
        if path:
            return path
    pytest.fail("no Chromium found: run scripts/setup.sh as root (apt-get install chromium), "
                "or set RAILTRAJ_CHROMIUM=/path/to/chrome")


class Browser:
    """A headless Chromium page driven over the DevTools pipe, collecting page errors."""

    def __init__(self, binary: str, profile: Path, width: int = 1100, height: int = 1400) -> None:
        to_chrome, self._out = os.pipe()
        self._in, from_chrome = os.pipe()
        # the child's ends must become fds 3 and 4: move them clear of those numbers first
        child_in, child_out = (fcntl.fcntl(fd, fcntl.F_DUPFD, 100)
                               for fd in (to_chrome, from_chrome))
        os.close(to_chrome)
        os.close(from_chrome)

        def wire() -> None:
            os.dup2(child_in, 3)
            os.dup2(child_out, 4)

        self.proc = subprocess.Popen(
            [binary, "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
             "--remote-debugging-pipe", f"--user-data-dir={profile}", "--no-first-run",
             "--hide-scrollbars", "--allow-file-access-from-files", "about:blank"],
            pass_fds=(3, 4), preexec_fn=wire, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(child_in)
        os.close(child_out)
        self._buf, self._id, self.events = b"", 0, []
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        attached = self.call("Target.attachToTarget", targetId=target, flatten=True)
        self.session = attached["sessionId"]
        for method in ("Page.enable", "Runtime.enable", "Log.enable"):
            self.call(method, session=True)
        self.call("Emulation.setDeviceMetricsOverride", session=True, width=width, height=height,
                  deviceScaleFactor=1, mobile=False)

    def _receive(self, timeout: float) -> dict:
        while b"\0" not in self._buf:
            ready, _, _ = select.select([self._in], [], [], timeout)
            chunk = os.read(self._in, 1 << 20) if ready else b""
            if not chunk:
                raise TimeoutError("Chromium stopped answering on the DevTools pipe")
            self._buf += chunk
        message, self._buf = self._buf.split(b"\0", 1)
        return json.loads(message)

    def call(self, method: str, session: bool = False, timeout: float = 60.0, **params) -> dict:
        """Send one command and return its result (events arriving meanwhile are kept)."""
        self._id += 1
        msg = {"id": self._id, "method": method, "params": params}
        if session:
            msg["sessionId"] = self.session
        os.write(self._out, json.dumps(msg).encode() + b"\0")
        while True:
            reply = self._receive(timeout)
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})
            self.events.append(reply)

    def open(self, url: str, timeout: float = 60.0) -> None:
        """Navigate and wait for the load event (all inline images decoded by then)."""
        self.call("Page.navigate", session=True, url=url)
        deadline = time.monotonic() + timeout
        while not any(e.get("method") == "Page.loadEventFired" for e in self.events):
            self.events.append(self._receive(max(0.1, deadline - time.monotonic())))

    def evaluate(self, expression: str):
        return self.call("Runtime.evaluate", session=True, expression=expression,
                         returnByValue=True)["result"].get("value")

    def errors(self) -> list[str]:
        """Uncaught exceptions, console.error/assert calls and browser log errors of the page."""
        out = []
        for e in self.events:
            m, p = e.get("method"), e.get("params", {})
            if m == "Runtime.exceptionThrown":
                out.append(p["exceptionDetails"].get("text", "exception"))
            elif m == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
                args = (a.get("value", a.get("description", "")) for a in p["args"])
                out.append(" ".join(str(a) for a in args))
            elif m == "Log.entryAdded" and p["entry"].get("level") == "error":
                entry = p["entry"]
                out.append(f"{entry.get('source')}: {entry.get('text')} {entry.get('url', '')}")
        return out

    def screenshot(self, path: Path, height: int) -> None:
        width = self.evaluate("document.documentElement.scrollWidth")
        shot = self.call("Page.captureScreenshot", session=True, format="png",
                         captureBeyondViewport=True,
                         clip={"x": 0, "y": 0, "width": width, "height": height, "scale": 1})
        path.write_bytes(base64.b64decode(shot["data"]))

    def close(self) -> None:
        try:
            self.call("Browser.close", timeout=10)
        except (TimeoutError, RuntimeError, OSError):
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
        os.close(self._in)
        os.close(self._out)


IMAGES = "Array.from(document.images).map(i => [i.alt, i.complete, i.naturalWidth])"


def check_page(binary: str, page: Path, profile: Path,
               shot: Path | None = None) -> tuple[list, list[str]]:
    """Images (alt, complete, naturalWidth) and page errors of ``page``; optionally a screenshot."""
    browser = Browser(binary, profile)
    try:
        browser.open(page.resolve().as_uri())
        images = browser.evaluate(IMAGES)
        if shot is not None:
            height = browser.evaluate("document.body.scrollHeight")
            browser.screenshot(shot, height=min(2400, height))
        return images, browser.errors()
    finally:
        browser.close()


def test_the_checks_catch_a_broken_page(tmp_path):
    """The test's own eyes: a broken image and a console error are both seen."""
    page = tmp_path / "broken.html"
    page.write_text("<!doctype html><html><body><img alt='bad' src='data:image/png;base64,AAAA'>"
                    "<script>console.error('boom')</script></body></html>")
    images, errors = check_page(find_chromium(), page, tmp_path / "profile")
    assert images == [["bad", True, 0]]
    assert any("boom" in e for e in errors)


def test_report_renders_in_chromium(tmp_path):
    from railtraj.sim import generate

    sim = generate("control", tmp_path / "sim", seed=0, size=0.2)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "railtraj.cli", f"survey_dir={sim.survey_dir}", f"out_dir={out}",
           f"truth_dir={Path(sim.survey_dir).parent / 'truth'}", "anchors=false"]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    report = out / "report.html"
    text = report.read_text()
    for heading in ("Summary", "Verdict per tunnel section", "Correction applied to each run",
                    "Misalignment between runs", "Refused and ambiguous tile pairs",
                    "Control points",
                    "Against the simulator's truth", "Configuration", "Timings"):
        assert heading in text, heading
    assert "http://" not in text and "https://" not in text   # self-contained
    shot = tmp_path / "report.png"
    images, errors = check_page(find_chromium(), report, tmp_path / "profile", shot)
    assert len(images) >= 6, images
    assert all(complete and width > 0 for _, complete, width in images), images
    assert errors == []
    assert shot.stat().st_size > 10_000
    if os.environ.get("RAILTRAJ_UPDATE_DOCS") == "1":
        shutil.copy(shot, REPO / "docs" / "report.png")
