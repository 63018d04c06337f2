"""Self-calibration over the session: distortion, principal point, a base that moves every
frame, the lens model chosen by the data, known intrinsics kept."""

from dataclasses import replace

import numpy as np
import pytest
from conftest import write_opencv_intrinsics

from mocap.calibration import CalibrationOptions, Observations, calibrate
from mocap.calibration.solve import template_camera
from mocap.io.machine_toml import load_machine
from mocap.reconstruct.refine import RefineOptions, _Bundle, refine
from mocap.reconstruct.triangulate import TriangulateOptions, triangulate
from mocap.synthetic.lens_scene import board_scene
from mocap.synthetic.scenes import observe, random_joints, ring_of_cameras

NOISE = 0.3


def numeric_jacobian(bundle, x):
    out = np.empty((len(bundle.residuals(x)), len(x)))
    for p in range(len(x)):
        step = np.zeros_like(x)
        step[p] = 1e-6
        out[:, p] = (bundle.residuals(x + step) - bundle.residuals(x - step)) / 2e-6
    return out


@pytest.mark.parametrize("distortion", ["k1", "full"])
def test_jacobian_of_lens_principal_point_and_base_matches_finite_differences(distortion):
    machine = load_machine("hitachi_ex3500")
    rng = np.random.default_rng(11)
    cameras = ring_of_cameras(2, np.array([5.0, 0.0, 5.0]), (30.0, 60.0), rng)
    cameras = [replace(c, distortion=np.array([-0.2, 0.05, 0.001, -0.001, 0.01])) for c in cameras]
    joints = random_joints(machine, 3, rng)
    pixels = observe(cameras, machine, joints, rng, noise_px=NOISE).dense(
        [c.name for c in cameras], machine.marker_names, np.arange(3))
    options = RefineOptions(markers=True, distortion=distortion, fit_principal_point=True, base_motion=True)
    base = np.c_[rng.normal(0, 0.02, (3, 3)), rng.normal(0, 0.1, (3, 3))]
    bundle = _Bundle(machine, tuple(cameras), pixels, options, NOISE, base)
    n_camera = bundle.n_camera_params * len(cameras)
    x = np.r_[rng.normal(0, 0.01, n_camera), joints.ravel(), rng.normal(0, 0.02, 18),
              rng.normal(0, 0.05, 3 * len(machine.marker_names))]
    analytic = bundle.jacobian(x).toarray()
    numeric = numeric_jacobian(bundle, x)
    assert np.abs(analytic).max() > 100.0
    assert np.abs(analytic[:, bundle.base_start : bundle.marker_start]).max() > 10.0
    np.testing.assert_allclose(analytic, numeric, atol=1e-6 * np.abs(analytic).max())


def one_frame_calibration(scene):
    c, m = np.nonzero(np.isfinite(scene.pixels[:, 0, :, 0]))
    templates = [template_camera(camera.name, camera.size) for camera in scene.cameras]
    return calibrate(scene.board, Observations(c, m, scene.pixels[c, 0, m]), templates, CalibrationOptions()).cameras


def adjacent_error(scene, cameras):
    """RMS error (m) of the distance between horizontally adjacent corners triangulated
    through the cameras, against the true 40 mm."""
    xyz = triangulate(list(cameras), scene.pixels, TriangulateOptions(max_error_px=1000.0)).xyz
    step = np.linalg.norm(np.diff(xyz.reshape(len(xyz), 6, 9, 3), axis=2), axis=-1)
    return float(np.sqrt(np.nanmean((step - 0.04) ** 2)))


@pytest.fixture(scope="module")
def lens_scene():
    return board_scene(np.random.default_rng(3), n_frames=16, noise_px=NOISE)


def test_refine_frees_the_lens_and_follows_a_hand_held_board(lens_scene):
    start = one_frame_calibration(lens_scene)
    result = refine(lens_scene.board, list(start), lens_scene.pixels,
                    RefineOptions(distortion="auto", fit_principal_point=True, base_motion=True))
    assert result.distortion in ("k1", "k1k2")
    assert result.criterion["none"] > result.criterion[result.distortion]
    assert result.rms_after == pytest.approx(NOISE, rel=0.25)
    assert result.base.shape == (16, 6)
    for refined, true in zip(result.cameras, lens_scene.cameras):
        assert refined.distortion[0] == pytest.approx(true.distortion[0], abs=0.03)
    assert adjacent_error(lens_scene, result.cameras) < 0.5 * adjacent_error(lens_scene, start)
    assert adjacent_error(lens_scene, result.cameras) < 0.001


def test_auto_keeps_a_pinhole_when_the_lens_has_no_distortion():
    machine = load_machine("hitachi_ex3500")
    rng = np.random.default_rng(4)
    cameras = ring_of_cameras(3, np.array([5.0, 0.0, 5.0]), (30.0, 60.0), rng, fov_deg=(40.0, 60.0))
    joints = random_joints(machine, 12, rng)
    pixels = observe(cameras, machine, joints, rng, noise_px=0.5).dense(
        [c.name for c in cameras], machine.marker_names, np.arange(12))
    result = refine(machine, cameras, pixels, RefineOptions(distortion="auto", fixed_intrinsics=frozenset({"cam1"})))
    assert result.distortion == "none"
    assert set(result.criterion) == {"none", "k1"}
    assert np.array_equal(result.cameras[0].matrix, cameras[0].matrix)


def test_known_intrinsics_are_kept(lens_scene):
    cameras = list(lens_scene.cameras)
    moved = [replace(c, cam_from_world=replace(c.cam_from_world, translation=c.cam_from_world.translation + 0.01))
             for c in cameras]
    names = frozenset(c.name for c in cameras[:2])
    result = refine(lens_scene.board, moved, lens_scene.pixels,
                    RefineOptions(distortion="k1k2", fit_principal_point=True, base_motion=True, fixed_intrinsics=names))
    for refined, true in zip(result.cameras[:2], cameras[:2]):
        assert np.array_equal(refined.matrix, true.matrix) and np.array_equal(refined.distortion, true.distortion)
    assert not np.array_equal(result.cameras[2].distortion, cameras[2].distortion)


def test_unknown_lens_model_is_refused():
    with pytest.raises(ValueError, match="distortion must be one of"):
        RefineOptions(distortion="k9")


def write_inputs(folder, scene, cameras):
    from mocap.core.calibration import Calibration
    from mocap.io.cameras_toml import save_calibration
    from mocap.io.machine_toml import save_machine
    from mocap.io.tracks_csv import save_tracks

    save_tracks(scene.tracks(), folder / "tracks.csv")
    save_machine(scene.board, folder / "board.toml")
    save_calibration(Calibration(tuple(cameras)), folder / "cameras.toml")
    return [str(folder / "board.toml"), str(folder / "cameras.toml"), str(folder / "tracks.csv")]


def test_refine_command_chooses_the_lens_and_keeps_known_intrinsics(lens_scene, tmp_path, capsys):
    from mocap.cli import main
    from mocap.io.cameras_toml import load_calibration

    args = write_inputs(tmp_path, lens_scene, one_frame_calibration(lens_scene))
    true = lens_scene.cameras[0]
    write_opencv_intrinsics(tmp_path / "cam1.yaml", true.size, true.matrix, true.distortion)
    out = tmp_path / "refined.toml"
    assert main(["refine", *args, "--out", str(out), "--base-motion", "--fit-principal-point",
                 "--intrinsics", str(tmp_path / "cam1.yaml")]) == 0
    report = capsys.readouterr().out
    assert "lens distortion chosen by the data: k1" in report and "intrinsics of cam1 kept as given" in report
    refined = load_calibration(out).cameras
    np.testing.assert_allclose(refined[0].matrix, true.matrix, rtol=1e-9)
    np.testing.assert_allclose(refined[0].distortion, true.distortion, atol=1e-12)
    for camera, truth in zip(refined[1:], lens_scene.cameras[1:]):
        assert camera.distortion[0] == pytest.approx(truth.distortion[0], abs=0.03)

    (tmp_path / "other.yaml").write_text((tmp_path / "cam1.yaml").read_text())
    assert main(["refine", *args, "--out", str(out), "--base-motion", "--intrinsics", str(tmp_path / "other.yaml")]) == 2
    assert "none of the calibration's" in capsys.readouterr().err
