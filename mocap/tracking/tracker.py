"""Model-guided labelled tracking of disk markers through one camera's video.

Each frame: predict the joint values from the last two (constant velocity), project the
markers, refine a disk from each predicted marker with its last image ellipse (and, for markers not
found so, look for disks in a window around the prediction), assign detections
to markers (gated, optimal: `scipy.optimize.linear_sum_assignment` on squared distances),
fit the joint values to the assigned pixels (robust Gauss-Newton), drop assignments the fit
disowns, refine a disk again from where the fit puts each marker no disk was found near (the
prediction of a swing speeding up is a pixel or two off), then assign again against the
fitted projection with a tight gate: a marker that comes back after an occlusion is picked
up there. A joint no labelled marker has shown for a few frames is swept over its range
(`Tracker._sweep`), and one seen again moves on at its mean velocity since it was last seen.
A blob is labelled only if it passes the
disk tests and lies where the model puts a marker. When too few markers are found the
joints coast on the prediction with widening windows; after a longer loss the whole frame
is searched again (`propose.propose_labels`).

Shapes: M markers, N detections, J joints.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment

from mocap.tracking.detect import (DetectOptions, Detections, accept, accepted, concatenate, find_candidates,
                          refine, length, refine_and_accept, refine_converged, refine_sourced, unique)
from mocap.tracking.model import CameraModel, View

log = logging.getLogger(__name__)

_INFEASIBLE = 1e12
_SWEEP_EVERY = 4  # frames between sweeps of an unseen joint's range (`Tracker._sweep`)
_SWEEP_SLOW = 60  # ... and 4 times as many after this many frames unseen
_SWEEP_MARKERS = 2  # markers a swept step must show
_SWEEP_CONTRAST = 0.25  # share of `DetectOptions.min_contrast` a marker's box contrast must reach
_SWEEP_CHECKED = 4  # the best steps whose markers are refined
_NEVER = 1000  # frames since a joint was last swept, for one never swept
_SLIVER_PX = 2.0  # px: an ellipse whose minor semi-axis reads under this is at blur's and the pixel grid's floor
# (a disk turned nearly edge on: its true width unknown, its faint ends lost, its ring past its square)


@dataclass(frozen=True)
class TrackOptions:
    """Tracking settings (pixels unless stated).

    gate_px: least search radius around a prediction; gate_radii: search radius in marker
    radii; tight_px: least gate of the final assignment against the fitted model;
    outlier_px: least residual at which the fit disowns a detection; regain_px_per_frame,
    regain_max_px: how far the search for a marker not seen for a while reaches, growing
    with the frames it was missed; min_markers: markers enough to fit the joints (fewer
    if they fix the joints they show with coordinates to spare: `CameraModel.determined`);
    lost_frames: frames without a fit before the whole frame is searched again;
    near_contrast: where the model puts a marker, the share of `detect.min_contrast` a disk
    needs (a full-frame search holds to `detect`), and where the boxes hide a marker not
    followed lately, the share of the median contrast of the disks of the markers shown
    (`Tracker._take_hidden`); near_ring_spread: the factor on
    `detect.max_ring_spread` a disk refined from a small window there may reach, if it
    stays put (`Tracker._refine_again`); agree_rms, agree_px: a disk whose centre lies within
    `agree_rms` times the fit's inlier residual RMS (at least `agree_px`) of where the fitted
    model puts a marker is that marker whatever its size and ring say (`Tracker._agreeing`);
    occlusion:
    predict markers hidden by the machine's links (boxes); perspective: move each labelled
    centre from its image ellipse's centre to the image of the disk's centre, by the
    fitted model (`CameraModel.centre_offsets`).
    """

    gate_px: float = 10.0
    gate_radii: float = 2.0
    tight_px: float = 2.5
    outlier_px: float = 3.0
    regain_px_per_frame: float = 3.0
    regain_max_px: float = 60.0
    min_markers: int = 5
    lost_frames: int = 15
    near_contrast: float = 0.5
    near_ring_spread: float = 1.25
    agree_rms: float = 3.0
    agree_px: float = 0.5
    occlusion: bool = True
    perspective: bool = True
    detect: DetectOptions = field(default_factory=DetectOptions)

    def __post_init__(self) -> None:
        if not (self.gate_px > 0 and self.tight_px > 0 and self.outlier_px > 0):
            raise ValueError("gate_px, tight_px and outlier_px must be positive")
        if self.min_markers < 1 or self.lost_frames < 1:
            raise ValueError("min_markers and lost_frames must be >= 1")
        if not (self.agree_rms >= 0 and self.agree_px >= 0):
            raise ValueError("agree_rms and agree_px must be >= 0")


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
    uv: np.ndarray  # (M, 2) the markers' pixels at the last frame's joints
    shape: np.ndarray  # (M, 2, 2) each marker's last image ellipse (semi-axis matrix, px²)
    missed: np.ndarray  # (M,) int, frames since each marker was last labelled
    visible: np.ndarray  # (M,) bool, the markers the model showed in the last frame
    unseen: np.ndarray  # (J,) int, frames since a labelled marker last showed each joint
    disk_m: float  # the disks' radius (m), estimated from the labelled ellipses
    lost: int = 0  # frames since the last fit
    anchor: np.ndarray | None = None  # (J,) the joints of the last frame fitted after a fitted one
    shift: np.ndarray = field(default_factory=lambda: np.zeros(2))  # (2,) px, the image's from the model
    swept: np.ndarray | None = None  # (J,) int, frames since each joint's range was last swept (`Tracker._sweep`)
    thin: int = 0  # frames since the last fit of `TrackOptions.min_markers` markers or more

    def __post_init__(self) -> None:
        if self.swept is None:  # never swept: at once when due
            self.swept = np.full(len(self.joints), _NEVER)

    @property
    def radius(self) -> np.ndarray:
        """(M,) the markers' last radii: the geometric mean of the semi-axes (px)."""
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
        view = model.view(start.joints[None])
        visible = self._visible(view)
        self.state = TrackState(start.joints.copy(), start.joints.copy(), view.uv[0], shape, missed, visible, unseen,
                                np.nan, anchor=start.joints.copy())
        self._update_disk(view.scale[0], start.markers, start.detections.radius)

    def step(self, gray: np.ndarray) -> FrameResult:
        options, state, model = self.options, self.state, self.model
        velocity = state.joints - state.previous if state.lost == 0 else 0.0
        predicted = model.machine.clip_to_limits(state.joints + velocity)
        if state.lost == 0:
            predicted = self._sweep(gray, predicted)
        view = model.view(predicted[None])
        uv = view.uv[0]
        recent = state.missed <= 2
        visible = state.visible = self._visible(view)
        expected = self._expected_radius(view.scale[0])
        motion = np.nan_to_num(length(uv - state.uv))
        widen = 1.0 + min(state.lost, 10)
        gate = widen * np.maximum(options.gate_px, options.gate_radii * expected) + motion
        if not model.determined(np.flatnonzero(recent & visible), options.min_markers):
            recent = np.ones_like(recent)  # after a loss: every marker at once
        reach = np.where(recent, gate, gate + np.minimum(options.regain_px_per_frame * state.missed, options.regain_max_px))
        seen = self._search(gray, uv + state.shift, reach, visible, expected, recent)
        found = replace(seen, xy=seen.xy - state.shift)  # in the model's pixels: the last frame's shake out
        # the markers followed until now fix the joints they observe
        markers, index = assign(uv, found.xy, gate, visible & recent, found.radius, expected)
        if not model.determined(markers, options.min_markers):
            return self._coast(predicted, uv, visible, seen, expected)
        observed = np.full(uv.shape, np.nan)
        observed[markers] = found.xy[index]
        fit = model.fit(observed[None], predicted, iterations=1)
        joints, fitted_uv = fit.joints[0], fit.uv[0]
        # the camera's shake: what the joints leave, the median over the markers followed,
        # is the image's shift from the model; taken out before the joints are fitted again
        # (the frame's own until its fit is kept: a fit refused leaves the last one's)
        shift = state.shift + np.median(found.xy[index] - fitted_uv[markers], axis=0)
        found = replace(seen, xy=seen.xy - shift)
        observed[markers] = found.xy[index]
        # ... the joints again from the prediction: the first fit took part of the shake for a
        # turn of the links (the base's markers, fixed in the world, moved by the shake), and the
        # markers of the links it turned would be disowned against it
        fit = model.fit(observed[None], predicted, iterations=1)
        joints, fitted_uv = fit.joints[0], fit.uv[0]
        residual = length(observed[markers] - fitted_uv[markers])
        keep = residual <= np.maximum(options.outlier_px, 0.5 * expected[markers])
        if not model.determined(markers[keep], options.min_markers):
            return self._coast(predicted, uv, visible, seen, expected)
        observed[markers[~keep]] = np.nan
        refit = model.fit(observed[None], joints, iterations=1)
        joints, fitted_uv = refit.joints[0], refit.uv[0]
        held, held_index = markers[keep], index[keep]
        # markers coming back (after an occlusion, or a link the camera did not see, or
        # where the single camera fixes the joints poorly): found by gates narrowing from
        # their reach, kept only while the held markers agree; markers on links whose
        # joints the held markers show may also be picked up by the final assignment
        known = model.known_markers(held)
        returning = visible & ~recent
        if returning.any():
            joints, known, moved_uv = self._regain(found, observed, joints, held, held_index, returning, reach, expected,
                                                   known)
            fitted_uv = fitted_uv if moved_uv is None else moved_uv
        residual = length(fitted_uv[held] - found.xy[held_index])
        inlier_rms = float(np.sqrt(np.mean(residual**2)))
        tight = np.full(len(uv), max(options.tight_px, 3.0 * inlier_rms))
        agree = max(options.agree_rms * inlier_rms, options.agree_px)
        # the fitted joints put the markers nearer their disks than the prediction did (a
        # swing speeding up leaves it 1-2 px off, farther than a small or oblique disk's
        # refinement converges from): those the model now knows and no disk was found near
        # are refined again from where the fit puts them
        # ... and so are those the guessed shapes call hidden or turned away (the model's
        # visibility is a prior, not a veto): a clear disk (the full-frame detection's contrast)
        # where the fitted model puts one, within the tight gate, labels it
        prior_hidden = disks_in_view(model, view, occlusion=False) & ~visible & known
        again = (visible | prior_hidden) & known & ~_near_any(fitted_uv, found.xy, tight)
        if again.any():
            extra = self._search_fitted(gray, fitted_uv + shift, np.flatnonzero(again), expected, agree, visible)
            extra = extra.select(~_near_any(extra.xy, seen.xy, 0.5 * np.maximum(extra.radius, 1.0)))
            if len(extra):
                seen = concatenate([seen, extra])
                found = replace(seen, xy=seen.xy - shift)
        # a marker not followed lately: the size its guessed normal gives may be far off (a
        # plate turned from the box's face); its ellipse's major semi-axis is the disk's radius
        # at its depth however it is turned
        # ... and a disk where the fit puts a marker, within the fit's own noise, is that marker
        # whatever its size: the fit of the other markers vouches for it (an oblique disk's
        # image a sliver under two pixels wide loses its faint ends to blur and the pixel grid,
        # and its major semi-axis reads well under the face-on radius); only a disk larger than
        # the marker's can be at its depth is refused
        followed = state.missed <= 2
        face_on = self._face_on_radius(joints)
        agreeing = self._agreeing(fitted_uv, found, agree, face_on)
        sized = np.where(followed[:, None], _same_size(found.radius[None], expected[:, None]),
                         _same_size(found.axes[None, :, 0], face_on[:, None])) | agreeing
        markers, index = assign(fitted_uv, found.xy, tight, visible & known, allowed=sized)
        if not model.determined(markers, options.min_markers):
            return self._coast(predicted, uv, visible, seen, expected)
        if prior_hidden.any():
            # the contrast a hidden marker not followed lately needs, learned from the disks of
            # the markers shown (the same paint in the same light): a solid's shade or a hose at
            # a hidden marker's place is a third or less of theirs
            least = max(options.detect.min_contrast, options.near_contrast * float(np.median(found.contrast[index])))
            seen = self._converge_faint(gray, seen, found, fitted_uv, tight, prior_hidden, least)
            found = replace(seen, xy=seen.xy - shift)
            markers, index = self._take_hidden(fitted_uv, found, tight, prior_hidden, visible & known, markers, index,
                                               face_on, agreeing, least)
        # two markers' disks cannot lie one inside the other: a detection centred inside a
        # larger labelled one's ellipse is a part of that disk (a marker on the machine's far
        # side, projected onto a near marker's disk, took a piece of it)
        inside = ~_inside_larger(found.select(index))
        markers, index = markers[inside], index[inside]
        final = np.full(uv.shape, np.nan)
        final[markers] = found.xy[index]
        if not np.array_equal(np.isfinite(final), np.isfinite(observed)) or not np.allclose(final, observed, equal_nan=True):
            refit = model.fit(final[None], joints, iterations=1)
            joints, fitted_uv, residual = refit.joints[0], refit.uv[0], refit.residual
            rms = float(np.sqrt(np.nanmean(residual[0] ** 2)))
        else:
            rms = inlier_rms
        seen_joints = model.observed_joints(markers)
        # a joint no marker shows keeps its value: it does not drift on its last velocity; one
        # that markers show again after n frames unseen moves on at its mean velocity since it
        # was last seen, 1 / (n + 1) of its change (the value it held, where it was left or a
        # proposal's guess, is no position of the frame before)
        catch_up = (joints - state.joints) / (state.unseen + 1)
        state.previous = np.where(seen_joints, joints - catch_up, joints)
        state.unseen = np.where(seen_joints, 0, state.unseen + 1)
        if state.lost == 0:  # a fit right after a loss may have turned links no marker shows yet
            state.anchor = joints
        state.joints, state.lost, state.shift = joints, 0, shift
        state.thin = 0 if len(markers) >= options.min_markers else state.thin + 1
        state.uv = fitted_uv
        state.shape[markers] = found.shape[index]
        state.missed += 1
        state.missed[markers] = 0
        self._update_disk(view.scale[0], markers, found.radius[index])
        labelled = seen.select(index)
        if options.perspective and np.isfinite(state.disk_m):
            offset = np.nan_to_num(model.centre_offsets(joints[None], state.disk_m)[0, markers])
            # the shift is a small share of a disk's radius; a larger one comes from joints not yet
            # fitted well (just after the machine was found again) and is not applied
            plausible = length(offset) <= 0.2 * labelled.radius
            labelled = replace(labelled, xy=labelled.xy + offset * plausible[:, None])
        return FrameResult(markers, labelled, joints, True, rms)

    @property
    def lost(self) -> int:
        return self.state.lost

    def needs_search(self) -> bool:
        """Whether a full-frame search could help: a joint has not been seen by any labelled
        marker for `lost_frames` frames (its link may have come back far from where it was
        left, or out of the model's view), or the fits have had fewer than `min_markers`
        markers for as long (the few they kept may be all the camera shows, or markers lost
        on the way that a search finds again)."""
        return bool((self.state.unseen >= self.options.lost_frames).any()
                    or self.state.thin >= self.options.lost_frames)

    def restart(self, start: FrameResult, gray: np.ndarray | None = None) -> None:
        """Carry on from a fresh labelling of the current frame (after a loss). The joints
        its markers do not show are whichever of the tracker's last steady fit, where the
        tracker carried them since, and the proposal's, puts the most of the markers they
        move on disks of the frame `gray` (refined from there, as `step` looks for them;
        ties in that order): the proposal's are whatever its start had, and a link whose
        blurred markers the full-frame detection misses would be left turned wherever the
        start put it, its markers looked for there and never found again."""
        state, model = self.state, self.model
        shown = model.observed_joints(start.markers)
        anchor = state.joints if state.anchor is None else state.anchor
        candidates = np.where(shown, start.joints, np.array([anchor, state.joints, start.joints]))
        joints = candidates[0]
        unshown = model.machine.marker_moves[~shown].any(axis=0)  # (M,) the markers they move
        if gray is not None and unshown.any():
            view = model.view(candidates)
            radius = view.scale * state.disk_m if np.isfinite(state.disk_m) else np.full(view.scale.shape, np.median(
                start.detections.radius) if len(start.detections) else 3.0)
            options = self.options
            detect = replace(options.detect, min_contrast=options.near_contrast * options.detect.min_contrast)
            counts = []
            for k in range(len(candidates)):
                seeds = np.flatnonzero(self._visible(View(view.uv[k:k + 1], view.visible[k:k + 1], view.scale[k:k + 1]))
                                       & unshown & np.isfinite(radius[k]))
                r = np.maximum(radius[k, seeds], 1.0)
                found = refine_and_accept(gray, view.uv[k, seeds], r[:, None, None] ** 2 * np.eye(2), detect)
                counts.append(int(np.sum(_near_any(view.uv[k, seeds], found.xy, np.maximum(0.5 * r, 1.0)))))
            joints = candidates[int(np.argmax(counts))]
        state.joints = joints
        state.previous = joints.copy()
        state.uv = self.model.pixels(joints[None])[0]
        state.lost = state.thin = 0
        state.swept[:] = _NEVER  # the joints the new labels do not show are swept at once
        state.shift = np.zeros(2)
        state.missed[start.markers] = 0
        state.unseen[self.model.observed_joints(start.markers)] = 0
        state.shape[start.markers] = start.detections.shape

    def _visible(self, view: View) -> np.ndarray:
        """(M,) the disks the model shows (`disks_in_view`)."""
        return disks_in_view(self.model, view, self.options.occlusion)

    def _expected_radius(self, scale: np.ndarray) -> np.ndarray:
        """(M,) radii (px) to expect: a marker's last one while it is followed, else the
        model's (the disk's size at the marker's distance and angle), else the last one."""
        state = self.state
        modelled = scale * state.disk_m
        use_model = (state.missed > 2) & np.isfinite(modelled) & (modelled > 0)
        return np.where(use_model, modelled, state.radius)

    def _take_hidden(self, fitted_uv: np.ndarray, found: Detections, tight: np.ndarray, hidden: np.ndarray,
                     shown: np.ndarray, markers: np.ndarray, index: np.ndarray, face_on: np.ndarray,
                     agreeing: np.ndarray, least: float) -> tuple[np.ndarray, np.ndarray]:
        """The assignment (`markers`, `index`) of the markers the model shows, with the markers
        it calls `hidden` (M,) added: each takes a disk of contrast `least` or more within
        its `tight` gate of the fitted pixels (M, 2) whose ellipse's major semi-axis is the
        disk's radius at its depth face on (the guessed normal is wrong for it). They rank after
        the shown markers (`shown` (M,) bool): a disk goes to a hidden one only if it lies under
        half as far from it as any shown marker (which then gives it up: a marker wrongly shown
        on a hidden one's disk). `face_on` (M,) px: the disks' radii face on at the fitted joints
        (`_face_on_radius`). `agreeing` (M, N) bool: the pairs a disk where the fit puts the
        marker vouches for (`_agreeing`), taken at any size (but the contrast is kept: where the
        boxes hide a marker, a solid may hide it too and show something dark at its place): the
        full detection's, and `least` for a marker not followed lately on a disk wider than the
        blur's floor (`_SLIVER_PX`: a sliver's middle is not as dark as a wide disk's)."""
        options = self.options
        followed = self.state.missed <= 2
        wide = found.axes[:, 1] > _SLIVER_PX
        clear = (found.contrast >= options.detect.min_contrast)[None] & (
            followed[:, None] | ~(wide & (found.contrast < least))[None])
        allowed = (_same_size(found.axes[None, :, 0], face_on[:, None]) | agreeing) & clear
        more, more_index = assign(fitted_uv, found.xy, tight, hidden, allowed=allowed)
        if len(more) == 0:
            return markers, index
        mine = length(fitted_uv[more] - found.xy[more_index])
        theirs = length(fitted_uv[shown][:, None] - found.xy[more_index][None]).min(axis=0, initial=np.inf)
        wins = mine < 0.5 * theirs
        keep = ~np.isin(index, more_index[wins])
        return np.r_[markers[keep], more[wins]], np.r_[index[keep], more_index[wins]]

    def _converge_faint(self, gray: np.ndarray, seen: Detections, found: Detections, fitted_uv: np.ndarray,
                        tight: np.ndarray, hidden: np.ndarray, least: float) -> Detections:
        """`seen` (N, image pixels; `found` the same in the model's) with each detection fainter
        than `least`, wider than the blur's floor, within the `tight` gate (M,) of the fitted
        pixel (`fitted_uv` (M, 2)) of a `hidden` (M,) marker not followed lately (`_take_hidden`'s
        contrast test) refined once more from its own ellipse, where it stays a disk there:
        a refinement started from a circle a disk is not has not reached the disk's ellipse, and
        its ring and middle, measured on the ellipse it reached, read a contrast short of the
        disk's (a third short for a marker the boxes hide, first looked for after a cover); a
        solid's shade or a hose keeps its low contrast."""
        hidden = hidden & (self.state.missed > 2)
        near = length(fitted_uv[hidden][:, None] - found.xy[None]) <= tight[hidden][:, None]
        rows = np.flatnonzero(near.any(axis=0) & (found.contrast < least) & (found.axes[:, 1] > _SLIVER_PX))
        if len(rows) == 0:
            return seen
        options = self.options
        detect = replace(options.detect, min_contrast=options.near_contrast * options.detect.min_contrast)
        old = seen.select(rows)
        again, ring = refine(gray, old.xy, old.shape)
        stays = accept(again, ring, detect) & (length(again.xy - old.xy) <= 0.5 * np.maximum(old.radius, 1.0))
        if not stays.any():
            return seen
        rows, again = rows[stays], again.select(stays)
        fields = {name: getattr(seen, name).copy() for name in ("xy", "axes", "angle", "contrast", "fill", "score")}
        for name, value in fields.items():
            value[rows] = getattr(again, name)
        return Detections(**fields)

    def _face_on_radius(self, joints: np.ndarray) -> np.ndarray:
        """(M,) px: each disk's radius at its depth at joint values `joints` (J,), seen face on
        (NaN behind the camera)."""
        camera = self.model.camera
        world = self.model.machine.markers(joints[None])[0]
        depth = world @ camera.cam_from_world.rotation[2] + camera.cam_from_world.translation[2]
        focal = 0.5 * (camera.matrix[0, 0] + camera.matrix[1, 1])
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(depth > 0, focal * self.state.disk_m / depth, np.nan)

    def _agreeing(self, fitted_uv: np.ndarray, found: Detections, agree: float, face_on: np.ndarray) -> np.ndarray:
        """(M, N) bool: the pairs of markers and detections (model pixels) whose centre lies
        within `agree` px of where the fitted model puts the marker (`fitted_uv` (M, 2)), and
        whose major semi-axis is no larger than the disk can be at its depth (`face_on` (M,),
        `_same_size`'s bound above it), and whose minor semi-axis is at the blur's floor
        (`_SLIVER_PX`): only such a sliver's major semi-axis reads short."""
        near = length(fitted_uv[:, None] - found.xy[None]) <= agree
        with np.errstate(invalid="ignore"):
            small = ~(found.axes[None, :, 0] > face_on[:, None]) | _same_size(found.axes[None, :, 0], face_on[:, None])
        # a wider ellipse reads its major semi-axis whole: its size test stands (a dark spot of
        # a solid that hides the marker, at the marker's place, is no thinner than the blur)
        thin = found.axes[None, :, 1] <= _SLIVER_PX
        return near & small & thin

    def _update_disk(self, scale: np.ndarray, markers: np.ndarray, radius: np.ndarray) -> None:
        """Refresh the disks' radius in metres from labelled radii (px), by the median."""
        ratio = radius / scale[markers]
        ratio = ratio[np.isfinite(ratio) & (ratio > 0)]
        if len(ratio) >= 3:
            now = float(np.median(ratio))
            self.state.disk_m = now if not np.isfinite(self.state.disk_m) else 0.9 * self.state.disk_m + 0.1 * now

    def _regain(self, found, observed, joints, held, held_index, returning, reach, expected, known):
        """Returning markers: assigned within gates narrowing from their reach, each step
        refitting the joints, and taken only while the held markers still agree (a marker
        alone on a link whose joint no held marker shows only if it is the one blob in its
        reach: `CameraModel.supported`).
        Returns the joints, the markers now known and the fitted pixels (None if the
        joints did not move)."""
        options, model = self.options, self.model
        taken = np.zeros(len(found), dtype=bool)
        taken[held_index] = True
        free = np.where(taken[:, None], np.inf, found.xy)
        near = length(self.state.uv[returning, None] - free[None]) <= 2.0 * reach[returning, None]
        if not near.any():  # no free detection anywhere near a returning marker
            return joints, known, None
        moved_uv = None
        back_uv = model.pixels(joints[None])[0]
        for g in (1.0, 0.5, 0.25):
            gate = np.maximum(g * reach, options.tight_px)
            back, back_index = assign(back_uv, free, gate, returning, found.radius, expected)
            # a marker alone on its link fits any blob along its arc: only the one blob in reach
            alone = np.sum(length(back_uv[back, None] - free[None]) <= gate[back, None], axis=1) == 1
            # ... and only if it alone shows at most one joint: with two, its two coordinates
            # fix them with nothing to spare, and it fits any blob at all
            alone &= np.sum(model.machine.marker_moves[:, back] & ~model.observed_joints(held)[:, None], axis=0) <= 1
            keep_back = model.supported(back, held) | alone
            back, back_index = back[keep_back], back_index[keep_back]
            if len(back) == 0:
                break
            trial = observed.copy()
            trial[back] = found.xy[back_index]
            moved = model.fit(trial[None], joints, iterations=2)
            if np.nanmax(moved.residual[0, held]) > options.outlier_px:
                break  # the returning candidates disagree with the markers held
            joints, back_uv = moved.joints[0], moved.uv[0]
            moved_uv = back_uv
            observed = trial
            known = known | model.known_markers(np.r_[held, back])
        return joints, known, moved_uv

    def _sweep(self, gray: np.ndarray, predicted: np.ndarray) -> np.ndarray:
        """`predicted` (J,) with a joint that no labelled marker has shown for a while set
        where its own markers (those it moves and no other unseen joint does) lie on disks of
        `gray`: its range is swept in steps of half a disk's radius at the fastest marker,
        each step scored by the markers' contrast against their surround (box means of an
        integral image, all steps at once), and the best few steps checked by refining a
        disk at each marker; a step at which two or more are found wins. A link turned while
        the picture was covered, or while the camera saw only the undercarriage, is left
        where the tracker last had it: its markers lie beyond the widest gate, and the
        full-frame detection misses the faint ones (dark disks straight on the paint, in
        haze) that a refinement where the model puts them takes. Swept at once, then every
        `_SWEEP_EVERY` frames of the joint's absence (every 4 x that after `_SWEEP_SLOW`)."""
        state, model = self.state, self.model
        machine = model.machine
        unseen = state.unseen > 0
        state.swept += 1
        due = (state.unseen >= _SWEEP_EVERY) & (state.swept >= np.where(state.unseen > _SWEEP_SLOW, 4 * _SWEEP_EVERY,
                                                                          _SWEEP_EVERY))
        if not due.any() or not np.isfinite(state.disk_m):
            return predicted
        state.swept[due] = 0
        moves = machine.marker_moves & (machine.tags < 0)  # (J, M), disks only
        options = self.options
        detect = replace(options.detect, min_contrast=options.near_contrast * options.detect.min_contrast)
        integral = None
        # the disks of the markers labelled in the last frame are theirs (a bucket swept past
        # the arm would find its markers on the arm's); a swept joint moves none of them
        held = state.uv[state.missed == 0] + state.shift
        for j in np.flatnonzero(due):
            own = moves[j] & ~np.delete(moves & unseen[:, None], j, axis=0).any(axis=0)
            if np.sum(own) < _SWEEP_MARKERS:
                continue
            low, high = machine.joint_limits[j]
            if machine.wraps[j] or not np.isfinite(high - low):
                low, high = predicted[j] - np.pi, predicted[j] + np.pi
            coarse = np.tile(predicted, (64, 1))
            coarse[:, j] = np.linspace(low, high, 64)
            moved = length(np.diff(model.pixels(coarse)[:, own], axis=0))
            if not np.isfinite(moved).any():
                continue  # its markers behind the camera all along
            speed = np.nanmax(moved) / (coarse[1, j] - coarse[0, j])
            if speed <= 0:
                continue
            steps = int(min(np.ceil((high - low) * speed / (0.5 * max(np.nanmedian(state.radius), 1.0))), 4000)) + 1
            samples = np.tile(predicted, (steps, 1))
            samples[:, j] = np.linspace(low, high, steps)
            view = model.view(samples)
            visible = view.visible[:, own] & np.isfinite(view.scale[:, own])
            if integral is None:
                integral = cv2.integral(gray, sdepth=cv2.CV_64F)
            radius = np.maximum(view.scale[:, own] * state.disk_m, 1.0)
            contrast = _box_contrast(integral, view.uv[:, own], radius)
            shows = visible & (contrast > _SWEEP_CONTRAST * options.detect.min_contrast)
            count = np.sum(shows, axis=1)
            if count.max() < _SWEEP_MARKERS:
                continue
            ranking = count + np.sum(np.where(shows, np.minimum(contrast / 255.0, 1.0), 0.0), axis=1) / (own.sum() + 1)
            best, best_found = None, _SWEEP_MARKERS - 1
            for k in _peaks(ranking, count >= _SWEEP_MARKERS, _SWEEP_CHECKED):
                seeds = np.flatnonzero(visible[k])
                r = radius[k, seeds]
                found = refine_and_accept(gray, view.uv[k, own][seeds] + state.shift,
                                          r[:, None, None] ** 2 * np.eye(2), detect)
                found = found.select(~_near_any(found.xy, held, np.full(len(found), 2.0 * np.median(r))))
                at = view.uv[k, own][seeds] + state.shift
                n_found = int(np.sum(_near_any(at, found.xy, 0.5 * np.maximum(r, 2.0))))
                if n_found > best_found:
                    best, best_found = k, n_found
            if best is not None:
                log.debug("joint %d swept to %.3f (%d markers)", j, samples[best, j], best_found)
                predicted = predicted.copy()
                predicted[j] = samples[best, j]
                state.previous[j] = state.joints[j] = predicted[j]
                state.uv = model.pixels(state.joints[None])[0]
        return predicted

    def _coast(self, predicted: np.ndarray, uv: np.ndarray, visible: np.ndarray, found: Detections,
               expected: np.ndarray) -> FrameResult:
        """Too few markers to fit: the joints carry on as predicted; detections `found`
        (image pixels) within the tight gate of a predicted marker are still labelled."""
        state = self.state
        markers, index = assign(uv + state.shift, found.xy, np.full(len(uv), self.options.tight_px), visible,
                                found.radius, expected)
        state.previous, state.joints, state.uv = state.joints, predicted, uv
        state.lost += 1
        state.thin += 1
        state.missed += 1
        state.missed[markers] = 0
        state.unseen += 1
        return FrameResult(markers, found.select(index), predicted, False, float("nan"))

    def _refine_again(self, gray: np.ndarray, xy: np.ndarray, shape: np.ndarray, detect: DetectOptions,
                      whole: tuple[Detections, np.ndarray] | None = None) -> Detections:
        """Disks missed by a refinement from `xy` (K, 2) with `shape` (K, 2, 2), looked for
        again. A small disk on a narrow square beside dark paint: a window started at a full
        radius from a prediction a pixel or two off takes in the paint and slides onto it;
        started at half the radius it stays on the disk, and grows to it. A disk whose
        square is narrower than its ring: the ring reaches the paint around it and its
        darkest part is darker than a clean ring's; such a disk, refused by the ring test,
        is taken with `near_ring_spread` times the test's bound if it stays put when refined
        again from a smaller window where it arrived (a window that straddles a disk's edge,
        whose ring the disk itself darkens, moves on). `whole`: the refinement from `xy` with
        `shape` where the caller has it already (`refine_converged`'s detections and rings)."""
        small = refine_converged(gray, xy, 0.25 * shape)
        strict = accepted(*small, detect)
        loose_options = replace(detect, max_ring_spread=self.options.near_ring_spread * detect.max_ring_spread)
        whole = refine_converged(gray, xy, shape) if whole is None else whole
        loose = unique(concatenate([accepted(*whole, loose_options),
                                    accepted(*small, loose_options)]))
        loose = loose.select(~_near_any(loose.xy, strict.xy, 0.5 * np.maximum(loose.radius, 1.0)))
        if len(loose) == 0:
            return strict
        again, _ = refine(gray, loose.xy, 0.5 * loose.shape)
        stays = length(again.xy - loose.xy) <= 0.1 * np.maximum(loose.radius, 1.0)
        return concatenate([strict, loose.select(stays)])

    def _search_fitted(self, gray: np.ndarray, uv: np.ndarray, markers: np.ndarray, expected: np.ndarray,
                       agree: float = 0.0, shown: np.ndarray | None = None) -> Detections:
        """Disks refined from the fitted pixels `uv` (M, 2) (image) of `markers` (K,): from
        the last ellipse of a marker followed until now, else a circle of the expected
        radius; for those not found so, as `_refine_again` does, then from the ellipse's
        semi-axes times 1/sqrt(2) (a small disk a pixel from the start converges from
        that window where neither the full one nor the half one took it); for those still
        missed, a disk that any of these refinements put within `agree` px of the fitted pixel,
        with the contrast, fill and elongation of a disk and a minor semi-axis at the blur's
        floor (`_SLIVER_PX`), whatever its ring (a sliver of an
        oblique disk on its foreshortened square: the ring around its blurred ellipse reaches
        the paint beside the square), `_agreeing` then takes it; only for the markers the
        model's boxes show (`shown` (M,) bool, where given): where they hide one, a solid may
        hide it too, and the ring is what tells its disk from the solid's edge."""
        options = self.options
        detect = replace(options.detect, min_contrast=options.near_contrast * options.detect.min_contrast)
        circles = expected[markers, None, None] ** 2 * np.eye(2)
        shapes = np.where((self.state.missed[markers] <= 2)[:, None, None], self.state.shape[markers], circles)
        first = refine_sourced(gray, uv[markers], shapes)
        found = accepted(first.detections, first.ring, detect)
        missing = ~_near_any(uv[markers], found.xy, 0.5 * np.maximum(expected[markers], 2.0))
        # the slower refinements for those missed for long (covered, or truly hidden) only every
        # 4th frame, as `_search` looks around them
        missed = self.state.missed[markers]
        missing &= (missed <= 3) | (missed % 4 == 0)
        if missing.any():
            found = unique(concatenate([found, self._refine_again(gray, uv[markers[missing]], shapes[missing], detect,
                                                                  first.of(missing))]))
            missing = ~_near_any(uv[markers], found.xy, 0.5 * np.maximum(expected[markers], 2.0))
        if missing.any():
            found = unique(concatenate([found, refine_and_accept(gray, uv[markers[missing]], 0.5 * shapes[missing], detect)]))
            missing = ~_near_any(uv[markers], found.xy, 0.5 * np.maximum(expected[markers], 2.0))
        missing &= (missed <= 3) | (missed % 4 == 0)
        if shown is not None:
            missing &= shown[markers]
        if missing.any() and agree > 0:
            ringless = replace(detect, max_ring_spread=np.inf)
            small = refine_converged(gray, uv[markers[missing]], 0.25 * shapes[missing])
            candidates = concatenate([accepted(*first.of(missing), ringless), accepted(*small, ringless)])
            candidates = candidates.select(_near_any(candidates.xy, uv[markers[missing]], np.full(len(candidates), agree))
                                           & (candidates.axes[:, 1] <= _SLIVER_PX))
            if len(candidates):
                found = unique(concatenate([found, candidates]))
        return found

    def _search(self, gray: np.ndarray, uv: np.ndarray, gate: np.ndarray, visible: np.ndarray,
                expected: np.ndarray, recent: np.ndarray) -> Detections:
        """Disks near the predicted markers: refined from each prediction (with the marker's
        last ellipse while it is followed, else a circle of the expected radius); for
        markers not found so (those missed for long only every 4th frame), searched in a
        window (gate) around the prediction. Duplicates merged."""
        missed = self.state.missed
        # where the model puts a marker, a fainter disk (worn paint at a grazing angle) is
        # taken than a full-frame search would take: the gates and the fit vouch for it
        options = self.options
        detect = replace(options.detect, min_contrast=options.near_contrast * options.detect.min_contrast)
        seeds = np.flatnonzero(visible)
        circles = expected[seeds, None, None] ** 2 * np.eye(2)
        shapes = np.where((missed[seeds] <= 2)[:, None, None], self.state.shape[seeds], circles)
        first = refine_sourced(gray, uv[seeds], shapes)
        found = accepted(first.detections, first.ring, detect)
        close = 0.5 * np.maximum(expected[seeds], 2.0) + options.tight_px
        missing = ~_near_any(uv[seeds], found.xy, close)
        if missing.any():
            again = self._refine_again(gray, uv[seeds[missing]], shapes[missing], detect, first.of(missing))
            found = unique(concatenate([found, again]))
            missing[missing] = ~_near_any(uv[seeds[missing]], again.xy, close[missing])
        followed = missing & (missed[seeds] <= 2)
        if followed.any():  # the last ellipse a blurred, noisy one (a small disk smeared): a circle
            again = refine_and_accept(gray, uv[seeds[followed]], circles[followed], detect)
            found = unique(concatenate([found, again]))
            missing[followed] = ~_near_any(uv[seeds[followed]], again.xy, close[followed])
        missing = seeds[missing]
        missing = missing[(missed[missing] <= 3) | (missed[missing] % 4 == 0)]
        if len(missing) == 0:
            return found
        height, width = gray.shape
        xys, shapes = [], []
        for m in missing:
            r = expected[m]
            half = gate[m] + 2.6 * r + 3
            x0, y0 = int(max(uv[m, 0] - half, 0)), int(max(uv[m, 1] - half, 0))
            x1, y1 = int(min(uv[m, 0] + half + 1, width)), int(min(uv[m, 1] + half + 1, height))
            if x1 - x0 < 3 or y1 - y0 < 3:
                continue
            # a neighbourhood of three radii, and one of 1.5 (a small disk's square beside dark
            # paint: the larger one's mean takes in the paint and the disk is not below it)
            parts = [find_candidates(gray[y0:y1, x0:x1], replace(detect, block=max(int(2 * np.ceil(k * r) + 1), 7)),
                                     (x0, y0)) for k in (3.0, 1.5)]
            xy, shape = np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
            size = np.sqrt(np.abs(np.linalg.det(shape))) ** 0.5 if len(xy) else np.zeros(0)
            near = (length(xy - uv[m]) <= gate[m] + r) & (size > 0.4 * r) & (size < 2.5 * r)
            xys.append(xy[near])
            shapes.append(shape[near])
        if not xys:
            return found
        xy, shape = np.concatenate(xys), np.concatenate(shapes)
        _, first = np.unique(np.round(xy * 4), axis=0, return_index=True)
        extra = refine_and_accept(gray, xy[first], shape[first], detect)
        return unique(concatenate([found, extra]))


def disks_in_view(model: CameraModel, view: View, occlusion: bool = True) -> np.ndarray:
    """(M,) bool: the disks the model shows in the first frame of `view` (markers that carry
    tags are found by their ids): in the image, facing the camera and, with `occlusion`,
    not hidden behind a link's box."""
    disks = model.machine.tags < 0
    if occlusion:
        return view.visible[0] & disks
    uv = view.uv[0]
    w, h = model.camera.size
    inside = np.isfinite(uv).all(axis=-1) & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0)
    return inside & (uv[:, 1] <= h - 1) & disks


def _box_contrast(integral: np.ndarray, uv: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """(S, K) the mean grey of a ring of boxes around each pixel `uv` (S, K, 2) less the mean
    of a box on it (half-sides 0.7 and 2.2 x `radius` (S, K)), from the image's `integral`
    (H+1, W+1): a dark disk of that radius on a lighter surround scores its contrast; NaN
    outside the image."""
    height, width = integral.shape[0] - 1, integral.shape[1] - 1

    def box(half):
        x0 = np.clip(np.round(uv[..., 0] - half), 0, width).astype(int)
        x1 = np.clip(np.round(uv[..., 0] + half) + 1, 0, width).astype(int)
        y0 = np.clip(np.round(uv[..., 1] - half), 0, height).astype(int)
        y1 = np.clip(np.round(uv[..., 1] + half) + 1, 0, height).astype(int)
        total = integral[y1, x1] - integral[y0, x1] - integral[y1, x0] + integral[y0, x0]
        return total, (x1 - x0) * (y1 - y0)

    finite = np.isfinite(uv).all(axis=-1)
    uv = np.where(finite[..., None], uv, -1e6)
    inner, inner_area = box(np.maximum(0.7 * radius, 0.5))
    outer, outer_area = box(2.2 * radius)
    with np.errstate(divide="ignore", invalid="ignore"):
        contrast = (outer - inner) / (outer_area - inner_area) - inner / inner_area
    inside = finite & (inner_area > 0) & (outer_area > inner_area)
    return np.where(inside, contrast, np.nan)


def _peaks(score: np.ndarray, eligible: np.ndarray, n: int) -> list[int]:
    """Up to `n` indices of the highest `score` (S,) among `eligible` (S,), each the highest
    of its run of eligible neighbours (one per stretch of steps that show the same disks)."""
    order = np.flatnonzero(eligible)
    if len(order) == 0:
        return []
    runs = np.split(order, np.flatnonzero(np.diff(order) > 1) + 1)
    tops = [run[np.argmax(score[run])] for run in runs]
    return sorted(tops, key=lambda k: -score[k])[:n]


def assign(
    predicted: np.ndarray,
    detected: np.ndarray,
    gate: np.ndarray,
    visible: np.ndarray,
    detected_radius: np.ndarray | None = None,
    expected_radius: np.ndarray | None = None,
    size_ratio: float = 1.33,
    size_px: float = 1.0,
    allowed: np.ndarray | None = None,
    penalty: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Optimal one-to-one assignment of detections to predicted markers: the least sum of
    squared distances, a marker left unassigned counting as a pair at its gate.

    predicted (M, 2), detected (N, 2), gate (M,) px, visible (M,) bool; with the radii (N,)
    and (M,), pairs whose radii differ by more than `size_ratio` and by more than `size_px`
    are not allowed (a small disk's radius, measured on a few blurred pixels, varies by
    more than a third from frame to frame); `allowed` (M, N) bool, where given, the only pairs
    allowed at all; `penalty` (M,) px², where given, added to each of a marker's pairs (a
    marker the prior calls unlikely loses a disk to one it does not, and stays unassigned
    sooner: the gate is not widened).
    Returns marker indices (K,) and detection indices (K,) of the gated pairs.
    """
    if len(detected) == 0 or not visible.any():
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    cost = np.sum((predicted[:, None] - detected[None]) ** 2, axis=-1)
    allowed = visible[:, None] & (cost <= gate[:, None] ** 2) & np.isfinite(cost) & (True if allowed is None else allowed)
    if detected_radius is not None and expected_radius is not None:
        allowed &= _same_size(detected_radius[None], expected_radius[:, None], size_ratio, size_px)
    rows = np.nonzero(allowed.any(axis=1))[0]
    cols = np.nonzero(allowed.any(axis=0))[0]
    if len(rows) == 0:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    if penalty is not None:
        cost = cost + penalty[:, None]
    sub = np.where(allowed, cost, _INFEASIBLE)[rows][:, cols]
    # a marker may stay unassigned at the cost of a pair at its gate: without that choice
    # every marker takes some detection, and one not detected takes another's and passes
    # it on, which drags a fit from even the right joints
    miss = np.full((len(rows), len(rows)), _INFEASIBLE)
    np.fill_diagonal(miss, gate[rows] ** 2)
    r, c = linear_sum_assignment(np.hstack([sub, miss]))
    pair = c < len(cols)
    r, c = r[pair], c[pair]
    ok = sub[r, c] < _INFEASIBLE
    return rows[r[ok]], cols[c[ok]]


def _same_size(detected: np.ndarray, expected: np.ndarray, ratio: float = 1.33, px: float = 1.0) -> np.ndarray:
    """Whether radii `detected` and `expected` (broadcast) agree: within a factor `ratio`, or
    within `px` (`assign`)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        share = detected / np.maximum(expected, 1e-6)
    return ((share > 1.0 / ratio) & (share < ratio)) | (np.abs(detected - expected) <= px)


def _inside_larger(detections: Detections) -> np.ndarray:
    """(N,) bool: the detections whose centre lies inside the ellipse of a larger one (by area)."""
    if len(detections) < 2:
        return np.zeros(len(detections), dtype=bool)
    d = detections.xy[None, :] - detections.xy[:, None]  # [k, j]: from k's centre to j's
    inverse = np.linalg.inv(detections.shape)  # (N, 2, 2)
    rho2 = np.einsum("kji,kil,kjl->kj", d, inverse, d)
    area = detections.axes[:, 0] * detections.axes[:, 1]
    larger = area[:, None] > area[None, :]  # [k, j]: k larger than j
    return (larger & (rho2 < 1.0)).any(axis=0)


def _near_any(points: np.ndarray, xy: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """(K,) whether each of `points` (K, 2) has one of `xy` (N, 2) within its `radius` (K,)."""
    if len(xy) == 0:
        return np.zeros(len(points), dtype=bool)
    return (length(points[:, None] - xy[None]) < radius[:, None]).any(axis=1)
