"""The classic 11-parameter direct linear transform (DLT): a camera from >= 6 known 3-D
points, the method APAS used with surveyed control points. The baseline the model-based
calibration is compared with, and the fallback for a camera that sees too few markers per
link but at least six reference points.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mocap.camera import Camera
from mocap.errors import DegenerateError
from mocap.geometry import Rigid

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
    matrix, rotation, center_h = cv2.decomposeProjectionMatrix(projection)[:3]
    center = (center_h[:3] / center_h[3]).reshape(3)
    # cv2 returns K with positive diagonal; make the rotation proper (det +1)
    if np.linalg.det(rotation) < 0:
        rotation = -rotation
    matrix = matrix / matrix[2, 2]
    camera = Camera(name, size, matrix, np.zeros(5), Rigid(rotation, -rotation @ center))
    projected = camera.project(points)
    if not np.all(np.isfinite(projected)):
        rotation = np.diag([-1.0, -1.0, 1.0]) @ rotation
        matrix = matrix @ np.diag([-1.0, -1.0, 1.0])
        camera = Camera(name, size, matrix, np.zeros(5), Rigid(rotation, -rotation @ center))
        projected = camera.project(points)
    residuals = projected - pixels
    rms = float(np.sqrt(np.mean(np.sum(residuals**2, axis=1))))
    return DltResult(camera, projection, residuals, rms)


def _normaliser(points: np.ndarray) -> np.ndarray:
    """Hartley normalisation: centroid to the origin, mean distance sqrt(d)."""
    d = points.shape[1]
    mean = points.mean(axis=0)
    scale = np.sqrt(d) / np.mean(np.linalg.norm(points - mean, axis=1))
    out = np.eye(d + 1)
    out[:d, :d] *= scale
    out[:d, d] = -scale * mean
    return out
