"""The camera model's projection of one point, compiled (numba), for the compiled solvers
(the tracker's joint fit, triangulation): `mocap.core.camera`'s own lens model and Jacobian
(`distorted`, `distorted_jacobian`) compiled, with the Jacobian by the camera-frame point."""

from __future__ import annotations

import math

from numba import njit

from mocap.core.camera import distorted, distorted_jacobian

_distorted = njit(cache=True, nogil=True)(distorted)
_distorted_jacobian = njit(cache=True, nogil=True)(distorted_jacobian)


@njit(cache=True, nogil=True)
def project_point(p, matrix, distortion, uv, jac):
    """Pixel (2,) of a camera-frame point p (3,) into `uv` and d(uv)/dp (2, 3) into `jac`
    (`camera.project_cam`'s lens model); False (uv NaN) at or behind the camera."""
    z = p[2]
    if not z > 0:
        uv[0] = uv[1] = math.nan
        return False
    x, y = p[0] / z, p[1] / z
    uv[0], uv[1] = _distorted(x, y, matrix, distortion)
    jac[0, 0], jac[0, 1], jac[0, 2], jac[1, 0], jac[1, 1], jac[1, 2] = _distorted_jacobian(x, y, 1.0 / z, matrix,
                                                                                           distortion)
    return True
