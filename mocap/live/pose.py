"""The pose of each reference frame as it comes: every camera's labelled pixels placed on
the reference clock, the machine model fitted from the frame before (the batched kernel of
`mocap fit`), and a fixed-lag smoother that gives the row of the frame `lag` frames back.

No file or thread here: arrays in, arrays out (`mocap.live.run` wires them to the sources).
Shapes: C cameras, M markers, J joints, W frames in the smoother's window.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, replace

import numpy as np

from mocap.camera import Camera
from mocap.machine import Machine
from mocap.reconstruct.kinfit import FitOptions, FrameFitter, fit_joints
from mocap.reconstruct.smooth import SmoothOptions, smooth
from mocap.reconstruct.uncertainty import point_quantities

log = logging.getLogger(__name__)

_RAYLEIGH_MEDIAN = np.sqrt(2 * np.log(2))  # median of a 2-D residual's length over its per-axis SD
_NOISE_FRAMES = 90  # frames whose residuals give the pixel noise
_RESTART_RATIO = 4.0  # a frame whose cost per observation is this much above the typical one is fitted from the grid
_PROCESS_NOISE_EVERY = 30  # frames between estimates of the smoother's process noise
_FIRST_PROCESS_NOISE = 10.0  # (rad or m)^2 / s^3 until the window holds enough to estimate it: little smoothing


class CameraHistory:
    """A camera's last labelled frames: (time on the reference clock, pixels (M, 2))."""

    def __init__(self, fps: float, depth: int = 8):
        self.fps = fps
        self.frames: deque[tuple[float, np.ndarray]] = deque(maxlen=depth)

    def add(self, time: float, pixels: np.ndarray) -> None:
        self.frames.append((time, pixels))

    @property
    def latest(self) -> float:
        return self.frames[-1][0] if self.frames else -np.inf

    def pixels_at(self, time: float) -> np.ndarray | None:
        """(M, 2) the markers at `time`: interpolated between the frames either side (a marker
        seen in only one of them taken from it if that frame is within half an interval), or the
        nearest frame within half an interval; None if no frame is near."""
        if not self.frames:
            return None
        interval = 1.0 / self.fps
        times = np.array([t for t, _ in self.frames])
        before = np.flatnonzero(times <= time)
        after = np.flatnonzero(times >= time)
        a = self.frames[before[-1]] if len(before) else None
        b = self.frames[after[0]] if len(after) else None
        if a is not None and b is not None and b[0] - a[0] <= 1.5 * interval:
            share = 0.0 if b[0] == a[0] else (time - a[0]) / (b[0] - a[0])
            both = a[1] + share * (b[1] - a[1])
            near = a if share <= 0.5 else b
            return np.where(np.isfinite(both), both, near[1] if abs(near[0] - time) <= 0.5 * interval else np.nan)
        near = min((f for f in (a, b) if f is not None), key=lambda f: abs(f[0] - time))
        return near[1] if abs(near[0] - time) <= 0.5 * interval else None


@dataclass(frozen=True)
class FrameFit:
    """One frame's fit: joints (J,), information (J, J) per px² of noise divided in,
    valid, rms_px, observations."""

    joints: np.ndarray
    information: np.ndarray
    valid: bool
    rms_px: float
    observations: int


class WarmFit:
    """The machine fitted frame after frame, each from the frame before's joints moved on at
    their last velocity; the first frame, and one that ends far worse than is typical, from
    the whole fit's grid and restarts (`fit_joints`). The pixel noise behind the information
    is estimated from the last frames' residuals (or `options.noise_px`)."""

    def __init__(self, machine: Machine, cameras: list[Camera], options: FitOptions | None = None):
        self.machine, self.cameras = machine, list(cameras)
        self.options = options or FitOptions()
        self.fitter = FrameFitter(machine, self.cameras, self.options)
        self.last: deque[np.ndarray] = deque(maxlen=2)
        self.lengths: deque[np.ndarray] = deque(maxlen=_NOISE_FRAMES)
        self.per_obs: deque[float] = deque(maxlen=_NOISE_FRAMES)

    @property
    def noise_px(self) -> float:
        if self.options.noise_px:
            return self.options.noise_px
        if not self.lengths:
            return 1.0
        return max(float(np.median(np.concatenate(self.lengths))) / _RAYLEIGH_MEDIAN, 0.05)

    def __call__(self, pixels: np.ndarray) -> FrameFit:
        """pixels (C, M, 2), NaN where not seen."""
        n_joints = self.machine.n_joints
        seen = np.isfinite(pixels[..., 0])
        n_obs = int(seen.sum())
        if 2 * n_obs < self.fitter.n_params:
            self.last.clear()
            return FrameFit(np.full(n_joints, np.nan), np.zeros((n_joints, n_joints)), False, np.nan, n_obs)
        frame = pixels[:, None]
        if not self.last:
            state = self._from_grid(frame)
        else:
            start = self.last[-1] if len(self.last) < 2 else 2 * self.last[-1] - self.last[-2]
            state = self.fitter.fit(frame, start[None])
            per_obs = state.cost[0] / n_obs
            if self.per_obs and per_obs > _RESTART_RATIO * np.median(self.per_obs) + self.options.scale_px**2:
                again = self._from_grid(frame)
                if again.cost[0] < state.cost[0]:
                    state = again
        residual = state.residual[0].reshape(-1, 2)[seen.reshape(-1)]
        length = np.hypot(residual[:, 0], residual[:, 1])
        weight = state.weight[0].reshape(-1, 2)[seen.reshape(-1), 0]
        self.lengths.append(length)
        self.per_obs.append(float(state.cost[0] / n_obs))
        joints = state.joints[0]
        self.last.append(joints.copy())
        rms = float(np.sqrt(np.sum(weight * length**2) / max(np.sum(weight), 1e-12)))
        information = state.hessian[0, :n_joints, :n_joints] / self.noise_px**2
        return FrameFit(joints, information, True, rms, n_obs)

    def _from_grid(self, frame: np.ndarray):
        """The frame (C, 1, M, 2) fitted as `mocap fit` fits a frame without a start."""
        fit = fit_joints(self.machine, self.cameras, frame, options=self.options)
        start = np.where(np.isfinite(fit.joints), fit.joints, 0.0)
        return self.fitter.fit(frame, start)


@dataclass(frozen=True)
class Pose:
    """A row's pose: joints (J,) and their SDs, named points (N, 3) and SDs (N,), bucket
    angle and SD (rad); `filled` when the smoother predicted it (no fit of its own)."""

    joints: np.ndarray
    joints_sd: np.ndarray
    points: np.ndarray
    points_sd: np.ndarray
    bucket_angle: float
    bucket_angle_sd: float
    filled: bool


class FixedLagSmoother:
    """The Rauch-Tung-Striebel smoother of `mocap fit` (`mocap.reconstruct.smooth`) over a
    sliding window of the last `window` frames; a frame's pose is given `lag` frames after it
    came (lag 0: the filter's estimate, from the frames before only). The process noise is
    estimated from the window every `_PROCESS_NOISE_EVERY` frames once it holds enough."""

    def __init__(self, machine: Machine, lag: int, window: int = 90, options: SmoothOptions | None = None):
        if lag < 0 or window <= lag:
            raise ValueError(f"need 0 <= lag < window, got lag {lag}, window {window}")
        self.machine, self.lag, self.window = machine, lag, window
        self.options = options or SmoothOptions()
        self.time: deque[float] = deque(maxlen=window)
        self.values: deque[np.ndarray] = deque(maxlen=window)
        self.information: deque[np.ndarray] = deque(maxlen=window)
        self.valid: deque[bool] = deque(maxlen=window)
        self.process_noise = np.full(machine.n_joints, _FIRST_PROCESS_NOISE)
        self.count = 0
        self.pending = 0  # frames pushed whose pose is not given yet

    def push(self, time: float, fit: FrameFit) -> Pose | None:
        """Add a frame; the pose of the frame `lag` back once there is one."""
        self.time.append(time)
        self.values.append(fit.joints)
        self.information.append(fit.information)
        self.valid.append(fit.valid)
        self.count += 1
        self.pending += 1
        if self.count % _PROCESS_NOISE_EVERY == 0 and self.count >= self.window:
            self._estimate_process_noise()
        if self.pending <= self.lag:
            return None
        self.pending -= 1
        return self._pose(len(self.time) - 1 - self.lag)

    def flush(self) -> list[Pose]:
        """The poses not yet given (the last `lag` frames), from the frames there are."""
        out = [self._pose(len(self.time) - k) for k in range(self.pending, 0, -1)]
        self.pending = 0
        return out

    def _arrays(self):
        return (np.array(self.time), np.array(self.values), np.array(self.information), np.array(self.valid))

    def _estimate_process_noise(self) -> None:
        time, values, information, valid = self._arrays()
        if valid.sum() < 3:
            return
        result = smooth(time, values, information, valid, self.machine.wraps, replace(self.options, process_noise=None))
        self.process_noise = np.maximum(result.process_noise, 1e-6)

    def _pose(self, at: int) -> Pose:
        time, values, information, valid = self._arrays()
        machine, n_joints = self.machine, self.machine.n_joints
        if not valid[: at + 1 + self.lag].any():
            nan = np.full(n_joints, np.nan)
            return _pose(machine, nan, np.full((n_joints, n_joints), np.nan), True)
        result = smooth(time, values, information, valid, machine.wraps,
                        replace(self.options, process_noise=self.process_noise))
        joints = result.values[at]
        limits = machine.joint_limits
        span = limits[:, 1] - limits[:, 0]
        wrapped = limits[:, 0] + np.mod(joints - limits[:, 0], np.where(machine.wraps, span, 1.0))
        return _pose(machine, np.where(machine.wraps, wrapped, joints), result.covariance[at], bool(result.filled[at]))


def _pose(machine: Machine, joints: np.ndarray, covariance: np.ndarray, filled: bool) -> Pose:
    quantities = point_quantities(machine, joints[None], covariance[None])
    sd = np.sqrt(np.abs(np.diagonal(covariance)))
    return Pose(joints, sd, quantities.points[0], quantities.points_sd[0], float(quantities.bucket_angle[0]),
                float(quantities.bucket_angle_sd[0]) if quantities.bucket_angle_sd is not None else np.nan, filled)
