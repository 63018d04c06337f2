"""Labelling one frame: from the user's digitised marker pixels, or proposed by fitting the
machine model to the frame's detections.

The proposal searches joint values starting from the calibration's (and a few swings and
boom/arm moves around them): each start alternates an optimal gated assignment of the
detections to the projected markers with a robust fit of the joint values, the gate
shrinking from coarse to tight (from 15 px down, with the image's shift from the model, the
median of what the fit leaves: a camera shaken or a little off its calibrated pose), and
each start again from the fine gates only (from 8 px: a start near the frame's joints, where
a coarse gate lets a marker that was not detected take a neighbour's disk and turn its link
to reach it); the refined start that labels the most detections within the tight gate (then
the lowest residual) wins.

Which markers the camera sees (`CameraModel.view`: facing it, not behind another link's
guessed box) is a prior, never a veto: the coarse gates match the markers it calls seen
(unless fewer than three are), the fine ones every marker inside the image, one the prior
calls hidden or turned away paying `_HIDDEN_SHARE` of the gate² (it loses a disk to a seen
one, and must lie nearer its disk to take it). A machine's guessed boxes are not its shape:
a tapered boom, a cab beyond the box or a plate turned from the box's face shows markers the
boxes hide.

Shapes: M markers, N detections, J joints.
"""

from __future__ import annotations

import logging

import numpy as np

from mocap.tracking.detect import Detections
from mocap.tracking.model import CameraModel, View
from mocap.tracking.tracker import FrameResult, assign

log = logging.getLogger(__name__)

_GATES_PX = (120.0, 60.0, 30.0, 15.0, 8.0, 4.0)
_SHIFT_GATE_PX = 15.0  # from this gate down, the image's shift from the model is fitted too
_FINE_START_PX = 8.0  # each start is also refined from this gate down only
_PRIOR_GATE_PX = 15.0  # from this gate down, the markers the prior calls hidden are matched too
_HIDDEN_SHARE = 0.25  # of a gate², the price of a pair for a marker the prior calls hidden


def starts_around(model: CameraModel, joints: np.ndarray, n_swing: int = 7, spread_deg: float = 25.0) -> np.ndarray:
    """Starting joint values (S, J): `joints` and variations of each joint by ±`spread_deg`
    (swing by a wider fan of `n_swing` values), clipped to the limits."""
    joints = np.asarray(joints, dtype=float)
    starts = [joints]
    spread = np.radians(spread_deg)
    for j in range(model.machine.n_joints):
        values = np.linspace(-3, 3, n_swing) * spread if j == 0 else np.array([-spread, spread])
        for v in values:
            if v == 0:
                continue
            s = joints.copy()
            s[j] += v
            starts.append(s)
    return model.machine.clip_to_limits(np.array(starts))


def propose_labels(
    model: CameraModel,
    detections: Detections,
    starts: np.ndarray,
    tight_px: float = 3.0,
    min_markers: int = 5,
) -> FrameResult | None:
    """Label detections by fitting the model from each of `starts` (S, J), all starts
    together; None when no start explains enough detections (`CameraModel.determined`)."""
    starts = np.array(np.atleast_2d(starts), dtype=float)
    n_markers = len(model.machine.marker_names)
    # from coarse gates down (a start far off), and from the fine ones alone (a start near the
    # frame's joints, where a coarse gate would let an undetected marker take another's disk)
    fine = tuple(g for g in _GATES_PX if g <= _FINE_START_PX)
    searches = [_search(model, detections, starts, gates + (tight_px,)) for gates in (_GATES_PX, fine)]
    joints, shift, alive = (np.concatenate(parts) for parts in zip(*searches))
    if not np.any(alive):
        return None
    view = model.view(joints)
    best, best_key = None, None
    for k in np.flatnonzero(alive):
        uv = view.uv[k] + shift[k]
        candidates, penalty = _prior(model, view, k, tight_px)
        markers, index = assign(uv, detections.xy, np.full(n_markers, tight_px), candidates, penalty=penalty)
        if len(markers) == 0:
            continue
        rms = float(np.sqrt(np.mean(np.sum((uv[markers] - detections.xy[index]) ** 2, axis=-1))))
        key = (len(markers), -rms)
        if best_key is None or key > best_key:
            best, best_key = FrameResult(markers, detections.select(index), joints[k], True, rms), key
    if best is None or not model.determined(best.markers, min_markers):
        return None
    best = _determined(model, _same_size(model, best))
    return best if model.determined(best.markers, min_markers) else None


def _search(model: CameraModel, detections: Detections, starts: np.ndarray, gates: tuple[float, ...]):
    """Each start (S, J) refined by assigning the detections within each of `gates` in turn
    and fitting the joints. Returns the joints (S, J), the image's shift from the model
    (S, 2) and which starts kept at least three markers (S,)."""
    joints = starts.copy()
    n_starts, n_markers = len(joints), len(model.machine.marker_names)
    alive = np.ones(n_starts, dtype=bool)
    shift = np.zeros((n_starts, 2))  # the image's from the model (the camera off its calibrated pose)
    for gate in gates:
        view = model.view(joints)
        observed = np.full((n_starts, n_markers, 2), np.nan)
        for k in np.flatnonzero(alive):
            candidates, penalty = _prior(model, view, k, gate)
            markers, index = assign(view.uv[k] + shift[k], detections.xy, np.full(n_markers, gate), candidates,
                                    penalty=penalty)
            alive[k] = len(markers) >= 3
            observed[k, markers] = detections.xy[index]
        if not np.any(alive):
            break
        fit = model.fit(observed[alive] - shift[alive, None], joints[alive], iterations=8, scale_px=max(gate / 4, 1.0))
        joints[alive] = fit.joints
        if gate <= _SHIFT_GATE_PX:  # what the joints leave, common to all the markers
            left = observed[alive] - shift[alive, None] - fit.uv
            seen = np.isfinite(left[..., 0])
            median = np.nanmedian(np.where(seen[..., None], left, np.nan), axis=1) if np.any(seen) else 0.0
            shift[alive] += np.where(np.sum(seen, axis=1)[:, None] >= 5, np.nan_to_num(median), 0.0)
    return joints, shift, alive


def _prior(model: CameraModel, view: View, k: int, gate: float) -> tuple[np.ndarray, np.ndarray | None]:
    """The markers start `k` of `view` may match within `gate` px (M,) bool, and the price
    (M,) px² of a pair for each (None: none): above `_PRIOR_GATE_PX` those the prior calls seen
    (all inside the image if fewer than three), from it down all inside the image, those the
    prior calls hidden at `_HIDDEN_SHARE` of gate²."""
    seen = view.visible[k]
    uv = view.uv[k]
    width, height = model.camera.size
    inside = (np.all(np.isfinite(uv), axis=-1) & (uv[:, 0] >= 0) & (uv[:, 0] <= width - 1) & (uv[:, 1] >= 0)
              & (uv[:, 1] <= height - 1) & np.isfinite(view.scale[k]))
    if gate > _PRIOR_GATE_PX and np.sum(seen) >= 3:
        return seen, None
    return inside | seen, np.where(seen, 0.0, _HIDDEN_SHARE * gate**2)


def _determined(model: CameraModel, result: FrameResult) -> FrameResult:
    """`result` without a marker that alone shows two or more joints (no other labelled
    marker moves with them): its two coordinates fix those joints with nothing to spare, so
    the fit puts it on any blob (a bucket marker on the other's disk, the arm and bucket
    turned to reach it); the tracker takes it back when the model can tell."""
    moves = model.machine.marker_moves  # (J, M)
    keep = np.ones(len(result.markers), dtype=bool)
    for k, m in enumerate(result.markers):
        others = np.delete(result.markers, k)
        keep[k] = np.sum(moves[:, m] & ~model.observed_joints(others)) < 2
    if np.all(keep):
        return result
    return FrameResult(result.markers[keep], result.detections.select(keep), result.joints, result.fitted, result.rms_px)


def _same_size(model: CameraModel, result: FrameResult, factor: float = 1.6) -> FrameResult:
    """`result` without the detections whose size disagrees with the others': the disks are
    painted alike, so each one's radius over the model's px per metre at its marker is about
    the same (a blob of the machine's own paint, ten times a disk's size, is no marker)."""
    scale = model.view(result.joints[None]).scale[0, result.markers]
    disk_m = result.detections.radius / scale
    typical = np.nanmedian(disk_m)
    keep = (disk_m < factor * typical) & (disk_m > typical / factor)
    if np.all(keep):
        return result
    return FrameResult(result.markers[keep], result.detections.select(keep), result.joints, result.fitted, result.rms_px)


def labels_from_pixels(
    model: CameraModel,
    detections: Detections,
    labelled: np.ndarray,
    start: np.ndarray,
    snap_px: float = 6.0,
    tight_px: float = 3.0,
) -> FrameResult:
    """Label a frame from digitised pixels `labelled` (M, 2) (NaN for markers not given):
    each is snapped to the nearest detection within `snap_px`, the model is fitted to
    them from `start` (J,) and every detection the fitted model explains is labelled."""
    given = np.all(np.isfinite(labelled), axis=-1)
    markers, index = assign(labelled, detections.xy, np.full(len(labelled), snap_px), given)
    observed = np.where(given[:, None], labelled, np.nan)
    observed[markers] = detections.xy[index]
    starts = starts_around(model, start)
    fitted, residual, _ = model.fit(np.broadcast_to(observed, (len(starts),) + observed.shape), starts, iterations=15)
    rms_of = np.sqrt(np.nanmean(residual**2, axis=1))
    best = int(np.nanargmin(rms_of))
    joints, rms = fitted[best], float(rms_of[best])
    # the markers not given: found by widening the model's reach, the given ones kept
    n_markers = len(labelled)
    for gate in (40.0, 20.0, 10.0, max(tight_px, 3 * rms)):
        uv = model.pixels(joints[None])[0]
        free = model.visible(joints[None])[0] & ~given
        taken = np.zeros(len(detections), dtype=bool)
        taken[index] = True
        extra, extra_index = assign(uv, np.where(taken[:, None], np.inf, detections.xy), np.full(n_markers, gate), free)
        combined = observed.copy()
        combined[extra] = detections.xy[extra_index]
        fitted, residual, _ = model.fit(combined[None], joints, iterations=8)
        joints, rms = fitted[0], float(np.sqrt(np.nanmean(residual**2)))
    markers = np.r_[markers, extra]
    index = np.r_[index, extra_index]
    order = np.argsort(markers)
    markers, index = markers[order], index[order]
    uv = model.pixels(joints[None])[0]
    rms = float(np.sqrt(np.mean(np.sum((uv[markers] - detections.xy[index]) ** 2, axis=-1)))) if len(markers) else np.nan
    return FrameResult(markers, detections.select(index), joints, True, rms)
