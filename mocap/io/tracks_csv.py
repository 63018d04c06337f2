"""The 2-D observations / tracks CSV: ``camera,frame,marker,x,y`` and optional ``time,score``.

One row per marker seen in a frame; a marker not seen has no row. Pixels in the OpenCV
convention (x right, y down, centre of the top-left pixel at 0, 0).
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

import pyarrow as pa

from mocap.core.tracks import Coded, Tracks, concatenate
from mocap.errors import InputError
from mocap.io import columnar
from mocap.io.columnar import is_parquet
from mocap.io.text import read_text

REQUIRED = ("camera", "frame", "marker", "x", "y")
OPTIONAL = ("time", "score")


MAX_FRAME = 100_000_000  # about five weeks at 30 fps: a larger frame number is a typo
MAX_NAME = 200  # characters of a camera or marker name
MAX_PIXEL = 1e6  # no image is this large, however wide its margin
SPARSE_SPAN = 100_000  # frames: a longer span must have rows in at least a tenth of its frames


def load_tracks(paths) -> Tracks:
    """Read one or several tracks files (one per camera, or all cameras in one): CSV, or
    Parquet with the same columns for a ``.parquet`` path."""
    if isinstance(paths, (str, Path)):
        paths = [paths]
    paths = [Path(p) for p in paths]
    parts = [_load_one(p) for p in paths]
    tracks = concatenate([part for part, _ in parts])
    if len(paths) > 1:  # rows named by file and line
        starts = np.cumsum([0] + [len(part) for part, _ in parts])

        def place(k: int) -> str:
            i = int(np.searchsorted(starts, k, side="right")) - 1
            if is_parquet(paths[i]):
                return f"{paths[i]} row {k - starts[i] + 1}"
            lines = parts[i][1]
            if lines is None:  # read columnar: number the lines the checked way
                lines = _parse(read_text(paths[i], "check the tracks path"), paths[i])[2]
            return f"{paths[i]} line {lines[k - starts[i]]}"

        where = ", ".join(map(str, paths))
        _check_duplicates(tracks, place, where)
        _check_span(tracks, place, where)
    return tracks


TYPES = {"camera": columnar.NAMES, "frame": columnar.NAMES, "marker": columnar.NAMES, "x": pa.float64(),
         "y": pa.float64(), "time": pa.float64(), "score": pa.float64()}


def _load_one(path: Path) -> tuple[Tracks, np.ndarray | None]:
    """The file's tracks and each row's line number (R,), None when it was read columnar
    with nothing to report."""
    if is_parquet(path):
        return _load_parquet(path)
    table = columnar.read_csv_strict(path, TYPES, counts=("frame",))
    tracks = None if table is None else _from_table(table)
    if tracks is not None:
        return tracks, None
    header, columns, lines = _parse(read_text(path, "check the tracks path"), path)
    return _validate(header, columns, lines, path), lines


def _load_parquet(path: Path) -> tuple[Tracks, np.ndarray | None]:
    table = columnar.read_parquet(path, "check the tracks path", names=("camera", "marker"))
    missing = [h for h in REQUIRED if h not in table.column_names]
    if missing:
        raise InputError(f"lacks the columns {', '.join(missing)}; expected columns "
                         f"{','.join(REQUIRED)}[,time,score]", path=path)
    tracks = _from_table(table)
    if tracks is not None:
        return tracks, None
    header = [h for h in REQUIRED + OPTIONAL if h in table.column_names]
    text = {h: np.array(["" if v is None else str(v) for v in table[h].to_pylist()], dtype=str).reshape(-1)
            for h in header}
    rows = np.arange(1, table.num_rows + 1)
    return _validate(header, {h: np.char.strip(v) for h, v in text.items()}, rows, path, unit="row"), rows


def _from_table(table) -> Tracks | None:
    """Tracks of a typed table that passes every check, else None (the checked reader then
    names the first bad row)."""
    if any(h not in table.column_names for h in REQUIRED):
        return None
    camera = columnar.plain_strings(table["camera"], MAX_NAME)
    marker = columnar.plain_strings(table["marker"], MAX_NAME)
    frame = columnar.whole_numbers(table["frame"], MAX_FRAME)
    if camera is None or marker is None or frame is None:
        return None
    xy = columnar.float_columns([table["x"], table["y"]])
    values = {key: columnar.floats(table[key]) if key in table.column_names else np.full(table.num_rows, np.nan)
              for key in ("time", "score")}
    if xy is None or any(v is None for v in values.values()):
        return None
    if not (len(xy) and -MAX_PIXEL <= xy.min() and xy.max() <= MAX_PIXEL):  # NaN (an empty field) fails too
        return None
    for key in ("time", "score"):
        if key in table.column_names and (np.any(np.isinf(values[key]))
                                          or table[key].null_count < np.isnan(values[key]).sum()):
            return None  # infinite, or a NaN written out rather than an empty field
    tracks = Tracks(Coded(*camera), frame, Coded(*marker), xy, values["time"], values["score"])  # codes known
    if _first_duplicate(tracks) is not None or _sparse_camera(tracks) is not None:
        return None
    return tracks


def _parse(text: str, path: Path) -> tuple[list[str], dict[str, np.ndarray], np.ndarray]:
    """The header and the text columns (R,) of the data rows, with their line numbers (R,);
    blank rows are skipped. Only the shape of the table is checked here."""
    reader = csv.reader(io.StringIO(text))
    try:
        header = next(reader, None)
        if header is None:
            raise InputError(f"empty file; expected a header {','.join(REQUIRED)}", path=path)
        header = [h.strip() for h in header]
        rows, lines = [], []
        for row in reader:
            if row and any(v.strip() for v in row):
                rows.append(row)
                lines.append(reader.line_num)
    except csv.Error as exc:
        raise InputError(f"not a readable CSV ({exc})", path=path, where=f"line {reader.line_num}") from None
    missing = [h for h in REQUIRED if h not in header]
    if missing:
        raise InputError(
            f"header lacks {', '.join(missing)}; expected columns {','.join(REQUIRED)}[,time,score]",
            path=path,
            where="line 1",
        )
    lines = np.asarray(lines, dtype=int)
    widths = np.fromiter((len(r) for r in rows), dtype=int, count=len(rows))
    bad = np.flatnonzero(widths != len(header))
    if len(bad):
        raise InputError(f"{widths[bad[0]]} fields, the header has {len(header)}", path=path,
                         where=f"line {lines[bad[0]]}")
    table = np.array(rows, dtype=str).reshape(len(rows), len(header))
    columns = {h: np.char.strip(table[:, header.index(h)]) for h in REQUIRED + OPTIONAL if h in header}
    return header, columns, lines


def _validate(header: list[str], columns: dict[str, np.ndarray], lines: np.ndarray, path: Path,
              unit: str = "line") -> Tracks:
    """Whole-column checks of parsed text columns -> Tracks; the first bad row is named
    (its `unit` and number: line of a CSV, row of a Parquet file)."""

    def fail(mask: np.ndarray, message) -> None:
        bad = np.flatnonzero(mask)
        if len(bad):
            k = bad[0]
            raise InputError(message(k), path=path, where=f"{unit} {lines[k]}")

    camera, marker = columns["camera"], columns["marker"]
    fail((np.char.str_len(camera) == 0) | (np.char.str_len(marker) == 0),
         lambda k: "camera and marker must not be empty")
    fail((np.char.str_len(camera) > MAX_NAME) | (np.char.str_len(marker) > MAX_NAME),
         lambda k: f"a camera or marker name longer than {MAX_NAME} characters")

    text = columns["frame"]
    digits = ascii_digits(text)
    fail(np.char.startswith(text, "-") & ascii_digits(np.char.lstrip(text, "-")),
         lambda k: f"frame {text[k]} is negative; frames count from 0")
    fail(~digits, lambda k: f"frame {str(text[k])[:40]!r} is not an integer")
    fail(np.char.str_len(np.char.lstrip(text, "0")) > 9, lambda k: f"frame {text[k]} is beyond {MAX_FRAME:,}; a typo?")
    frame = text.astype(np.int64)
    fail(frame > MAX_FRAME, lambda k: f"frame {frame[k]:,} is beyond {MAX_FRAME:,}; a typo?")

    values = {}
    for key in ("x", "y", "time", "score"):
        if key not in columns:
            values[key] = np.full(len(frame), np.nan)
            continue
        text = columns[key]
        empty = np.char.str_len(text) == 0
        if key in ("x", "y"):
            fail(empty, lambda k: f"{key} is empty; a marker not seen has no row")
        values[key] = columnar.parse_floats(np.where(empty, "nan", text), key, lines, path, unit)
        fail(~empty & ~np.isfinite(values[key]),
             lambda k: f"{'x and y must be finite numbers' if key in 'xy' else key + ' must be a finite number'}, "
                     f"got {key} {str(text[k])!r}")
    xy = np.c_[values["x"], values["y"]]
    fail(np.any(np.abs(xy) > MAX_PIXEL, axis=1),
         lambda k: f"pixel ({xy[k, 0]:g}, {xy[k, 1]:g}) is far outside any image")

    tracks = Tracks.from_rows(camera.astype(object), frame, marker.astype(object), xy,
                              values["time"], values["score"])
    _check_duplicates(tracks, lambda k: f"{unit} {lines[k]}", path)
    _check_span(tracks, lambda k: f"{unit} {lines[k]}", path)
    return tracks


def ascii_digits(text: np.ndarray) -> np.ndarray:
    """(R,) whether each string is made of the digits 0-9 only (no '²', no other scripts' digits)."""
    ascii = np.char.str_len(np.char.encode(text, "utf-8")) == np.char.str_len(text)
    return np.char.isdigit(text) & ascii


def _first_duplicate(tracks: Tracks) -> tuple[int, int] | None:
    """The first two rows (in file order) of one (camera, marker, frame), or None."""
    if len(tracks) < 2:
        return None
    camera_id, marker_id = tracks.camera_codes.codes, tracks.marker_codes.codes
    key_id = camera_id.astype(np.int64) * (marker_id.max() + 1) + marker_id
    low = int(tracks.frame.min())
    span = int(tracks.frame.max()) - low + 1
    pair = key_id * span + (tracks.frame - low)
    if int(key_id.max() + 1) * span <= 8 * len(tracks):  # a dense count finds a repeat without sorting
        if np.bincount(pair).max() < 2:
            return None
    order = np.argsort(pair, kind="stable")
    repeat = np.flatnonzero(pair[order][1:] == pair[order][:-1])
    if not len(repeat):
        return None
    first, second = sorted((order[repeat[0]], order[repeat[0] + 1]))
    return int(first), int(second)


def _check_duplicates(tracks: Tracks, place, where) -> None:
    """One row per (camera, frame, marker): a second is an error naming both (`place`(k)
    names row k)."""
    pair = _first_duplicate(tracks)
    if pair is not None:
        first, second = pair
        raise InputError(
            f"marker {tracks.marker[first]!r} of camera {tracks.camera[first]!r} appears twice in frame "
            f"{tracks.frame[first]} ({place(first)} and {place(second)}); keep one row per marker "
            "and frame", path=where)


def _sparse_camera(tracks: Tracks) -> tuple[str, int, int] | None:
    """A camera whose frames run over a span far larger than the frames it has rows in (the
    stages allocate by the span): its name, the row of its last frame and the count of its
    frames, or None."""
    if not len(tracks) or int(tracks.frame.max() - tracks.frame.min()) + 1 <= SPARSE_SPAN:
        return None  # no camera's frames span more
    camera_id = tracks.camera_codes.codes
    for code in range(int(camera_id.max()) + 1):  # the codes number the cameras from 0
        mine = np.flatnonzero(camera_id == code)
        if not len(mine):
            continue
        name = tracks.camera_codes.names[code]
        frames = tracks.frame[mine]
        span = int(frames.max() - frames.min()) + 1
        if span <= SPARSE_SPAN:
            continue
        if len(frames) * 10 < span:  # fewer rows than a tenth: fewer frames too
            present = len(np.unique(frames))
        else:
            seen = np.zeros(span, bool)
            seen[frames - frames.min()] = True
            present = int(np.count_nonzero(seen))
        if present * 10 < span:
            return name, int(mine[np.argmax(frames)]), present
    return None


def _check_span(tracks: Tracks, place, where) -> None:
    """A stray frame number far from a camera's others is refused, naming its row."""
    sparse = _sparse_camera(tracks)
    if sparse is not None:
        name, k, present = sparse
        frames = tracks.frame[tracks.rows_of_camera(name)]
        span = int(frames.max() - frames.min()) + 1
        raise InputError(
            f"camera {name!r} has rows in only {present:,} of the {span:,} frames from "
            f"{frames.min()} to {frames.max()} ({place(k)}); a stray frame number?",
            path=where)


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


IMAGE_MARGIN = 0.25  # share of the image's width / height a pixel may lie beyond its edge


def check_in_images(tracks: Tracks, sizes: dict, where, what: str = "calibration") -> None:
    """Every row's pixel within its camera's image (`sizes` {camera: (width, height)}), with a
    margin of a quarter of the image; the first row outside is named."""
    if not sizes or not len(tracks):
        return
    size = np.array(list(sizes.values()), dtype=float)  # (C, 2)
    if np.all(tracks.xy.min(0) >= (-IMAGE_MARGIN * size).max(0)) and np.all(
            tracks.xy.max(0) <= ((1 + IMAGE_MARGIN) * size).min(0)):
        return  # every row inside every camera's image: nothing to look for camera by camera
    for name, (width, height) in sizes.items():
        mine = np.flatnonzero(tracks.rows_of_camera(name))
        if not len(mine):
            continue
        xy = tracks.xy[mine]
        low = -IMAGE_MARGIN * np.array([width, height])
        high = (1 + IMAGE_MARGIN) * np.array([width, height])
        outside = np.flatnonzero(np.any((xy < low) | (xy > high), axis=1))
        if len(outside):
            k = mine[outside[0]]
            raise InputError(
                f"camera {name!r}, frame {tracks.frame[k]}, marker {tracks.marker[k]!r}: pixel "
                f"({tracks.xy[k, 0]:g}, {tracks.xy[k, 1]:g}) lies outside the {width}x{height} image of "
                f"the {what}; check the pixels or the image size", path=where)
