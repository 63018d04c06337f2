"""The dig cycles CSV: one row per cycle.

Readers need each cycle's first and last frame: columns ``start_frame,end_frame``
(reference-camera frames, inclusive), and optionally ``cycle`` (its number or name). The
synthetic truth writes all of `COLUMNS` (class, scaling, dig start and end, times); other
columns are ignored when reading.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mocap.errors import InputError
from mocap.io.atomic import atomic_path
from mocap.io.text import csv_rows, read_text

REQUIRED = ("start_frame", "end_frame")
COLUMNS = ("cycle", "class", "scaling", "scale_x", "scale_z", "redirection", "start_frame", "end_frame",
           "dig_start_frame", "dig_end_frame", "start_time", "end_time", "dig_start_time", "dig_end_time")


@dataclass(frozen=True)
class Cycles:
    """K cycles: name (K,) str, start (K,) and end (K,) frames, inclusive."""

    name: tuple[str, ...]
    start: np.ndarray
    end: np.ndarray

    def __post_init__(self) -> None:
        k = len(self.name)
        if np.shape(self.start) != (k,) or np.shape(self.end) != (k,):
            raise ValueError(
                f"Cycles needs start ({k},) and end ({k},), got {np.shape(self.start)}, {np.shape(self.end)}"
            )

    def __len__(self) -> int:
        return len(self.name)

    @classmethod
    def whole(cls, frames: np.ndarray) -> Cycles:
        """One cycle spanning all of `frames`."""
        frames = np.asarray(frames)
        if len(frames) == 0:
            return cls((), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
        return cls(("all",), np.array([frames.min()]), np.array([frames.max()]))


def load_cycles(path: str | Path) -> Cycles:
    path = Path(path)
    text = read_text(path, "check the cycles path")
    reader = iter(csv_rows(text, path))
    header = [h.strip() for h in next(reader, [])]
    missing = [c for c in REQUIRED if c not in header]
    if missing:
        raise InputError(
            f"header lacks {', '.join(missing)}; a cycles CSV needs {','.join(REQUIRED)}[,cycle]",
            path=path,
            where="line 1",
        )
    col = {h: i for i, h in enumerate(header)}
    names, starts, ends = [], [], []
    for line, row in enumerate(reader, start=2):
        if not row or all(not v.strip() for v in row):
            continue
        if len(row) != len(header):
            raise InputError(f"{len(row)} fields, the header has {len(header)}", path=path, where=f"line {line}")
        try:
            start, end = int(row[col["start_frame"]]), int(row[col["end_frame"]])
        except ValueError:
            raise InputError(
                "start_frame and end_frame must be integers", path=path, where=f"line {line}"
            ) from None
        if end < start:
            raise InputError(f"end_frame {end} is before start_frame {start}", path=path, where=f"line {line}")
        if not 0 <= start <= end <= 100_000_000:
            raise InputError(f"start_frame {start} and end_frame {end} must be frames from 0 to 100,000,000",
                             path=path, where=f"line {line}")
        names.append(row[col["cycle"]].strip() if "cycle" in col else str(len(names) + 1))
        starts.append(start)
        ends.append(end)
    return Cycles(tuple(names), np.array(starts, dtype=np.int64), np.array(ends, dtype=np.int64))


def save_cycles(rows: list[tuple], path: str | Path) -> None:
    """Write rows of `COLUMNS` values (frames of the reference camera, times in seconds)."""
    with atomic_path(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh, lineterminator="\n")
        writer.writerow(COLUMNS)
        writer.writerows(rows)
