"""The batched kinematic fit on seeded synthetic EX3500 scenes."""

import numpy as np
import pytest

from mocap.core.geometry import rotvec_to_matrix
from mocap.io.machine_toml import load_machine
from mocap.reconstruct import kinfit, kinmodel
from mocap.reconstruct.kinfit import FitOptions, fit_joints
from mocap.synthetic.scenes import observe, random_joints, ring_of_cameras

NOISE = 0.5


@pytest.fixture(scope="module")
def machine():
    return load_machine("hitachi_ex3500")


def scene(machine, n_cameras, n_frames, seed, **observe_options):
    rng = np.random.default_rng(seed)
    cameras = ring_of_cameras(n_cameras, np.array([5.0, 0.0, 5.0]), (30.0, 60.0), rng, fov_deg=(40.0, 60.0))
    joints = random_joints(machine, n_frames, rng)
    tracks = observe(cameras, machine, joints, rng, noise_px=NOISE, **observe_options)
    pixels = tracks.dense([c.name for c in cameras], machine.marker_names, np.arange(n_frames))
    return cameras, joints, pixels


def test_jacobian_matches_finite_differences(machine):
    rng = np.random.default_rng(1)
    cameras, joints, pixels = scene(machine, 3, 4, seed=1)
    problem = kinfit._Problem(machine, tuple(cameras), FitOptions(base_motion=True))
    rotation = rotvec_to_matrix(rng.normal(0, 0.05, (4, 3)))
    state = kinmodel.FrameState(joints, rotation, rng.normal(0, 0.3, (4, 3)), np.zeros(4))
    obs = np.moveaxis(pixels, 1, 0)
    _, jac = problem.evaluate(obs, state)
    numeric = np.zeros_like(jac)
    h = 1e-6
    for p in range(problem.n_params):
        delta = np.zeros((4, problem.n_params))
        delta[:, p] = h
        plus, _ = problem.evaluate(obs, problem.step(state, delta))
        minus, _ = problem.evaluate(obs, problem.step(state, -delta))
        numeric[..., p] = -(plus - minus) / (2 * h)  # residual = observed - predicted
    assert np.abs(jac).max() > 10.0
    np.testing.assert_allclose(jac, numeric, atol=1e-5 * np.abs(jac).max())


@pytest.mark.parametrize("base_motion", [False, True])
def test_compiled_solve_ends_at_a_stationary_point_with_the_models_normal_matrix(machine, base_motion):
    """The compiled Levenberg-Marquardt (kinkernel) against the numpy model: at its solution
    the robustly weighted gradient Jᵀ W r vanishes and its normal matrix is Jᵀ W J, with J and
    r from KinematicModel.evaluate (whose Jacobian the test above checks)."""
    rng = np.random.default_rng(3)
    cameras, joints, pixels = scene(machine, 3, 6, seed=3)
    problem = kinfit._Problem(machine, tuple(cameras), FitOptions(base_motion=base_motion))
    rotation = rotvec_to_matrix(rng.normal(0, 0.02, (6, 3))) if base_motion else None
    translation = rng.normal(0, 0.05, (6, 3)) if base_motion else None
    start = kinmodel.FrameState(joints + rng.normal(0, 0.05, joints.shape), rotation, translation, np.zeros(6))
    obs = np.moveaxis(pixels, 1, 0)
    solved = problem.levenberg_marquardt(obs, start)
    residual, jac = problem.evaluate(obs, solved)
    weight, cost = problem.robust(residual)
    np.testing.assert_allclose(solved.cost, cost, rtol=1e-9)
    np.testing.assert_allclose(solved.residual, residual, atol=1e-4)  # stored as float32
    normal = np.einsum("fnp,fn,fnq->fpq", jac, weight, jac)
    np.testing.assert_allclose(solved.hessian, normal, rtol=1e-9, atol=1e-9 * np.abs(normal).max())
    gradient = np.einsum("fnp,fn,fn->fp", jac, weight, residual)
    scale = np.sqrt(np.einsum("fpp->fp", normal) * cost[:, None])  # |J_p| |r|: what a gradient could be
    assert np.abs(gradient / scale).max() < 1e-3
    assert np.degrees(np.abs(solved.joints - joints)).max() < 1.5


def test_recovers_joints_from_the_grid_with_honest_covariance(machine):
    cameras, joints, pixels = scene(machine, 3, 300, seed=2)
    fit = fit_joints(machine, cameras, pixels)
    assert fit.valid.all()
    assert abs(fit.noise_px - NOISE) < 0.05 * NOISE
    z = (fit.joints - joints) / fit.joints_sd
    coverage = np.mean(np.abs(z) < 1.96)
    assert 0.92 < coverage < 0.975
    assert np.degrees(np.abs(fit.joints - joints)).max() < 1.5
    assert np.median(fit.rms_px) == pytest.approx(NOISE, rel=0.25)
    residual = fit.residuals[np.isfinite(fit.residuals)]
    assert np.std(residual) == pytest.approx(NOISE, rel=0.1)


def test_single_camera_fit(machine):
    cameras, joints, pixels = scene(machine, 1, 200, seed=3)
    fit = fit_joints(machine, cameras, pixels, initial=joints + 0.05)
    z = (fit.joints - joints) / fit.joints_sd
    assert fit.valid.all()
    assert np.sqrt(np.mean(z**2)) < 1.3


def test_robust_to_outliers(machine):
    cameras, joints, pixels = scene(machine, 3, 200, seed=4, outliers=600)
    robust = fit_joints(machine, cameras, pixels, options=FitOptions(loss="cauchy", scale_px=2.0))
    plain = fit_joints(machine, cameras, pixels, initial=joints, options=FitOptions(loss="linear"))
    robust_error = np.abs(robust.joints - joints)
    plain_error = np.abs(plain.joints - joints)
    assert np.sqrt(np.mean(robust_error**2)) < 0.5 * np.sqrt(np.mean(plain_error**2))
    assert np.mean(np.abs(robust.joints - joints) / robust.joints_sd < 1.96) > 0.85
    assert np.nanmin(robust.weights) < 0.1  # outliers were down-weighted


def test_base_motion(machine):
    rng = np.random.default_rng(5)
    cameras = ring_of_cameras(3, np.array([5.0, 0.0, 5.0]), (30.0, 60.0), rng, fov_deg=(40.0, 60.0))
    joints = random_joints(machine, 100, rng)
    base = np.c_[rng.normal(0, 0.02, (100, 3)), rng.normal(0, 0.2, (100, 3))]
    world = machine.markers(joints, kinmodel.base_matrices(base))
    pixels = np.stack([c.project(world) for c in cameras]) + rng.normal(0, NOISE, (3, 100, len(machine.marker_names), 2))
    fixed = fit_joints(machine, cameras, pixels, initial=joints)
    moving = fit_joints(machine, cameras, pixels, initial=joints, options=FitOptions(base_motion=True))
    assert np.median(moving.rms_px) < 0.7 < np.median(fixed.rms_px)
    base_sd = np.sqrt(np.diagonal(moving.covariance, axis1=1, axis2=2)[:, 4:])
    z = (moving.base - base) / base_sd
    assert np.mean(np.abs(z) < 1.96) > 0.9
    assert np.abs(moving.base[:, 3:] - base[:, 3:]).max() < 0.05


def test_unobserved_frames_and_joints(machine):
    cameras, joints, pixels = scene(machine, 3, 20, seed=6)
    pixels[:, 5] = np.nan  # nothing seen
    bucket = [i for i, name in enumerate(machine.marker_names) if name.startswith("K")]
    pixels[:, 8][:, bucket] = np.nan  # bucket markers hidden: bucket joint unobserved
    fit = fit_joints(machine, cameras, pixels, initial=joints)
    assert not fit.valid[5] and np.isnan(fit.joints[5]).all()
    assert fit.valid[8] and fit.joints_sd[8, 3] > 100.0 > 10 * fit.joints_sd[8, :3].max()
    assert fit.n_observations[5] == 0


def test_guards(machine):
    cameras, _, pixels = scene(machine, 2, 3, seed=7)
    with pytest.raises(ValueError, match="pixels must have shape"):
        fit_joints(machine, cameras, pixels[:1])
    with pytest.raises(ValueError, match="initial must have shape"):
        fit_joints(machine, cameras, pixels, initial=np.zeros((2, 4)))
    with pytest.raises(ValueError, match="loss must be one of"):
        FitOptions(loss="tukey")
    with pytest.raises(ValueError, match="scale_px must be positive"):
        FitOptions(scale_px=0)
