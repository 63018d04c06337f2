"""Rotations and rigid transforms.

Conventions (stated once, here):
- Rotation matrices act on column vectors: ``x_b = b_from_a.rotation @ x_a + b_from_a.translation``.
- ``rpy`` is (roll, pitch, yaw) with ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``, as in URDF.
- Rotation vectors are Rodrigues vectors (axis times angle, radians), as in OpenCV.
- Angles are radians inside the package; degrees only in files.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def rot_x(angle: np.ndarray | float) -> np.ndarray:
    """Rotation about x by `angle` (rad). Shape (*, 3, 3) for `angle` of shape (*)."""
    c, s = np.cos(angle), np.sin(angle)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack([o, z, z, z, c, -s, z, s, c], axis=-1).reshape(np.shape(c) + (3, 3))


def rot_y(angle: np.ndarray | float) -> np.ndarray:
    """Rotation about y by `angle` (rad). Shape (*, 3, 3)."""
    c, s = np.cos(angle), np.sin(angle)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack([c, z, s, z, o, z, -s, z, c], axis=-1).reshape(np.shape(c) + (3, 3))


def rot_z(angle: np.ndarray | float) -> np.ndarray:
    """Rotation about z by `angle` (rad). Shape (*, 3, 3)."""
    c, s = np.cos(angle), np.sin(angle)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack([c, -s, z, s, c, z, z, z, o], axis=-1).reshape(np.shape(c) + (3, 3))


def rpy_to_matrix(rpy: np.ndarray) -> np.ndarray:
    """(roll, pitch, yaw) in rad, shape (*, 3) -> R = Rz(yaw) Ry(pitch) Rx(roll), (*, 3, 3)."""
    rpy = np.asarray(rpy, dtype=float)
    return rot_z(rpy[..., 2]) @ rot_y(rpy[..., 1]) @ rot_x(rpy[..., 0])


def matrix_to_rpy(matrix: np.ndarray) -> np.ndarray:
    """Inverse of `rpy_to_matrix`: (*, 3, 3) -> (*, 3) (roll, pitch, yaw) in rad.
    Matrices holding a NaN or an infinity (a frame with no pose) give NaN angles.
    """
    from scipy.spatial.transform import Rotation  # here: scipy.spatial takes a while to import

    matrix = np.asarray(matrix, dtype=float)
    finite = np.isfinite(matrix).all(axis=(-2, -1))
    if finite.all():
        return Rotation.from_matrix(matrix).as_euler("ZYX")[..., ::-1]
    rpy = np.full(matrix.shape[:-2] + (3,), np.nan)
    if finite.any():
        rpy[finite] = Rotation.from_matrix(matrix[finite]).as_euler("ZYX")[..., ::-1]
    return rpy


def rotvec_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues vectors (*, 3) -> rotation matrices (*, 3, 3): I + a [w]x + b [w]x² with
    a = sin(t) / t and b = (1 - cos(t)) / t², t = |w| (their series near 0). In numpy: loading
    a calibration need not import scipy.spatial (0.1-0.3 s of a command's start)."""
    w = np.asarray(rotvec, dtype=float)
    if w.shape[-1:] != (3,):
        raise ValueError(f"rotation vectors must have shape (*, 3), got {w.shape}")
    t2 = np.sum(w**2, axis=-1)[..., None, None]
    t = np.sqrt(t2)
    small = t2 < 1e-8
    safe = np.where(small, 1.0, t)
    a = np.where(small, 1.0 - t2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    o = np.zeros_like(x)
    skew = np.stack([o, -z, y, z, o, -x, -y, x, o], axis=-1).reshape(w.shape[:-1] + (3, 3))
    return np.eye(3) + a * skew + b * (skew @ skew)


def matrix_to_rotvec(matrix: np.ndarray) -> np.ndarray:
    """Rotation matrices (*, 3, 3) -> Rodrigues vectors (*, 3)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(matrix, dtype=float)).as_rotvec()


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b for broadcastable (*, 3) arrays (faster than np.cross on small last axes)."""
    return np.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


def rotation_angle_between(a_from_b: np.ndarray, a_from_c: np.ndarray) -> np.ndarray:
    """Angle (rad) of the rotation that takes one orientation to the other; (*, 3, 3) each."""
    rel = np.swapaxes(a_from_b, -1, -2) @ a_from_c
    cos = (np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(cos, -1.0, 1.0))


@dataclass(frozen=True)
class Rigid:
    """A rigid transform ``b_from_a``: ``x_b = rotation @ x_a + translation``."""

    rotation: np.ndarray
    translation: np.ndarray

    def __post_init__(self) -> None:
        rotation = np.asarray(self.rotation, dtype=float)
        translation = np.asarray(self.translation, dtype=float)
        if rotation.shape != (3, 3) or translation.shape != (3,):
            raise ValueError(
                f"Rigid needs rotation (3, 3) and translation (3,), got {rotation.shape} and "
                f"{translation.shape}"
            )
        object.__setattr__(self, "rotation", rotation)
        object.__setattr__(self, "translation", translation)

    @classmethod
    def identity(cls) -> Rigid:
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_rotvec(cls, rotvec: np.ndarray, translation: np.ndarray) -> Rigid:
        return cls(rotvec_to_matrix(rotvec), translation)

    @classmethod
    def from_matrix(cls, matrix: np.ndarray) -> Rigid:
        """From a homogeneous (4, 4) matrix."""
        matrix = np.asarray(matrix, dtype=float)
        return cls(matrix[:3, :3], matrix[:3, 3])

    @property
    def rotvec(self) -> np.ndarray:
        return matrix_to_rotvec(self.rotation)

    @property
    def matrix(self) -> np.ndarray:
        """Homogeneous (4, 4) matrix."""
        out = np.eye(4)
        out[:3, :3] = self.rotation
        out[:3, 3] = self.translation
        return out

    def inverse(self) -> Rigid:
        """``a_from_b`` from ``b_from_a``."""
        return Rigid(self.rotation.T, -self.rotation.T @ self.translation)

    def __matmul__(self, other: Rigid) -> Rigid:
        """Composition reads right to left: ``c_from_a = c_from_b @ b_from_a``."""
        return Rigid(self.rotation @ other.rotation, self.rotation @ other.translation + self.translation)

    def apply(self, points_a: np.ndarray) -> np.ndarray:
        """Transform points (*, 3) from frame a to frame b."""
        return np.asarray(points_a, dtype=float) @ self.rotation.T + self.translation
