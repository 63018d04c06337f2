"""The reports as a browser shows them: the dig report (`analyze`'s report.html) and the
session report rendered by headless Chromium, with a script put in the page's head that
records, once the page has loaded, whether every figure loaded, whether anything reaches
past the page's width, the console's errors and the tables' text. The summary's numbers are
checked against cycles.csv. Without Chromium the test is skipped, except in CI (CI=true),
where it fails."""

import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from mocap import cli
from mocap.io.cameras_toml import load_calibration, save_calibration
from mocap.io.cycles_csv import load_cycle_table
from mocap.io.motion_csv import load_motion, save_motion
from mocap.io.session import Session
from mocap.io.tracks_csv import load_tracks, save_tracks

CHECK = (Path(__file__).parent / "data" / "page_check.js").read_text()
BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def find_chromium() -> str:
    for name in BROWSERS:
        if path := shutil.which(name):
            return path
    if os.environ.get("CI") == "true":
        pytest.fail("Chromium is not installed (.ci/run installs the Debian package `chromium`)")
    pytest.skip("Chromium is not installed (Debian: apt-get install chromium)")


def rendered(page: Path, tmp_path: Path, width: int = 1280) -> dict:
    """What the check script recorded for `page` in a `width` px wide window."""
    checked = tmp_path / f"checked_{page.name}"
    checked.write_text(page.read_text().replace("<head>", "<head>" + CHECK, 1))
    run = subprocess.run(
        [find_chromium(), "--headless=new", "--no-sandbox", "--disable-gpu", f"--window-size={width},900",
         "--virtual-time-budget=5000", "--dump-dom", checked.as_uri()],
        capture_output=True, text=True, timeout=120)
    found = re.search(r'<pre id="mocap-check"[^>]*>([^<]*)</pre>', run.stdout)
    assert found, f"the page did not finish loading: {run.stderr[-500:]}"
    return json.loads(found.group(1).replace("&amp;", "&").replace("&lt;", "<").replace("&gt;", ">"))


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """A session folder from a synthetic session's truth (3 cycles, no video): the truth's
    calibration, tracks and motion, analysed and reported."""
    find_chromium()
    root = tmp_path_factory.mktemp("browser") / "s"
    assert cli.main(["synth", "--machine", "hitachi_ex3500", "--cycles", "3", "--no-video", "--scale", "0.5",
                     "--fps", "10", "--out", str(root)]) == 0
    s = Session.open(root)
    truth = load_calibration(s.truth_dir / "cameras.toml")
    save_calibration(truth, s.calibration_path)
    tracks = load_tracks(s.truth_dir / "tracks.csv")
    for name in truth.names:
        save_tracks(tracks.select(np.asarray(tracks.camera) == name), s.tracks_path(name))
    save_motion(load_motion(s.truth_dir / "motion.csv", s.machine()), s.machine(), s.motion_path)
    assert cli.main(["analyze", "hitachi_ex3500", str(s.motion_path), "--out", str(s.results_dir)]) == 0
    assert cli.main(["report", str(root)]) == 0
    return s


def test_dig_report_in_a_browser(session, tmp_path):
    page = rendered(session.results_dir / "report.html", tmp_path)
    assert page["images"] == 6 and page["broken"] == 0
    assert page["scroll_width"] <= page["client_width"] and page["overflowing"] == []
    assert page["errors"] == []
    facts, spread = page["tables"][0], page["tables"][1]
    table = load_cycle_table(session.results_dir / "cycles.csv")
    times = np.array([float(v) if v.strip() else np.nan for v in table["cycle_time_s"]])
    assert facts[1][0] == str(len(table["cycle"])) == "3" and facts[1][1] == str(np.isfinite(times).sum())
    rows = {row[0]: row for row in spread[1:]}
    assert rows["cycle time (s)"][1] == f"{np.nanmedian(times):.1f}"
    assert rows["cycle time (s)"][3] == f"{np.nanmin(times):.1f}–{np.nanmax(times):.1f}"
    dig = np.array([float(v) for v in table["dig_s"]])
    assert rows["dig (s)"][1] == f"{np.median(dig):.1f}"


def test_session_report_in_a_browser(session, tmp_path):
    page = rendered(session.results_dir / "session_report.html", tmp_path)
    assert page["images"] == 3 and page["broken"] == 0
    assert page["scroll_width"] <= page["client_width"] and page["overflowing"] == []
    assert page["errors"] == []
    cameras = page["tables"][0]
    assert [row[0] for row in cameras[1:]] == ["cam1", "cam2", "cam3"]
