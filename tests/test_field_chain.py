"""Refine then fit on a field scene whose machine file states no tolerance (every marker
coordinate off by up to ±5 %, 0.8 px noise, 2 % wild pixels): the tolerance calibrate
estimates from its residuals is written with the calibration, and refine and fit use it
where neither the command nor the model states one; the covariance refine writes is read
back by fit."""

import numpy as np
import pytest

from mocap.cli import main
from mocap.core.calibration import Calibration
from mocap.io.cameras_toml import load_calibration, save_calibration
from mocap.io.machine_toml import save_machine
from mocap.io.motion_csv import load_motion
from mocap.io.tracks_csv import save_tracks
from mocap.reconstruct.camera_share import CameraCovariance
from mocap.synthetic.machines import SceneOptions, random_scene

ALONG_ONE_DRAW_99 = 2.6
ESTIMATED = 1000011  # a field scene (3 cameras) whose calibration estimates a tolerance near 5 %


def test_a_covariance_rounded_near_zero_is_read_and_a_skewed_one_refused():
    rng = np.random.default_rng(0)
    root = rng.normal(size=(6, 6))
    matrix = root @ root.T
    matrix[0, 1], matrix[1, 0] = 1e-20, -1e-20  # two entries of about nothing, rounded apart
    names = [f"cam1.{p}" for p in ("rx", "ry", "rz", "tx", "ty", "tz")]
    assert np.allclose(CameraCovariance.from_table({"parameters": names, "matrix": matrix.tolist()}).matrix, matrix)
    matrix[2, 3] += 1e-3 * np.sqrt(matrix[2, 2] * matrix[3, 3])
    with pytest.raises(ValueError, match="symmetric"):
        CameraCovariance.from_table({"parameters": names, "matrix": matrix.tolist()})


def test_refine_then_fit_run_on_a_field_scene_within_the_estimated_tolerance(tmp_path, capsys):
    scene = random_scene(np.random.default_rng(ESTIMATED), SceneOptions.field(), n_frames=40)
    assert scene.model.tolerance is None or not scene.model.tolerance
    machine, tracks = str(tmp_path / "machine.toml"), str(tmp_path / "tracks.csv")
    save_machine(scene.model, machine)
    save_tracks(scene.tracks, tracks)
    size = ["--size", "x".join(map(str, scene.cameras[0].size))] if len({c.size for c in scene.cameras}) == 1 else []
    assert main(["calibrate", machine, tracks, "--out", str(tmp_path / "cameras.toml"), *size]) == 0
    calibration = load_calibration(tmp_path / "cameras.toml")
    assert 0.02 < calibration.metadata["estimated_tolerance"] < 0.2
    save_calibration(Calibration(calibration.cameras, tuple({**e, "fps": 30.0} for e in calibration.extras),
                                 calibration.metadata), tmp_path / "cameras.toml")
    capsys.readouterr()
    assert main(["refine", machine, str(tmp_path / "cameras.toml"), tracks, "--frames", "40",
                 "--out", str(tmp_path / "refined.toml")]) == 0
    assert "estimated_tolerance" in load_calibration(tmp_path / "refined.toml").metadata
    assert main(["fit", machine, str(tmp_path / "refined.toml"), tracks, "--out", str(tmp_path / "motion.csv")]) == 0
    assert "marker offsets estimated over the session" in capsys.readouterr().out
    motion = load_motion(tmp_path / "motion.csv", scene.model)
    truth = scene.machine.points(scene.joints[motion.frame])[:, 0]
    z = np.linalg.norm(motion.points[:, 0] - truth, axis=1) / motion.points_sd[:, 0]
    # the cameras' and the offsets' errors are common to every frame: one draw, |N(0, 1)|-like, 2.6 at 99 %
    assert np.sqrt(np.mean(z**2)) < ALONG_ONE_DRAW_99, np.sqrt(np.mean(z**2))
