"""The triangulated / reference points CSV: ``frame,marker,x,y,z,error_px,views``.

Positions in metres in the world (base) frame; `error_px` the RMS reprojection error of
the point; `views` the number of cameras that saw it; then, where computed, ``x_sd,y_sd,z_sd``
each coordinate's standard deviation (metres: the pixel noise's and the calibration's).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mocap.core.points import Points
from mocap.errors import InputError
from mocap.io import columnar
from mocap.io.columnar import ascii_digits
from mocap.io.text import csv_rows, is_parquet, read_text

COLUMNS = ("frame", "marker", "x", "y", "z", "error_px", "views")
SD_COLUMNS = ("x_sd", "y_sd", "z_sd")


def points_columns(points: Points) -> dict[str, np.ndarray]:
    """The points file's columns, each (N,)."""
    columns = {"frame": points.frame.astype(np.int64), "marker": points.marker, "x": points.xyz[:, 0],
               "y": points.xyz[:, 1], "z": points.xyz[:, 2], "error_px": points.error_px,
               "views": points.views.astype(np.int64)}
    if points.sd is not None:
        columns.update({name: points.sd[:, k] for k, name in enumerate(SD_COLUMNS)})
    return columns


def save_points(points: Points, path: str | Path) -> None:
    """Write the points as CSV, or as Parquet for a ``.parquet`` path."""
    if is_parquet(path):
        columnar.write_parquet(points_columns(points), path)
        return
    columnar.write_csv(points_columns(points), path, {"x": 5, "y": 5, "z": 5, "error_px": 4,
                                                      **{name: 6 for name in SD_COLUMNS}})


def load_points(path: str | Path) -> Points:
    """Read a points CSV, or Parquet with the same columns for a ``.parquet`` path."""
    path = Path(path)
    if is_parquet(path):
        return _load_parquet(path)
    text = read_text(path, "check the points path")
    reader = iter(csv_rows(text, path))
    header = [h.strip() for h in next(reader, [])]
    missing = [c for c in ("frame", "marker", "x", "y", "z") if c not in header]
    if missing:
        raise InputError(
            f"header lacks {', '.join(missing)}; expected {','.join(COLUMNS)}", path=path, where="line 1"
        )
    rows = [(line, row) for line, row in enumerate(reader, start=2) if row and any(v.strip() for v in row)]
    lines = np.array([line for line, _ in rows], dtype=int)
    bad = [line for line, row in rows if len(row) != len(header)]
    if bad:
        raise InputError(f"expected {len(header)} fields as in the header", path=path, where=f"line {bad[0]}")
    table = np.array([row for _, row in rows], dtype=str).reshape(len(rows), len(header))
    column = {h: np.char.strip(table[:, i]) for i, h in enumerate(header)}
    return _validate(column, lines, path)


def _load_parquet(path: Path) -> Points:
    table = columnar.read_parquet(path, "check the points path")
    missing = [c for c in ("frame", "marker", "x", "y", "z") if c not in table.column_names]
    if missing:
        raise InputError(f"lacks the columns {', '.join(missing)}; expected {','.join(COLUMNS)}", path=path)
    column = {h: np.char.strip(np.array([("nan" if h in ("x", "y", "z") else "") if v is None else str(v)
                                         for v in table[h].to_pylist()], dtype=str).reshape(-1))
              for h in table.column_names if h in COLUMNS + SD_COLUMNS}  # a null position is not finite
    return _validate(column, np.arange(1, table.num_rows + 1), path, unit="row")


MAX_FRAME = 100_000_000


def _validate(column: dict[str, np.ndarray], lines: np.ndarray, path: Path, unit: str = "line") -> Points:
    """Whole-column checks of the parsed text columns -> Points; the first bad row is named
    (its `unit` and number: line of a CSV, row of a Parquet file)."""

    def fail(mask: np.ndarray, message: str) -> None:
        bad = np.flatnonzero(mask)
        if len(bad):
            raise InputError(message, path=path, where=f"{unit} {lines[bad[0]]}")

    n = len(lines)
    fail(~ascii_digits(column["frame"]) | (np.char.str_len(column["frame"]) > 9),
         f"frame must be a whole number from 0 to {MAX_FRAME:,}")
    frame = column["frame"].astype(np.int64)
    fail(np.char.str_len(column["marker"]) == 0, "the marker name is empty")
    xyz = np.stack([columnar.parse_floats(column[c], c, lines, path, unit) for c in "xyz"], axis=1).reshape(n, 3)
    fail(~np.all(np.isfinite(xyz), axis=1), "x, y and z must be finite numbers (metres)")
    error = column.get("error_px", np.full(n, ""))
    error = columnar.parse_floats(np.where(error == "", "nan", error), "error_px", lines, path, unit)
    views = column.get("views", np.full(n, "0"))
    fail(~ascii_digits(views) | (np.char.str_len(views) > 3), "views must be a whole number of cameras")
    marker = column["marker"].astype(object)
    keys = np.char.add(np.char.add(column["frame"], "\0"), column["marker"])
    _, first = np.unique(keys, return_index=True)
    fail(~np.isin(np.arange(n), first), "this frame and marker appear twice; keep one row each")
    sd = None
    if all(name in column for name in SD_COLUMNS):
        sd = np.stack([columnar.parse_floats(np.where(column[c] == "", "nan", column[c]), c, lines, path, unit)
                       for c in SD_COLUMNS], axis=1).reshape(n, 3)
        fail(np.any(sd < 0, axis=1), "x_sd, y_sd and z_sd must not be negative (metres; empty where unknown)")
    return Points(frame, marker, xyz, error, views.astype(int), sd)
