"""The triangulated / reference points CSV: ``frame,marker,x,y,z,error_px,views``.

Positions in metres in the world (base) frame; `error_px` the RMS reprojection error of
the point; `views` the number of cameras that saw it.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mocap.errors import InputError
from mocap.io.atomic import atomic_path
from mocap.io.text import csv_rows, read_text

COLUMNS = ("frame", "marker", "x", "y", "z", "error_px", "views")


@dataclass(frozen=True)
class Points:
    """N rows: frame (N,) int, marker (N,) str, xyz (N, 3) m, error_px (N,), views (N,) int."""

    frame: np.ndarray
    marker: np.ndarray
    xyz: np.ndarray
    error_px: np.ndarray
    views: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.frame)
        if np.shape(self.xyz) != (n, 3) or len(self.marker) != n:
            raise ValueError(f"Points needs marker (N,) and xyz (N, 3) for N={n}")

    def __len__(self) -> int:
        return len(self.frame)


def save_points(points: Points, path: str | Path) -> None:
    with atomic_path(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh, lineterminator="\n")
        writer.writerow(COLUMNS)
        for k in range(len(points)):
            x, y, z = points.xyz[k]
            err = points.error_px[k]
            writer.writerow(
                [
                    int(points.frame[k]),
                    points.marker[k],
                    f"{x:.5f}",
                    f"{y:.5f}",
                    f"{z:.5f}",
                    f"{err:.4f}" if np.isfinite(err) else "",
                    int(points.views[k]),
                ]
            )


def load_points(path: str | Path) -> Points:
    path = Path(path)
    text = read_text(path, "check the points path")
    reader = iter(csv_rows(text, path))
    header = [h.strip() for h in next(reader, [])]
    missing = [c for c in ("frame", "marker", "x", "y", "z") if c not in header]
    if missing:
        raise InputError(
            f"header lacks {', '.join(missing)}; expected {','.join(COLUMNS)}", path=path, where="line 1"
        )
    col = {h: i for i, h in enumerate(header)}
    frames, markers, xyz, errors, views = [], [], [], [], []
    for line, row in enumerate(reader, start=2):
        if not row:
            continue
        try:
            frames.append(int(row[col["frame"]]))
            markers.append(row[col["marker"]].strip())
            xyz.append([float(row[col[c]]) for c in ("x", "y", "z")])
            e = row[col["error_px"]].strip() if "error_px" in col else ""
            errors.append(float(e) if e else np.nan)
            views.append(int(row[col["views"]]) if "views" in col else 0)
        except (ValueError, IndexError):
            raise InputError(
                "expected frame (integer), marker, x, y, z (numbers)", path=path, where=f"line {line}"
            ) from None
        if frames[-1] < 0 or not np.all(np.isfinite(xyz[-1])) or not markers[-1]:
            raise InputError("expected a frame >= 0, a marker name and finite x, y, z", path=path,
                             where=f"line {line}")
    return Points(
        np.array(frames, dtype=int),
        np.array(markers, dtype=object),
        np.array(xyz, dtype=float).reshape(-1, 3),
        np.array(errors, dtype=float),
        np.array(views, dtype=int),
    )
