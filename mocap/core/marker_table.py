"""The markers' 3-D positions over consecutive frames: the type the C3D and TRC formats
write and read, and the marker export makes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MarkerTable:
    """Markers over F consecutive frames: names (N,), frame (F,) int, rate (Hz), xyz (F, N, 3)
    in metres in the world frame, NaN where a marker is not seen. Frame f is at f / rate s."""

    names: tuple[str, ...]
    frame: np.ndarray
    rate: float
    xyz: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "names", tuple(self.names))
        object.__setattr__(self, "frame", np.asarray(self.frame, dtype=int))
        shape = (len(self.frame), len(self.names), 3)
        if np.shape(self.xyz) != shape:
            raise ValueError(f"MarkerTable.xyz must have shape {shape}, got {np.shape(self.xyz)}")
        if not self.rate > 0:
            raise ValueError(f"MarkerTable.rate must be positive, got {self.rate}")
        if len(set(self.names)) != len(self.names):
            raise ValueError(f"MarkerTable.names repeat: {self.names}")
        if len(self.frame) and np.any(np.diff(self.frame) != 1):
            raise ValueError("MarkerTable.frame must be consecutive")

    @property
    def time(self) -> np.ndarray:
        """(F,) seconds: frame / rate."""
        return self.frame / self.rate
