"""Camera offsets refined on the pixels themselves.

The joint-value curves (`align`) come from single-camera fits: a view that sees a joint
edge-on, or lands on a mirror solution for a stretch, leaves them biased or noisy. Once
every offset is known to a frame, each camera's offset is refined by what the offsets are
for: the machine model (its base's bouncing included) fitted to that camera and the
reference camera together (`fit_joints`), the camera's pixels interpolated onto times of
the reference's clock, explains the pixels best (the least robust sum of squared
reprojection residuals) when the camera's clock is right. Each camera is searched within
a window around its start with the reference alone (a pair: no third camera's own offset
error drags it). The tracks are smoothed first (`CameraPixels.smoothed`, every camera's
alike) and the fitted times spread over every share of a frame (VERNIER), so that the
noise left after interpolation does not change as the search moves the clock.

Shapes: C cameras, F frames, M markers, J joints.
"""

from __future__ import annotations

import inspect
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import make_smoothing_spline
from scipy.optimize import minimize_scalar

from mocap.core.camera import Camera
from mocap.core.machine import Machine
from mocap.reconstruct.kinfit import FitOptions, fit_joints

MAX_FRAMES = 240  # about as many times of the reference's clock fitted (evenly spread)
VERNIER = 7  # the fitted times step by whole frames and a VERNIER-th of one
_OPTIONS = FitOptions(base_motion=True)  # the base's bouncing, seen by two cameras, is fitted


def _smooth(time: np.ndarray, values: np.ndarray, lam: float) -> np.ndarray:
    """values (T, K, 2) along `time` (T,) through one smoothing spline of `lam` per column.
    Every column has the same system matrix: from SciPy 1.16 on one call solves them all
    (each column's numbers as its own call gives them), before it one call per column."""
    if _BATCHED:
        return make_smoothing_spline(time, values, lam=lam)(time)
    out = np.empty_like(values)
    for k in range(values.shape[1]):
        for axis in range(2):
            out[:, k, axis] = make_smoothing_spline(time, values[:, k, axis], lam=lam)(time)
    return out


_BATCHED = "axis" in inspect.signature(make_smoothing_spline).parameters


@dataclass(frozen=True)
class CameraPixels:
    """One camera's pixels on its own frames: `frames` (F,) consecutive int, `pixels` (F, M, 2)
    NaN where not seen, at `fps`."""

    frames: np.ndarray
    pixels: np.ndarray
    fps: float

    def __post_init__(self) -> None:
        if np.ndim(self.pixels) != 3 or len(self.pixels) != len(self.frames) or np.shape(self.pixels)[2] != 2:
            raise ValueError(f"CameraPixels: pixels must be (F={len(self.frames)}, M, 2), got {np.shape(self.pixels)}")

    @classmethod
    def smoothed(cls, frames: np.ndarray, pixels: np.ndarray, fps: float, span_s: float) -> CameraPixels:
        """The pixels (F, M, 2) smoothed along each marker's track over stretches seen
        without a break: a smoothing spline whose kernel spans `span_s` (symmetric: it moves
        nothing in time). Interpolated raw pixels carry noise that changes as the search
        moves a clock between two frames; smoothed, that noise barely changes."""
        out = np.array(pixels, dtype=float)
        seen = np.all(np.isfinite(out), axis=-1)  # (F, M)
        time = np.asarray(frames, dtype=float) / fps
        runs: dict[tuple[int, int], list[int]] = {}  # (start, end) of a seen run: the markers seen over it
        for m in range(out.shape[1]):
            edges = np.flatnonzero(np.diff(np.r_[0, seen[:, m].astype(int), 0]))  # starts and ends of seen runs
            for a, b in zip(edges[::2], edges[1::2]):
                if b - a >= 8:
                    runs.setdefault((int(a), int(b)), []).append(m)
        for (a, b), markers in runs.items():
            out[a:b, markers] = _smooth(time[a:b], out[a:b, markers], fps * span_s**4)
        return cls(np.asarray(frames), out, float(fps))

    def at(self, time: np.ndarray, offset: float, span: float = 0.0) -> np.ndarray:
        """(T, M, 2) the pixels at reference-clock `time` (T,) s, the camera's frame f showing
        f / fps + `offset`: linear between the two frames around each time, NaN where either
        is missing or outside the recording, and (with `span` s) wherever the frames around
        any time within ±span would be (so the set of pixels stays the same over a search)."""
        position = (np.asarray(time, dtype=float) - offset) * self.fps - self.frames[0]  # (T,) in frames
        low = np.floor(position - span * self.fps).astype(int)
        high = np.floor(position + span * self.fps).astype(int) + 1
        seen = np.all(np.isfinite(self.pixels), axis=-1)  # (F, M)
        ok = (low >= 0) & (high < len(self.frames))
        index = np.clip(np.floor(position).astype(int), 0, len(self.frames) - 2)
        weight = np.clip(position - index, 0.0, 1.0)[:, None, None]
        out = (1.0 - weight) * self.pixels[index] + weight * self.pixels[index + 1]
        cumulative = np.vstack([np.zeros((1, seen.shape[1]), int), np.cumsum(~seen, axis=0)])  # (F+1, M) misses so far
        lo, hi = np.clip(low, 0, len(self.frames) - 1), np.clip(high, 0, len(self.frames) - 1)
        complete = (cumulative[hi + 1] - cumulative[lo]) == 0  # (T, M) every frame in [low, high] seen
        out[~(ok[:, None] & complete)] = np.nan
        return out


def refine_offsets(machine: Machine, cameras: list[Camera], recordings: list[CameraPixels], offsets: np.ndarray,
                   reference: int, width: float) -> tuple[np.ndarray, np.ndarray]:
    """Offsets (C,) s refined on the pixels within ±`width` s of `offsets` (C,) (camera 0's
    clock; NaN for a camera left out), `reference` the camera whose frames are fitted (its
    own offset held); and (C,) the RMS reprojection residual (px) of each camera with the
    reference at the end (the reference's own: NaN)."""
    offsets = np.array(offsets, dtype=float)
    residual = np.full(len(cameras), np.nan)
    own = recordings[reference]
    # the times fitted step by whole frames and a VERNIER-th of one: the pixels interpolated
    # there (the reference's too) fall at every share of the way between two frames alike,
    # wherever the search moves a camera's clock, so the noise that survives the interpolation
    # (less midway between frames) draws the search nowhere
    step = (max(1, len(own.frames) // MAX_FRAMES) + 1.0 / VERNIER) / own.fps
    time = np.arange(own.frames[0] / own.fps, own.frames[-1] / own.fps, step) + offsets[reference]
    held = own.at(time, offsets[reference])
    for k in range(len(cameras)):
        if k == reference or not np.isfinite(offsets[k]):
            continue
        pair = [cameras[reference], cameras[k]]
        state = {"joints": None}  # each fit starts from the last one's joints; the first from the grid

        # the pixels every offset of the search can interpolate: the same set wherever it looks
        kept = np.isfinite(recordings[k].at(time, offsets[k], width)[..., 0])  # (F, M)

        def fit(o: float):
            moved = np.where(kept[..., None], recordings[k].at(time, o), np.nan)
            result = fit_joints(machine, pair, np.stack([held, moved]), state["joints"], _OPTIONS)
            if np.all(np.isfinite(result.joints)):
                state["joints"] = result.joints
            return result

        def cost(o: float) -> float:
            result = fit(o)
            return float(np.nansum(result.weights * np.sum(result.residuals**2, axis=-1)))

        fit(offsets[k])
        best = minimize_scalar(cost, bounds=(offsets[k] - width, offsets[k] + width), method="bounded",
                               options={"xatol": 1e-3 / own.fps})
        offsets[k] = float(best.x)
        final = fit(offsets[k])
        residual[k] = float(np.sqrt(np.nanmean(np.sum(final.residuals[1] ** 2, axis=-1))))
    return offsets, residual
