"""The 2-D observations / tracks CSV: ``camera,frame,marker,x,y`` and optional ``time,score``.

One row per marker seen in a frame; a marker not seen has no row. Pixels in the OpenCV
convention (x right, y down, centre of the top-left pixel at 0, 0).
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

REQUIRED = ("camera", "frame", "marker", "x", "y")
OPTIONAL = ("time", "score")


@dataclass(frozen=True)
class Tracks:
    """Observations in long form, R rows: camera (R,) str, frame (R,) int, marker (R,) str,
    xy (R, 2) px, time (R,) s and score (R,), NaN where not given."""

    camera: np.ndarray
    frame: np.ndarray
    marker: np.ndarray
    xy: np.ndarray
    time: np.ndarray
    score: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.frame)
        for name in ("camera", "marker", "time", "score"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"Tracks.{name} has {len(getattr(self, name))} rows, expected {n}")
        if np.shape(self.xy) != (n, 2):
            raise ValueError(f"Tracks.xy must have shape ({n}, 2), got {np.shape(self.xy)}")

    @classmethod
    def from_rows(cls, camera, frame, marker, xy, time=None, score=None) -> Tracks:
        n = len(frame)
        nan = np.full(n, np.nan)
        return cls(
            np.asarray(camera, dtype=object),
            np.asarray(frame, dtype=int),
            np.asarray(marker, dtype=object),
            np.asarray(xy, dtype=float).reshape(n, 2),
            nan if time is None else np.asarray(time, dtype=float),
            nan.copy() if score is None else np.asarray(score, dtype=float),
        )

    def __len__(self) -> int:
        return len(self.frame)

    @property
    def cameras(self) -> tuple[str, ...]:
        """Camera names in order of first appearance."""
        _, first = np.unique(self.camera, return_index=True)
        return tuple(self.camera[np.sort(first)])

    @property
    def frames(self) -> np.ndarray:
        return np.unique(self.frame)

    def select(self, mask: np.ndarray) -> Tracks:
        return Tracks(*(getattr(self, f)[mask] for f in ("camera", "frame", "marker", "xy", "time", "score")))

    def of_camera(self, name: str) -> Tracks:
        return self.select(self.camera == name)

    def of_frame(self, frame: int) -> Tracks:
        return self.select(self.frame == frame)

    def dense(self, cameras, markers, frames) -> np.ndarray:
        """Pixels as (C, F, M, 2), NaN where not seen; rows of other cameras, markers or
        frames are ignored."""
        cam_index = {name: i for i, name in enumerate(cameras)}
        mark_index = {name: i for i, name in enumerate(markers)}
        frames = np.asarray(frames)
        out = np.full((len(cameras), len(frames), len(markers), 2), np.nan)
        c = np.array([cam_index.get(name, -1) for name in self.camera], dtype=int)
        m = np.array([mark_index.get(name, -1) for name in self.marker], dtype=int)
        f = np.searchsorted(frames, self.frame)
        f_ok = (f < len(frames)) & (frames[np.minimum(f, len(frames) - 1)] == self.frame)
        ok = (c >= 0) & (m >= 0) & f_ok
        out[c[ok], f[ok], m[ok]] = self.xy[ok]
        return out


def concatenate(parts: list[Tracks]) -> Tracks:
    fields = ("camera", "frame", "marker", "xy", "time", "score")
    return Tracks(*(np.concatenate([getattr(p, f) for p in parts]) for f in fields))


MAX_FRAME = 100_000_000  # about five weeks at 30 fps: a larger frame number is a typo
MAX_NAME = 200  # characters of a camera or marker name
MAX_PIXEL = 1e6  # no image is this large, however wide its margin
SPARSE_SPAN = 100_000  # frames: a longer span must have rows in at least a tenth of its frames


def load_tracks(paths) -> Tracks:
    """Read one or several tracks CSV files (one per camera, or all cameras in one)."""
    if isinstance(paths, (str, Path)):
        paths = [paths]
    parts = [_load_one(Path(p)) for p in paths]
    tracks = concatenate([part for part, _ in parts])
    if len(paths) > 1:  # rows named by file and line
        places = np.concatenate([np.char.add(f"{p} line ", lines.astype(str)) for p, (_, lines) in zip(paths, parts)])
        where = ", ".join(map(str, paths))
        _check_duplicates(tracks, places, where)
        _check_span(tracks, places, where)
    return tracks


def _load_one(path: Path) -> tuple[Tracks, np.ndarray]:
    """The file's tracks and each row's line number (R,)."""
    header, columns, lines = _parse(read_text(path, "check the tracks path"), path)
    return _validate(header, columns, lines, path), lines


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


def _validate(header: list[str], columns: dict[str, np.ndarray], lines: np.ndarray, path: Path) -> Tracks:
    """Whole-column checks of parsed text columns -> Tracks; the first bad row is named."""

    def fail(mask: np.ndarray, message) -> None:
        bad = np.flatnonzero(mask)
        if len(bad):
            k = bad[0]
            raise InputError(message(k), path=path, where=f"line {lines[k]}")

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
    fail(np.char.str_len(text) > 9, lambda k: f"frame {text[k]} is beyond {MAX_FRAME:,}; a typo?")
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
        values[key] = _floats(np.where(empty, "nan", text), key, lines, path)
        fail(~empty & ~np.isfinite(values[key]),
             lambda k: f"{'x and y must be finite numbers' if key in 'xy' else key + ' must be a finite number'}, "
                     f"got {key} {str(text[k])!r}")
    xy = np.c_[values["x"], values["y"]]
    fail(np.any(np.abs(xy) > MAX_PIXEL, axis=1),
         lambda k: f"pixel ({xy[k, 0]:g}, {xy[k, 1]:g}) is far outside any image")

    tracks = Tracks.from_rows(camera.astype(object), frame, marker.astype(object), xy,
                              values["time"], values["score"])
    places = np.char.add("line ", lines.astype(str))
    _check_duplicates(tracks, places, path)
    _check_span(tracks, places, path)
    return tracks


def ascii_digits(text: np.ndarray) -> np.ndarray:
    """(R,) whether each string is made of the digits 0-9 only (no '²', no other scripts' digits)."""
    ascii = np.char.str_len(np.char.encode(text, "utf-8")) == np.char.str_len(text)
    return np.char.isdigit(text) & ascii


def _floats(text: np.ndarray, key: str, lines: np.ndarray, path) -> np.ndarray:
    try:
        return text.astype(float)
    except ValueError:
        for k, value in enumerate(text):  # only on the way to the error: find the row
            try:
                float(value)
            except ValueError:
                raise InputError(f"{key} {str(value)[:40]!r} is not a number", path=path,
                                 where=f"line {lines[k]}") from None
        raise


def _check_duplicates(tracks: Tracks, places: np.ndarray, where) -> None:
    """One row per (camera, frame, marker): a second is an error naming both."""
    if len(tracks) < 2:
        return
    keys = np.char.add(np.char.add(tracks.camera.astype(str), "\0"), tracks.marker.astype(str))
    _, key_id = np.unique(keys, return_inverse=True)
    pair = key_id.astype(np.int64) * (MAX_FRAME + 1) + tracks.frame
    order = np.argsort(pair, kind="stable")
    repeat = np.flatnonzero(pair[order][1:] == pair[order][:-1])
    if len(repeat):
        first, second = sorted((order[repeat[0]], order[repeat[0] + 1]))
        raise InputError(
            f"marker {tracks.marker[first]!r} of camera {tracks.camera[first]!r} appears twice in frame "
            f"{tracks.frame[first]} ({places[first]} and {places[second]}); keep one row per marker "
            "and frame", path=where)


def _check_span(tracks: Tracks, places: np.ndarray, where) -> None:
    """A camera's frames must not run over a span far larger than the frames it has rows in
    (the stages allocate by the span): a stray frame number is refused, naming its row."""
    for name in tracks.cameras:
        mine = np.flatnonzero(tracks.camera == name)
        frames = tracks.frame[mine]
        span = int(frames.max() - frames.min()) + 1
        present = len(np.unique(frames))
        if span > SPARSE_SPAN and present * 10 < span:
            k = mine[np.argmax(frames)]
            raise InputError(
                f"camera {name!r} has rows in only {present:,} of the {span:,} frames from "
                f"{frames.min()} to {frames.max()} ({places[k]}); a stray frame number?",
                path=where)


def save_tracks(tracks: Tracks, path: str | Path) -> None:
    has_time = bool(np.any(np.isfinite(tracks.time)))
    has_score = bool(np.any(np.isfinite(tracks.score)))
    header = list(REQUIRED) + (["time"] if has_time else []) + (["score"] if has_score else [])
    with atomic_path(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh, lineterminator="\n")
        writer.writerow(header)
        for k in range(len(tracks)):
            row = [tracks.camera[k], int(tracks.frame[k]), tracks.marker[k]]
            row += [f"{tracks.xy[k, 0]:.4f}", f"{tracks.xy[k, 1]:.4f}"]
            if has_time:
                row.append(_num(tracks.time[k], 6))
            if has_score:
                row.append(_num(tracks.score[k], 4))
            writer.writerow(row)


def _num(value: float, digits: int) -> str:
    return "" if not np.isfinite(value) else f"{value:.{digits}f}"


IMAGE_MARGIN = 0.25  # share of the image's width / height a pixel may lie beyond its edge


def check_in_images(tracks: Tracks, sizes: dict, where, what: str = "calibration") -> None:
    """Every row's pixel within its camera's image (`sizes` {camera: (width, height)}), with a
    margin of a quarter of the image; the first row outside is named."""
    for name, (width, height) in sizes.items():
        mine = np.flatnonzero(tracks.camera == name)
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
