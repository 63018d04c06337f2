"""Dig cycles as frame ranges with their class and phases: the type the cycles formats read
and write and the analysis makes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Cycles:
    """K cycles: name (K,) str, start (K,) and end (K,) frames, inclusive; label (K,) the
    dig class or "" (empty tuple when the file has none); phases (K, 4) the frames where
    dig, swing loaded, dump and swing back begin, -1 where not known (None without)."""

    name: tuple[str, ...]
    start: np.ndarray
    end: np.ndarray
    label: tuple[str, ...] = ()
    phases: np.ndarray | None = None

    def __post_init__(self) -> None:
        k = len(self.name)
        if np.shape(self.start) != (k,) or np.shape(self.end) != (k,):
            raise ValueError(
                f"Cycles needs start ({k},) and end ({k},), got {np.shape(self.start)}, {np.shape(self.end)}"
            )
        if self.label and len(self.label) != k:
            raise ValueError(f"Cycles needs label ({k},) or none, got {len(self.label)}")
        if self.phases is not None and np.shape(self.phases) != (k, 4):
            raise ValueError(f"Cycles needs phases ({k}, 4) or None, got {np.shape(self.phases)}")

    def __len__(self) -> int:
        return len(self.name)

    @classmethod
    def whole(cls, frames: np.ndarray) -> Cycles:
        """One cycle spanning all of `frames`."""
        frames = np.asarray(frames)
        if len(frames) == 0:
            return cls((), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
        return cls(("all",), np.array([frames.min()]), np.array([frames.max()]))
