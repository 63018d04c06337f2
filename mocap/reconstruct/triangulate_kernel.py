"""Triangulation's per-point solve, compiled (numba): the linear start (DLT) and the
Gauss-Newton steps of mocap.reconstruct.triangulate for all points in one call, with the
same arithmetic (pinhole with OpenCV's five distortion terms, the damped 3 x 3 normal
equations). Shapes: C cameras, N points."""

from __future__ import annotations

import numpy as np
from numba import njit

from mocap.core.camera_kernel import project_point

EPS = 1e-9  # as mocap.reconstruct.triangulate._EPS


@njit(cache=True, nogil=True)
def solve_points(pixels, normalised, used, start, has_start, rotation, translation, matrix, distortion,
                 iterations, xyz, residual, jac):
    """Fill xyz (N, 3), residual (C, N, 2) observed minus projected (zero where a view is
    unused or the point lies behind its camera) and jac (N, 2C, 3) d(projection)/d(xyz)
    (zero where unused, NaN where behind) for the points of pixels (C, N, 2) seen by the
    views `used` (C, N): from `start` (N, 3) if has_start, else from the linear
    triangulation of the normalised coordinates (C, N, 2), then `iterations` damped
    Gauss-Newton steps (none for a point whose normal equations are not finite).
    Cameras: rotation (C, 3, 3) and translation (C, 3) cam_from_world, matrix (C, 3, 3),
    distortion (C, 5) k1, k2, p1, p2, k3."""
    n_cams, n = used.shape
    lhs = np.empty((3, 3))
    rhs = np.empty(3)
    point, uv, d_uv = np.empty(3), np.empty(2), np.empty((2, 3))
    for i in range(n):
        if has_start:
            x0, x1, x2 = start[i, 0], start[i, 1], start[i, 2]
        else:
            x0, x1, x2 = _dlt(normalised, used, rotation, translation, i, lhs, rhs)
        for _ in range(iterations):
            _residuals(pixels, used, rotation, translation, matrix, distortion, i, x0, x1, x2, residual, jac,
                       point, uv, d_uv)
            trace = 0.0
            for a in range(3):
                for b in range(3):
                    total = 0.0
                    for r in range(2 * n_cams):
                        total += jac[i, r, a] * jac[i, r, b]
                    lhs[a, b] = total
                trace += lhs[a, a]
                total = 0.0
                for r in range(2 * n_cams):
                    total += jac[i, r, a] * residual[r // 2, i, r % 2]
                rhs[a] = total
            damping = (1.0 + trace / 3) * EPS
            finite = True
            for a in range(3):
                lhs[a, a] += damping
                finite = finite and np.isfinite(rhs[a])
                for b in range(3):
                    finite = finite and np.isfinite(lhs[a, b])
            if not finite:  # a point gone behind a camera: no step
                continue
            s0, s1, s2 = _solve3(lhs, rhs)
            x0, x1, x2 = x0 + s0, x1 + s1, x2 + s2
        _residuals(pixels, used, rotation, translation, matrix, distortion, i, x0, x1, x2, residual, jac,
                   point, uv, d_uv)
        xyz[i, 0], xyz[i, 1], xyz[i, 2] = x0, x1, x2


@njit(cache=True, nogil=True, inline="always")
def _dlt(normalised, used, rotation, translation, i, lhs, rhs):
    """Point i's linear triangulation: least squares of x P3 - P1 = 0, y P3 - P2 = 0 over
    its used views, P = [R | t]."""
    n_cams = used.shape[0]
    normal = np.zeros((4, 4))
    row = np.empty(4)
    for c in range(n_cams):
        if not used[c, i]:
            continue
        for k in range(2):
            value = normalised[c, i, k]
            for j in range(3):
                row[j] = value * rotation[c, 2, j] - rotation[c, k, j]
            row[3] = value * translation[c, 2] - translation[c, k]
            for a in range(4):
                for b in range(4):
                    normal[a, b] += row[a] * row[b]
    for a in range(3):
        for b in range(3):
            lhs[a, b] = normal[a, b]
        lhs[a, a] += EPS
        rhs[a] = -normal[a, 3]
    return _solve3(lhs, rhs)


@njit(cache=True, nogil=True, inline="always")
def _residuals(pixels, used, rotation, translation, matrix, distortion, i, x0, x1, x2, residual, jac, point, uv, d_uv):
    """Point i's residuals residual[:, i] (C, 2) and Jacobian jac[i] (2C, 3) at (x0, x1, x2);
    point (3,), uv (2,) and d_uv (2, 3) scratch."""
    n_cams = used.shape[0]
    for c in range(n_cams):
        for k in range(3):
            point[k] = rotation[c, k, 0] * x0 + rotation[c, k, 1] * x1 + rotation[c, k, 2] * x2 + translation[c, k]
        if not project_point(point, matrix[c], distortion[c], uv, d_uv):  # behind the camera (or NaN)
            residual[c, i, 0], residual[c, i, 1] = 0.0, 0.0
            for k in range(2):
                for j in range(3):
                    jac[i, 2 * c + k, j] = np.nan
            continue
        ok = used[c, i] and np.isfinite(uv[0])
        weight = 1.0 if ok else 0.0
        for k in range(2):
            residual[c, i, k] = pixels[c, i, k] - uv[k] if ok else 0.0
            for j in range(3):  # d(uv)/d(point_cam) @ rotation
                jac[i, 2 * c + k, j] = (d_uv[k, 0] * rotation[c, 0, j] + d_uv[k, 1] * rotation[c, 1, j]
                                        + d_uv[k, 2] * rotation[c, 2, j]) * weight


@njit(cache=True, nogil=True, inline="always")
def _solve3(lhs, rhs):
    """The solution of lhs (3, 3) x = rhs (3,) by Gaussian elimination with partial
    pivoting (LAPACK's gesv on a 3 x 3); lhs and rhs are overwritten."""
    for k in range(3):
        pivot = k
        for r in range(k + 1, 3):
            if abs(lhs[r, k]) > abs(lhs[pivot, k]):
                pivot = r
        if pivot != k:
            for j in range(3):
                lhs[k, j], lhs[pivot, j] = lhs[pivot, j], lhs[k, j]
            rhs[k], rhs[pivot] = rhs[pivot], rhs[k]
        for r in range(k + 1, 3):
            factor = lhs[r, k] / lhs[k, k]
            for j in range(k + 1, 3):
                lhs[r, j] -= factor * lhs[k, j]
            rhs[r] -= factor * rhs[k]
    x2 = rhs[2] / lhs[2, 2]
    x1 = (rhs[1] - lhs[1, 2] * x2) / lhs[1, 1]
    x0 = (rhs[0] - lhs[0, 1] * x1 - lhs[0, 2] * x2) / lhs[0, 0]
    return x0, x1, x2
