"""The track stage: load the machine, the calibrated camera, the video and the optional first
frame labels; label and track; write the tracks CSV (or the proposed labels)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from mocap.core.calibration import Calibration
from mocap.core.machine import Machine
from mocap.core.tracks import Tracks, check_in_images
from mocap.errors import InputError
from mocap.io.cameras_toml import load_calibration
from mocap.io.machine_toml import load_machine
from mocap.io.tracks_csv import load_tracks, save_tracks
from mocap.io.video import Video
from mocap.progress import progress
from mocap.tracking.model import CameraModel
from mocap.tracking.run import (TooFewMarkersError, TrackSummary, frame_rows, label_first_frame, track_frames,
                                track_tags)
from mocap.tracking.tracker import TrackOptions

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrackRequest:
    """What `mocap track` was asked to do; paths as given. `calibration` may be None when
    every marker of the machine carries a tag; `camera` None: the calibration's one camera,
    or the one named as the video file."""

    video: Path
    machine: str
    calibration: Path | None
    camera: str | None
    out: Path | None = None
    labels: Path | None = None
    propose_labels: Path | None = None
    start: int = 0
    stop: int | None = None
    options: TrackOptions = field(default_factory=TrackOptions)
    whole_video: bool = False  # a video that breaks part-way is an error, not half the tracks
    preview: Path | None = None


@dataclass(frozen=True)
class TrackReport:
    """`camera` the camera's name, `summary` of the tracking (None when only labels were
    proposed), `labels` the first frame's labels, `broken_at` the frame where the video
    broke, or None."""

    camera: str
    summary: TrackSummary | None
    labels: Tracks
    broken_at: int | None
    tracks: Tracks | None = None  # every frame's (None when only labels were proposed)

    def text(self, out, propose_labels=None, preview=None) -> str:
        """What `mocap track` prints of it."""
        if self.summary is None:
            lines = [f"proposed labels of frame {int(self.labels.frame[0])} ({len(self.labels)} markers), "
                     f"written to {propose_labels}; check them, then run with --labels"]
            lines += [f"  {self.labels.marker[k]:>8}  x {self.labels.xy[k, 0]:9.2f}  y {self.labels.xy[k, 1]:9.2f}"
                      for k in range(len(self.labels))]
            return "\n".join(lines)
        s = self.summary
        fitted = f"{s.fitted} with a model fit, " if s.fitted else ""  # tags alone need no fit
        lines = [f"{self.camera}: {s.frames} frames, {fitted}{s.labelled} marker "
                 f"positions written to {out}" + (f", {s.restarts} re-acquisitions" if s.restarts else "")]
        if s.unplaced:
            lines.append(f"in view but seldom or never labelled: {', '.join(s.unplaced)} (see them with --preview)")
        if preview:
            lines.append(f"labels drawn on the video in {preview}")
        return "\n".join(lines)


def run_track(request: TrackRequest) -> TrackReport:
    machine = load_machine(request.machine)
    video = Video(request.video)
    calibration = load_calibration(request.calibration) if request.calibration is not None else None
    labels = load_tracks(request.labels) if request.labels is not None else None
    return track_video(request, machine, calibration, labels, video)


def track_video(request: TrackRequest, machine: Machine, calibration: Calibration | None = None,
                labels: Tracks | None = None, video: Video | None = None) -> TrackReport:
    """Label and track the markers of `machine` in the video `request.video` through the
    camera of `calibration`; `labels` the first frame's marker pixels (else fitted or the
    tags). The tracks are written to `request.out` when it is given (and returned)."""
    video = Video(request.video) if video is None else video
    disks = [name for name, tag in zip(machine.marker_names, machine.tags) if tag < 0]
    if calibration is None:
        if disks:
            raise InputError(
                f"--calibration is required: {len(disks)} of the model's markers ({', '.join(disks[:6])}"
                f"{', ...' if len(disks) > 6 else ''}) are painted disks, which are labelled by fitting the "
                "model through the calibrated camera; only a model whose markers all carry tags needs none",
                path=request.machine,
            )
        return _run_tags(request, machine, video, request.camera or request.video.stem, video.info.fps)
    name = _camera_name(request, calibration.names)
    index = calibration.names.index(name)
    camera = calibration.cameras[index]
    if tuple(video.info.size) != tuple(camera.size):
        raise InputError(
            f"the video is {video.info.size[0]}x{video.info.size[1]} but camera {camera.name!r} "
            f"was calibrated at {camera.size[0]}x{camera.size[1]}; use the camera's own video",
            path=request.video,
        )
    fps = video.info.fps or float(calibration.extras[index].get("fps", 0.0))
    if not disks:
        return _run_tags(request, machine, video, camera.name, fps)
    start = calibration.joints(machine, index)
    if start is None:
        start = machine.clip_to_limits(np.zeros(machine.n_joints))
    model = CameraModel(machine, camera, solid=machine.n_joints > 0)
    labelled = None
    if labels is not None:
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
        first = _first(frames, request)
        result = label_first_frame(model, first[1], start, labelled, options)
        if result is None:
            raise InputError(
                f"frame {first[0]}: the model explains too few detected disks; digitise the "
                "markers of this frame and pass them with --labels",
                path=request.video,
            )
        labels = frame_rows(camera.name, first[0], fps, machine.marker_names, result)
        save_tracks(labels, request.propose_labels)
        return TrackReport(camera.name, None, labels, None)
    try:
        tracks, summary = track_frames(model, _progress(frames, request, video, camera.name), start, labelled, fps,
                                       options)
    except TooFewMarkersError as exc:
        raise InputError(f"{exc}; check the calibration, or film the machine from where more of its markers show",
                         path=request.video) from None
    except ValueError as exc:
        raise InputError(f"{exc}; digitise the markers of the first frame and pass them with --labels", path=request.video) from None
    return _finish(request, video, camera.name, tracks, summary, machine)


def _run_tags(request: TrackRequest, machine, video: Video, camera: str, fps: float) -> TrackReport:
    """A machine whose markers all carry tags: each frame's tags by their ids."""
    frames = video.frames(gray=True, start=request.start, stop=request.stop, prefetch=4)
    if request.propose_labels is not None:
        index, gray = _first(frames, request)
        labels, _ = track_tags(machine, [(index, gray)], camera, fps)
        if len(labels) == 0:
            raise InputError(f"frame {index}: {_NO_TAGS.format(dictionary=machine.tag_dictionary)}", path=request.video)
        save_tracks(labels, request.propose_labels)
        return TrackReport(camera, None, labels, None)
    tracks, summary = track_tags(machine, _progress(frames, request, video, camera), camera, fps)
    return _finish(request, video, camera, tracks, summary, machine)


_NO_TAGS = ("no tag of the machine model found; check the tag dictionary ({dictionary}, the model's [tags] "
            "dictionary) and the tags' ids, and that the tags are in the picture, at least 12 px across and in focus")


def _finish(request: TrackRequest, video: Video, camera: str, tracks: Tracks, summary: TrackSummary,
            machine) -> TrackReport:
    """Refuse an empty result, write the tracks (and the preview)."""
    if summary.frames == 0:
        raise InputError(f"no frame {request.start} in the video", path=request.video)
    if len(tracks) == 0:
        if not np.any(machine.tags < 0):
            what = _NO_TAGS.format(dictionary=machine.tag_dictionary)
        else:
            what = "no marker found; check the machine model, the calibration and --min-contrast"
        raise InputError(f"{summary.frames} frames read: {what}", path=request.video)
    if request.whole_video and video.broken_at is not None:
        raise InputError(
            f"the video breaks at frame {video.broken_at} of {video.info.frame_count} (truncated or "
            "corrupt); nothing written: repair or re-copy the video", path=request.video)
    if request.out is not None:
        save_tracks(tracks, request.out)
    if request.preview is not None:
        from mocap.tracking.preview import write_preview  # its video encoder only when asked for

        write_preview(video, tracks, request.preview, request.start, request.stop)
    first = tracks.select(tracks.frame == tracks.frame.min())
    return TrackReport(camera, summary, first, video.broken_at, tracks)


def _camera_name(request: TrackRequest, names: list[str]) -> str:
    """The camera to track: --camera, else the calibration's only camera, else the one named
    as the video file."""
    if request.camera is not None:
        if request.camera not in names:
            raise InputError(f"no camera named {request.camera!r}; the file has {', '.join(names)}",
                             path=request.calibration)
        return request.camera
    if len(names) == 1:
        return names[0]
    if request.video.stem in names:
        return request.video.stem
    raise InputError(f"the file has cameras {', '.join(names)}; say which one filmed the video with --camera",
                     path=request.calibration)


def _first(frames, request: TrackRequest) -> tuple[int, np.ndarray]:
    first = next(iter(frames), None)
    frames.close()
    if first is None:
        raise InputError(f"no frame {request.start} in the video", path=request.video)
    return first


def _progress(frames, request: TrackRequest, video: Video, camera: str):
    total = (request.stop or video.info.frame_count or 0) - request.start
    return progress(frames, total=max(total, 0) or None, desc=f"track {camera}", unit="frame")


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
