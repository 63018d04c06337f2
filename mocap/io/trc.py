"""The TRC marker file (OpenSim, Mokka): tab-separated text, one row per frame.

    PathFileType  4  (X/Y/Z)  NAME.trc
    DataRate  CameraRate  NumFrames  NumMarkers  Units  OrigDataRate  OrigDataStartFrame  OrigNumFrames
    30.00  30.00  937  20  mm  30.00  1  937
    Frame#  Time  U1 _ _  U2 _ _ ...
    _  _  X1  Y1  Z1  X2  Y2  Z2 ...
    (a blank line)
    1  0.000000  1500.000  1000.000  300.000  ...

`Frame#` counts from 1 (our frame 0 is Frame# 1); `Time` is in seconds; a
marker not seen in a frame has three empty fields (a gap, as OpenSim and Mokka read it).
Positions are in the units of the header (we write millimetres) in the frame they were
given: the machine's world frame, z up.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mocap.errors import InputError
from mocap.core.marker_table import MarkerTable
from mocap.io.atomic import atomic_path
from mocap.io.text import read_text

_UNITS_TO_METRES = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}


_CHUNK = 4096  # frames formatted at a time, so that a long session makes no huge string array


def _header(table: MarkerTable, name: str) -> list[str]:
    n_frames, n_markers = len(table.frame), len(table.names)
    first = int(table.frame[0]) if n_frames else 0
    rate = f"{table.rate:.6g}"
    return [
        f"PathFileType\t4\t(X/Y/Z)\t{name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"{rate}\t{rate}\t{n_frames}\t{n_markers}\tmm\t{rate}\t{first + 1}\t{n_frames}",
        "\t".join(["Frame#", "Time"] + [f"{m}\t\t" for m in table.names]).rstrip("\t"),
        "\t".join(["", ""] + [f"X{k}\tY{k}\tZ{k}" for k in range(1, n_markers + 1)]),
        "",
    ]


def _rows(table: MarkerTable, start: int, stop: int) -> list[str]:
    """Data lines of frames [start, stop): millimetres with 3 decimals, gaps empty."""
    mm = np.round(table.xyz[start:stop] * 1000.0, 3).reshape(stop - start, -1)
    values = np.where(np.isfinite(mm), np.char.mod("%.3f", np.nan_to_num(mm)), "")
    time = table.time
    return [f"{table.frame[k] + 1}\t{time[k]:.6f}\t" + "\t".join(values[k - start]) for k in range(start, stop)]


def save_trc(table: MarkerTable, path: str | Path) -> None:
    """Write the TRC file (millimetres, 3 decimals), `Frame#` = our frame + 1."""
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8", newline="\n") as fh:
        fh.write("\n".join(_header(table, Path(path).name)) + "\n")
        for start in range(0, len(table.frame), _CHUNK):
            fh.write("\n".join(_rows(table, start, min(start + _CHUNK, len(table.frame)))) + "\n")


def load_trc(path: str | Path) -> MarkerTable:
    """Read a TRC file into metres; `frame` counts from 0 (the file's Frame# minus 1)."""
    path = Path(path)
    lines = read_text(path, "check the TRC path").splitlines()
    if len(lines) < 5 or not lines[0].startswith("PathFileType"):
        raise InputError("not a TRC file (the first line must start with PathFileType)", path=path, where="line 1")
    keys = lines[1].split("\t")
    values = lines[2].split("\t")
    header = dict(zip(keys, values))
    try:
        rate = float(header["DataRate"])
        n_markers = int(header["NumMarkers"])
        scale = _UNITS_TO_METRES[header["Units"].strip()]
    except (KeyError, ValueError):
        raise InputError(
            "lines 2-3 need DataRate, NumMarkers and Units (mm, cm or m)", path=path, where="line 3"
        ) from None
    names = tuple(v.strip() for v in lines[3].split("\t")[2:] if v.strip())
    if len(names) != n_markers:
        raise InputError(f"{len(names)} marker names, NumMarkers says {n_markers}", path=path, where="line 4")
    rows = []
    for line_no, line in enumerate(lines[5:], start=6):
        if not line.strip():
            continue
        fields = line.split("\t")
        fields += [""] * (2 + 3 * n_markers - len(fields))
        try:
            rows.append([float(v) if v.strip() else np.nan for v in fields[: 2 + 3 * n_markers]])
        except ValueError:
            raise InputError("a field is not a number", path=path, where=f"line {line_no}") from None
    data = np.array(rows, dtype=float).reshape(-1, 2 + 3 * n_markers)
    xyz = data[:, 2:].reshape(len(data), n_markers, 3) * scale
    return MarkerTable(names, data[:, 0].astype(int) - 1, rate, xyz)
