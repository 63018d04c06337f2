"""Model-guided labelled tracking of disk markers through one camera's video.

Each frame: predict the joint values from the last two (constant velocity), project the
markers, refine a disk from each predicted marker with its last image ellipse (and, for markers not
found so, look for disks in a window around the prediction), assign detections
to markers (gated, optimal: `scipy.optimize.linear_sum_assignment` on squared distances),
fit the joint values to the assigned pixels (robust Gauss-Newton), drop assignments the fit
disowns, then assign again against the fitted projection with a tight gate: a marker that
comes back after an occlusion is picked up there. A blob is labelled only if it passes the
disk tests and lies where the model puts a marker. When too few markers are found the
joints coast on the prediction with widening windows; after a longer loss the whole frame
is searched again (`propose.propose_labels`).

Shapes: M markers, N detections, J joints.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import linear_sum_assignment

from mocap.detect import DetectOptions, Detections, concatenate, find_candidates, refine_and_accept, unique
from mocap.tracking.model import CameraModel

log = logging.getLogger(__name__)

_INFEASIBLE = 1e12


@dataclass(frozen=True)
class TrackOptions:
    """Tracking settings (pixels unless stated).

    gate_px: least search radius around a prediction; gate_radii: search radius in marker
    radii; tight_px: least gate of the final assignment against the fitted model;
    outlier_px: least residual at which the fit disowns a detection; regain_px_per_frame,
    regain_max_px: how far the search for a marker not seen for a while reaches, growing
    with the frames it was missed; min_markers: markers needed to fit the joints;
    lost_frames: frames without a fit before the whole frame is searched again; occlusion:
    predict markers hidden by the machine's links (boxes).
    """

    gate_px: float = 10.0
    gate_radii: float = 2.0
    tight_px: float = 2.5
    outlier_px: float = 3.0
    regain_px_per_frame: float = 3.0
    regain_max_px: float = 60.0
    min_markers: int = 5
    lost_frames: int = 15
    occlusion: bool = True
    detect: DetectOptions = field(default_factory=DetectOptions)

    def __post_init__(self) -> None:
        if not (self.gate_px > 0 and self.tight_px > 0 and self.outlier_px > 0):
            raise ValueError("gate_px, tight_px and outlier_px must be positive")
        if self.min_markers < 1 or self.lost_frames < 1:
            raise ValueError("min_markers and lost_frames must be >= 1")


@dataclass(frozen=True)
class FrameResult:
    """One frame's labels: `markers` (K,) model marker indices, `detections` (K) their
    detections, `joints` (J,) the fitted joint values (the prediction when `fitted` is False),
    `rms_px` the fit's residual RMS."""

    markers: np.ndarray
    detections: Detections
    joints: np.ndarray
    fitted: bool
    rms_px: float


@dataclass
class TrackState:
    """What the tracker carries between frames (mutable: one per tracker)."""

    joints: np.ndarray  # (J,) at the last frame
    previous: np.ndarray  # (J,) at the frame before
    shape: np.ndarray  # (M, 2, 2) each marker's last image ellipse (semi-axis matrix, px²)
    missed: np.ndarray  # (M,) int, frames since each marker was last labelled
    visible: np.ndarray  # (M,) bool, the markers the model showed in the last frame
    unseen: np.ndarray  # (J,) int, frames since a labelled marker last showed each joint
    lost: int = 0  # frames since the last fit

    @property
    def radius(self) -> np.ndarray:
        """(M,) expected marker radii: the geometric mean of the semi-axes (px)."""
        return np.sqrt(np.sqrt(np.maximum(np.linalg.det(self.shape), 1e-12)))


class Tracker:
    """Labelled tracking for one camera; `step(gray)` per frame, in order."""

    def __init__(self, model: CameraModel, start: FrameResult, options: TrackOptions | None = None):
        self.model = model
        self.options = options or TrackOptions()
        n_markers = len(model.machine.marker_names)
        typical = np.median(start.detections.radius) if len(start.detections) else 5.0
        shape = np.tile(np.eye(2) * typical**2, (n_markers, 1, 1))
        shape[start.markers] = start.detections.shape
        missed = np.full(n_markers, 1000)
        missed[start.markers] = 0
        unseen = np.where(model.observed_joints(start.markers), 0, 1000)
        self.state = TrackState(start.joints.copy(), start.joints.copy(), shape, missed, self._visible(start.joints), unseen)

    def step(self, gray: np.ndarray) -> FrameResult:
        options, state, model = self.options, self.state, self.model
        velocity = state.joints - state.previous if state.lost == 0 else 0.0
        predicted = model.machine.clip_to_limits(state.joints + velocity)
        uv = model.pixels(predicted[None])[0]
        visible = state.visible = self._visible(predicted)
        motion = np.linalg.norm(uv - model.pixels(state.joints[None])[0], axis=-1)
        widen = 1.0 + min(state.lost, 10)
        gate = widen * np.maximum(options.gate_px, options.gate_radii * state.radius) + np.nan_to_num(motion)
        recent = state.missed <= 2
        if np.sum(recent & visible) < options.min_markers:  # after a loss: every marker at once
            recent = np.ones_like(recent)
        reach = np.where(recent, gate, gate + np.minimum(options.regain_px_per_frame * state.missed, options.regain_max_px))
        found = self._search(gray, uv, reach, visible)
        # the markers followed until now fix the joints they observe
        markers, index = assign(uv, found.xy, gate, visible & recent, found.radius, state.radius)
        if len(markers) < options.min_markers:
            return self._coast(predicted, uv, visible, found)
        observed = np.full(uv.shape, np.nan)
        observed[markers] = found.xy[index]
        joints, residual = model.fit(observed[None], predicted, iterations=2)
        keep = residual[0, markers] <= np.maximum(options.outlier_px, 0.5 * state.radius[markers])
        if np.sum(keep) < options.min_markers:
            return self._coast(predicted, uv, visible, found)
        if not np.all(keep):
            observed[markers[~keep]] = np.nan
            joints, residual = model.fit(observed[None], joints[0], iterations=1)
        joints = joints[0]
        # markers coming back (after an occlusion, or a link the camera did not see): found
        # by narrowing gates from their reach, the others held
        returning = visible & ~recent  # visibility at the prediction serves the frame
        if np.any(returning):
            taken = np.zeros(len(found), dtype=bool)
            taken[index[keep]] = True
            held = markers[keep]
            for g in (1.0, 0.5, 0.25):
                back_uv = model.pixels(joints[None])[0]
                free = np.where(taken[:, None], np.inf, found.xy)
                back, back_index = assign(back_uv, free, np.maximum(g * reach, options.tight_px), returning, found.radius, state.radius)
                keep_back = model.supported(back, held)
                back, back_index = back[keep_back], back_index[keep_back]
                if len(back) == 0:
                    break
                trial = observed.copy()
                trial[back] = found.xy[back_index]
                moved, moved_residual = model.fit(trial[None], joints, iterations=2)
                if np.nanmax(moved_residual[0, held]) > options.outlier_px:
                    break  # the returning candidates disagree with the markers held
                joints = moved[0]
        fitted_uv = model.pixels(joints[None])[0]
        residual = np.linalg.norm(fitted_uv[markers[keep]] - found.xy[index[keep]], axis=-1)
        inlier_rms = float(np.sqrt(np.mean(residual**2))) if len(residual) else 0.0
        tight = np.full(len(uv), max(options.tight_px, 3.0 * inlier_rms))
        markers, index = assign(fitted_uv, found.xy, tight, visible, found.radius, state.radius)
        if len(markers) < options.min_markers:
            return self._coast(predicted, uv, visible, found)
        observed = np.full(uv.shape, np.nan)
        observed[markers] = found.xy[index]
        joints, residual = model.fit(observed[None], joints, iterations=1)
        joints = joints[0]
        seen_joints = model.observed_joints(markers)
        # a joint no marker shows keeps its value: it does not drift on its last velocity
        state.previous = np.where(seen_joints, state.joints, joints)
        state.unseen = np.where(seen_joints, 0, state.unseen + 1)
        state.joints, state.lost = joints, 0
        state.shape[markers] = found.shape[index]
        state.missed += 1
        state.missed[markers] = 0
        rms = float(np.sqrt(np.nanmean(residual[0] ** 2)))
        return FrameResult(markers, found.select(index), joints, True, rms)

    @property
    def lost(self) -> int:
        return self.state.lost

    def needs_search(self) -> bool:
        """Whether a full-frame search could help: two or more markers the model shows have
        not been labelled for `lost_frames` frames, or a joint has not been seen that long
        (its link may have come back far from where it was left, or out of the model's view)."""
        stale = self.state.visible & (self.state.missed >= self.options.lost_frames)
        return bool(np.sum(stale) >= 2 or np.any(self.state.unseen >= self.options.lost_frames))

    def restart(self, start: FrameResult) -> None:
        """Carry on from a fresh labelling of the current frame (after a loss)."""
        self.state.joints = start.joints.copy()
        self.state.previous = start.joints.copy()
        self.state.lost = 0
        self.state.missed[start.markers] = 0
        self.state.unseen[self.model.observed_joints(start.markers)] = 0
        self.state.shape[start.markers] = start.detections.shape

    def _visible(self, joints: np.ndarray) -> np.ndarray:
        if self.options.occlusion:
            return self.model.visible(joints[None])[0]
        uv = self.model.pixels(joints[None])[0]
        w, h = self.model.camera.size
        return np.all(np.isfinite(uv), axis=-1) & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)

    def _coast(self, predicted: np.ndarray, uv: np.ndarray, visible: np.ndarray, found: Detections) -> FrameResult:
        """Too few markers to fit: the joints carry on as predicted; detections within the
        tight gate of a predicted marker are still labelled."""
        state = self.state
        markers, index = assign(uv, found.xy, np.full(len(uv), self.options.tight_px), visible, found.radius, state.radius)
        state.previous, state.joints = state.joints, predicted
        state.lost += 1
        state.missed += 1
        state.missed[markers] = 0
        state.unseen += 1
        return FrameResult(markers, found.select(index), predicted, False, float("nan"))

    def _search(self, gray: np.ndarray, uv: np.ndarray, gate: np.ndarray, visible: np.ndarray) -> Detections:
        """Disks near the predicted markers: refined from each prediction with the marker's
        last ellipse; for markers not found so, searched in a window (gate) around the
        prediction. Duplicates merged."""
        seeds = np.nonzero(visible)[0]
        found = refine_and_accept(gray, uv[seeds], self.state.shape[seeds], self.options.detect)
        near = np.linalg.norm(found.xy[None] - uv[seeds, None], axis=-1) if len(found) else np.zeros((len(seeds), 0))
        close = 0.5 * np.maximum(self.state.radius[seeds], 2.0)
        missing = seeds[~np.any(near < close[:, None] + self.options.tight_px, axis=1)]
        missed = self.state.missed[missing]
        missing = missing[(missed <= 3) | (missed % 4 == 0)]  # long-missed: every 4th frame
        if len(missing) == 0:
            return found
        height, width = gray.shape
        xys, shapes = [], []
        for m in missing:
            r = self.state.radius[m]
            half = gate[m] + 2.6 * r + 3
            x0, y0 = int(max(uv[m, 0] - half, 0)), int(max(uv[m, 1] - half, 0))
            x1, y1 = int(min(uv[m, 0] + half + 1, width)), int(min(uv[m, 1] + half + 1, height))
            if x1 - x0 < 3 or y1 - y0 < 3:
                continue
            block = int(2 * np.ceil(3.0 * r) + 1)
            options = replace(self.options.detect, block=max(block, 7))
            xy, shape = find_candidates(gray[y0:y1, x0:x1], options, (x0, y0))
            size = np.sqrt(np.abs(np.linalg.det(shape))) ** 0.5 if len(xy) else np.zeros(0)
            near = (np.linalg.norm(xy - uv[m], axis=1) <= gate[m] + r) & (size > 0.4 * r) & (size < 2.5 * r)
            xys.append(xy[near])
            shapes.append(shape[near])
        if not xys:
            return found
        xy, shape = np.concatenate(xys), np.concatenate(shapes)
        _, first = np.unique(np.round(xy * 4), axis=0, return_index=True)
        extra = refine_and_accept(gray, xy[first], shape[first], self.options.detect)
        return unique(concatenate([found, extra]))


def assign(
    predicted: np.ndarray,
    detected: np.ndarray,
    gate: np.ndarray,
    visible: np.ndarray,
    detected_radius: np.ndarray | None = None,
    expected_radius: np.ndarray | None = None,
    size_ratio: float = 1.33,
) -> tuple[np.ndarray, np.ndarray]:
    """Optimal one-to-one assignment of detections to predicted markers.

    predicted (M, 2), detected (N, 2), gate (M,) px, visible (M,) bool; with the radii (N,)
    and (M,), pairs whose radii differ by more than `size_ratio` are not allowed.
    Returns marker indices (K,) and detection indices (K,) of the gated pairs.
    """
    if len(detected) == 0 or not np.any(visible):
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    cost = np.sum((predicted[:, None] - detected[None]) ** 2, axis=-1)
    allowed = visible[:, None] & (cost <= gate[:, None] ** 2) & np.isfinite(cost)
    if detected_radius is not None and expected_radius is not None:
        ratio = detected_radius[None] / np.maximum(expected_radius[:, None], 1e-6)
        allowed &= (ratio > 1.0 / size_ratio) & (ratio < size_ratio)
    rows = np.nonzero(np.any(allowed, axis=1))[0]
    cols = np.nonzero(np.any(allowed, axis=0))[0]
    if len(rows) == 0:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    sub = np.where(allowed[np.ix_(rows, cols)], cost[np.ix_(rows, cols)], _INFEASIBLE)
    r, c = linear_sum_assignment(sub)
    ok = sub[r, c] < _INFEASIBLE
    return rows[r[ok]], cols[c[ok]]
