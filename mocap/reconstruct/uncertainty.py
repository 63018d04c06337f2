"""Named points, bucket angle, their velocities and their uncertainties from the
parameters of a fit (or of the smoother) and their covariance.

The SD of a named point is the root of the trace of its 3-D covariance ``G Σ Gᵀ`` with G
the point's Jacobian by the parameters (analytic, as for the markers); the bucket angle's
from its gradient, analytic too: the angle is that of the bucket link's direction to the
house's horizontal forward axis, each the difference of two link-fixed points whose
Jacobians come with the named points'. Point velocities are ``G q̇`` from the smoother's
velocities; accelerations the time derivative of those.

Shapes: F frames, P parameters (J joints, then 6 base parameters with base motion),
N named points.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from mocap.core.machine import Machine
from mocap.reconstruct.kinmodel import KinematicModel, FrameState, base_matrices



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
    points, jac = _point_jacobian(machine, safe, base_motion)  # the named points, then the angle's four
    n_named = len(machine.point_names)
    if machine.bucket_angle is not None:
        angle, gradient = _bucket_angle(points[:, n_named:], jac[:, n_named:])
    else:
        angle, gradient = np.full(n, np.nan), np.zeros((n, p))
    points, jac = points[:, :n_named], jac[:, :n_named]
    point_cov = jac @ covariance[:, None] @ np.swapaxes(jac, -1, -2)  # (F, N, 3, 3)
    points_sd = np.sqrt(np.trace(point_cov, axis1=-2, axis2=-1))
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


def _bucket_angle(ends: np.ndarray, jac: np.ndarray):
    """The bucket angle (F,) and its gradient by the parameters (F, P) from the bucket
    link's origin and the tip of its unit direction, then the house link's origin and the
    tip of its forward (x) axis (F, 4, 3), and their Jacobians (F, 4, 3, P)
    (as mocap.core.machine.Machine.bucket_angles: atan2 of the direction's height over its
    component along the forward axis made horizontal and unit)."""
    direction, d_direction = ends[:, 1] - ends[:, 0], jac[:, 1] - jac[:, 0]  # (F, 3), (F, 3, P)
    forward, d_forward = ends[:, 3] - ends[:, 2], jac[:, 3] - jac[:, 2]
    forward, d_forward = forward * [1.0, 1.0, 0.0], d_forward * np.array([1.0, 1.0, 0.0])[:, None]
    length = np.linalg.norm(forward, axis=-1, keepdims=True)
    unit = forward / length
    d_unit = (d_forward - unit[..., None] * np.einsum("fi,fip->fp", unit, d_forward)[:, None]) / length[..., None]
    rise, run = direction[:, 2], np.einsum("fi,fi->f", direction, unit)
    d_rise = d_direction[:, 2]
    d_run = np.einsum("fip,fi->fp", d_direction, unit) + np.einsum("fi,fip->fp", direction, d_unit)
    gradient = (run[:, None] * d_rise - rise[:, None] * d_run) / (run**2 + rise**2)[:, None]
    return np.arctan2(rise, run), gradient


def _point_jacobian(machine: Machine, values: np.ndarray, base_motion: bool):
    """Points (F, N, 3) and d point / d parameters (F, N, 3, P) of the named points, then
    (with a bucket angle) of the bucket link's origin and the tip of its direction and the
    house link's origin and the tip of its x axis; the base parameters are the rotation
    vector and translation of ``world_from_base`` (small-increment derivative)."""
    links, positions = list(machine.point_links), list(machine.point_positions)
    if machine.bucket_angle is not None:
        links += [machine.bucket_angle.link] * 2 + [machine.house_link] * 2
        positions += [np.zeros(3), machine.bucket_angle.direction, np.zeros(3), np.array([1.0, 0.0, 0.0])]
    if not links:
        n = len(values)
        return np.zeros((n, 0, 3)), np.zeros((n, 0, 3, values.shape[1]))
    points_machine = replace(machine, marker_names=tuple(f"point{k}" for k in range(len(links))),
                             marker_links=np.array(links, dtype=int), marker_positions=np.array(positions, dtype=float),
                             marker_tags=None, marker_normals=None)
    n_joints = points_machine.n_joints
    problem = KinematicModel(points_machine, (), base_motion)
    rotation = translation = None
    if base_motion:
        pose = base_matrices(values[:, n_joints:])
        rotation, translation = pose[:, :3, :3], pose[:, :3, 3]
    return problem.world_markers(FrameState(values[:, :n_joints], rotation, translation, np.zeros(len(values))))
