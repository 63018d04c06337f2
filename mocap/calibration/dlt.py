"""The classic 11-parameter direct linear transform (DLT): a camera from >= 6 known 3-D
points, the method APAS used with surveyed control points. The baseline the model-based
calibration is compared with, and the fallback for a camera that sees too few markers per
link but at least six reference points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from mocap.core.camera import Camera
from mocap.core.geometry import Rigid
from mocap.errors import DegenerateError

COPLANAR_RATIO = 1e-3


@dataclass(frozen=True)
class DltResult:
    camera: Camera
    projection: np.ndarray  # (3, 4), scaled so that its last row has unit norm
    residuals: np.ndarray  # (N, 2) px, projected minus observed
    rms_px: float


def dlt_camera(name: str, size: tuple[int, int], points: np.ndarray, pixels: np.ndarray) -> DltResult:
    """Fit P (3 x 4, 11 degrees of freedom) to points (N, 3) and pixels (N, 2), N >= 6, by
    the normalised homogeneous linear system, then split it into K, R, t."""
    points = np.asarray(points, dtype=float)
    pixels = np.asarray(pixels, dtype=float)
    if len(points) < 6:
        raise DegenerateError(
            f"camera {name!r}: the DLT needs at least 6 reference points (11 unknowns), got "
            f"{len(points)}"
        )
    centred = points - points.mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False)
    if s[2] / s[0] < COPLANAR_RATIO:
        raise DegenerateError(
            f"camera {name!r}: the {len(points)} reference points are coplanar; the DLT needs "
            "points spread in depth (use the model-based calibration instead)"
        )
    t_world = _normaliser(points)
    t_image = _normaliser(pixels)
    x = np.c_[points, np.ones(len(points))] @ t_world.T
    u = np.c_[pixels, np.ones(len(pixels))] @ t_image.T
    rows = np.zeros((2 * len(points), 12))
    rows[0::2, 0:4] = x
    rows[0::2, 8:12] = -u[:, 0:1] * x
    rows[1::2, 4:8] = x
    rows[1::2, 8:12] = -u[:, 1:2] * x
    _, _, vt = np.linalg.svd(rows)
    projection = np.linalg.inv(t_image) @ vt[-1].reshape(3, 4) @ t_world
    projection /= np.linalg.norm(projection[2, :3])
    matrix, rotation, center = decompose_projection(projection)
    camera = Camera(name, size, matrix, np.zeros(5), Rigid(rotation, -rotation @ center))
    projected = camera.project(points)
    residuals = projected - pixels
    rms = float(np.sqrt(np.mean(np.sum(residuals**2, axis=1))))
    return DltResult(camera, projection, residuals, rms)


def decompose_projection(projection: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split P (3, 4) = s·K·[R | −R·C] into K (3, 3) with positive diagonal and K[2, 2] = 1,
    R (3, 3) with det +1, and the centre C (3,).

    P is known only up to a scale of either sign; flipping it flips det(M) of its left 3 × 3
    block M = s·K·R, so the sign that makes det(M) > 0 is the one with a proper rotation
    and a positive K (Hartley & Zisserman, 6.2.4). The RQ split is done here, not by
    OpenCV's decomposeProjectionMatrix, whose signs changed between OpenCV 4 and 5.
    """
    if np.linalg.det(projection[:, :3]) < 0:
        projection = -projection
    left = projection[:, :3]
    matrix, rotation = scipy.linalg.rq(left)
    signs = np.diag(np.sign(np.diag(matrix)))  # K·R = (K·D)·(D·R) with D = D⁻¹
    matrix, rotation = matrix @ signs, signs @ rotation
    center = -np.linalg.solve(left, projection[:, 3])
    return matrix / matrix[2, 2], rotation, center


def _normaliser(points: np.ndarray) -> np.ndarray:
    """Hartley normalisation: centroid to the origin, mean distance sqrt(d)."""
    d = points.shape[1]
    mean = points.mean(axis=0)
    scale = np.sqrt(d) / np.mean(np.linalg.norm(points - mean, axis=1))
    out = np.eye(d + 1)
    out[:d, :d] *= scale
    out[:d, d] = -scale * mean
    return out
