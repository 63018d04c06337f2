"""Screenshots of a session's reports and of its replay, as headless Chromium shows them, for
the README and docs/ (so that the pictures show the current output):

    python scripts/screenshots.py mocap-demo [--out docs/screenshots]

writes dig_report.png and session_report.png (the pages' first 2,400 px at 1,280 px wide)
and replay.png (the Rerun web viewer, served by `rerun --serve-web` on the session's
results/session.rrd, after it has loaded). Needs the `chromium` package (Debian) and the
session's results (`mocap demo` or `mocap run`).
"""

from __future__ import annotations

import argparse
import base64
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
HEADLESS = ("--headless=new", "--no-sandbox", "--disable-gpu", "--hide-scrollbars")


def chromium() -> str:
    for name in BROWSERS:
        if path := shutil.which(name):
            return path
    sys.exit("screenshots: Chromium not found; install it (Debian: apt-get install chromium)")


def page_screenshot(page: Path, out: Path, width: int = 1280, height: int = 2400) -> None:
    subprocess.run([chromium(), *HEADLESS, f"--window-size={width},{height}", "--virtual-time-budget=5000",
                    f"--screenshot={out}", page.resolve().as_uri()], check=True, capture_output=True, timeout=120)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def browser_binary() -> str:
    """Chromium's own binary: Debian's `chromium` is a shell script that closes the file
    descriptors the DevTools pipe needs."""
    path = Path(chromium()).resolve()
    with path.open("rb") as f:
        script = f.read(2) == b"#!"
    for candidate in (Path("/usr/lib/chromium/chromium"), Path("/usr/lib/chromium-browser/chromium-browser")):
        if script and candidate.is_file():
            return str(candidate)
    return str(path)


class DevTools:
    """Chromium driven over its DevTools pipe (fds 3 and 4: JSON messages ended by NUL)."""

    def __init__(self, width: int, height: int, profile: str):
        to_browser, self._write = os.pipe()
        self._read, from_browser = os.pipe()

        def pipes() -> None:
            a, b = os.dup(to_browser), os.dup(from_browser)  # dup2 onto a different fd clears close-on-exec
            os.dup2(a, 3)
            os.dup2(b, 4)

        self.process = subprocess.Popen(
            [browser_binary(), "--headless=new", "--no-sandbox", "--use-angle=swiftshader",
             "--enable-unsafe-swiftshader",
             "--hide-scrollbars", f"--user-data-dir={profile}", f"--window-size={width},{height}",
             "--remote-debugging-pipe", "about:blank"],
            close_fds=False, preexec_fn=pipes, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(to_browser)
        os.close(from_browser)
        self._buffer, self._next = b"", 0

    def call(self, method: str, session: str | None = None, **params) -> dict:
        self._next += 1
        message = {"id": self._next, "method": method, "params": params, **({"sessionId": session} if session else {})}
        os.write(self._write, json.dumps(message).encode() + b"\0")
        while True:
            while b"\0" not in self._buffer:
                chunk = os.read(self._read, 1 << 20)
                if not chunk:
                    raise RuntimeError(f"Chromium closed its DevTools pipe during {method}")
                self._buffer += chunk
            raw, self._buffer = self._buffer.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == self._next:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply["result"]

    def close(self) -> None:
        try:
            self.call("Browser.close")
        except (RuntimeError, OSError):
            pass
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        os.close(self._write)
        os.close(self._read)


def live_screenshot(url: str, out: Path, wait_s: float, width: int = 1600, height: int = 1000) -> None:
    """`url` shot after `wait_s` seconds of real time (a WebAssembly viewer compiles in real
    time, which --virtual-time-budget runs past)."""
    with tempfile.TemporaryDirectory() as profile:
        browser = DevTools(width, height, profile)
        try:
            target = browser.call("Target.createTarget", url=url)["targetId"]
            session = browser.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
            browser.call("Emulation.setDeviceMetricsOverride", session, width=width, height=height,
                         deviceScaleFactor=1, mobile=False)
            time.sleep(wait_s)
            png = browser.call("Page.captureScreenshot", session, format="png")["data"]
            out.write_bytes(base64.b64decode(png))
        finally:
            browser.close()


def replay_screenshot(recording: Path, out: Path, wait_s: float = 60.0) -> None:
    """The web viewer on `recording`, served by the Rerun beside this Python, shot after `wait_s`."""
    web, grpc = _free_port(), _free_port()
    server = subprocess.Popen([sys.executable, "-m", "rerun", "--serve-web", "--web-viewer-port", str(web),
                               "--port", str(grpc), str(recording)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        time.sleep(3.0 + recording.stat().st_size / 20e6)  # the server reads the whole file first
        live_screenshot(f"http://127.0.0.1:{web}/?url=rerun%2Bhttp://127.0.0.1:{grpc}/proxy", out, wait_s)
    finally:  # `python -m rerun` runs the viewer's binary as a child: stop the whole group
        os.killpg(server.pid, signal.SIGTERM)
        server.wait(timeout=10)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("session", type=Path, help="session folder with results/")
    parser.add_argument("--out", type=Path, default=Path("docs/screenshots"), help="default docs/screenshots")
    parser.add_argument("--no-replay", action="store_true", help="the reports only")
    args = parser.parse_args(argv)
    results = args.session / "results"
    args.out.mkdir(parents=True, exist_ok=True)
    for page, name in (("report.html", "dig_report.png"), ("session_report.html", "session_report.png")):
        if (results / page).is_file():
            page_screenshot(results / page, args.out / name)
            print(f"wrote {args.out / name}")
    if not args.no_replay and (results / "session.rrd").is_file():
        replay_screenshot(results / "session.rrd", args.out / "replay.png")
        print(f"wrote {args.out / 'replay.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
