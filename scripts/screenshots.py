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


def replay_screenshot(recording: Path, out: Path, wait_s: float = 60.0) -> None:
    """The web viewer on `recording`, served by the Rerun beside this Python, shot after `wait_s`."""
    web, grpc = _free_port(), _free_port()
    server = subprocess.Popen([sys.executable, "-m", "rerun", "--serve-web", "--web-viewer-port", str(web),
                               "--port", str(grpc), str(recording)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        time.sleep(3.0 + recording.stat().st_size / 20e6)  # the server reads the whole file first
        url = f"http://127.0.0.1:{web}/?url=rerun%2Bhttp://127.0.0.1:{grpc}/proxy"
        with tempfile.TemporaryDirectory() as profile:
            subprocess.run([chromium(), "--headless=new", "--no-sandbox", "--use-angle=swiftshader",
                            "--enable-unsafe-swiftshader", "--hide-scrollbars", f"--user-data-dir={profile}",
                            "--window-size=1600,1000", f"--virtual-time-budget={int(wait_s * 1000)}",
                            f"--screenshot={out}", url], check=True, capture_output=True, timeout=wait_s + 120)
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
