"""The second-order bias of a calibration's least squares, removed (Box 1971; Cook, Tsai
and Wei 1986).

A far camera's distance is fixed only by the perspective its markers show, which falls as
the inverse of the distance: the least-squares estimate of the distance is skewed (a
pixel error that flattens the perspective sends the camera far away, one that deepens it
brings it in by less). To second order the estimate's bias is

    b = -1/2 (J^T J)^-1 J^T d,    d_i = tr(Sigma H_i),

with J the whitened Jacobian, Sigma the estimate's covariance and H_i the Hessian of the
i-th residual. With Sigma = sum_k s_k s_k^T over the covariance's principal directions
scaled to one SD, tr(Sigma H_i) = sum_k s_k^T H_i s_k, each term a second difference of the
residuals one SD either side: 2P residual evaluations, no Hessian formed.

Shapes: R residual rows, P free parameters.
"""

from __future__ import annotations

import logging

import numpy as np

from mocap.calibration.identify import inverse_information
from mocap.calibration.problem import BEHIND_PX, Problem

log = logging.getLogger(__name__)

SHIFT_LIMIT = 0.25  # a correction that moves a camera by more than this share of its distance: past the expansion


def bias_corrected(problem: Problem, x: np.ndarray, free: np.ndarray, sigma_px: float) -> np.ndarray:
    """The least-squares solution x (P,) less its second-order bias, over the parameters
    `free` (P,) bool, the residuals' noise `sigma_px` per row. x itself where a step of one
    SD puts a marker behind a camera or the correction moves a camera by more than
    `SHIFT_LIMIT` of its distance from the markers: there the estimate is too non-linear for
    a second-order correction to mean anything."""
    jacobian = problem.jacobian(x)[:, free]
    information = jacobian.T @ jacobian
    diagonal = np.diag(information)
    if not np.all(diagonal > 0):
        return x
    scale = 1.0 / np.sqrt(diagonal)
    values, vectors = np.linalg.eigh(sigma_px**2 * inverse_information(information) / np.outer(scale, scale))
    base = problem.residuals(x)
    curvature = np.zeros_like(base)
    for value, vector in zip(values, vectors.T):
        if value <= 0:
            continue
        step = np.sqrt(value) * vector * scale
        for sign in (1.0, -1.0):
            moved = x.copy()
            moved[free] += sign * step
            residuals = problem.residuals(moved)
            if np.any(np.abs(residuals) >= BEHIND_PX) or not np.all(np.isfinite(residuals)):
                return x
            curvature += residuals
        curvature -= 2.0 * base
    bias = -0.5 * inverse_information(information) @ (jacobian.T @ curvature)
    out = x.copy()
    out[free] -= bias
    shift = _largest_shift(problem, x, out)
    if shift > SHIFT_LIMIT:
        log.info("the second-order bias moves a camera by %.0f %% of its distance: the estimate is too non-linear "
                 "to correct", 100 * shift)
        return x
    return out


def _largest_shift(problem: Problem, x: np.ndarray, corrected: np.ndarray) -> float:
    """The largest move of a camera's centre from x to `corrected` (P,) over its distance
    from the markers' centre."""
    layout, templates = problem.layout, problem.templates
    before, joints = layout.unpack(x, templates)
    after, _ = layout.unpack(corrected, templates)
    first = joints[0] if layout.per_camera else joints
    target = problem.machine_at(x).markers(first[None])[0].mean(axis=0)
    return max(float(np.linalg.norm(a.center - b.center) / np.linalg.norm(b.center - target))
               for a, b in zip(after, before))
