"""Cameras on one clock: every camera's tracks resampled to the reference camera's frames.

Camera k's frame f shows time ``f / fps_k + offset_k`` (DESIGN.md); the first camera of
the calibration is the reference clock (offset 0). A camera's marker position at a
reference frame's time is interpolated linearly between the two neighbouring frames of
that camera in which the marker was seen; where either neighbour is missing (a gap, or
outside the camera's recording) it is NaN: nothing is extrapolated.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from mocap.core.tracks import Tracks
from mocap.errors import InputError
from mocap.io.tracks_csv import SPARSE_SPAN
from mocap.reconstruct.outliers import track_outliers

if TYPE_CHECKING:
    from mocap.core.calibration import Calibration

log = logging.getLogger(__name__)

_TIME_EPS = 1e-6  # frames: a sample this close to a camera frame takes that frame as is


@dataclass(frozen=True)
class Resampled:
    """Pixels of C cameras at F reference frames: frame (F,) int, time (F,) s,
    pixels (C, F, M, 2) NaN where not seen."""

    frame: np.ndarray
    time: np.ndarray
    pixels: np.ndarray
    dropped: int = 0  # pixels dropped as contradicted by their own tracks

    def __post_init__(self) -> None:
        n = len(self.frame)
        if np.shape(self.time) != (n,) or np.ndim(self.pixels) != 4 or np.shape(self.pixels)[1] != n:
            raise ValueError(f"Resampled needs time ({n},) and pixels (C, {n}, M, 2)")


def resample(
    pixels: list[np.ndarray],
    first_frames: np.ndarray,
    fps: np.ndarray,
    offsets: np.ndarray,
) -> Resampled:
    """Resample each camera's pixels to the reference camera's frames.

    Parameters
    ----------
    pixels : C arrays (F_k, M, 2), camera k's pixels at its frames
        ``first_frames[k] .. first_frames[k] + F_k - 1``, NaN where not seen.
    first_frames : (C,) int; fps : (C,) frames per second; offsets : (C,) seconds, camera
        k's frame f shows time ``f / fps[k] + offsets[k]``; camera 0 is the reference.

    Returns
    -------
    Resampled over every reference frame (from 0) whose time lies inside some camera's
    recording.
    """
    fps = np.asarray(fps, dtype=float)
    offsets = np.asarray(offsets, dtype=float)
    first_frames = np.asarray(first_frames, dtype=int)
    if not (len(pixels) == len(fps) == len(offsets) == len(first_frames)) or not len(pixels):
        raise ValueError("one pixel array, fps, offset and first frame per camera")
    if np.any(~(fps > 0)):
        raise ValueError(f"fps must be positive, got {fps}")
    offsets = offsets - offsets[0]  # the first camera is the clock
    starts = first_frames / fps + offsets
    ends = (first_frames + np.array([len(p) for p in pixels]) - 1) / fps + offsets
    present = np.array([len(p) > 0 for p in pixels])
    if not present.any():
        n_markers = pixels[0].shape[1] if np.ndim(pixels[0]) == 3 else 0
        return Resampled(np.zeros(0, int), np.zeros(0), np.zeros((len(pixels), 0, n_markers, 2)))
    first = max(0, int(np.ceil(starts[present].min() * fps[0] - _TIME_EPS)))  # frames count from 0
    last = int(np.floor(ends[present].max() * fps[0] + _TIME_EPS))
    frame = np.arange(first, last + 1)
    time = frame / fps[0]
    out = np.stack([_sample(p, f0, rate, offset, time) for p, f0, rate, offset in zip(pixels, first_frames, fps, offsets)])
    return Resampled(frame, time, out)


def _sample(pixels: np.ndarray, first_frame: int, fps: float, offset: float, time: np.ndarray) -> np.ndarray:
    """One camera's pixels (F_k, M, 2) at times (F,) -> (F, M, 2), linear, NaN across gaps."""
    n_markers = pixels.shape[1]
    position = (time - offset) * fps - first_frame  # fractional index into `pixels`
    out = np.full((len(time), n_markers, 2), np.nan)
    if not len(pixels):
        return out
    lower = np.floor(position + _TIME_EPS).astype(int)
    fraction = np.clip(position - lower, 0.0, None)
    exact = fraction < _TIME_EPS
    inside = (lower >= 0) & (lower < len(pixels)) & (exact | (lower + 1 < len(pixels)))
    rows = np.flatnonzero(inside)
    values = pixels[lower[rows]]  # exact samples as they are
    between = np.flatnonzero(~exact[rows])
    if len(between):
        a = fraction[rows[between], None, None]
        values[between] = (1.0 - a) * values[between] + a * pixels[lower[rows[between]] + 1]
    out[rows] = values
    return out


def tracks_on_reference_clock(
    tracks: Tracks, camera_names, marker_names, fps: np.ndarray, offsets: np.ndarray,
    drop_outliers: bool = True,
) -> Resampled:
    """Tracks of the named cameras and markers on the first camera's clock; cameras with
    no rows give NaN pixels. With `drop_outliers`, pixels their own track contradicts
    (`mocap.reconstruct.outliers.track_outliers`) are dropped first, and counted."""
    pixels, first_frames, dropped = [], [], 0
    for name in camera_names:
        span = tracks.frame_span(name)
        first = span[0] if span else 0
        dense = tracks.dense_of_camera(name, marker_names, np.arange(first, span[1] + 1) if span else np.zeros(0, int))
        if drop_outliers and len(dense):
            wild = track_outliers(dense)
            dense[wild] = np.nan
            dropped += int(wild.sum())
        pixels.append(dense)
        first_frames.append(first)
    if dropped:
        log.info("%d pixel(s) dropped: their own tracks contradict them", dropped)
    return replace(resample(pixels, np.array(first_frames), fps, offsets), dropped=dropped)


def on_reference_clock(calibration: Calibration, tracks: Tracks, markers, path=None) -> Resampled:
    """The tracks of `markers` on the calibration's reference clock (its cameras' fps and time
    offsets); `path` names the calibration in messages."""
    offsets = calibration.time_offsets
    missing_fps = [n for n, e in zip(calibration.names, calibration.extras) if "fps" not in e]
    if missing_fps and np.any(offsets != 0):
        log.warning("camera(s) %s have no fps in the calibration; assuming 30", missing_fps)
    _check_clock_span(calibration, tracks, path)
    return tracks_on_reference_clock(tracks, calibration.names, markers, calibration.fps(), offsets)


def _check_clock_span(calibration: Calibration, tracks: Tracks, path) -> None:
    """The cameras' recordings placed on the reference clock by their time offsets must not
    spread over far more reference frames than they hold (the resampling allocates by the
    span): time offsets hours apart on seconds of tracks are refused."""
    fps, offsets = calibration.fps(), calibration.time_offsets - calibration.time_offsets[0]
    starts, ends, held = [], [], 0
    for name, rate, offset in zip(calibration.names, fps, offsets):
        frames = tracks.frame[tracks.rows_of_camera(name)]
        if len(frames):
            starts.append(frames.min() / rate + offset)
            ends.append(frames.max() / rate + offset)
            held += int(frames.max() - frames.min()) + 1
    span = (max(ends) - max(min(starts), 0.0)) * fps[0] if starts else 0.0
    if span > SPARSE_SPAN and span > 10 * held:
        raise InputError(
            f"the cameras' tracks, placed on the reference clock by their time offsets, spread over "
            f"{span:,.0f} frames but cover {held:,}: check each camera's time_offset and fps", path=path)
