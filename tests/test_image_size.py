"""The image size: a stated size the pixels contradict (every observation in one quadrant,
the image centre far from them all: labels of 960x540 images calibrated with --size
1920x1080) is refused with one line; without --size, calibrate reads it from the session's
videos, and a stated size that a video contradicts is refused."""

import numpy as np
import pytest

from mocap import cli
from mocap.io.cameras_toml import load_calibration
from mocap.io.machine_toml import load_machine
from mocap.io.tracks_csv import save_tracks
from mocap.synthetic.encode import video_writer
from mocap.synthetic.scenes import observe, ring_of_cameras

SIZE = (960, 540)


@pytest.fixture(scope="module")
def labels(tmp_path_factory):
    """A session folder: 2 cameras of 960x540 (tiny black videos of that size), the first
    frame's labels in tracks/labels.csv."""
    root = tmp_path_factory.mktemp("session")
    machine = load_machine("hitachi_ex3500")
    rng = np.random.default_rng(5)
    cameras = ring_of_cameras(2, np.array([5.0, 0.0, 5.0]), (30.0, 50.0), rng, fov_deg=(45.0, 55.0), size=SIZE)
    joints = np.radians([[0.0, 40.0, -70.0, 30.0]])
    save_tracks(observe(cameras, machine, joints, rng, noise_px=0.5), root / "tracks" / "labels.csv")
    text = 'machine = "hitachi_ex3500"\n'
    for camera in cameras:
        text += f'[[cameras]]\nname = "{camera.name}"\nvideo = "videos/{camera.name}.mp4"\nfps = 30\n'
    (root / "session.toml").write_text(text)
    return root, cameras


def test_a_size_the_pixels_contradict_is_refused(labels, tmp_path, capsys):
    root, _ = labels
    args = ["calibrate", "hitachi_ex3500", str(root / "tracks" / "labels.csv"), "--out", str(tmp_path / "c.toml")]
    assert cli.main(args + ["--size", "1920x1080"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "top-left quadrant of the stated 1920x1080 image" in err and "the pixels fit 960x540" in err
    assert not (tmp_path / "c.toml").exists()
    assert cli.main(args + ["--size", "960x540", "--distortion", "none"]) == 0
    assert load_calibration(tmp_path / "c.toml").cameras[0].size == SIZE


def test_the_size_is_read_from_the_session_videos(labels, tmp_path, capsys):
    root, cameras = labels
    for camera in cameras:
        with video_writer(root / "videos" / f"{camera.name}.mp4", SIZE, 30.0, codec="mp4v") as write:
            write(np.zeros((SIZE[1], SIZE[0], 3), np.uint8))
    args = ["calibrate", "hitachi_ex3500", str(root / "tracks" / "labels.csv"), "--distortion", "none",
            "--out", str(tmp_path / "c.toml")]
    assert cli.main(args) == 0
    assert [c.size for c in load_calibration(tmp_path / "c.toml").cameras] == [SIZE, SIZE]
    capsys.readouterr()
    assert cli.main(args + ["--size", "cam1=1280x720"]) == 2
    assert "--size 1280x720 for camera 'cam1', but its video" in capsys.readouterr().err
