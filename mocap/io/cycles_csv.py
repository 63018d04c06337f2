"""The dig cycles CSV: one row per cycle.

Readers need each cycle's first and last frame: columns ``start_frame,end_frame``
(reference-camera frames, inclusive), and optionally ``cycle`` (its number or name). The
synthetic truth writes all of `COLUMNS` (class, scaling, dig start and end, times); other
columns are ignored when reading.
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mocap.errors import InputError
from mocap.io.atomic import atomic_path
from mocap.io.text import read_text

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
    reader = csv.reader(io.StringIO(text))
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


PHASE_COLUMNS = ("cycle", "class", "start_frame", "end_frame", "dig_start_frame", "dig_end_frame")


@dataclass(frozen=True)
class CyclePhases:
    """K cycles as `mocap analyze` writes them: name (K,), label (K,) class (`Type 1` …
    `other`), start, end, dig_start, dig_end (K,) reference frames (inclusive)."""

    name: tuple[str, ...]
    label: tuple[str, ...]
    start: np.ndarray
    end: np.ndarray
    dig_start: np.ndarray
    dig_end: np.ndarray

    def __len__(self) -> int:
        return len(self.name)


def load_cycle_phases(path: str | Path) -> CyclePhases:
    """Read the columns `PHASE_COLUMNS` of a cycles CSV (others are ignored)."""
    path = Path(path)
    reader = csv.reader(io.StringIO(read_text(path, "check the cycles path")))
    header = [h.strip() for h in next(reader, [])]
    missing = [c for c in PHASE_COLUMNS if c not in header]
    if missing:
        raise InputError(f"header lacks {', '.join(missing)}; expected {','.join(PHASE_COLUMNS)}",
                         path=path, where="line 1")
    col = {h: i for i, h in enumerate(header)}
    rows = []
    for line, row in enumerate(reader, start=2):
        if not row or all(not v.strip() for v in row):
            continue
        try:
            frames = [int(row[col[c]]) for c in PHASE_COLUMNS[2:]]
        except (ValueError, IndexError):
            raise InputError("the frame columns must be integers", path=path, where=f"line {line}") from None
        rows.append((row[col["cycle"]].strip(), row[col["class"]].strip(), *frames))
    columns = list(zip(*rows)) if rows else [()] * len(PHASE_COLUMNS)
    return CyclePhases(tuple(columns[0]), tuple(columns[1]),
                       *(np.array(c, dtype=np.int64) for c in columns[2:]))
