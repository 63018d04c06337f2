"""Triangulation's per-point solve, compiled (numba): the linear start (DLT) and the
Gauss-Newton steps of mocap.reconstruct.triangulate for all points in one call, with the
same arithmetic (pinhole with OpenCV's five distortion terms, the damped 3 x 3 normal
equations). Shapes: C cameras, N points."""

from __future__ import annotations

import numpy as np
from numba import njit

EPS = 1e-9  # as mocap.reconstruct.triangulate._EPS


@njit(cache=True, nogil=True)
def solve_points(pixels, normalised, used, start, has_start, rotation, translation, intrinsics, distortion,
                 iterations, xyz, residual, jac):
    """Fill xyz (N, 3), residual (C, N, 2) observed minus projected (zero where a view is
    unused or the point lies behind its camera) and jac (N, 2C, 3) d(projection)/d(xyz)
    (zero where unused, NaN where behind) for the points of pixels (C, N, 2) seen by the
    views `used` (C, N): from `start` (N, 3) if has_start, else from the linear
    triangulation of the normalised coordinates (C, N, 2), then `iterations` damped
    Gauss-Newton steps (none for a point whose normal equations are not finite).
    Cameras: rotation (C, 3, 3) and translation (C, 3) cam_from_world, intrinsics (C, 5)
    fx, skew, cx, fy, cy, distortion (C, 5) k1, k2, p1, p2, k3."""
    n_cams, n = used.shape
    lhs = np.empty((3, 3))
    rhs = np.empty(3)
    for i in range(n):
        if has_start:
            x0, x1, x2 = start[i, 0], start[i, 1], start[i, 2]
        else:
            x0, x1, x2 = _dlt(normalised, used, rotation, translation, i, lhs, rhs)
        for _ in range(iterations):
            _residuals(pixels, used, rotation, translation, intrinsics, distortion, i, x0, x1, x2, residual, jac)
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
        _residuals(pixels, used, rotation, translation, intrinsics, distortion, i, x0, x1, x2, residual, jac)
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
def _residuals(pixels, used, rotation, translation, intrinsics, distortion, i, x0, x1, x2, residual, jac):
    """Point i's residuals residual[:, i] (C, 2) and Jacobian jac[i] (2C, 3) at (x0, x1, x2)."""
    n_cams = used.shape[0]
    for c in range(n_cams):
        px = rotation[c, 0, 0] * x0 + rotation[c, 0, 1] * x1 + rotation[c, 0, 2] * x2 + translation[c, 0]
        py = rotation[c, 1, 0] * x0 + rotation[c, 1, 1] * x1 + rotation[c, 1, 2] * x2 + translation[c, 1]
        pz = rotation[c, 2, 0] * x0 + rotation[c, 2, 1] * x1 + rotation[c, 2, 2] * x2 + translation[c, 2]
        if not pz > 0:  # behind the camera (or NaN): no projection, the Jacobian NaN
            residual[c, i, 0], residual[c, i, 1] = 0.0, 0.0
            for k in range(2):
                for j in range(3):
                    jac[i, 2 * c + k, j] = np.nan
            continue
        fx, s, cx, fy, cy = intrinsics[c, 0], intrinsics[c, 1], intrinsics[c, 2], intrinsics[c, 3], intrinsics[c, 4]
        k1, k2, p1, p2, k3 = distortion[c, 0], distortion[c, 1], distortion[c, 2], distortion[c, 3], distortion[c, 4]
        x = px / pz
        y = py / pz
        inv_z = 1.0 / pz
        if k1 == 0.0 and k2 == 0.0 and p1 == 0.0 and p2 == 0.0 and k3 == 0.0:
            u = fx * x + s * y + cx
            v = fy * y + cy
            du_dx, du_dy, dv_dx, dv_dy = fx, s, 0.0, fy
            d00, d01, d02 = fx * inv_z, s * inv_z, -(fx * x + s * y) * inv_z
            d10, d11, d12 = 0.0, fy * inv_z, -fy * y * inv_z
        else:
            r2 = x * x + y * y
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            u = fx * xd + s * yd + cx
            v = fy * yd + cy
            dradial = k1 + r2 * (2 * k2 + 3 * k3 * r2)
            dxd_dx = radial + 2 * x * x * dradial + 2 * p1 * y + 6 * p2 * x
            dxd_dy = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y
            dyd_dx = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y
            dyd_dy = radial + 2 * y * y * dradial + 6 * p1 * y + 2 * p2 * x
            du_dx = fx * dxd_dx + s * dyd_dx
            du_dy = fx * dxd_dy + s * dyd_dy
            dv_dx = fy * dyd_dx
            dv_dy = fy * dyd_dy
            d00, d01, d02 = du_dx * inv_z, du_dy * inv_z, -(du_dx * x + du_dy * y) * inv_z
            d10, d11, d12 = dv_dx * inv_z, dv_dy * inv_z, -(dv_dx * x + dv_dy * y) * inv_z
        ok = used[c, i] and np.isfinite(u)
        residual[c, i, 0] = pixels[c, i, 0] - u if ok else 0.0
        residual[c, i, 1] = pixels[c, i, 1] - v if ok else 0.0
        weight = 1.0 if ok else 0.0
        for j in range(3):  # d(uv)/d(point_cam) @ rotation
            jac[i, 2 * c, j] = (d00 * rotation[c, 0, j] + d01 * rotation[c, 1, j] + d02 * rotation[c, 2, j]) * weight
            jac[i, 2 * c + 1, j] = (d10 * rotation[c, 0, j] + d11 * rotation[c, 1, j] + d12 * rotation[c, 2, j]) * weight


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
