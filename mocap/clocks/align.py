"""Camera synchronisation from the motion itself.

Each camera alone, with the machine model, measures the joint values at its own frames
(the batched kinematic fit, one camera at a time): joint-value curves over each camera's
own clock. Camera k's frame f shows time ``f / fps_k + offset_k`` (DESIGN.md; the first
camera is the reference, offset 0). The curves are smoothed (a smoothing spline spanning
SMOOTH_S: the same symmetric kernel for every camera moves nothing in time) and laid on the
curves of the camera that fixes time best (the most joint motion per noise): a coarse
search over shifts of half a frame (the mean squared difference of the joint values, each
scaled by its spread, against the other curves interpolated at the shifted times), then a
sub-frame refinement in which each joint is weighted by its own scatter about the other
camera's curves and a difference beyond TRUNCATE_SD of it (a stretch of mirror solutions)
counts as a fixed penalty. The offsets are then expressed against camera 0's clock.
Different frame rates (29.97 and 30) are handled by the time axes themselves. The offsets
are refined further on the pixels (`mocap.clocks.pixels`).

Shapes: C cameras, F frames, M markers, J joints.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline, make_smoothing_spline
from scipy.optimize import minimize_scalar

from mocap.core.camera import Camera
from mocap.core.machine import Machine
from mocap.reconstruct.kinfit import FitOptions, fit_joints

log = logging.getLogger(__name__)

TRUNCATE = 0.3  # scaled joint-value difference beyond which a sample counts as an outlier
NOISY = 10.0  # a rigid pose parameter varying less than this many of its SDs is not aligned on
TRUNCATE_SD = 4.0  # a joint's difference beyond this many of its own scatter counts as an outlier
SMOOTH_S = 0.1  # s: the span of the smoothing of the joint-value curves and of the pixel tracks
_NOISE_FLOOR = 1e-5  # of a joint's spread: the least noise assumed (exact curves)


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
    """`offsets` (C,) s (camera 0's 0; NaN where not found), `residual` (C,) robust RMS of
    the scaled joint-value difference at the offset (`_Reference.scatter`), `overlap` (C,)
    samples compared, `reasons` (C,) why a camera's offset was not found ('' when it was),
    `reference` the camera the others' curves were laid on."""

    offsets: np.ndarray
    residual: np.ndarray
    overlap: np.ndarray
    reasons: tuple[str, ...]
    reference: int = 0

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
    max_residual : the largest RMS difference of the scaled (smoothed) joint values at the
        best offset for it to count as found (the motions agree).

    The curves are laid on those of the camera whose curves fix time best (the most joint
    motion per noise; `_Reference.information`), and the offsets then expressed against
    camera 0's clock; when camera 0 itself cannot be laid on that camera, on camera 0's.
    """
    fps = np.asarray(fps, dtype=float)
    if len(fps) != len(curves):
        raise ValueError(f"one frame rate per camera: {len(fps)} for {len(curves)} cameras")
    n = len(curves)
    built = [_Reference.build(c, fps[k]) for k, c in enumerate(curves)]
    if built[0] is None:
        reasons = ("the reference camera's joint values do not vary; nothing to align",) * n
        return SyncResult(np.full(n, np.nan), np.full(n, np.nan), np.zeros(n, dtype=int), reasons)
    best = int(np.argmax([-np.inf if b is None else b.information for b in built]))
    for r in dict.fromkeys((best, 0)):
        shifts, residual, overlap, reasons = _against(built[r], r, curves, fps, max_offset, min_overlap, max_residual)
        if not reasons[0]:
            break
    offsets = shifts - shifts[0]  # camera k's clock to r's, less camera 0's: to camera 0's
    for k in range(n):
        if not reasons[k]:
            log.info("camera %d: offset %.4f s (%.3f reference frames), residual %.3f", k, offsets[k],
                     offsets[k] * fps[0], residual[k])
    return SyncResult(np.where([not why for why in reasons], offsets, np.nan), residual, overlap, tuple(reasons), r)


def _against(reference: _Reference, r: int, curves: list[JointCurves], fps: np.ndarray, max_offset: float,
             min_overlap: float, max_residual: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Each camera's shift (s) onto camera r's clock (0 for r), residual, overlap, reason."""
    n = len(curves)
    shifts, residual, overlap = np.zeros(n), np.zeros(n), np.zeros(n, dtype=int)
    reasons = [""] * n
    overlap[r] = int(np.sum(np.any(np.isfinite(curves[r].joints), axis=1)))
    name = "the reference camera's" if r == 0 else f"camera {r}'s"
    for k in range(n):
        if k == r:
            continue
        ok = np.any(np.isfinite(curves[k].joints), axis=1)
        if ok.sum() < 4:
            shifts[k], residual[k], reasons[k] = np.nan, np.nan, "fewer than 4 frames with a model fit"
            continue
        time = curves[k].frames[ok] / fps[k]
        values = curves[k].joints[ok]
        smooth = _smoothed(time, values)
        need = max(4, int(min_overlap * ok.sum()))
        step = 0.5 / fps[r]
        grid = np.arange(-max_offset, max_offset + step / 2, step)
        stride = max(1, len(time) // _COARSE_SAMPLES)  # the coarse search on a long session's every stride-th sample
        costs = reference.costs(time[::stride], grid, smooth[::stride], max(4, need // stride))
        if not np.any(np.isfinite(costs)):
            shifts[k], residual[k], reasons[k] = np.nan, np.nan, "the recordings do not overlap within the search range"
            continue
        coarse = float(grid[np.argmin(costs)])
        shifts[k] = reference.refine(time, values, coarse, 2 * step, need)
        residual[k], overlap[k] = reference.scatter(time + shifts[k], smooth)
        if not residual[k] <= max_residual:
            reasons[k] = (
                f"no offset within ±{max_offset:g} s makes the motions agree with {name} "
                f"(residual {residual[k]:.2f} of the joints' spread at the best)"
            )
            shifts[k] = np.nan
    return shifts, residual, overlap, reasons


def _noise_sd(time: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(J,) each joint's noise SD from the second differences of its values (F, J) at
    `time` (F,) over evenly spaced samples (a robust scale: a stretch of wrong fits does not
    set it); NaN where fewer than 8 such samples."""
    spacing = np.diff(time)
    even = np.r_[False, np.abs(spacing[1:] - spacing[:-1]) < 1e-3 * spacing[1:], False]  # (F,)
    second = values[2:] - 2 * values[1:-1] + values[:-2]  # (F-2, J)
    second = np.where(even[1:-1, None], second, np.nan)
    out = np.full(values.shape[1], np.nan)
    for j in range(values.shape[1]):
        d = second[:, j][np.isfinite(second[:, j])]
        if len(d) >= 8:
            out[j] = 1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(6.0)
    return out


def _smoothed(time: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Values (F, J) at `time` (F,) with each joint's noise smoothed away where it has 8 valid
    samples or more: a smoothing spline whose equivalent kernel spans SMOOTH_S (a symmetric
    kernel moves no feature in time, and every camera's curves get the same)."""
    out = values.copy()
    for j in range(values.shape[1]):
        ok = np.isfinite(values[:, j])
        if ok.sum() >= 8 and np.ptp(values[ok, j]) > 0:
            rate = (ok.sum() - 1) / np.ptp(time[ok])  # samples per second
            out[ok, j] = make_smoothing_spline(time[ok], values[ok, j], lam=rate * SMOOTH_S**4)(time[ok])
    return out


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
    """A camera's joint-value curves, smoothed, each scaled by its spread, to lay the
    others' on."""

    curves: tuple[_Curve | None, ...]  # (J,), None for a joint that does not vary
    scale: np.ndarray  # (J,)
    gap: float  # s: interpolation across a longer gap is not trusted
    information: float  # s^-2: the Fisher information of a shift of time in these curves

    @classmethod
    def build(cls, joints: JointCurves, fps: float) -> _Reference | None:
        counted = np.isfinite(joints.joints).sum(axis=0) >= 2  # (J,) joints seen twice or more
        spread = np.zeros(joints.joints.shape[1])
        spread[counted] = np.nanstd(joints.joints[:, counted], axis=0)
        if spread.max(initial=0.0) < 1e-6:
            return None
        ok = np.any(np.isfinite(joints.joints), axis=1)
        time = joints.frames[ok] / fps
        noise = _noise_sd(time, joints.joints[ok]) / np.where(spread > 0, spread, 1.0)
        smooth = _smoothed(time, joints.joints[ok])
        curves, information = [], 0.0
        for j in range(joints.joints.shape[1]):
            valid = np.isfinite(smooth[:, j])
            if valid.sum() < 4 or spread[j] <= 1e-3 * spread.max():
                curves.append(None)
                continue
            values = smooth[valid, j] / spread[j]
            spline = CubicSpline(time[valid], values)
            curves.append(_Curve(time[valid], values, spline))
            if np.isfinite(noise[j]):
                information += float(np.sum(spline(time[valid], 1) ** 2)) / max(noise[j], _NOISE_FLOOR) ** 2
        if all(c is None for c in curves):
            return None
        return cls(tuple(curves), np.where(spread > 0, spread, 1.0), 1.5 / fps, information)

    def refine(self, time: np.ndarray, joints: np.ndarray, coarse: float, width: float, need: int) -> float:
        """The shift within `width` of `coarse` (s) that lays `joints` (N, J) at `time` (N,)
        best on these curves: each joint's squared difference weighted by its own scatter
        about the curves at `coarse` (a robust scale: noise and the single-camera fit's
        errors alike), truncated at TRUNCATE_SD of it (a stretch of mirror solutions)."""
        weights = np.zeros(len(self.curves))
        for j, curve in enumerate(self.curves):
            if curve is None:
                continue
            predicted, inside = curve.at(time + coarse, self.gap, False)
            difference = joints[:, j] / self.scale[j] - predicted
            inside &= np.isfinite(difference)
            if inside.sum() >= 4:
                d = difference[inside]
                sd = 1.4826 * np.median(np.abs(d - np.median(d)))
                weights[j] = 1.0 / max(sd, _NOISE_FLOOR) ** 2
        if not np.any(weights > 0):
            return coarse
        fine = minimize_scalar(
            lambda o: self.cost(time + o, joints, need, weights=weights, truncate=TRUNCATE_SD)[0],
            bounds=(coarse - width, coarse + width), method="bounded", options={"xatol": 1e-5 * width},
        )
        return float(fine.x)

    def scatter(self, time: np.ndarray, joints: np.ndarray) -> tuple[float, int]:
        """A robust RMS of the scaled `joints` (N, J) at `time` (N,) about these curves (1.4826
        times the median absolute difference: a stretch of mirror solutions, under half of
        the samples, does not set it) and the frames compared; inf when none."""
        differences, frames = [], np.zeros(len(time), dtype=bool)
        for j, curve in enumerate(self.curves):
            if curve is None:
                continue
            predicted, inside = curve.at(time, self.gap, False)
            inside &= np.isfinite(joints[:, j])
            differences.append(joints[inside, j] / self.scale[j] - predicted[inside])
            frames |= inside
        d = np.concatenate(differences) if differences else np.zeros(0)
        return (1.4826 * float(np.median(np.abs(d))) if len(d) else np.inf), int(frames.sum())

    def cost(self, time: np.ndarray, joints: np.ndarray, need: int, linear: bool = False,
             weights: np.ndarray | None = None, truncate: float = TRUNCATE) -> tuple[float, int]:
        """Mean squared difference of the scaled `joints` (N, J) at `time` (N,) from the
        reference curves, over samples inside the reference recording and not in a gap
        (NaN joints skipped), each joint's times its `weights` (J,) (default 1), each sample's
        truncated at `truncate` squared; inf if fewer than `need` samples compare."""
        total, count, frames = 0.0, 0, np.zeros(len(time), dtype=bool)
        for j, curve in enumerate(self.curves):
            if curve is None:
                continue
            values = joints[:, j] / self.scale[j]
            predicted, inside = curve.at(time, self.gap, linear)
            inside &= np.isfinite(values)
            # truncated at TRUNCATE: a single camera's fit can land on a mirror solution
            # (swing seen side-on) for a stretch of frames; those count as a fixed penalty
            w = 1.0 if weights is None else weights[j]
            if w <= 0:
                continue
            total += float(np.sum(np.minimum(w * (values[inside] - predicted[inside]) ** 2, truncate**2)))
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
