"""The camera model's projection of one point, compiled (numba), for the compiled solvers
(the tracker's joint fit, triangulation): the same lens model and arithmetic as
`mocap.camera.project_cam`, with the Jacobian by the camera-frame point."""

from __future__ import annotations

import math

from numba import njit


@njit(cache=True, nogil=True)
def project_point(p, matrix, distortion, uv, jac):
    """Pixel (2,) of a camera-frame point p (3,) into `uv` and d(uv)/dp (2, 3) into `jac`
    (`camera.project_cam`'s lens model); False (uv NaN) at or behind the camera."""
    z = p[2]
    if not z > 0:
        uv[0] = uv[1] = math.nan
        return False
    x, y = p[0] / z, p[1] / z
    fx, s, cx = matrix[0, 0], matrix[0, 1], matrix[0, 2]
    fy, cy = matrix[1, 1], matrix[1, 2]
    k1, k2, p1, p2, k3 = distortion[0], distortion[1], distortion[2], distortion[3], distortion[4]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    uv[0] = fx * xd + s * yd + cx
    uv[1] = fy * yd + cy
    dradial = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    dxd_dx = radial + 2 * x * x * dradial + 2 * p1 * y + 6 * p2 * x
    dxd_dy = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y
    dyd_dx = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y
    dyd_dy = radial + 2 * y * y * dradial + 6 * p1 * y + 2 * p2 * x
    du_dx = fx * dxd_dx + s * dyd_dx
    du_dy = fx * dxd_dy + s * dyd_dy
    dv_dx = fy * dyd_dx
    dv_dy = fy * dyd_dy
    inv_z = 1.0 / z
    jac[0, 0] = du_dx * inv_z
    jac[0, 1] = du_dy * inv_z
    jac[0, 2] = -(du_dx * x + du_dy * y) * inv_z
    jac[1, 0] = dv_dx * inv_z
    jac[1, 1] = dv_dy * inv_z
    jac[1, 2] = -(dv_dx * x + dv_dy * y) * inv_z
    return True
