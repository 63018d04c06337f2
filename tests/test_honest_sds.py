"""The fit's SDs carry the calibration's uncertainty: a camera's error is common to every
frame, so the pixel noise alone understates the bucket tip's error however many frames
there are. The calibration's covariance is written with the cameras, read back by the fit,
and its propagation (mocap.reconstruct.camera_share) matches the spread of fits through
cameras drawn from it, within the chi-square bounds of the number of draws."""

import numpy as np
import pytest
from scipy.stats import chi2

from mocap.calibration import CalibrationOptions, calibrate, template_camera
from mocap.calibration.report import to_calibration
from mocap.errors import InputError
from mocap.io.cameras_toml import load_calibration, save_calibration
from mocap.reconstruct.camera_share import CameraCovariance, camera_share, perturbed
from mocap.reconstruct.kinfit import FitOptions, fit_joints
from mocap.reconstruct.motion import reconstruct_motion
from mocap.reconstruct.stage import covariance_of
from mocap.reconstruct.uncertainty import point_quantities
from mocap.synthetic.machines import SceneOptions, random_scene

SEED = 4  # a clean scene with one camera whose one-frame calibration leaves the tip's SD 3 times too small
DRAWS = 40


@pytest.fixture(scope="module")
def calibrated():
    scene = random_scene(np.random.default_rng(SEED), SceneOptions(), n_frames=12)
    templates = [template_camera(c.name, c.size) for c in scene.cameras]
    result = calibrate(scene.model, scene.observations(), templates, CalibrationOptions())
    return scene, result


def test_propagated_camera_covariance_matches_fits_through_drawn_cameras(calibrated):
    """Exact pixels of the true cameras moved by draws from the calibration's covariance:
    the tip's mean squared error over the draws, per frame, over its propagated variance
    lies within chi-square of the draws (each draw a 1-dof chi-square at worst)."""
    scene, result = calibrated
    machine, cameras = scene.model, list(scene.cameras)
    covariance = CameraCovariance.of_cameras(result.parameter_names, result.covariance, cameras)
    world = machine.markers(scene.joints)
    rng = np.random.default_rng(0)
    options = FitOptions(loss="linear", noise_px=0.5)
    exact = np.stack([c.project(world) for c in cameras])
    reference = fit_joints(machine, cameras, exact, initial=scene.joints, options=options)
    share = camera_share(machine, cameras, reference, covariance)
    predicted = point_quantities(machine, reference.joints, share + 1e-18 * np.eye(machine.n_joints)).points_sd[:, 0]
    squared = []
    for draw in rng.multivariate_normal(np.zeros(len(covariance.names)), covariance.matrix, DRAWS):
        moved = list(cameras)
        for name, delta in zip(covariance.names, draw):
            owner, parameter = name.rsplit(".", 1)
            k = [c.name for c in cameras].index(owner)
            moved[k] = perturbed(moved[k], parameter, delta)
        pixels = np.stack([c.project(world) for c in moved])
        fit = fit_joints(machine, cameras, pixels, initial=scene.joints, options=options)
        squared.append(np.sum((machine.points(fit.joints)[:, 0] - machine.points(scene.joints)[:, 0]) ** 2, axis=1))
    ratio = np.mean(squared, axis=0) / predicted**2  # (F,) each ~ chi-square(DRAWS) / DRAWS or narrower
    assert np.all(ratio > chi2.ppf(0.001, DRAWS) / DRAWS) and np.all(ratio < chi2.ppf(0.999, DRAWS) / DRAWS), ratio


def test_fit_reads_the_calibration_files_covariance(calibrated, tmp_path):
    """calibrate writes the cameras' covariance; the fit adds it to every frame's: with it
    the one-frame cameras' tip errors lie within their SDs' chi-square bound over the
    frames (1 dof, the error common to them), without it far beyond."""
    scene, result = calibrated
    path = tmp_path / "cameras.toml"
    save_calibration(to_calibration(result, 0), path)
    calibration = load_calibration(path)
    covariance = covariance_of(calibration, path)
    assert covariance is not None and covariance.names[0].endswith(".rx")
    assert np.allclose(covariance.matrix, CameraCovariance.of_cameras(
        result.parameter_names, result.covariance, result.cameras).matrix)
    pixels, frames = scene.pixels(), np.arange(len(scene.joints))
    truth = scene.machine.points(scene.joints)[:, 0]
    ratios = []
    for carried in (covariance, None):
        motion = reconstruct_motion(scene.model, list(calibration.cameras), frames, frames / 30.0, pixels,
                                    smoothing=False, camera_covariance=carried).motion
        z = np.linalg.norm(motion.points[:, 0] - truth, axis=1) / motion.points_sd[:, 0]
        ratios.append(float(np.sqrt(np.mean(z**2))))
    within, alone = ratios
    assert within < np.sqrt(chi2.ppf(0.999, 1)), ratios
    assert alone > 2 * within, ratios


def test_a_malformed_covariance_is_refused(calibrated, tmp_path):
    scene, result = calibrated
    calibration = to_calibration(result, 0)
    broken = calibration.metadata | {"camera_covariance": {"parameters": ["cam1.rx", "cam1.ry"], "matrix": [[1.0]]}}
    path = tmp_path / "cameras.toml"
    with pytest.raises(InputError, match="camera_covariance.*2 parameters need a 2 x 2"):
        covariance_of(type(calibration)(calibration.cameras, calibration.extras, broken), path)
