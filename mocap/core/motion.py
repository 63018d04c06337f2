"""A machine's motion over frames in internal units (rad, m): the type the motion formats
read and write and the fit makes."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Motion:
    """F frames of a machine's motion, internal units (rad, m).

    frame (F,) reference-camera frames; time (F,) s; joints (F, J); points (F, P, 3);
    bucket_angle (F,) rad; joints_sd (F, J), points_sd (F, P), bucket_angle_sd (F,) or None;
    extra: {column name: (F,) array}, written as is.
    """

    joint_names: tuple[str, ...]
    point_names: tuple[str, ...]
    frame: np.ndarray
    time: np.ndarray
    joints: np.ndarray
    points: np.ndarray
    bucket_angle: np.ndarray
    joints_sd: np.ndarray | None = None
    points_sd: np.ndarray | None = None
    bucket_angle_sd: np.ndarray | None = None
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        n, j, p = len(self.frame), len(self.joint_names), len(self.point_names)
        checks = {
            "time": (self.time, (n,)),
            "joints": (self.joints, (n, j)),
            "points": (self.points, (n, p, 3)),
            "bucket_angle": (self.bucket_angle, (n,)),
            "joints_sd": (self.joints_sd, (n, j)),
            "points_sd": (self.points_sd, (n, p)),
            "bucket_angle_sd": (self.bucket_angle_sd, (n,)),
        }
        for name, (value, shape) in checks.items():
            if value is not None and np.shape(value) != shape:
                raise ValueError(f"Motion.{name}: expected shape {shape}, got {np.shape(value)}")
        for name, value in self.extra.items():
            if np.shape(value) != (n,):
                raise ValueError(f"Motion.extra[{name!r}]: expected shape ({n},), got {np.shape(value)}")

    def __len__(self) -> int:
        return len(self.frame)

    def point(self, name: str) -> np.ndarray:
        """(F, 3) positions of one named point."""
        return self.points[:, self.point_names.index(name)]
