"""The track stage: load the machine, the calibrated camera, the video and the optional first
frame labels; label and track; write the tracks CSV (or the proposed labels)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from mocap.errors import InputError
from mocap.io.cameras_toml import load_calibration
from mocap.io.machine_toml import load_machine
from mocap.io.tracks_csv import Tracks, check_in_images, load_tracks, save_tracks
from mocap.io.video import Video
from mocap.progress import progress
from mocap.tracking.model import CameraModel
from mocap.tracking.run import TrackSummary, frame_rows, label_first_frame, track_frames
from mocap.tracking.tracker import TrackOptions

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrackRequest:
    """What `mocap track` was asked to do; paths as given."""

    video: Path
    machine: str
    calibration: Path
    camera: str
    out: Path | None = None
    labels: Path | None = None
    propose_labels: Path | None = None
    start: int = 0
    stop: int | None = None
    options: TrackOptions = field(default_factory=TrackOptions)
    whole_video: bool = False  # a video that breaks part-way is an error, not half the tracks


@dataclass(frozen=True)
class TrackReport:
    """`summary` of the tracking (None when only labels were proposed), `labels` the
    first frame's labels, `broken_at` the frame where the video broke, or None."""

    summary: TrackSummary | None
    labels: Tracks
    broken_at: int | None


def run_track(request: TrackRequest) -> TrackReport:
    machine = load_machine(request.machine)
    calibration = load_calibration(request.calibration)
    if request.camera not in calibration.names:
        raise InputError(
            f"no camera named {request.camera!r}; the file has {', '.join(calibration.names)}",
            path=request.calibration,
        )
    index = calibration.names.index(request.camera)
    camera = calibration.cameras[index]
    video = Video(request.video)
    if tuple(video.info.size) != tuple(camera.size):
        raise InputError(
            f"the video is {video.info.size[0]}x{video.info.size[1]} but camera {camera.name!r} "
            f"was calibrated at {camera.size[0]}x{camera.size[1]}; use the camera's own video",
            path=request.video,
        )
    start = calibration.joints(machine, index)
    if start is None:
        start = machine.clip_to_limits(np.zeros(machine.n_joints))
    fps = video.info.fps or float(calibration.extras[index].get("fps", 0.0))
    model = CameraModel(machine, camera, solid=machine.n_joints > 0)
    labelled = None
    if request.labels is not None:
        labels = load_tracks(request.labels)
        check_in_images(labels.of_camera(camera.name), {camera.name: camera.size}, request.labels)
        labelled = _first_frame_pixels(labels, machine, camera.name, request.start, request.labels)
    options = request.options
    if machine.n_joints == 0 and options.occlusion:
        # a rigid model's one link box is the hull of its markers, not its shape: it would hide
        # markers that the camera sees
        log.info("%s is rigid: no occlusion by its link box", machine.name)
        options = replace(options, occlusion=False)
    frames = video.frames(gray=True, start=request.start, stop=request.stop, prefetch=4)
    if request.propose_labels is not None:
        first = next(iter(frames), None)
        frames.close()
        if first is None:
            raise InputError(f"no frame {request.start} in the video", path=request.video)
        result = label_first_frame(model, first[1], start, labelled, options)
        if result is None:
            raise InputError(
                f"frame {first[0]}: the model explains too few detected disks; digitise the "
                "markers of this frame and pass them with --labels",
                path=request.video,
            )
        labels = frame_rows(camera.name, first[0], fps, machine.marker_names, result)
        save_tracks(labels, request.propose_labels)
        return TrackReport(None, labels, None)
    total = (request.stop or video.info.frame_count or 0) - request.start
    bar = progress(frames, total=max(total, 0) or None, desc=f"track {camera.name}", unit="frame")
    try:
        tracks, summary = track_frames(model, bar, start, labelled, fps, options)
    except ValueError as exc:
        raise InputError(f"{exc}; digitise the markers of the first frame and pass them with --labels", path=request.video) from None
    if request.whole_video and video.broken_at is not None:
        raise InputError(
            f"the video breaks at frame {video.broken_at} of {video.info.frame_count} (truncated or "
            "corrupt); nothing written: repair or re-copy the video", path=request.video)
    save_tracks(tracks, request.out)
    first = tracks.select(tracks.frame == (tracks.frame.min() if len(tracks) else -1))
    return TrackReport(summary, first, video.broken_at)


def _first_frame_pixels(labels: Tracks, machine, camera: str, frame: int, path) -> np.ndarray:
    """The digitised pixels (M, 2) of `camera` at `frame` from a labels tracks CSV."""
    if camera not in labels.cameras:
        raise InputError(f"labels of camera(s) {', '.join(labels.cameras)}, none of {camera!r}; give "
                         f"this camera's labels (camera column {camera})", path=path)
    rows = labels.of_camera(camera)
    unknown = sorted(set(rows.marker) - set(machine.marker_names))
    if unknown:
        raise InputError(f"markers not in the machine model: {', '.join(unknown)}", path=path)
    at = rows.select(rows.frame == frame)
    if len(at) == 0:
        frames = ", ".join(str(f) for f in rows.frames[:5])
        raise InputError(
            f"no labels at the first tracked frame {frame} (labels are for frame(s) {frames}); "
            "pass --start with the labels' frame",
            path=path,
        )
    return at.dense([camera], machine.marker_names, [frame])[0, 0]
