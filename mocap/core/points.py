"""Triangulated marker positions, one row per frame and marker: the type the points formats
read and write and the reconstruction makes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Points:
    """N rows: frame (N,) int, marker (N,) str, xyz (N, 3) m, error_px (N,), views (N,) int;
    sd (N, 3) m each coordinate's standard deviation (the pixel noise's and the cameras'),
    None where not computed."""

    frame: np.ndarray
    marker: np.ndarray
    xyz: np.ndarray
    error_px: np.ndarray
    views: np.ndarray
    sd: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = len(self.frame)
        if np.shape(self.xyz) != (n, 3) or len(self.marker) != n:
            raise ValueError(f"Points needs marker (N,) and xyz (N, 3) for N={n}")
        if self.sd is not None and np.shape(self.sd) != (n, 3):
            raise ValueError(f"Points' sd must be (N, 3) for N={n}, got {np.shape(self.sd)}")

    def __len__(self) -> int:
        return len(self.frame)
