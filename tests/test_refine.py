"""Bundle adjustment of cameras and marker positions, and `mocap refine`."""

from dataclasses import replace

import numpy as np
import pytest

from mocap import cli
from mocap.core.calibration import Calibration
from mocap.core.geometry import Rigid, rotvec_to_matrix
from mocap.errors import ConvergenceError, DegenerateError
from mocap.io.cameras_toml import load_calibration, save_calibration
from mocap.io.machine_toml import load_machine, save_machine
from mocap.io.tracks_csv import save_tracks
from mocap.reconstruct.kinfit import fit_joints
from mocap.reconstruct.refine import RefineOptions, refine
from mocap.synthetic.scenes import observe, random_joints, ring_of_cameras

NOISE = 0.5


@pytest.fixture(scope="module")
def machine():
    return load_machine("hitachi_ex3500")


def scene(machine, n_frames, seed):
    rng = np.random.default_rng(seed)
    cameras = ring_of_cameras(3, np.array([5.0, 0.0, 5.0]), (30.0, 60.0), rng, fov_deg=(40.0, 60.0))
    joints = random_joints(machine, n_frames, rng)
    tracks = observe(cameras, machine, joints, rng, noise_px=NOISE)
    pixels = tracks.dense([c.name for c in cameras], machine.marker_names, np.arange(n_frames))
    return cameras, joints, tracks, pixels, rng


def perturbed(cameras, rng):
    """Cameras as a one-frame calibration might leave them: 0.2 deg, 10 cm, 1 % focal off."""
    out = []
    for camera in cameras:
        pose = camera.cam_from_world
        matrix = camera.matrix.copy()
        matrix[:2, :2] *= 1.01
        rotation = rotvec_to_matrix(rng.normal(0, np.radians(0.2), 3)) @ pose.rotation
        out.append(replace(camera, matrix=matrix, cam_from_world=Rigid(rotation, pose.translation + rng.normal(0, 0.1, 3))))
    return out


def tip_rmse(machine_fit, truth_machine, cameras, pixels, joints):
    fit = fit_joints(machine_fit, cameras, pixels, initial=joints)
    error = machine_fit.points(fit.joints) - truth_machine.points(joints)
    return float(np.sqrt(np.mean(np.sum(error**2, -1))))


@pytest.mark.parametrize("markers", [False, True])
def test_jacobian_matches_finite_differences(machine, markers):
    from mocap.reconstruct.refine import _Bundle

    cameras, joints, _, pixels, rng = scene(machine, 4, seed=5)
    bundle = _Bundle(machine, tuple(perturbed(cameras, rng)), pixels, RefineOptions(markers=markers), NOISE)
    x = np.r_[rng.normal(0, 0.01, 7 * 3), joints.ravel(), rng.normal(0, 0.05, 3 * len(machine.marker_names) * markers)]
    analytic = bundle.jacobian(x).toarray()
    numeric = np.empty_like(analytic)
    for p in range(len(x)):
        step = np.zeros_like(x)
        step[p] = 1e-6
        numeric[:, p] = (bundle.residuals(x + step) - bundle.residuals(x - step)) / 2e-6
    assert np.abs(analytic).max() > 100.0
    np.testing.assert_allclose(analytic, numeric, atol=1e-6 * np.abs(analytic).max())


def test_refines_cameras_to_the_noise(machine):
    cameras, joints, _, pixels, rng = scene(machine, 60, seed=1)
    start = perturbed(cameras, rng)
    result = refine(machine, start, pixels, RefineOptions(frames=40))
    assert result.rms_before > 3 * NOISE
    assert result.rms_after == pytest.approx(NOISE, rel=0.2)
    for refined, true, initial in zip(result.cameras, cameras, start):
        assert np.linalg.norm(refined.center - true.center) < 0.3 * np.linalg.norm(initial.center - true.center)
    assert tip_rmse(machine, machine, list(result.cameras), pixels, joints) < 0.3 * tip_rmse(machine, machine, start, pixels, joints)


def test_marker_refinement_halves_the_tip_error(machine):
    cameras, joints, _, pixels, rng = scene(machine, 60, seed=2)
    cameras = perturbed(cameras, rng)  # one-frame calibration error too
    tape = replace(machine, marker_positions=machine.marker_positions * (1 + rng.uniform(-0.05, 0.05, machine.marker_positions.shape)))
    before = tip_rmse(tape, machine, cameras, pixels, joints)
    result = refine(tape, cameras, pixels, RefineOptions(frames=40, markers=True))
    after = tip_rmse(result.machine, machine, list(result.cameras), pixels, joints)
    assert after < 0.5 * before
    moved = np.abs(result.machine.marker_positions - tape.marker_positions)
    assert (moved < 3 * 0.05 * np.maximum(np.linalg.norm(tape.marker_positions, axis=1), 0.5)[:, None]).all()
    assert np.mean(np.abs(result.machine.marker_positions - machine.marker_positions)) < np.mean(
        np.abs(tape.marker_positions - machine.marker_positions)
    )


def test_guards(machine):
    cameras, _, _, pixels, _ = scene(machine, 3, seed=3)
    with pytest.raises(DegenerateError, match="fewer than 2 frames"):
        refine(machine, cameras, np.full_like(pixels, np.nan))
    with pytest.raises(ValueError, match="pixels must have shape"):
        refine(machine, cameras[:2], pixels)
    with pytest.raises(ValueError, match="frames >= 2"):
        RefineOptions(frames=1)


def test_cli_refine(tmp_path, machine, capsys):
    cameras, _, tracks, _, rng = scene(machine, 20, seed=4)
    save_calibration(Calibration(tuple(perturbed(cameras, rng))), tmp_path / "cameras.toml")
    save_tracks(tracks, tmp_path / "tracks.csv")
    save_machine(machine, tmp_path / "machine.toml")
    args = ["refine", str(tmp_path / "machine.toml"), str(tmp_path / "cameras.toml"), str(tmp_path / "tracks.csv"),
            "--out", str(tmp_path / "refined.toml"), "--frames", "15"]
    assert cli.main(args + ["--markers", "--out-machine", str(tmp_path / "refined_machine.toml")]) == 0
    refined = load_calibration(tmp_path / "refined.toml")
    assert refined.metadata["refined_frames"] == 15 and refined.metadata["error"] < 2 * NOISE
    assert load_machine(tmp_path / "refined_machine.toml").marker_names == machine.marker_names
    assert "residual RMS" in capsys.readouterr().out
    assert cli.main(args + ["--out-machine", str(tmp_path / "m.toml")]) == 2
    assert "--out-machine needs --markers" in capsys.readouterr().err


def test_refuses_to_move_cameras_onto_consistently_wrong_labels(machine):
    """One camera's labels permuted in every frame (a tracker locked onto the wrong
    markers): no camera pose explains them, and moving the cameras to fit them would spoil
    the calibration, so refine refuses instead of returning cameras metres off."""
    cameras, joints, _, pixels, rng = scene(machine, 60, seed=4)
    wrong = pixels.copy()
    swap = rng.permutation(len(machine.marker_names))
    wrong[1] = pixels[1][:, swap]
    with pytest.raises(ConvergenceError, match=r"camera .*tracks lie .* px \(median\)"):
        refine(machine, perturbed(cameras, rng), wrong, RefineOptions(frames=40))
    # the same tracks with the right labels refine, within the same bound
    result = refine(machine, perturbed(cameras, rng), pixels, RefineOptions(frames=40))
    assert result.rms_after == pytest.approx(NOISE, rel=0.2)
