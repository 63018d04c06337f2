"""Cramér–Rao bounds at the truth: the least error any unbiased estimator can reach from
pixels with Gaussian noise of `noise_px` per axis. Tests and benchmarks divide the
errors of calibration, kinematic fit and triangulation by these.

Shapes: C cameras, F frames, M markers, J joints, N points.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from mocap.calibration.identify import inverse_information
from mocap.calibration.problem import Layout, Observations, Problem
from mocap.core.camera import Camera, project_cam
from mocap.core.geometry import rotvec_to_matrix
from mocap.core.machine import Machine
from mocap.reconstruct.kinmodel import FrameState, KinematicModel
from mocap.reconstruct.uncertainty import point_quantities


def calibration_centre_sd(machine: Machine, cameras: list[Camera], joints: np.ndarray, obs: Observations,
                          noise_px: float, marker_sd: np.ndarray | None = None) -> np.ndarray:
    """(C,) bound on each camera centre's error (m, root of the trace of its covariance) of
    a one-frame calibration of focal length, pose and shared joint values from `obs`.

    marker_sd (M, 3): SDs (m) of the model's marker coordinates (link frames) when the
    model is only measured: the markers' offsets are then unknowns with that prior (a
    Bayesian bound), so the bound holds what the model's error costs as well.
    """
    covariance = calibration_centre_covariance(machine, cameras, joints, obs, noise_px, marker_sd)
    return np.sqrt(np.trace(covariance, axis1=1, axis2=2))


def calibration_centre_covariance(machine: Machine, cameras: list[Camera], joints: np.ndarray, obs: Observations,
                                  noise_px: float, marker_sd: np.ndarray | None = None) -> np.ndarray:
    """(C, 3, 3) the bound's covariance of each camera centre (m^2); see `calibration_centre_sd`."""
    layout = Layout(len(cameras), machine.n_joints)
    x = layout.pack(cameras, joints)
    problem = Problem(machine, obs, layout, list(cameras))
    jac = problem.jacobian(x) / noise_px
    information = jac.T @ jac
    if marker_sd is not None:
        d_marker = _marker_jacobian(machine, obs, layout, list(cameras), x) / noise_px  # (2N, 3M)
        sd = np.maximum(np.asarray(marker_sd, dtype=float).reshape(-1), 1e-6)
        cross_term = jac.T @ d_marker
        markers_information = d_marker.T @ d_marker + np.diag(1.0 / sd**2)
        # the offsets marginalised out: the Schur complement of their block
        information = information - cross_term @ np.linalg.solve(markers_information, cross_term.T)
    covariance = inverse_information(information)
    out = np.empty((len(cameras), 3, 3))
    for c in range(len(cameras)):
        s = layout.camera_slice(c)
        gradient = numeric_jacobian(_centre, x[s])
        out[c] = gradient @ covariance[s, s] @ gradient.T
    return out


def fit_point_sd(machine: Machine, cameras: list[Camera], joints: np.ndarray, seen: np.ndarray,
                 noise_px: float, marker_sd: np.ndarray | None = None) -> np.ndarray:
    """(F, P) bound on each named point's error (m, root of the trace) of a per-frame fit
    of the joint values at the true joints (F, J) from the observations `seen` (C, F, M);
    with marker_sd (M, 3) the model's marker coordinates are uncertain too (marginalised
    frame by frame, as in `calibration_centre_sd`). Infinite where a joint that moves the
    point moves no marker seen in that frame."""
    state = FrameState(joints, None, None, np.zeros(len(joints)))
    truth = np.stack([c.project(machine.markers(joints)) for c in cameras], 1)  # (F, C, M, 2)
    pixels = np.where(np.moveaxis(seen, 0, 1)[..., None], truth, np.nan)
    _, jac = KinematicModel(machine, tuple(cameras)).evaluate(pixels, state)  # d predicted / d joints
    jac = jac / noise_px
    information = np.swapaxes(jac, 1, 2) @ jac
    if marker_sd is not None:
        step = 1e-6
        columns = []
        for i in range(machine.marker_positions.size):
            positions = machine.marker_positions.copy()
            positions.flat[i] += step
            moved, _ = KinematicModel(replace(machine, marker_positions=positions), tuple(cameras)).evaluate(pixels, state)
            columns.append(-moved / step / noise_px)  # residual = observed - predicted, 0 at the truth
        d_marker = np.stack(columns, -1)  # (F, N, 3M): d predicted / d marker coordinates
        sd = np.maximum(np.asarray(marker_sd, dtype=float).reshape(-1), 1e-6)
        cross_term = np.swapaxes(jac, 1, 2) @ d_marker
        markers_information = np.swapaxes(d_marker, 1, 2) @ d_marker + np.diag(1.0 / sd**2)
        information = information - cross_term @ np.linalg.solve(markers_information, np.swapaxes(cross_term, 1, 2))
    covariance = inverse_information(information)
    sd = point_quantities(machine, joints, covariance).points_sd
    diagonal = np.diagonal(information, axis1=1, axis2=2)
    unobserved = diagonal <= 1e-12 * np.max(diagonal, axis=1, keepdims=True)  # (F, J) no marker it moves seen
    blind = (unobserved[:, :, None] & machine.moves[:, machine.point_links][None]).any(axis=1)
    return np.where(blind, np.inf, sd)  # no estimator knows a point whose joint nothing shows


def triangulation_sd(cameras: list[Camera], points: np.ndarray, seen: np.ndarray, noise_px: float) -> np.ndarray:
    """(N,) bound on each point's error (m, root of the trace) from the cameras that see
    it: points (N, 3) world, seen (C, N) bool. NaN for a point seen by fewer than two."""
    covariance = triangulation_covariance(cameras, points, seen, noise_px)
    return np.sqrt(np.trace(covariance, axis1=1, axis2=2))


def triangulation_covariance(cameras: list[Camera], points: np.ndarray, seen: np.ndarray,
                             noise_px: float) -> np.ndarray:
    """(N, 3, 3) m², the bound on each point's error covariance from the cameras that see
    it (as `triangulation_sd`); NaN for a point seen by fewer than two."""
    information = np.zeros((len(points), 3, 3))
    for camera, mine in zip(cameras, seen):
        rotation = camera.cam_from_world.rotation
        points_cam = points @ rotation.T + camera.cam_from_world.translation
        _, d_uv = project_cam(points_cam, camera.matrix, camera.distortion, True)
        d_uv_world = d_uv @ rotation  # (N, 2, 3)
        information += np.where(mine[:, None, None], np.swapaxes(d_uv_world, 1, 2) @ d_uv_world, 0.0)
    enough = seen.sum(0) >= 2
    covariance = inverse_information(information / noise_px**2)
    return np.where(enough[:, None, None], covariance, np.nan)


def _marker_jacobian(machine: Machine, obs: Observations, layout: Layout, cameras, x: np.ndarray,
                     step: float = 1e-6) -> np.ndarray:
    """(2N, 3M) derivatives of the pixels by the markers' link-frame coordinates."""
    out = np.empty((2 * len(obs), machine.marker_positions.size))
    for i in range(machine.marker_positions.size):
        shifted = []
        for sign in (1.0, -1.0):
            positions = machine.marker_positions.copy()
            positions.flat[i] += sign * step
            moved = replace(machine, marker_positions=positions)
            shifted.append(Problem(moved, obs, layout, cameras).residuals(x))
        out[:, i] = (shifted[0] - shifted[1]) / (2 * step)
    return out


def _centre(block: np.ndarray) -> np.ndarray:
    """A camera's centre (3,) from its parameter block (rotation vector, translation, ...)."""
    return -rotvec_to_matrix(block[:3]).T @ block[3:6]


def numeric_jacobian(function, x: np.ndarray, step: float = 1e-6) -> np.ndarray:
    """(K, N) central differences of function (N,) -> (K,) at x, steps relative to |x|."""
    base = function(x)
    out = np.empty((len(base), len(x)))
    for i in range(len(x)):
        dx = np.zeros_like(x)
        dx[i] = step * max(1.0, abs(x[i]))
        out[:, i] = (function(x + dx) - function(x - dx)) / (2 * dx[i])
    return out

