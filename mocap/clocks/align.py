"""Camera synchronisation from the motion itself.

Each camera alone, with the machine model, measures the joint values at its own frames
(the batched kinematic fit, one camera at a time): joint-value curves over each camera's
own clock. Camera k's frame f shows time ``f / fps_k + offset_k`` (DESIGN.md; the first
camera is the reference, offset 0). Its offset is the shift that best lays its curves on
the reference camera's: a coarse search over shifts of half a reference frame (the mean
squared difference of the joint values, each scaled by its spread over the reference
recording, against the reference curves interpolated at the shifted times), then a
sub-frame refinement of that difference with cubic-spline interpolation. Different frame
rates (29.97 and 30) are handled by the time axes themselves.

Shapes: C cameras, F frames, M markers, J joints.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.optimize import minimize_scalar

from mocap.core.camera import Camera
from mocap.core.machine import Machine
from mocap.reconstruct.kinfit import FitOptions, fit_joints

log = logging.getLogger(__name__)

TRUNCATE = 0.3  # scaled joint-value difference beyond which a sample counts as an outlier
NOISY = 10.0  # a rigid pose parameter varying less than this many of its SDs is not aligned on


@dataclass(frozen=True)
class JointCurves:
    """One camera's joint values over its own frames: `frames` (F,) int, `joints` (F, J)
    rad / m, NaN where the fit failed."""

    frames: np.ndarray
    joints: np.ndarray

    def __post_init__(self) -> None:
        if np.ndim(self.joints) != 2 or len(self.joints) != len(self.frames):
            raise ValueError(f"JointCurves: joints must be (F={len(self.frames)}, J), got {np.shape(self.joints)}")

_COARSE_SAMPLES = 2_000  # samples compared at each offset of the coarse grid


@dataclass(frozen=True)
class SyncResult:
    """`offsets` (C,) s (the reference's 0; NaN where not found), `residual` (C,) RMS of
    the scaled joint-value difference at the offset, `overlap` (C,) samples compared,
    `reasons` (C,) why a camera's offset was not found ('' when it was)."""

    offsets: np.ndarray
    residual: np.ndarray
    overlap: np.ndarray
    reasons: tuple[str, ...]

    def __post_init__(self) -> None:
        n = len(self.offsets)
        if np.shape(self.residual) != (n,) or np.shape(self.overlap) != (n,) or len(self.reasons) != n:
            raise ValueError("SyncResult: one residual, overlap and reason per camera")


def window_frames(
    spans: list[tuple[int, int]], fps: np.ndarray, max_offset: float, windows: int = 8, window_s: float = 60.0,
) -> list[np.ndarray]:
    """The frames of each camera that sync fits: (first, last) frame `spans` (C,) at `fps` (C,).

    A session no longer than `windows` windows of `window_s` s (each widened by `max_offset`
    on both sides) is fitted whole. A longer one in `windows` windows spread evenly over the
    reference camera's (camera 0's) recording: the other cameras' windows span `window_s` of
    their own clock, the reference's are widened by `max_offset` on both sides, so that every
    other camera's window stays inside the reference's at any offset in the search range. An
    offset is a constant, so a few minutes of motion fix it as well as two hours do.
    """
    fps = np.asarray(fps, dtype=float)
    everything = [np.arange(first, last + 1) for first, last in spans]
    first, last = spans[0][0] / fps[0], spans[0][1] / fps[0]
    if last - first <= windows * (window_s + 2 * max_offset):
        return everything
    starts = first + np.linspace(max_offset, last - first - window_s - max_offset, windows)  # s
    chosen = []
    for k, frames in enumerate(everything):
        margin = max_offset if k == 0 else 0.0
        time = frames / fps[k]
        inside = np.any((time[:, None] >= starts - margin) & (time[:, None] <= starts + window_s + margin), axis=1)
        chosen.append(frames[inside])
    return chosen


def joint_curves(
    machine: Machine, camera: Camera, frames: np.ndarray, pixels: np.ndarray, start: np.ndarray | None = None,
    max_rms_px: float = 5.0, max_sd: float = 0.02,
) -> JointCurves:
    """Single-camera kinematic fits of every frame: pixels (F, M, 2) NaN where not seen.

    A frame the fit cannot explain (too few markers, residual RMS above `max_rms_px`) is NaN,
    and so is a joint value whose standard deviation exceeds `max_sd` (rad or m; a joint
    the camera does not see).
    """
    fit = fit_joints(machine, [camera], np.asarray(pixels, dtype=float)[None], start, FitOptions())
    good = (fit.valid & (fit.rms_px <= max_rms_px))[:, None] & (fit.joints_sd <= max_sd)
    return JointCurves(np.asarray(frames, dtype=int), np.where(good, fit.joints, np.nan))


def pose_curves(
    machine: Machine, camera: Camera, frames: np.ndarray, pixels: np.ndarray, max_rms_px: float = 5.0,
) -> JointCurves:
    """A rigid model's (no joints) pose over one camera's frames, the curves to align in place
    of joint values: (F, 6) ``world_from_base`` as rotation vector (rad) and translation (m),
    NaN where the fit failed or explains the pixels (F, M, 2) worse than `max_rms_px`, and
    NaN throughout for a parameter that varies by less than NOISY times its own standard
    deviation (the depth seen by one camera, say: mostly noise to align on)."""
    fit = fit_joints(machine, [camera], np.asarray(pixels, dtype=float)[None], None, FitOptions(base_motion=True))
    good = fit.valid & (fit.rms_px <= max_rms_px)
    pose = np.where(good[:, None], fit.base, np.nan)
    if good.sum() >= 2:
        sd = np.sqrt(np.diagonal(fit.covariance, axis1=1, axis2=2))[good]
        still = np.nanstd(pose, axis=0) <= NOISY * np.median(sd, axis=0)
        pose[:, still] = np.nan
    return JointCurves(np.asarray(frames, dtype=int), pose)


def synchronise(
    curves: list[JointCurves], fps: np.ndarray, max_offset: float = 10.0, min_overlap: float = 0.3,
    max_residual: float = 0.15,
) -> SyncResult:
    """Time offsets of cameras 1.. against camera 0 from their joint-value curves.

    curves : C JointCurves, each on its camera's own frames.
    fps : (C,) frame rates.
    max_offset : the search range, ± seconds.
    min_overlap : the least fraction of a camera's valid samples that must fall inside the
        reference recording at a candidate offset.
    max_residual : the largest RMS difference of the scaled joint values at the best
        offset for it to count as found (the motions agree).
    """
    fps = np.asarray(fps, dtype=float)
    if len(fps) != len(curves):
        raise ValueError(f"one frame rate per camera: {len(fps)} for {len(curves)} cameras")
    n = len(curves)
    offsets, residual, overlap = np.zeros(n), np.zeros(n), np.zeros(n, dtype=int)
    reasons = [""] * n
    reference = _Reference.build(curves[0], fps[0])
    if reference is None:
        reasons = ["the reference camera's joint values do not vary; nothing to align"] * n
        return SyncResult(np.full(n, np.nan), np.full(n, np.nan), overlap, tuple(reasons))
    overlap[0] = int(np.sum(np.any(np.isfinite(curves[0].joints), axis=1)))
    for k in range(1, n):
        ok = np.any(np.isfinite(curves[k].joints), axis=1)
        if ok.sum() < 4:
            offsets[k], residual[k], reasons[k] = np.nan, np.nan, "fewer than 4 frames with a model fit"
            continue
        time = curves[k].frames[ok] / fps[k]
        values = curves[k].joints[ok]
        need = max(4, int(min_overlap * ok.sum()))
        step = 0.5 / fps[0]
        grid = np.arange(-max_offset, max_offset + step / 2, step)
        stride = max(1, len(time) // _COARSE_SAMPLES)  # the coarse search on a long session's every stride-th sample
        costs = reference.costs(time[::stride], grid, values[::stride], max(4, need // stride))
        if not np.any(np.isfinite(costs)):
            offsets[k], residual[k], reasons[k] = np.nan, np.nan, "the recordings do not overlap within the search range"
            continue
        coarse = grid[np.argmin(costs)]
        fine = minimize_scalar(
            lambda o: reference.cost(time + o, values, need)[0],
            bounds=(coarse - 2 * step, coarse + 2 * step),
            method="bounded",
            options={"xatol": 1e-4 / fps[0]},
        )
        offsets[k] = float(fine.x)
        cost, count = reference.cost(time + offsets[k], values, need)
        residual[k], overlap[k] = float(np.sqrt(cost)), count
        if not residual[k] <= max_residual:
            reasons[k] = (
                f"no offset within ±{max_offset:g} s makes the motions agree "
                f"(residual {residual[k]:.2f} of the joints' spread at the best)"
            )
            offsets[k] = np.nan
            continue
        log.info("camera %d: offset %.4f s (%.3f reference frames), residual %.3f", k, offsets[k], offsets[k] * fps[0], residual[k])
    return SyncResult(offsets, residual, overlap, tuple(reasons))


@dataclass(frozen=True)
class _Curve:
    """One reference joint's scaled values at its valid sample times, interpolable."""

    time: np.ndarray  # (F_j,) s
    values: np.ndarray  # (F_j,)
    spline: CubicSpline

    def at(self, time: np.ndarray, gap: float, linear: bool) -> tuple[np.ndarray, np.ndarray]:
        """Interpolated values at `time` (N,) and (N,) bool: inside, not across a gap."""
        index = np.searchsorted(self.time, time)
        inside = (index > 0) & (index < len(self.time))
        index = np.clip(index, 1, len(self.time) - 1)
        before, after = self.time[index - 1], self.time[index]
        inside &= (after - before) <= gap
        if linear:
            w = np.clip((time - before) / (after - before), 0.0, 1.0)
            return (1 - w) * self.values[index - 1] + w * self.values[index], inside
        return self.spline(time), inside


@dataclass(frozen=True)
class _Reference:
    """The reference camera's joint-value curves, each scaled by its spread."""

    curves: tuple[_Curve | None, ...]  # (J,), None for a joint that does not vary
    scale: np.ndarray  # (J,)
    gap: float  # s: interpolation across a longer gap is not trusted

    @classmethod
    def build(cls, joints: JointCurves, fps: float) -> _Reference | None:
        spread = np.nan_to_num(np.nanstd(joints.joints, axis=0)) if np.any(np.isfinite(joints.joints)) else None
        if spread is None or spread.max() < 1e-6:
            return None
        curves = []
        for j in range(joints.joints.shape[1]):
            ok = np.isfinite(joints.joints[:, j])
            if ok.sum() < 4 or spread[j] <= 1e-3 * spread.max():
                curves.append(None)
                continue
            time = joints.frames[ok] / fps
            values = joints.joints[ok, j] / spread[j]
            curves.append(_Curve(time, values, CubicSpline(time, values)))
        if all(c is None for c in curves):
            return None
        return cls(tuple(curves), np.where(spread > 0, spread, 1.0), 1.5 / fps)

    def cost(self, time: np.ndarray, joints: np.ndarray, need: int, linear: bool = False) -> tuple[float, int]:
        """Mean squared difference of the scaled `joints` (N, J) at `time` (N,) from the
        reference curves, over samples inside the reference recording and not in a gap
        (NaN joints skipped); inf if fewer than `need` samples compare."""
        total, count, frames = 0.0, 0, np.zeros(len(time), dtype=bool)
        for j, curve in enumerate(self.curves):
            if curve is None:
                continue
            values = joints[:, j] / self.scale[j]
            predicted, inside = curve.at(time, self.gap, linear)
            inside &= np.isfinite(values)
            # truncated at TRUNCATE: a single camera's fit can land on a mirror solution
            # (swing seen side-on) for a stretch of frames; those count as a fixed penalty
            total += float(np.sum(np.minimum((values[inside] - predicted[inside]) ** 2, TRUNCATE**2)))
            count += int(inside.sum())
            frames |= inside
        if frames.sum() < need or count == 0:
            return np.inf, int(frames.sum())
        return total / count, int(frames.sum())

    def costs(self, time: np.ndarray, offsets: np.ndarray, joints: np.ndarray, need: int) -> np.ndarray:
        """`cost` (linear) at `time` (N,) shifted by each of `offsets` (G,) -> (G,), all
        offsets at once (in blocks of a bounded size)."""
        out = np.empty(len(offsets))
        block = max(1, 2_000_000 // max(len(time), 1))
        for start in range(0, len(offsets), block):
            shifted = time[None, :] + offsets[start : start + block, None]  # (B, N)
            total, count = np.zeros(len(shifted)), np.zeros(len(shifted), dtype=int)
            frames = np.zeros(shifted.shape, dtype=bool)
            for j, curve in enumerate(self.curves):
                if curve is None:
                    continue
                values = joints[:, j] / self.scale[j]
                predicted, inside = curve.at(shifted.ravel(), self.gap, True)
                predicted, inside = predicted.reshape(shifted.shape), inside.reshape(shifted.shape)
                inside &= np.isfinite(values)[None, :]
                total += np.where(inside, np.minimum((values[None, :] - predicted) ** 2, TRUNCATE**2), 0.0).sum(1)
                count += inside.sum(1)
                frames |= inside
            n_frames = frames.sum(1)
            with np.errstate(invalid="ignore", divide="ignore"):
                out[start : start + block] = np.where((n_frames < need) | (count == 0), np.inf, total / count)
        return out
