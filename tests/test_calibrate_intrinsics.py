"""`mocap calibrate --intrinsics FILE`: known focal length, principal point and distortion
(ours/anipose TOML, OpenCV YAML, COLMAP: the readers of mocap.io.intrinsics) used and kept; only the poses (and
the cameras the file does not name) are fitted. Held to the truth of a board seen by
webcams with strong barrel distortion."""

import numpy as np
import pytest
from conftest import write_opencv_intrinsics

from mocap.calibration import Observations, calibrate, template_camera
from mocap.calibration.solve import CalibrationOptions
from mocap.cli import main
from mocap.core.calibration import Calibration
from mocap.io.cameras_toml import load_calibration, save_calibration
from mocap.io.machine_toml import save_machine
from mocap.io.tracks_csv import save_tracks
from mocap.synthetic.bounds import calibration_centre_sd
from mocap.synthetic.lens_scene import board_scene

NOISE_PX = 0.3


@pytest.fixture(scope="module")
def scene():
    return board_scene(np.random.default_rng(5), n_frames=1, noise_px=NOISE_PX)


def _inputs(folder, scene):
    save_tracks(scene.tracks(), folder / "tracks.csv")
    save_machine(scene.board, folder / "board.toml")
    w, h = scene.cameras[0].size
    return [str(folder / "board.toml"), str(folder / "tracks.csv"), "--size", f"{w}x{h}"]


def _bound(scene) -> np.ndarray:
    """The centres' bound with the focal lengths free: above the bound with them known."""
    c, _, m = np.nonzero(np.isfinite(scene.pixels[:, :1, :, 0]))
    obs = Observations(c, m, scene.pixels[c, 0, m])
    return calibration_centre_sd(scene.board, list(scene.cameras), np.zeros(0), obs, NOISE_PX)


def _centre_errors(cameras, scene) -> np.ndarray:
    return np.array([np.linalg.norm(a.center - b.center) for a, b in zip(cameras, scene.cameras)])


def test_calibrate_keeps_the_intrinsics_of_a_toml_file(scene, tmp_path, capsys):
    save_calibration(Calibration(scene.cameras), tmp_path / "intrinsics.toml")
    out = tmp_path / "cameras.toml"
    assert main(["calibrate", *_inputs(tmp_path, scene), "--out", str(out), "--intrinsics",
                 str(tmp_path / "intrinsics.toml")]) == 0
    report = capsys.readouterr().out
    assert "intrinsics of cam1, cam2, cam3, cam4 kept as given" in report
    assert "lens distortion chosen by the data" not in report  # nothing left to choose
    fitted = load_calibration(out).cameras
    for camera, truth in zip(fitted, scene.cameras):
        np.testing.assert_allclose(camera.matrix, truth.matrix, rtol=1e-12)
        np.testing.assert_allclose(camera.distortion, truth.distortion, atol=1e-15)
    error = _centre_errors(fitted, scene)
    assert np.all(error < 4 * _bound(scene)), f"centres {error / _bound(scene)} x the free-focal bound"
    assert load_calibration(out).metadata["error"] < 2 * NOISE_PX


def test_calibrate_keeps_an_opencv_yaml_and_fits_the_other_cameras(scene, tmp_path, capsys):
    true = scene.cameras[0]
    write_opencv_intrinsics(tmp_path / "cam1.yaml", true.size, true.matrix, true.distortion)
    out = tmp_path / "cameras.toml"
    assert main(["calibrate", *_inputs(tmp_path, scene), "--out", str(out), "--intrinsics",
                 str(tmp_path / "cam1.yaml")]) == 0
    report = capsys.readouterr().out
    assert "intrinsics of cam1 kept as given" in report and "lens distortion chosen by the data: k1" in report
    fitted = load_calibration(out).cameras
    np.testing.assert_allclose(fitted[0].matrix, true.matrix, rtol=1e-12)
    np.testing.assert_allclose(fitted[0].distortion, true.distortion, atol=1e-15)
    for camera in fitted[1:]:  # fitted (one frame of a board fixes barrel distortion only roughly)
        assert camera.distortion[0] < -0.05
    assert _centre_errors(fitted[:1], scene)[0] < 4 * _bound(scene)[0]


def test_known_intrinsics_place_a_camera_better_than_fitting_them_on_one_frame(scene):
    true = scene.cameras[1]
    c, _, m = np.nonzero(np.isfinite(scene.pixels[1:2, :1, :, 0]))
    obs = Observations(c, m, scene.pixels[1, 0, m])
    result = calibrate(scene.board, obs, [true], CalibrationOptions(fixed_intrinsics=frozenset({"cam2"})))
    np.testing.assert_allclose(result.cameras[0].matrix, true.matrix)
    free = calibrate(scene.board, obs, [template_camera("cam2", true.size)], CalibrationOptions(distortion="k1k2"))
    kept_error = np.linalg.norm(result.cameras[0].center - true.center)
    assert kept_error < np.linalg.norm(free.cameras[0].center - true.center)
    assert result.std[6] == 0.0 and result.rank == len(result.parameters)


def test_intrinsics_with_the_dlt_are_refused(scene, tmp_path, capsys):
    save_calibration(Calibration(scene.cameras), tmp_path / "intrinsics.toml")
    assert main(["calibrate", *_inputs(tmp_path, scene), "--out", str(tmp_path / "c.toml"), "--method", "dlt",
                 "--intrinsics", str(tmp_path / "intrinsics.toml")]) == 2
    assert "--intrinsics keeps known intrinsics in the model-based calibration" in capsys.readouterr().err


def test_intrinsics_naming_no_camera_are_refused(scene, tmp_path, capsys):
    other = [c.__class__(f"other{k}", c.size, c.matrix, c.distortion, c.cam_from_world)
             for k, c in enumerate(scene.cameras)]
    save_calibration(Calibration(tuple(other)), tmp_path / "intrinsics.toml")
    assert main(["calibrate", *_inputs(tmp_path, scene), "--out", str(tmp_path / "c.toml"),
                 "--intrinsics", str(tmp_path / "intrinsics.toml")]) == 2
    assert "none of the calibration's" in capsys.readouterr().err
