"""The dig cycles CSV: one row per cycle.

Readers need each cycle's first and last frame: columns ``start_frame,end_frame``
(reference-camera frames, inclusive), and optionally ``cycle`` (its number or name),
``class`` and the frames where the phases begin (`PHASE_COLUMNS`: dig, swing loaded, dump,
swing back; empty or negative where not seen). The synthetic truth writes all of `COLUMNS`
(class, scaling, dig start and end, times, the redirection's lift and turn); `mocap analyze` writes its own table
(`save_cycle_table`); other columns are ignored by `load_cycles`.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from mocap.core.cycles import Cycles
from mocap.errors import InputError
from mocap.io.atomic import atomic_path
from mocap.io.text import csv_rows, read_text

REQUIRED = ("start_frame", "end_frame")
PHASE_COLUMNS = ("dig_start_frame", "dig_end_frame", "dump_start_frame", "swing_back_start_frame")
COLUMNS = ("cycle", "class", "scaling", "scale_x", "scale_z", "redirection", "start_frame", "end_frame",
           "dig_start_frame", "dig_end_frame", "start_time", "end_time", "dig_start_time", "dig_end_time",
           "redirection_lift_m", "redirection_angle_deg")


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
    names, starts, ends, labels, phases = [], [], [], [], []
    phase_cols = [col.get(c) for c in PHASE_COLUMNS]
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
        labels.append(row[col["class"]].strip() if "class" in col else "")
        try:
            phases.append([int(float(row[c])) if c is not None and row[c].strip() else -1 for c in phase_cols])
        except ValueError:
            raise InputError(f"{', '.join(PHASE_COLUMNS)} must be frame numbers", path=path, where=f"line {line}") from None
        starts.append(start)
        ends.append(end)
    has_phases = any(c is not None for c in phase_cols)
    return Cycles(tuple(names), np.array(starts, dtype=np.int64), np.array(ends, dtype=np.int64),
                  tuple(labels) if "class" in col else (),
                  np.array(phases, dtype=np.int64).reshape(-1, 4) if has_phases else None)


def save_cycles(rows: list[tuple], path: str | Path) -> None:
    """Write rows of `COLUMNS` values (frames of the reference camera, times in seconds)."""
    with atomic_path(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh, lineterminator="\n")
        writer.writerow(COLUMNS)
        writer.writerows(rows)


def save_cycle_table(table: dict, path: str | Path) -> None:
    """Write the analysis' cycles CSV: one column per entry of `table` {name: (K,)}, in its
    order; integers as integers, other numbers with 4 decimals, NaN as an empty field."""
    names = list(table)
    columns = []
    for name in names:
        values = np.asarray(table[name])
        if values.dtype.kind in "iub":
            columns.append([str(int(v)) for v in values])
        elif values.dtype.kind == "f":
            columns.append(["" if not np.isfinite(v) else f"{v:.4f}" for v in values])
        else:
            columns.append([str(v) for v in values])
    with atomic_path(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh, lineterminator="\n")
        writer.writerow(names)
        writer.writerows(zip(*columns))


def load_cycle_table(path: str | Path) -> dict[str, np.ndarray]:
    """Every column of a cycles CSV as text (K,) arrays, checked like `load_cycles`."""
    load_cycles(path)
    rows = csv_rows(read_text(Path(path), "check the cycles path"), path)
    header = [h.strip() for h in rows[0]]
    body = [r for r in rows[1:] if r and any(v.strip() for v in r)]
    return {h: np.array([r[i].strip() for r in body], dtype=object) for i, h in enumerate(header)}
