"""Named points, bucket angle, their velocities and their uncertainties from the
parameters of a fit (or of the smoother) and their covariance.

The SD of a named point is the root of the trace of its 3-D covariance ``G Σ Gᵀ`` with G
the point's Jacobian by the parameters (analytic, as for the markers); the bucket angle's
by a central-difference gradient. Point velocities are ``G q̇`` from the smoother's
velocities; accelerations the time derivative of those.

Shapes: F frames, P parameters (J joints, then 6 base parameters with base motion),
N named points.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from mocap.machine import Machine
from mocap.reconstruct.kinmodel import KinematicModel, FrameState, base_matrices

_ANGLE_STEP = 1e-6


@dataclass(frozen=True)
class PointQuantities:
    """points (F, N, 3) m; points_sd (F, N) m; bucket_angle (F,) rad; bucket_angle_sd (F,);
    velocities (F, N, 3) m/s or None."""

    points: np.ndarray
    points_sd: np.ndarray
    bucket_angle: np.ndarray
    bucket_angle_sd: np.ndarray
    velocities: np.ndarray | None = None

    @property
    def speed(self) -> np.ndarray | None:
        """(F, N) m/s."""
        return None if self.velocities is None else np.linalg.norm(self.velocities, axis=-1)


def point_quantities(
    machine: Machine,
    values: np.ndarray,
    covariance: np.ndarray,
    base_motion: bool = False,
    velocities: np.ndarray | None = None,
) -> PointQuantities:
    """Named points, bucket angle and their SDs for parameters (F, P) with covariance
    (F, P, P); frames with NaN parameters give NaN."""
    values = np.asarray(values, dtype=float)
    n, p = values.shape
    n_joints = machine.n_joints
    if p != n_joints + (6 if base_motion else 0) or np.shape(covariance) != (n, p, p):
        raise ValueError(f"values must be (F, {n_joints + 6 * base_motion}) with covariance (F, P, P)")
    ok = np.isfinite(values).all(1) & np.isfinite(covariance).all((1, 2))
    safe = np.where(ok[:, None], values, _neutral(machine, p))
    joints = safe[:, :n_joints]
    world_from_base = base_matrices(safe[:, n_joints:]) if base_motion else None
    points_machine = replace(
        machine,
        marker_names=machine.point_names,
        marker_links=machine.point_links,
        marker_positions=machine.point_positions,
    )
    points, jac = _point_jacobian(points_machine, safe, base_motion)
    point_cov = jac @ covariance[:, None] @ np.swapaxes(jac, -1, -2)  # (F, N, 3, 3)
    points_sd = np.sqrt(np.trace(point_cov, axis1=-2, axis2=-1))
    angle = machine.bucket_angles(joints, world_from_base)
    gradient = np.empty((n, p))
    for k in range(p):
        step = np.zeros(p)
        step[k] = _ANGLE_STEP
        plus, minus = safe + step, safe - step
        gradient[:, k] = (
            _angle(machine, plus, base_motion) - _angle(machine, minus, base_motion)
        ) / (2 * _ANGLE_STEP)
    angle_sd = np.sqrt(np.einsum("fp,fpq,fq->f", gradient, covariance, gradient))
    velocity = None
    if velocities is not None:
        velocity = np.where(ok[:, None, None], (jac @ np.asarray(velocities)[:, None, :, None])[..., 0], np.nan)
    mask = ~ok
    points[mask], points_sd[mask], angle[mask], angle_sd[mask] = np.nan, np.nan, np.nan, np.nan
    return PointQuantities(points, points_sd, angle, angle_sd, velocity)


def _neutral(machine: Machine, p: int) -> np.ndarray:
    neutral = np.zeros(p)
    neutral[: machine.n_joints] = machine.clip_to_limits(np.zeros(machine.n_joints))
    return neutral


def _angle(machine: Machine, values: np.ndarray, base_motion: bool) -> np.ndarray:
    n_joints = machine.n_joints
    base = base_matrices(values[:, n_joints:]) if base_motion else None
    return machine.bucket_angles(values[:, :n_joints], base)


def _point_jacobian(points_machine: Machine, values: np.ndarray, base_motion: bool):
    """Points (F, N, 3) and d point / d parameters (F, N, 3, P); the base parameters are the
    rotation vector and translation of ``world_from_base`` (small-increment derivative)."""
    if not points_machine.marker_names:
        n = len(values)
        return np.zeros((n, 0, 3)), np.zeros((n, 0, 3, values.shape[1]))
    n_joints = points_machine.n_joints
    problem = KinematicModel(points_machine, (), base_motion)
    rotation = translation = None
    if base_motion:
        pose = base_matrices(values[:, n_joints:])
        rotation, translation = pose[:, :3, :3], pose[:, :3, 3]
    return problem.world_markers(FrameState(values[:, :n_joints], rotation, translation, np.zeros(len(values))))
