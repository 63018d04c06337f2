"""Log a replay into a Rerun recording stream, every series in one `send_columns` call.

Entity tree (it mirrors the frame tree; the world is the machine's base frame, z up):

    world                           view coordinates (right-handed, z up), marker names
    world/machine/<link>            the link's box (static) and world_from_link per frame
    world/markers/model             the model's markers at the fitted joints, per frame
    world/markers/observed          triangulated markers, per frame
    world/<point>                   named points (bucket tip ...) per frame
    world/trail/<cycle>             the bucket tip's path in one dig cycle, a segment a frame,
                                    coloured by the dig's class
    world/cameras/<cam>             world_from_cam and the pinhole (static, OpenCV axes RDF)
    world/cameras/<cam>/video       the camera's H.264 video and the frame shown per frame
    world/cameras/<cam>/first_frame the video's first frame as a JPEG (static), under the video
    world/cameras/<cam>/tracks      the camera's 2-D tracks
    plots/<group>/<series>          joints, bucket (angle), speed, uncertainty, base, one
                                    group per other column: one unit per group
    plots/phase                     the dig-cycle phase (1 dig, 2 swing loaded, 3 dump, 4 swing back)

Timelines: ``frame`` (the reference camera's frame number) and ``time`` (seconds).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import rerun as rr

from mocap.core.calibration import Calibration
from mocap.core.classes import DIG_CLASSES, OTHER
from mocap.core.machine import Machine
from mocap.core.motion import Motion
from mocap.core.points import Points
from mocap.core.shapes import link_boxes
from mocap.viewer import scene
from mocap.viewer.video import Video, first_frame_jpeg

LINK_COLORS = np.array(
    [[120, 120, 120], [230, 170, 40], [240, 200, 60], [220, 140, 40], [160, 160, 170], [200, 90, 60]],
    dtype=np.uint8,
)
MODEL_MARKER_COLOR = (90, 160, 255)
OBSERVED_MARKER_COLOR = (255, 80, 200)
TRACK_COLOR = (255, 230, 0)
TRAIL_COLORS = np.array(
    [[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189], [23, 190, 207]],
    dtype=np.uint8,
)
FIRST_FRAME_DRAW_ORDER = -30.0  # below the video's frames (Rerun draws video at -15)
CLASS_COLORS = dict(zip((*DIG_CLASSES, OTHER), [(31, 119, 180), (255, 127, 14), (44, 160, 44), (150, 150, 150)]))


def entity(*parts: str) -> str:
    """An entity path from names that may hold characters Rerun reserves."""
    return "/".join(rr.escape_entity_path_part(p) for p in parts)


def link_path(name: str) -> str:
    return "world/machine/" + entity(name)


def camera_path(name: str) -> str:
    return "world/cameras/" + entity(name)


def trail_path(name: str) -> str:
    return "world/trail/" + entity(name)


def time_columns(frame: np.ndarray, time: np.ndarray) -> list[rr.TimeColumn]:
    """The two timelines of a series: reference frames and seconds."""
    return [
        rr.TimeColumn("frame", sequence=np.asarray(frame, dtype=np.int64)),
        rr.TimeColumn("time", duration=np.asarray(time, dtype=float)),
    ]


def log_world(rec: rr.RecordingStream, machine: Machine) -> None:
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    labels = [(i, name) for i, name in enumerate(machine.marker_names)]
    rec.log("world", rr.AnnotationContext(labels), static=True)


def log_link_boxes(rec: rr.RecordingStream, machine: Machine) -> None:
    """Each link as a solid box in its own frame (static), at `link_path`."""
    boxes = link_boxes(machine)  # (L, 2, 3) min and max corners in the link frame
    for i, name in enumerate(machine.link_names):
        rec.log(
            link_path(name),
            rr.Boxes3D(
                centers=[boxes[i].mean(axis=0)],
                half_sizes=[(boxes[i, 1] - boxes[i, 0]) / 2],
                colors=[LINK_COLORS[i % len(LINK_COLORS)]],
                fill_mode="solid",
                labels=[name],
                show_labels=False,
            ),
            static=True,
        )


def log_machine(rec: rr.RecordingStream, machine: Machine, motion: Motion, series: scene.LinkSeries) -> None:
    """Each link as a solid box in its own frame, moved by world_from_link per frame."""
    log_link_boxes(rec, machine)
    if not len(series.rows):
        return
    quaternion = series.quaternions()
    times = time_columns(motion.frame[series.rows], motion.time[series.rows])
    for i, name in enumerate(machine.link_names):
        rec.send_columns(
            link_path(name),
            indexes=times,
            columns=rr.Transform3D.columns(translation=series.translation[:, i], quaternion=quaternion[:, i]),
        )


def log_markers(
    rec: rr.RecordingStream,
    machine: Machine,
    motion: Motion,
    series: scene.LinkSeries,
    points: Points | None,
    fps: float,
) -> None:
    """Model markers at the fitted joints, and the triangulated ones where given."""
    n_markers = len(machine.marker_names)
    rows, markers = series.rows, scene.model_markers(machine, series)
    path = "world/markers/model"
    rec.log(
        path,
        rr.Points3D.from_fields(class_ids=np.arange(n_markers), colors=[MODEL_MARKER_COLOR], radii=[-4.0],
                                show_labels=False),  # names on hover, not over the markers
        static=True,
    )
    if len(rows):
        rec.send_columns(
            path,
            indexes=time_columns(motion.frame[rows], motion.time[rows]),
            columns=rr.Points3D.columns(positions=markers.reshape(-1, 3)).partition([n_markers] * len(rows)),
        )
    if points is None or len(points) == 0:
        return
    lookup = {name: i for i, name in enumerate(machine.marker_names)}
    marker = np.array([lookup.get(name, -1) for name in points.marker], dtype=np.int64)
    keep = (marker >= 0) & np.all(np.isfinite(points.xyz), axis=1)
    order = np.argsort(points.frame[keep], kind="stable")
    frames, xyz, marker = points.frame[keep][order], points.xyz[keep][order], marker[keep][order]
    groups, counts = np.unique(frames, return_counts=True)
    path = "world/markers/observed"
    rec.log(path, rr.Points3D.from_fields(colors=[OBSERVED_MARKER_COLOR], radii=[-5.0], show_labels=False), static=True)
    if len(groups):
        rec.send_columns(
            path,
            indexes=time_columns(groups, scene.camera_time(groups, fps, 0.0)),
            columns=rr.Points3D.columns(positions=xyz, class_ids=marker).partition(counts),
        )


def log_points(rec: rr.RecordingStream, motion: Motion) -> None:
    """The motion's named points (bucket tip ...), one entity each."""
    for k, name in enumerate(motion.point_names):
        xyz = motion.points[:, k]
        rows = np.flatnonzero(np.all(np.isfinite(xyz), axis=1))
        path = "world/" + entity(name)
        rec.log(path, rr.Points3D.from_fields(labels=[name], radii=[-8.0], colors=[(255, 255, 255)]), static=True)
        if len(rows):
            rec.send_columns(
                path,
                indexes=time_columns(motion.frame[rows], motion.time[rows]),
                columns=rr.Points3D.columns(positions=xyz[rows]),
            )


def log_trails(rec: rr.RecordingStream, trails: Sequence[scene.Trail]) -> None:
    """A segment per frame per cycle, coloured by its dig class (by its order where the
    class is not known); the blueprint accumulates them from the cycle's start."""
    for k, trail in enumerate(trails):
        path = trail_path(trail.name)
        color = CLASS_COLORS.get(trail.label, TRAIL_COLORS[k % len(TRAIL_COLORS)])
        rec.log(path, rr.LineStrips3D.from_fields(colors=[color], radii=[-2.0]), static=True)
        if len(trail):
            rec.send_columns(
                path,
                indexes=time_columns(trail.frame, trail.time),
                columns=rr.LineStrips3D.columns(strips=trail.segments),
            )


def log_cameras(rec: rr.RecordingStream, calibration: Calibration, scale: float) -> None:
    """Each camera in its calibrated place, static; `scale` (m) sets the frustum's depth."""
    for camera in calibration.cameras:
        path = camera_path(camera.name)
        center, rotation = scene.camera_pose(camera)
        rec.log(path, rr.Transform3D(translation=center, mat3x3=rotation), static=True)
        rec.log(
            path,
            rr.Pinhole(
                image_from_camera=scene.rerun_intrinsics(camera),
                resolution=list(camera.size),
                camera_xyz=rr.ViewCoordinates.RDF,
                image_plane_distance=scale,
            ),
            static=True,
        )


def log_video(
    rec: rr.RecordingStream, camera: str, video: Video, motion: Motion, fps: float, offset: float,
    size: tuple[int, int] | None = None,
) -> None:
    """The camera's video asset and, at each motion frame, the video frame showing it. A
    camera whose video starts after the motion's first frame shows its first frame until
    then, with a note (at the top of its image of `size`) saying why."""
    path = camera_path(camera) + "/video"
    rec.log(path, video.asset, static=True)
    first = first_frame_jpeg(video.path)
    if first is not None:  # under the video: seen at once, before the viewer has decoded the video
        rec.log(camera_path(camera) + "/first_frame",
                rr.EncodedImage(contents=first, media_type="image/jpeg", draw_order=FIRST_FRAME_DRAW_ORDER),
                static=True)
    rows, frames = scene.video_frame_rows(motion, len(video), fps, offset)
    if len(rows) and rows[0] > 0:
        start = int(rows[0])  # the motion row of the video's first frame
        rows, frames = np.concatenate([np.arange(start), rows]), np.concatenate([np.zeros(start, int), frames])
        if size is not None:
            note = camera_path(camera) + "/note"
            text = f"starts {motion.time[start] - motion.time[0]:.2f} s later: first frame"
            for row, item in ((0, rr.Points2D([[size[0] / 2, 0.06 * size[1]]], labels=[text], radii=[0.5],
                                              colors=[(255, 255, 0)], show_labels=True)),
                              (start, rr.Clear(recursive=False))):
                rec.set_time("frame", sequence=int(motion.frame[row]))
                rec.set_time("time", duration=float(motion.time[row]))
                rec.log(note, item)
            rec.reset_time()
    if len(rows):
        rec.send_columns(
            path,
            indexes=time_columns(motion.frame[rows], motion.time[rows]),
            columns=rr.VideoFrameReference.columns_nanos(video.timestamps_ns[frames]),
        )


def log_tracks(rec: rr.RecordingStream, series: scene.TrackSeries, camera: str) -> None:
    """The camera's 2-D tracks over its image; nothing for a camera without tracks."""
    if len(series.counts) == 0:
        return
    path = camera_path(camera) + "/tracks"
    rec.log(path, rr.Points2D.from_fields(colors=[TRACK_COLOR], radii=[-3.0], show_labels=False), static=True)
    rec.send_columns(
        path,
        indexes=time_columns(series.frame, series.time),
        columns=rr.Points2D.columns(positions=series.xy, class_ids=series.marker).partition(series.counts),
    )


def log_scalar(rec: rr.RecordingStream, path: str, name: str, motion: Motion, values: np.ndarray) -> None:
    """One plotted series; frames where it is unknown are left as gaps."""
    values = np.asarray(values, dtype=float)
    rows = np.flatnonzero(np.isfinite(values))
    rec.log(path, rr.SeriesLines(names=[name]), static=True)
    if len(rows):
        rec.send_columns(
            path,
            indexes=time_columns(motion.frame[rows], motion.time[rows]),
            columns=rr.Scalars.columns(scalars=values[rows]),
        )


def log_phases(rec: rr.RecordingStream, motion: Motion, phases: np.ndarray) -> None:
    """The dig-cycle phase of every frame (F,) as a time series."""
    log_scalar(rec, "plots/phase", "phase (1 dig, 2 swing loaded, 3 dump, 4 swing back)", motion, phases)


def log_plots(rec: rr.RecordingStream, machine: Machine, motion: Motion, tip: str | None) -> None:
    """Joint values (deg / m), bucket angle (deg), speeds (m/s), uncertainties, other columns."""
    for series in scene.plot_series(machine, motion, tip):
        log_scalar(rec, f"plots/{series.group}/" + entity(series.name), series.label, motion, series.values)
