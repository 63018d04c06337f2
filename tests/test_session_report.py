"""The session report on a session folder made from a synthetic session's truth: the heat
map's shares are the truth tracks' own, the advice names what was made worse, the fit's
unexplained and filled frames are counted, and bad input is one line with exit 2."""

import shutil
from dataclasses import replace

import numpy as np
import pytest

from mocap import cli
from mocap.errors import InputError
from mocap.io.cameras_toml import load_calibration, save_calibration
from mocap.io.motion_csv import load_motion, save_motion
from mocap.io.session import Session
from mocap.io.tracks_csv import load_tracks, save_tracks
from mocap.report.session_report import advice, marker_shares, session_quality, write_session_report


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """A session folder whose calibration, tracks and motion are the truth's: the calibration
    with a residual and SDs written in, camera 2's residual four times the noise; cam1's
    tracks without marker U3 after 10 s; the motion with 60 frames marked unexplained."""
    root = tmp_path_factory.mktemp("session") / "s"
    assert cli.main(["synth", "--machine", "hitachi_ex3500", "--cycles", "1", "--no-video", "--scale", "0.5",
                     "--out", str(root)]) == 0
    session = Session.open(root)
    truth = load_calibration(session.truth_dir / "cameras.toml")
    truth = replace(truth, metadata={**truth.metadata, "sigma_px": 0.5})
    for k in range(len(truth.names)):
        sd = {"position": [0.1, 0.2, 0.05], "azimuth_deg": 0.1, "elevation_deg": 0.1, "tilt_deg": 0.05, "focal_px": 10.0}
        truth = truth.with_extras(k, error=2.0 if k == 1 else 0.5, paper={"sd": sd})
    save_calibration(truth, session.calibration_path)
    tracks = load_tracks(session.truth_dir / "tracks.csv")
    fps = dict(zip(truth.names, (e["fps"] for e in truth.extras)))
    lost = (np.asarray(tracks.camera) == "cam1") & (np.asarray(tracks.marker) == "U3") & (tracks.frame / 30.0 >= 10.0)
    tracks = tracks.select(~lost)
    for name in truth.names:
        save_tracks(tracks.select(np.asarray(tracks.camera) == name), session.tracks_path(name))
    machine = session.machine()
    motion = load_motion(session.truth_dir / "motion.csv", machine)
    flags = np.zeros(len(motion))
    flags[100:160] = 1
    motion = replace(motion, extra={**motion.extra, "unexplained": flags, "filled": np.zeros(len(motion))})
    save_motion(motion, machine, session.motion_path)
    return root, tracks, fps


def test_shares_are_the_tracks_own(folder):
    root, tracks, fps = folder
    markers, bins, share = marker_shares(tracks, "cam1", fps["cam1"], 0.0)
    u3 = share[markers.index("U3")]
    assert np.all(u3[bins + 2.0 <= 10.0] == 1.0) and np.all(u3[bins >= 10.0] == 0.0)  # seen all along, then lost
    # each marker's share over the whole video is its tracked frames over the video's frames
    own = tracks.select(np.asarray(tracks.camera) == "cam2")
    markers, bins, share = marker_shares(tracks, "cam2", fps["cam2"], 0.0, bin_s=1e6)
    frames = own.frame.max() - own.frame.min() + 1
    for m, s in zip(markers, share[:, 0]):
        assert s == pytest.approx(np.sum(np.asarray(own.marker) == m) / frames)


def test_advice_names_the_bad_camera_and_the_unexplained_frames(folder):
    root, _, _ = folder
    q = session_quality(root)
    words = advice(q)
    assert words[0].startswith("cam2: its calibration residual is 2.00 px")
    assert not any(w.startswith("cam1: its calibration") or w.startswith("cam3: its calibration") for w in words)
    assert any("cam1: markers tracked in under 50%" in w and "U3" in w for w in words)
    assert any(w.startswith(f"{60 / len(q.motion):.0%} of the fitted frames are unexplained") for w in words)


def test_report_command_writes_the_page(folder, tmp_path, capsys):
    root, _, _ = folder
    out = tmp_path / "r.html"
    assert cli.main(["report", str(root), "--out", str(out)]) == 0
    page = out.read_text()
    assert page.count("data:image/png;base64,") == 3 and "What to fix first" in page
    assert "60 unexplained, 0 filled" in page


def test_report_refuses_what_it_cannot_read(folder, tmp_path, capsys):
    root, _, _ = folder
    assert cli.main(["report", str(root), "--out", str(tmp_path / "r.txt")]) == 2
    assert "name it FILE.html" in capsys.readouterr().err
    empty = tmp_path / "empty"
    shutil.copytree(root, empty, ignore=shutil.ignore_patterns("calibration"))
    with pytest.raises(InputError, match="no calibration in this session yet"):
        write_session_report(empty)
    assert cli.main(["report", str(tmp_path / "nothing")]) == 2
