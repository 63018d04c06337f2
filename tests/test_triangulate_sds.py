"""Triangulated points' SDs carry the cameras' uncertainty: a one-frame calibration's error
is common to every point it triangulates, which the pixel noise alone leaves out. The
calibration's covariance, propagated through the triangulation (first order, all points at
once: mocap.reconstruct.camera_share.point_covariance), matches the spread of points
triangulated through cameras drawn from it, and makes the points' errors over their SDs
honest on random scenes; `mocap triangulate` writes the SDs."""

import numpy as np
import pytest
from scipy.stats import chi2

from mocap.calibration import CalibrationOptions, calibrate, template_camera
from mocap.calibration.report import to_calibration
from mocap.errors import DegenerateError, InputError
from mocap.io.points_csv import load_points, save_points
from mocap.reconstruct.camera_share import CameraCovariance, perturbed, point_covariance
from mocap.reconstruct.outliers import noise_from_fits
from mocap.reconstruct.stage import triangulate
from mocap.reconstruct.triangulate import triangulate as triangulate_points
from mocap.reconstruct.triangulate import triangulate_tracks
from mocap.synthetic.machines import SceneOptions, random_scene

SEEDS = range(20, 40)  # random clean scenes; those with two cameras or more and a calibration count
FRAMES = 8
DRAWS = 40


def one_frame(seed: int):
    """A clean scene of two cameras or more and its one-frame calibration (frame 0), or None."""
    try:
        scene = random_scene(np.random.default_rng(seed), SceneOptions(), n_frames=FRAMES)
    except DegenerateError:
        return None
    if len(scene.cameras) < 2:
        return None
    templates = [template_camera(c.name, c.size) for c in scene.cameras]
    try:
        result = calibrate(scene.model, scene.observations(), templates, CalibrationOptions())
    except InputError:
        return None
    return scene, result


@pytest.fixture(scope="module")
def calibrated():
    return one_frame(SEEDS.start + 8)


def test_propagated_covariance_matches_points_through_drawn_cameras(calibrated):
    """Exact pixels of the true cameras, triangulated through cameras moved by draws from the
    calibration's covariance: each point's mean squared error over the draws, over its
    propagated variance, lies within chi-square of the draws (1 dof per draw at worst)."""
    scene, result = calibrated
    cameras = list(scene.cameras)
    covariance = CameraCovariance.of_cameras(result.parameter_names, result.covariance, cameras)
    world = scene.machine.markers(scene.joints[:2]).reshape(-1, 3)
    exact = np.stack([c.project(world) for c in cameras])
    used = np.isfinite(exact[..., 0])
    keep = used.sum(0) >= 2
    world, exact, used = world[keep], exact[:, keep], used[:, keep]
    predicted = np.trace(point_covariance(cameras, world, used, 0.0, covariance), axis1=1, axis2=2)
    squared = []
    for draw in np.random.default_rng(0).multivariate_normal(np.zeros(len(covariance.names)), covariance.matrix, DRAWS):
        moved = list(cameras)
        for name, delta in zip(covariance.names, draw):
            owner, parameter = name.rsplit(".", 1)
            k = [c.name for c in cameras].index(owner)
            moved[k] = perturbed(moved[k], parameter, delta)
        squared.append(np.sum((triangulate_points(moved, exact).xyz - world) ** 2, axis=1))
    ratio = np.mean(squared, axis=0) / predicted
    assert np.all(ratio > chi2.ppf(0.001, DRAWS) / DRAWS) and np.all(ratio < chi2.ppf(0.999, DRAWS) / DRAWS), ratio


def test_points_errors_over_their_sds_are_honest_with_one_frame_cameras():
    """Random clean scenes triangulated with their one-frame cameras: the RMS of each
    coordinate's error over its SD is 0.8-1.25 with the cameras' covariance, and beyond
    1.25 with the pixel noise alone (the noise estimated from the points' residuals, as
    `mocap triangulate` does)."""
    z_with, z_alone = [], []
    for seed in SEEDS:
        made = one_frame(seed)
        if made is None:
            continue
        scene, result = made
        cameras = list(result.cameras)
        covariance = CameraCovariance.of_cameras(result.parameter_names, result.covariance, cameras)
        points = triangulate_tracks(cameras, scene.pixels())
        xyz, used = points.xyz.reshape(-1, 3), points.used.reshape(len(cameras), -1)
        ok = np.isfinite(xyz[:, 0])
        views, error = points.views.reshape(-1)[ok], points.error_px.reshape(-1)[ok]
        noise = noise_from_fits(error**2 * views, 2 * views - 3)
        truth = scene.machine.markers(scene.joints).reshape(-1, 3)[ok]
        for out, carried in ((z_with, covariance), (z_alone, None)):
            sd = np.sqrt(np.diagonal(point_covariance(cameras, xyz[ok], used[:, ok], noise, carried), axis1=1, axis2=2))
            out.append(np.mean(((xyz[ok] - truth) / sd) ** 2))  # each scene weighs the same: its cameras' error is one draw
    assert len(z_with) >= 10
    honest, alone = np.sqrt(np.mean(z_with)), np.sqrt(np.mean(z_alone))
    assert 0.8 <= honest <= 1.25 < alone, (honest, alone)


def test_triangulate_writes_the_points_sds(calibrated, tmp_path):
    """`triangulate` reads the calibration file's covariance: the points' SDs grow by the
    cameras' share, and the points file carries them (x_sd, y_sd, z_sd) and reads them back."""
    scene, result = calibrated
    calibration = to_calibration(result, 0)
    tracks = scene.tracks
    with_share = triangulate(calibration, tracks).points
    bare = type(calibration)(calibration.cameras, calibration.extras,
                             {k: v for k, v in calibration.metadata.items() if k != "camera_covariance"})
    alone = triangulate(bare, tracks).points
    assert np.all(np.isfinite(with_share.sd)) and np.all(with_share.sd >= alone.sd * (1 - 1e-9))
    assert np.median(with_share.sd / alone.sd) > 1.05
    path = tmp_path / "points.csv"
    save_points(with_share, path)
    assert "x_sd,y_sd,z_sd" in path.read_text().splitlines()[0]
    assert np.allclose(load_points(path).sd, with_share.sd, rtol=1e-3, atol=2e-6)


def test_a_negative_sd_is_refused(tmp_path):
    path = tmp_path / "points.csv"
    path.write_text("frame,marker,x,y,z,error_px,views,x_sd,y_sd,z_sd\n0,a,1,2,3,0.5,2,0.01,-0.01,0.01\n")
    with pytest.raises(InputError, match="line 2.*must not be negative"):
        load_points(path)
