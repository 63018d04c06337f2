"""Marker observations in long form: the type the tracks formats (CSV, Parquet) read and
write and the stages compute with; names kept as codes into their distinct values."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np
import pyarrow as pa

from mocap.errors import InputError

if TYPE_CHECKING:
    from mocap.core.calibration import Calibration
    from mocap.core.machine import Machine


class Tracks:
    """Observations in long form, R rows: camera (R,) str, frame (R,) int, marker (R,) str,
    xy (R, 2) px, time (R,) s and score (R,), NaN where not given.

    The camera and marker columns may be given as names (R,) or as `Coded` names; each
    form is made from the other when first asked for (the readers know the codes, and most
    stages use only them: no Python string per row is made for them)."""

    def __init__(self, camera, frame, marker, xy, time, score) -> None:
        for name, column in (("camera", camera), ("marker", marker)):
            self.__dict__[f"{name}_codes" if isinstance(column, Coded) else name] = column
        self.frame, self.xy, self.time, self.score = frame, xy, time, score
        n = len(frame)
        for name, column in (("camera", camera), ("marker", marker), ("time", time), ("score", score)):
            if len(column) != n:
                raise ValueError(f"Tracks.{name} has {len(column)} rows, expected {n}")
        if np.shape(xy) != (n, 2):
            raise ValueError(f"Tracks.xy must have shape ({n}, 2), got {np.shape(xy)}")

    def __repr__(self) -> str:
        return f"Tracks({len(self)} rows, cameras {self.cameras}, {len(self.markers)} markers)"

    @cached_property
    def camera(self) -> np.ndarray:
        """(R,) object array of the camera names."""
        return self.camera_codes.values()

    @cached_property
    def marker(self) -> np.ndarray:
        return self.marker_codes.values()

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

    def checked_against(self, calibration: Calibration, machine: Machine | None = None, calibration_path=None,
                        where=None) -> tuple[str, ...]:
        """The marker names the tracks are resampled to (the model's, else the tracks'); raises
        InputError for tracks that are empty, cameras the calibration lacks, a pixel outside
        its camera's image, or markers the model lacks. `calibration_path` and `where` (the
        tracks) name the inputs in messages."""
        if not len(self):
            raise InputError("no observations in the tracks file(s)", path=where)
        unknown = sorted(set(self.cameras) - set(calibration.names))
        if unknown:
            raise InputError(
                f"tracks name camera(s) {unknown} that the calibration lacks (it has "
                f"{list(calibration.names)}); calibrate them or rename the tracks' camera column",
                path=calibration_path,
            )
        check_in_images(self, {c.name: c.size for c in calibration.cameras}, where)
        if machine is None:
            return self.markers
        strange = sorted(set(self.markers) - set(machine.marker_names))
        if strange:
            raise InputError(
                f"marker(s) {strange[:5]}{' …' if len(strange) > 5 else ''} are not in the machine "
                f"model {machine.name!r}; check the model or the tracks' marker names",
                path=where,
            )
        return machine.marker_names

    @property
    def cameras(self) -> tuple[str, ...]:
        """Camera names in order of first appearance."""
        return self.camera_codes.in_order()

    @property
    def markers(self) -> tuple[str, ...]:
        """Marker names in order of first appearance."""
        return self.marker_codes.in_order()

    @property
    def frames(self) -> np.ndarray:
        return np.unique(self.frame)

    @cached_property
    def camera_codes(self) -> Coded:
        """The camera column as codes into its names (computed once; the readers know them)."""
        return Coded.of(self.camera)

    @cached_property
    def marker_codes(self) -> Coded:
        return Coded.of(self.marker)

    def rows_of_camera(self, name: str) -> np.ndarray:
        """(R,) bool: the rows of camera `name`."""
        return self.camera_codes.equal(name)

    def select(self, mask: np.ndarray) -> Tracks:
        camera, marker = (self.__dict__[f"{name}_codes"].select(mask) if f"{name}_codes" in self.__dict__
                          else self.__dict__[name][mask] for name in ("camera", "marker"))  # codes known are kept
        return Tracks(camera, self.frame[mask], marker, self.xy[mask], self.time[mask], self.score[mask])

    def of_camera(self, name: str) -> Tracks:
        return self.select(self.rows_of_camera(name))

    def of_frame(self, frame: int) -> Tracks:
        return self.select(self.frame == frame)

    def dense_of_camera(self, name: str, markers, frames=None) -> np.ndarray:
        """Camera `name`'s pixels as (F, M, 2) at `frames` (F,) (sorted), NaN where not
        seen; by default over its frames from its first to its last (`frame_span`). Rows
        of other markers or frames are ignored."""
        rows = np.flatnonzero(self.rows_of_camera(name))
        frame = self.frame[rows]
        if frames is None:
            frames = np.arange(frame.min(), frame.max() + 1) if len(rows) else np.zeros(0, int)
        frames = np.asarray(frames)
        out = np.full((len(frames), len(markers), 2), np.nan)
        if not len(rows) or not len(frames):
            return out
        if np.all(np.diff(frames) == 1):  # consecutive: an offset, no search
            f = frame - frames[0]
            f_ok = (f >= 0) & (f < len(frames))
        else:
            f = np.searchsorted(frames, frame)
            f_ok = (f < len(frames)) & (frames[np.minimum(f, len(frames) - 1)] == frame)
        m = self.marker_codes.index_in(markers)[rows]
        ok = (m >= 0) & f_ok
        out[f[ok], m[ok]] = self.xy[rows[ok]]
        return out

    def frame_span(self, name: str) -> tuple[int, int] | None:
        """Camera `name`'s first and last frame, None without rows."""
        frame = self.frame[self.rows_of_camera(name)]
        return (int(frame.min()), int(frame.max())) if len(frame) else None

    def first_repeat(self) -> tuple[int, int] | None:
        """The first two rows (in order) of one (camera, marker, frame), or None."""
        if len(self) < 2:
            return None
        camera_id, marker_id = self.camera_codes.codes, self.marker_codes.codes
        key_id = camera_id.astype(np.int64) * (marker_id.max() + 1) + marker_id
        low = int(self.frame.min())
        span = int(self.frame.max()) - low + 1
        pair = key_id * span + (self.frame - low)
        if int(key_id.max() + 1) * span <= 8 * len(self):  # a dense count finds a repeat without sorting
            if np.bincount(pair).max() < 2:
                return None
        order = np.argsort(pair, kind="stable")
        repeat = np.flatnonzero(pair[order][1:] == pair[order][:-1])
        if not len(repeat):
            return None
        first, second = sorted((order[repeat[0]], order[repeat[0] + 1]))
        return int(first), int(second)

    def sparse_camera(self, longest: int) -> tuple[str, int, int] | None:
        """A camera whose frames run over a span longer than `longest` frames and more than
        ten times the frames it has rows in (the stages allocate by the span): its name,
        the row of its last frame and the count of its frames, or None."""
        if not len(self) or int(self.frame.max() - self.frame.min()) + 1 <= longest:
            return None  # no camera's frames span more
        camera_id = self.camera_codes.codes
        for code in range(int(camera_id.max()) + 1):  # the codes number the cameras from 0
            mine = np.flatnonzero(camera_id == code)
            if not len(mine):
                continue
            frames = self.frame[mine]
            span = int(frames.max() - frames.min()) + 1
            if span <= longest:
                continue
            if len(frames) * 10 < span:  # fewer rows than a tenth: fewer frames too
                present = len(np.unique(frames))
            else:
                seen = np.zeros(span, bool)
                seen[frames - frames.min()] = True
                present = int(np.count_nonzero(seen))
            if present * 10 < span:
                return self.camera_codes.names[code], int(mine[np.argmax(frames)]), present
        return None

    def dense(self, cameras, markers, frames) -> np.ndarray:
        """Pixels as (C, F, M, 2), NaN where not seen; rows of other cameras, markers or
        frames are ignored."""
        frames = np.asarray(frames)
        out = np.full((len(cameras), len(frames), len(markers), 2), np.nan)
        c, m = self.camera_codes.index_in(cameras), self.marker_codes.index_in(markers)
        f = np.searchsorted(frames, self.frame)
        f_ok = (f < len(frames)) & (frames[np.minimum(f, len(frames) - 1)] == self.frame)
        ok = (c >= 0) & (m >= 0) & f_ok
        out[c[ok], f[ok], m[ok]] = self.xy[ok]
        return out


@dataclass(frozen=True)
class Coded:
    """A column of names (R,) as codes (R,) into distinct `names` (K,) (some may have no
    row, e.g. after a selection)."""

    names: tuple[str, ...]
    codes: np.ndarray

    @classmethod
    def of(cls, values: np.ndarray) -> Coded:
        """The codes of (R,) names: dictionary-encoded once, not compared per row."""
        if not len(values):
            return cls((), np.zeros(0, np.int64))
        encoded = pa.array(values, pa.string()).dictionary_encode()
        return cls(tuple(encoded.dictionary.to_pylist()), encoded.indices.to_numpy(zero_copy_only=False))

    def select(self, mask: np.ndarray) -> Coded:
        return Coded(self.names, self.codes[mask])

    def __len__(self) -> int:
        return len(self.codes)

    def values(self) -> np.ndarray:
        """(R,) object array of the names, one Python str per distinct name."""
        return np.take(np.array(self.names, dtype=object), self.codes)

    @classmethod
    def joined(cls, parts: list[Coded]) -> Coded:
        """The parts' rows one after the other, coded into the union of their names."""
        index: dict[str, int] = {}
        for part in parts:
            for name in part.names:
                index.setdefault(name, len(index))
        codes = [np.array([index[n] for n in part.names] + [-1], dtype=np.int64)[part.codes] for part in parts]
        return cls(tuple(index), np.concatenate(codes))

    def index_in(self, names) -> np.ndarray:
        """(R,) each row's index in `names`, -1 for a name not there: looked up once per
        distinct name."""
        index = {name: i for i, name in enumerate(names)}
        lookup = np.array([index.get(name, -1) for name in self.names] + [-1], dtype=np.int64)
        return lookup[self.codes]

    def equal(self, name: str) -> np.ndarray:
        """(R,) bool: the rows of `name`."""
        return np.array([n == name for n in self.names] + [False])[self.codes]

    def in_order(self) -> tuple[str, ...]:
        """The names that have rows, in order of their first row."""
        head, index = np.unique(self.codes[:65536], return_index=True)  # most names show early
        first = dict(zip(head.tolist(), index.tolist()))
        for k in np.flatnonzero(np.bincount(self.codes, minlength=len(self.names))):
            if int(k) not in first:
                first[int(k)] = int(np.argmax(self.codes == k))
        return tuple(self.names[k] for k in sorted(first, key=first.get))


def concatenate(parts: list[Tracks]) -> Tracks:
    if len(parts) == 1:
        return parts[0]

    def names(name: str):
        if all(f"{name}_codes" in p.__dict__ for p in parts):  # all coded: stays coded
            return Coded.joined([p.__dict__[f"{name}_codes"] for p in parts])
        return np.concatenate([getattr(p, name) for p in parts])

    frame, xy, time, score = (np.concatenate([getattr(p, f) for p in parts]) for f in ("frame", "xy", "time", "score"))
    return Tracks(names("camera"), frame, names("marker"), xy, time, score)


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
