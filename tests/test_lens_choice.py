"""The lens model of a one-frame calibration chosen by the data."""

from dataclasses import replace

import numpy as np
import pytest

from mocap.calibration import CalibrationOptions, Observations
from mocap.calibration.lens_choice import calibrate_choosing_lens
from mocap.calibration.solve import template_camera
from mocap.cli import main
from mocap.io.machine_toml import save_machine
from mocap.io.tracks_csv import save_tracks
from mocap.synthetic.lens_scene import board_scene


def one_frame(scene, frame=0):
    c, m = np.nonzero(np.isfinite(scene.pixels[:, frame, :, 0]))
    return Observations(c, m, scene.pixels[c, frame, m]), [template_camera(x.name, x.size) for x in scene.cameras]


@pytest.mark.parametrize("seed", [0, 1])
def test_barrel_distortion_is_freed_and_a_pinhole_kept(seed):
    distorted = board_scene(np.random.default_rng(seed), n_frames=1, noise_px=0.3)
    observations, templates = one_frame(distorted)
    result, criterion = calibrate_choosing_lens(distorted.board, observations, templates, CalibrationOptions())
    assert min(criterion, key=criterion.get) != "none"  # the distortion buys more than log(n) per coefficient
    assert result.rms_px < 1.5 * 0.3 * np.sqrt(2)  # per point, at the noise
    pinhole = board_scene(np.random.default_rng(seed), n_frames=1, noise_px=0.3, k1=0.0)
    observations, templates = one_frame(pinhole)
    _, criterion = calibrate_choosing_lens(pinhole.board, observations, templates, CalibrationOptions())
    assert min(criterion, key=criterion.get) == "none"


def test_calibrate_command_reports_the_choice_and_obeys_the_flag(tmp_path, capsys):
    scene = board_scene(np.random.default_rng(5), n_frames=1, noise_px=0.3)
    save_tracks(scene.tracks(), tmp_path / "tracks.csv")
    save_machine(scene.board, tmp_path / "board.toml")
    args = ["calibrate", str(tmp_path / "board.toml"), str(tmp_path / "tracks.csv"), "--size", "1280x720"]
    assert main([*args, "--out", str(tmp_path / "auto.toml")]) == 0
    assert "lens distortion chosen by the data: k1" in capsys.readouterr().out
    assert main([*args, "--out", str(tmp_path / "none.toml"), "--distortion", "none", "--max-rms", "100"]) == 0
    assert "chosen by the data" not in capsys.readouterr().out
    assert main([*args, "--out", str(tmp_path / "x.toml"), "--distortion", "k7"]) == 2
    assert "invalid choice: 'k7'" in capsys.readouterr().err
