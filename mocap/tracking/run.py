"""Tracking a whole video: label the first frame, follow the markers, collect the rows of
the tracks CSV (DESIGN.md). Frames come from any iterable of ``(index, grey image)``."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mocap.core.machine import Machine
from mocap.core.tracks import Tracks, concatenate
from mocap.tracking.detect import TagFinder, detect_disks, length
from mocap.tracking.labels import labels_from_pixels, propose_labels, starts_around
from mocap.tracking.model import CameraModel
from mocap.tracking.normals import NormalEvidence, NormalLearner
from mocap.tracking.tracker import FrameResult, Tracker, TrackOptions, _near_any, disks_in_view

log = logging.getLogger(__name__)

_MAX_SEARCH_INTERVAL = 16  # full-frame searches for an unseen joint back off to 16 x lost_frames
UNPLACED_MIN_FRAMES = 10
_MAX_LOST_INTERVAL = 2  # those for a lost machine to 2 x lost_frames: found again within a second
_DARK_EVERY = 8  # fitted frames between looks at the markers the boxes hide (`TrackSummary.why`)
_LEARN_SAMPLE = 3  # after the first _LEARN_EVERY fitted frames, those whose disks' ellipses are kept: every 3rd
_LEARN_EVERY = 60  # fitted frames between updates of the model's normals from them
_LEARN_RESIDUAL, _LEARN_RESIDUAL_PX = 3.0, 0.15  # a disk this many times the frame's median residual off, and
# this many px, is left out of the normals' evidence
_LEARNED_SPREAD_DEG = 5.0  # a learned normal whose agreeing candidates spread more is not used


class TooFewMarkersError(ValueError):
    """The camera sees too few of the model's markers at the start joints to fit them:
    no labelling of the first frame can help."""


@dataclass(frozen=True)
class TrackSummary:
    """`frames` read, `fitted` frames with a model fit, `labelled` rows written,
    `restarts` full-frame relabellings after a loss, `unplaced` the disk markers the fitted
    model showed in view in at least `UNPLACED_MIN_FRAMES` frames but that were labelled in
    under a tenth of them (not found, or refused: look at them in a preview), and the disk
    markers the model's boxes call hidden or turned away but where a disk of their size lay
    where the fit put them in most of the frames looked at (every `_DARK_EVERY`th fitted one, at
    least 3) while they were labelled in under a tenth of them; `why` says for each of
    `unplaced` why it was not labelled; `normals` the evidence of the markers' normals their
    disks' ellipses gave (`mocap.tracking.normals`; pool the cameras' and `learn`), None for a
    machine of tags."""

    frames: int
    fitted: int
    labelled: int
    restarts: int
    unplaced: tuple[str, ...] = ()
    why: tuple[str, ...] = ()
    normals: NormalEvidence | None = None


def label_first_frame(
    model: CameraModel,
    gray: np.ndarray,
    start: np.ndarray,
    labelled: np.ndarray | None,
    options: TrackOptions,
    finder: TagFinder | None = None,
) -> FrameResult | None:
    """The first frame's labels: from digitised pixels `labelled` (M, 2) NaN where not
    given (the machine's tags found in the frame count as given), or proposed by the model
    search from joint values `start` (J,)."""
    found = detect_disks(gray, options.detect)
    tags = tag_pixels(model.machine, gray, finder)
    if tags is not None and np.isfinite(tags[:, 0]).any():
        labelled = tags if labelled is None else np.where(np.isfinite(tags), tags, labelled)
    if labelled is not None:
        return labels_from_pixels(model, found, labelled, start)
    return propose_labels(model, found, starts_around(model, start), min_markers=options.min_markers)


def tag_pixels(machine: Machine, gray: np.ndarray, finder: TagFinder | None = None) -> np.ndarray | None:
    """(M, 2) the centres of the machine's tags found in the frame, by their ids (NaN for
    the markers not found and those that are disks); None if the machine carries no tags.
    `finder` the video's `TagFinder` (None: a new one, every pass)."""
    tags = machine.tags
    if not (tags >= 0).any():
        return None
    found = (finder or TagFinder(machine.tag_dictionary))(gray)
    pixels = np.full((len(tags), 2), np.nan)
    marker_of = {int(t): m for m, t in enumerate(tags) if t >= 0}
    for tag_id, xy in zip(found.ids, found.xy):
        if int(tag_id) in marker_of:
            pixels[marker_of[int(tag_id)]] = xy
    return pixels


def tag_rows(camera: str, frame: int, fps: float, names, pixels: np.ndarray) -> Tracks:
    """The tags found in a frame as tracks rows (score 1: a tag names itself)."""
    markers = np.flatnonzero(np.isfinite(pixels[:, 0]))
    time = np.full(len(markers), frame / fps) if fps > 0 else None
    return Tracks.from_rows(np.full(len(markers), camera, dtype=object), np.full(len(markers), frame),
                            np.asarray(names, dtype=object)[markers], pixels[markers], time, np.ones(len(markers)))


def frame_rows(camera: str, frame: int, fps: float, names, result: FrameResult) -> Tracks:
    """One frame's labels as tracks rows (time = frame / fps, the camera's own clock)."""
    n = len(result.markers)
    time = np.full(n, frame / fps) if fps > 0 else None
    return Tracks.from_rows(
        np.full(n, camera, dtype=object),
        np.full(n, frame),
        np.asarray(names, dtype=object)[result.markers],
        result.detections.xy,
        time,
        result.detections.score,
    )


def track_frames(
    model: CameraModel,
    frames,
    start: np.ndarray,
    labelled: np.ndarray | None = None,
    fps: float = 0.0,
    options: TrackOptions | None = None,
    on_frame: Callable[[int, Tracks], None] | None = None,
    keep: bool = True,
) -> tuple[Tracks, TrackSummary]:
    """Label and track markers through `frames` (iterable of (index, grey (H, W))).

    `on_frame(index, rows)`, if given, is called with each frame's rows as soon as they are
    known (`mocap live` tracks a stream this way, frame by frame); with `keep` False the rows
    go to `on_frame` only and the tracks returned are empty (a stream that runs for hours).

    `start` (J,) joint values near the first frame's (the calibration's); `labelled`
    (M, 2) the first frame's digitised pixels, or None to have them proposed. Returns the
    tracks of the frames read and a summary; raises ValueError if the first frame cannot
    be labelled. After a loss, or while a joint goes unseen, the whole frame is searched
    again every `lost_frames` frames, less often while those searches find nothing new (after
    a loss, at least every 2 x `lost_frames` frames).
    """
    options = options or TrackOptions()
    names = model.machine.marker_names
    camera = model.camera.name
    rows: list[Tracks] = []
    if not (model.machine.tags < 0).any():  # every marker a tag: they name themselves
        return track_tags(model.machine, frames, camera, fps, on_frame, keep)
    tracker = None
    finder = TagFinder(model.machine.tag_dictionary) if (model.machine.tags >= 0).any() else None
    n_frames = n_fitted = restarts = searched = 0
    in_view = np.zeros(len(names), dtype=int)  # frames the fitted model showed each disk marker
    placed = np.zeros(len(names), dtype=int)  # and of those, frames it was labelled
    looked = np.zeros(len(names), dtype=int)  # frames a marker the boxes hide was looked at
    dark = np.zeros(len(names), dtype=int)  # and of those, frames a dark spot lay where the fit put it
    hidden_placed = np.zeros(len(names), dtype=int)  # and of those, frames it was labelled
    interval = options.lost_frames  # frames between full-frame searches; doubles while they fail
    let_go = 0  # rows handed to `on_frame` and not kept
    blank_disks = 0  # while lost: disks the last failed full-frame search had (or fewest since)
    learner = NormalLearner(len(names))
    stated = (np.isfinite(model.machine.marker_normals).all(axis=1) if model.machine.marker_normals is not None
              else np.zeros(len(names), dtype=bool))
    for index, gray in frames:
        n_frames += 1
        tags = tag_pixels(model.machine, gray, finder)
        if tracker is None:
            first = label_first_frame(model, gray, start, labelled, options, finder)
            if first is None:
                view = model.view(np.asarray(start, dtype=float)[None])
                in_view = np.flatnonzero(disks_in_view(model, view, options.occlusion))
                shown = len(in_view)
                if not model.determined(in_view, options.min_markers):
                    raise TooFewMarkersError(
                        f"frame {index}: at the starting joint values (the calibration's) the camera sees {shown} of "
                        f"the model's {int(np.sum(model.machine.tags < 0))} disk markers, and a fit needs "
                        f"{options.min_markers} (or fewer that fix the joints they show with coordinates to spare)")
                raise ValueError(f"frame {index}: the model explains too few of the detected disks "
                                 f"({shown} of its markers in view)")
            tracker = Tracker(model, first, options)
            # the first frame tracked again from its own labels: the tracker takes the disks
            # where the model puts markers that the full-frame detection refused
            result = tracker.step(gray)
            if not result.fitted or len(result.markers) < len(first.markers):
                tracker, result = Tracker(model, first, options), first
            log.info("frame %d: %d markers labelled, residual %.2f px", index, len(result.markers), result.rms_px)
        else:
            was_lost = tracker.lost >= options.lost_frames
            result = tracker.step(gray)
            searched += 1
            lost = tracker.lost >= options.lost_frames
            if lost:
                interval = min(interval, _MAX_LOST_INTERVAL * options.lost_frames)
            # the machine picked up again by the tracker after a loss (it may have moved meanwhile
            # and left a link's markers on others' disks): the whole frame searched at once too
            found_again = was_lost and not lost
            frame_disks = None
            if lost and searched < interval:
                # the picture come back (a cover taken away, the machine back in view) while
                # the machine moved on: searched at once rather than at the next interval
                frame_disks = detect_disks(gray, options.detect)
                if len(frame_disks) < blank_disks + options.min_markers:
                    blank_disks = min(blank_disks, len(frame_disks))
                    frame_disks = None
            if (lost or tracker.needs_search()) and (searched >= interval or frame_disks is not None) or found_again:
                searched = 0
                frame_disks = detect_disks(gray, options.detect) if frame_disks is None else frame_disks
                again = propose_labels(model, frame_disks, starts_around(model, result.joints),
                                       min_markers=options.min_markers)
                if again is not None and not (lost or found_again):
                    again = _supported(model, again, result.markers)
                if again is not None and (lost or len(again.markers) > len(result.markers)
                                          or found_again and len(again.markers) == len(result.markers)
                                          and again.rms_px < result.rms_px):
                    tracker.restart(again, gray)
                    result = again
                    restarts += 1
                    interval = options.lost_frames
                    log.info("frame %d: markers found again by a full-frame search", index)
                else:
                    blank_disks = len(frame_disks)
                    most = _MAX_LOST_INTERVAL if lost else _MAX_SEARCH_INTERVAL
                    interval = min(2 * interval, most * options.lost_frames)
            elif not (lost or tracker.needs_search()):
                interval = options.lost_frames
        n_fitted += bool(result.fitted)
        if result.fitted:
            if n_fitted <= _LEARN_EVERY or n_fitted % _LEARN_SAMPLE == 0:
                _learn(learner, model, result)
            if n_fitted % _LEARN_EVERY == 0:
                model = tracker.model = _learned_model(model, stated, learner.evidence())
            in_view += tracker.state.visible
            placed[result.markers] += tracker.state.visible[result.markers]
            if n_fitted % _DARK_EVERY == 0:
                hidden, spot = _dark_spots(tracker, gray, result.joints, result.detections.xy)
                looked += hidden
                dark += hidden & spot
                hidden_placed[result.markers] += hidden[result.markers]
        known = len(rows)
        disks = model.machine.tags[result.markers] < 0  # a proposal may name a tag's square as a disk
        if disks.any():
            rows.append(frame_rows(camera, index, fps, names, _select(result, disks)))
        if tags is not None:
            rows.append(tag_rows(camera, index, fps, names, tags))
        if on_frame is not None:
            on_frame(index, _concatenate(rows[known:]))
        if not keep:
            let_go += sum(len(r) for r in rows[known:])
            del rows[known:]
    tracks = _concatenate(rows)
    unplaced = (in_view >= UNPLACED_MIN_FRAMES) & (placed < 0.1 * in_view)
    spotted = (looked >= 3) & (dark >= 0.5 * looked) & (hidden_placed < 0.1 * looked) & ~unplaced
    why = [f"the model shows it in {in_view[m]} fitted frames but no disk passing the tests lay where the fit put "
           f"it in {in_view[m] - placed[m]} of them (covered, worn paint, or its position in the model is off)"
           for m in np.flatnonzero(unplaced)]
    learned = learner.evidence().learn(model.normals)
    settled = learned.learned & learned.resolved & (learned.spread_deg <= _LEARNED_SPREAD_DEG)
    why += [f"the model's link boxes call it hidden or turned away, yet a disk of its size lay where the fit put it "
            f"in {dark[m]} of {looked[m]} frames looked at and was not taken (fainter than the detection's "
            f"--min-contrast?): state its `normal` in the machine file"
            + (f" (its disk's ellipses give normal = [{', '.join(f'{v:.3f}' for v in learned.normals[m])}])"
               if settled[m] else "") for m in np.flatnonzero(spotted)]
    order = np.r_[np.flatnonzero(unplaced), np.flatnonzero(spotted)]
    return tracks, TrackSummary(n_frames, n_fitted, len(tracks) + let_go, restarts,
                                tuple(np.asarray(names, dtype=object)[order].tolist()), tuple(why),
                                learner.evidence())


def _learned_model(model: CameraModel, stated: np.ndarray, evidence: NormalEvidence) -> CameraModel:
    """`model` with the normals its disks' ellipses settled (resolved, candidates agreeing
    within `_LEARNED_SPREAD_DEG`) in place of the guessed ones, where the machine file
    states none (`stated` (M,) bool); a prior like the guess: it orders the search and sizes
    the disks expected, and a marker it turns away is still looked for where the fit puts it."""
    learned = evidence.learn(model.normals)
    use = learned.learned & learned.resolved & (learned.spread_deg <= _LEARNED_SPREAD_DEG) & ~stated
    turn = np.einsum("mi,mi->m", np.nan_to_num(learned.normals), model.normals)
    use &= turn < np.cos(np.radians(1.0))  # no new model for a change too small to matter
    if not use.any():
        return model
    return model.with_normals(np.where(use[:, None], learned.normals, np.nan))


def _learn(learner: NormalLearner, model: CameraModel, result: FrameResult) -> None:
    """A fitted frame's labelled disks handed to `learner`, with their centres and links'
    rotations in the camera frame by the fit."""
    machine, camera = model.machine, model.camera
    disks = machine.tags[result.markers] < 0
    # a disk the fit leaves off its place (partly covered: its outline cut, its ellipse not the
    # disk's) is no evidence of its normal
    residual = length(result.detections.xy - model.pixels(result.joints[None])[0, result.markers])
    if disks.any():
        disks &= residual <= max(_LEARN_RESIDUAL * float(np.median(residual[disks])), _LEARN_RESIDUAL_PX)
    markers = result.markers[disks]
    if not len(markers):
        return
    poses = machine.link_poses(result.joints[None])[0, machine.marker_links[markers]]  # (K, 4, 4)
    rotation, translation = camera.cam_from_world.rotation, camera.cam_from_world.translation
    cam_from_link = rotation @ poses[:, :3, :3]
    centre = np.einsum("kij,kj->ki", cam_from_link, machine.marker_positions[markers])
    centre += poses[:, :3, 3] @ rotation.T + translation
    detections = result.detections.select(disks)
    learner.add(markers, detections.axes, detections.shape, centre, cam_from_link, camera.matrix, camera.distortion)


def _dark_spots(tracker: Tracker, gray: np.ndarray, joints: np.ndarray,
                taken: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(M,) the disk markers in the image that the model's boxes hide or turn away at the fitted
    `joints`, and (M,) whether a disk refined from where the fit puts it as the tracker refines
    one there (`Tracker._search_fitted`), of the marker's size face on (its ellipse's major
    semi-axis), lies within the tight gate of that place and is not one of the disks `taken`
    (K, 2) image pixels, labelled as other markers in the frame (a hidden marker whose image
    falls on a shown one's disk is no evidence)."""
    model, options = tracker.model, tracker.options
    view = model.view(joints[None])
    hidden = disks_in_view(model, view, occlusion=False) & ~disks_in_view(model, view, options.occlusion)
    spot = np.zeros_like(hidden)
    if not hidden.any() or not np.isfinite(tracker.state.disk_m):
        return hidden, spot
    markers = np.flatnonzero(hidden)
    face_on = np.maximum(np.nan_to_num(tracker._face_on_radius(joints)), 1.0)
    radius = face_on[markers]
    at = view.uv[0, markers] + tracker.state.shift
    found = tracker._search_fitted(gray, view.uv[0] + tracker.state.shift, markers, face_on)
    if taken is not None and len(found):
        found = found.select(~_near_any(found.xy, taken, 0.5 * np.maximum(found.radius, 2.0)))
    if len(found):
        near = length(at[:, None] - found.xy[None]) <= np.maximum(options.tight_px, 0.5 * radius)[:, None]
        ratio = found.axes[None, :, 0] / radius[:, None]
        sized = ((ratio > 0.75) & (ratio < 1.33)) | (np.abs(found.axes[None, :, 0] - radius[:, None]) <= 1.0)
        spot[markers] = (near & sized).any(axis=1)
    return hidden, spot


def track_tags(machine: Machine, frames, camera: str, fps: float = 0.0,
               on_frame: Callable[[int, Tracks], None] | None = None,
               keep: bool = True) -> tuple[Tracks, TrackSummary]:
    """The tracks of a machine whose markers all carry tags: each frame's tags by their ids
    (no camera model needed). `frames` iterable of (index, grey (H, W)); `on_frame` and `keep`
    as in `track_frames`."""
    rows, n_frames, let_go = [], 0, 0
    finder = TagFinder(machine.tag_dictionary)
    for index, gray in frames:
        n_frames += 1
        rows.append(tag_rows(camera, index, fps, machine.marker_names, tag_pixels(machine, gray, finder)))
        if on_frame is not None:
            on_frame(index, rows[-1])
        if not keep:
            let_go += len(rows.pop())
    tracks = _concatenate(rows)
    return tracks, TrackSummary(n_frames, 0, len(tracks) + let_go, 0)


def _supported(model: CameraModel, result: FrameResult, held: np.ndarray) -> FrameResult:
    """`result` without the new markers the tracked ones do not support (`CameraModel.supported`)."""
    new = ~np.isin(result.markers, held)
    keep = ~new
    keep[new] = model.supported(result.markers[new], held)
    return _select(result, keep)


def _select(result: FrameResult, keep: np.ndarray) -> FrameResult:
    return FrameResult(result.markers[keep], result.detections.select(keep), result.joints, result.fitted,
                       result.rms_px)


def _concatenate(rows: list[Tracks]) -> Tracks:
    if not rows:
        return Tracks.from_rows([], [], [], np.zeros((0, 2)))
    return concatenate(rows)
