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


def load_tracks(paths) -> Tracks:
    """Read one or several tracks CSV files (one per camera, or all cameras in one)."""
    if isinstance(paths, (str, Path)):
        paths = [paths]
    return concatenate([_load_one(Path(p)) for p in paths])


def _load_one(path: Path) -> Tracks:
    text = read_text(path, "check the tracks path")
    reader = csv.reader(io.StringIO(text))
    header = next(reader, None)
    if header is None:
        raise InputError(f"empty file; expected a header {','.join(REQUIRED)}", path=path)
    header = [h.strip() for h in header]
    missing = [h for h in REQUIRED if h not in header]
    if missing:
        raise InputError(
            f"header lacks {', '.join(missing)}; expected columns {','.join(REQUIRED)}[,time,score]",
            path=path,
            where="line 1",
        )
    col = {h: header.index(h) for h in REQUIRED + OPTIONAL if h in header}
    cameras, frames, markers, xs, ys, times, scores = [], [], [], [], [], [], []
    for line, row in enumerate(reader, start=2):
        if not row or all(not v.strip() for v in row):
            continue
        if len(row) != len(header):
            raise InputError(
                f"{len(row)} fields, the header has {len(header)}", path=path, where=f"line {line}"
            )
        try:
            frame = int(row[col["frame"]])
        except ValueError:
            raise InputError(
                f"frame {row[col['frame']]!r} is not an integer", path=path, where=f"line {line}"
            ) from None
        if frame < 0:
            raise InputError(f"frame {frame} is negative", path=path, where=f"line {line}")
        values = []
        for key in ("x", "y", "time", "score"):
            if key not in col or row[col[key]].strip() == "":
                values.append(np.nan)
                continue
            try:
                values.append(float(row[col[key]]))
            except ValueError:
                raise InputError(
                    f"{key} {row[col[key]]!r} is not a number", path=path, where=f"line {line}"
                ) from None
        if not (np.isfinite(values[0]) and np.isfinite(values[1])):
            raise InputError("x and y must be finite numbers", path=path, where=f"line {line}")
        camera, marker = row[col["camera"]].strip(), row[col["marker"]].strip()
        if not camera or not marker:
            raise InputError("camera and marker must not be empty", path=path, where=f"line {line}")
        cameras.append(camera)
        frames.append(frame)
        markers.append(marker)
        xs.append(values[0])
        ys.append(values[1])
        times.append(values[2])
        scores.append(values[3])
    return Tracks.from_rows(cameras, frames, markers, np.c_[xs, ys], times, scores)


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
