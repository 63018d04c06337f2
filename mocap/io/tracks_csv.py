"""The 2-D observations / tracks CSV: ``camera,frame,marker,x,y`` and optional ``time,score``.

One row per marker seen in a frame; a marker not seen has no row. Pixels in the OpenCV
convention (x right, y down, centre of the top-left pixel at 0, 0).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mocap.core.tracks import Coded, Tracks, concatenate
from mocap.errors import InputError
from mocap.io import columnar
from mocap.io.text import is_parquet, read_input

REQUIRED = ("camera", "frame", "marker", "x", "y")
OPTIONAL = ("time", "score")


MAX_FRAME = 100_000_000  # about five weeks at 30 fps: a larger frame number is a typo
MAX_NAME = 200  # characters of a camera or marker name
MAX_PIXEL = 1e6  # no image is this large, however wide its margin
SPARSE_SPAN = 100_000  # frames: a longer span must have rows in at least a tenth of its frames


LAYOUT = columnar.Layout(REQUIRED, OPTIONAL, names={"camera": MAX_NAME, "marker": MAX_NAME},
                         counts={"frame": MAX_FRAME}, vectors={"xy": ("x", "y")})


def load_tracks(paths) -> Tracks:
    """Read one or several tracks files (one per camera, or all cameras in one): CSV, or
    Parquet with the same columns for a ``.parquet`` path. Each file is read once and its
    columns checked in one pass (`_load_one`); then one row per marker and frame, and no
    stray frame, in each file and over them all."""
    if isinstance(paths, (str, Path)):
        paths = [paths]
    paths = [Path(p) for p in paths]
    tables, parts = [], []
    for path in paths:
        table, part = _load_one(path)
        tables.append(table)
        parts.append(part)
    tracks = concatenate(parts)
    # each file, its rows named by their lines; then, with several, all of them, by file and line
    scopes = [(part, lambda k, table=table: f"{table.unit} {table.rows[k]}", path)
              for part, table, path in zip(parts, tables, paths)]
    if len(paths) > 1:
        starts = np.cumsum([0] + [len(table) for table in tables])

        def file_and_line(k: int) -> str:
            i = int(np.searchsorted(starts, k, side="right")) - 1
            return f"{paths[i]} {tables[i].unit} {tables[i].rows[k - starts[i]]}"

        scopes.append((tracks, file_and_line, ", ".join(map(str, paths))))
    for rows, place, where in scopes:
        repeat = rows.first_repeat()
        if repeat is not None:
            first, second = repeat
            raise InputError(
                f"marker {rows.marker[first]!r} of camera {rows.camera[first]!r} appears twice in frame "
                f"{rows.frame[first]} ({place(first)} and {place(second)}); keep one row per marker "
                "and frame", path=where)
        sparse = rows.sparse_camera(SPARSE_SPAN)
        if sparse is not None:
            name, k, present = sparse
            frames = rows.frame[rows.rows_of_camera(name)]
            span = int(frames.max() - frames.min()) + 1
            raise InputError(
                f"camera {name!r} has rows in only {present:,} of the {span:,} frames from "
                f"{frames.min()} to {frames.max()} ({place(k)}); a stray frame number?",
                path=where)
    return tracks


def _load_one(path: Path) -> tuple[columnar.Table, Tracks]:
    """One file's table, read once, and its tracks, its columns checked in one pass; the
    first bad row is named (by its line of a CSV, its row of a Parquet file)."""
    parquet, hint = is_parquet(path), "check the tracks path"
    data = read_input(path, hint, text=not parquet)
    table = columnar.parse_table(data, path, LAYOUT, hint, parquet)  # counts and numbers checked
    text = table.text  # None: read the fast way, every value passed the checks of a text field

    def fail(mask: np.ndarray, message) -> None:
        bad = np.flatnonzero(mask)
        if len(bad):
            k = bad[0]
            raise InputError(message(k), path=path, where=f"{table.unit} {table.rows[k]}")

    (cameras, camera), (markers, marker) = table.names["camera"], table.names["marker"]
    long = f"a camera or marker name longer than {MAX_NAME} characters"
    for refused, message in ((lambda n: len(n) == 0, "camera and marker must not be empty"),
                             (lambda n: len(n) > MAX_NAME, long)):
        bad = [np.array([refused(n) for n in names] + [False]) for names in (cameras, markers)]  # per distinct name
        if bad[0].any() or bad[1].any():
            fail(bad[0][camera] | bad[1][marker], lambda k: message)

    xy = table.values["xy"]
    values = {key: table.values[key] if key in table.values else np.full(len(table), np.nan)
              for key in ("time", "score")}
    for key, number in (("x", xy[:, 0]), ("y", xy[:, 1]), ("time", values["time"]), ("score", values["score"])):
        if text is None or key not in text:
            continue
        empty = np.char.str_len(text[key]) == 0
        if key in ("x", "y"):
            fail(empty, lambda k: f"{key} is empty; a marker not seen has no row")
        fail(~empty & ~np.isfinite(number),
             lambda k: f"{'x and y must be finite numbers' if key in 'xy' else key + ' must be a finite number'}, "
                       f"got {key} {str(text[key][k])!r}")
    if len(xy) and not (-MAX_PIXEL <= xy.min() and xy.max() <= MAX_PIXEL):
        fail(np.any(np.abs(xy) > MAX_PIXEL, axis=1),
             lambda k: f"pixel ({xy[k, 0]:g}, {xy[k, 1]:g}) is far outside any image")
    tracks = Tracks(Coded(cameras, camera), table.counts["frame"], Coded(markers, marker), xy, values["time"],
                    values["score"])
    return table, tracks


def tracks_columns(tracks: Tracks) -> dict[str, np.ndarray]:
    """The tracks file's columns, each (N,), `time` and `score` NaN where absent."""
    return {"camera": tracks.camera, "frame": tracks.frame.astype(np.int64), "marker": tracks.marker,
            "x": tracks.xy[:, 0], "y": tracks.xy[:, 1], "time": tracks.time, "score": tracks.score}


def save_tracks(tracks: Tracks, path: str | Path) -> None:
    """Write the tracks as CSV, or as Parquet for a ``.parquet`` path."""
    has_time = bool(np.any(np.isfinite(tracks.time)))
    has_score = bool(np.any(np.isfinite(tracks.score)))
    header = list(REQUIRED) + (["time"] if has_time else []) + (["score"] if has_score else [])
    columns = tracks_columns(tracks)
    if is_parquet(path):
        columnar.write_parquet({h: columns[h] for h in header}, path)
        return
    columnar.write_csv({h: columns[h] for h in header}, path, {"x": 4, "y": 4, "time": 6, "score": 4})
