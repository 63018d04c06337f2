"""A rolling shutter: the rows of a picture read one after another over `readout` of the
frame interval, so that each row shows the scene at its own instant.

Pixel row v (continuous, OpenCV's convention: the top row's centre at 0) of an image H
rows high is read `readout * (clip(v + 0.5, 0, H) / H - 0.5)` frame intervals after the
frame's time when the frame's time is the middle row's (`centred`, the synthetic field
sessions: the picture's middle agrees with the frame's time, as a global shutter's would), or
`readout * clip(v + 0.5, 0, H) / H` after it when it is the top row's (the tag boards).

A moving point is seen where it is at the instant its own row is read; the row depends on
the position and the position on the instant, a small fixed point (`rolling_pixels`, a
few steps: each moves the row by the point's speed times the readout per row, a small
share). A renderer that draws whole pictures at a few instants composes them by rows
(`row_weights`): each row is the exposure's average of the pictures, linearly interpolated
in time between the instants drawn.

Shapes: H rows, K instants drawn.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def row_delay(v: np.ndarray, height: int, readout: float, centred: bool = True) -> np.ndarray:
    """Frame intervals (same shape as `v`) from the frame's time to the instant row `v` is read."""
    share = np.clip(np.asarray(v, dtype=float) + 0.5, 0.0, height) / height
    return readout * (share - 0.5 if centred else share)


def rolling_pixels(pixels_at: Callable[[np.ndarray], np.ndarray], frames: np.ndarray, height: int,
                   readout: float, centred: bool = True, steps: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Where points are seen by a rolling shutter, and when.

    `pixels_at(at)` gives the pixels (..., 2) of the points at their own fractional frames
    `at` (...); `frames` (...) each point's frame. Returns the pixels (..., 2) at the
    instants their rows are read and those instants (...) in fractional frames. A point
    not in the picture (NaN) keeps the frame's time.
    """
    frames = np.asarray(frames, dtype=float)
    at = frames
    uv = pixels_at(at)
    for _ in range(steps):
        v = np.where(np.isfinite(uv[..., 1]), uv[..., 1], (height - 1) / 2)
        at = frames + row_delay(v, height, readout, centred)
        uv = pixels_at(at)
    return uv, at


def instants(readout: float, exposure: float, count: int) -> np.ndarray:
    """(K,) instants, in frame intervals from the frame's time, that a picture composed by
    rows (`row_weights`) is drawn at: evenly over all the rows' exposures."""
    half = 0.5 * (readout + exposure)
    return np.linspace(-half, half, count) if count > 1 else np.zeros(1)


def row_weights(height: int, readout: float, exposure: float, count: int) -> np.ndarray:
    """(K, H) float32: how much of each picture drawn at `instants` makes each row.

    Row y's exposure is open `exposure` frame intervals centred on its read instant
    (`row_delay`, centred); the scene between two instants is their linear interpolation;
    the weights are each instant's share of the row's exposure (or, without one, the
    interpolation's at its instant). Each row's weights add up to 1."""
    times = instants(readout, exposure, count)
    if count == 1:
        return np.ones((1, height), np.float32)
    step = times[1] - times[0]
    middle = row_delay(np.arange(height), height, readout)  # (H,)

    def below(t: np.ndarray) -> np.ndarray:
        """(K, H) each instant's tent (width 2 steps, area 1 step) integrated up to `t` (H,), in steps."""
        u = np.clip((t[None] - times[:, None]) / step, -1.0, 1.0)
        return np.where(u < 0, 0.5 * (u + 1) ** 2, 1.0 - 0.5 * (1 - u) ** 2)

    if exposure > 0:
        weights = (below(middle + exposure / 2) - below(middle - exposure / 2)) * (step / exposure)
    else:
        weights = np.clip(1.0 - np.abs(middle[None] - times[:, None]) / step, 0.0, None)
    return (weights / weights.sum(axis=0, keepdims=True)).astype(np.float32)
