"""What a replay shows, as arrays: the pure part of the Rerun recording.

Everything here takes the project's data objects and returns plain arrays ready to be
logged column-wise; nothing touches a file or a recording stream.

Shapes: F motion frames, L links, M markers, C cameras, K dig cycles, R rows.
Clocks (DESIGN.md): camera k's frame n shows time ``n / fps_k + offset_k``; the motion's
frames are the reference camera's frames, its times the same clock in seconds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from mocap.core.camera import Camera
from mocap.core.machine import REVOLUTE, Machine
from mocap.core.motion import Motion
from mocap.core.tracks import Tracks
from mocap.io.motion_csv import BASE_ANGLES, BASE_POSITION, world_from_base_of

# OpenCV puts the centre of the top-left pixel at (0, 0), Rerun its top-left corner.
RERUN_FROM_OPENCV_PIXEL = 0.5


@dataclass(frozen=True)
class LinkSeries:
    """World-from-link transforms of the frames where the joints are known.

    rows (R,) indices into the motion's frames; rotation (R, L, 3, 3); translation (R, L, 3) m.
    """

    rows: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray

    def __post_init__(self) -> None:
        r = len(self.rows)
        if self.translation.shape[:1] != (r,) or self.translation.shape[2:] != (3,):
            raise ValueError(f"LinkSeries.translation: expected ({r}, L, 3), got {self.translation.shape}")
        if self.rotation.shape != self.translation.shape + (3,):
            raise ValueError(f"LinkSeries.rotation: expected ({r}, L, 3, 3), got {self.rotation.shape}")

    def quaternions(self) -> np.ndarray:
        """The rotations as quaternions (R, L, 4), scalar last (x, y, z, w) as scipy and Rerun use."""
        n_rows, n_links = self.translation.shape[:2]
        return Rotation.from_matrix(self.rotation.reshape(-1, 3, 3)).as_quat().reshape(n_rows, n_links, 4)

    def points(self, links: np.ndarray, positions: np.ndarray) -> np.ndarray:
        """World positions (R, N, 3) of points fixed in links: links (N,), positions (N, 3) in
        the link frames; one product per link over all frames at once."""
        out = np.empty((len(self.rows), len(links), 3))
        for link in np.unique(links):
            on = np.flatnonzero(links == link)
            out[:, on] = positions[on] @ self.rotation[:, link].swapaxes(1, 2) + self.translation[:, link, None]
        return out


def world_from_base(motion: Motion) -> np.ndarray | None:
    """(F, 4, 4) base poses from the motion's base columns (a base that bounces or has
    moved since calibration), missing ones 0; None if it has none."""
    return world_from_base_of(motion.extra, len(motion))


def known_rows(motion: Motion) -> np.ndarray:
    """(R,) indices of the frames whose joint values (and base pose, if any) are all finite."""
    known = np.all(np.isfinite(motion.joints), axis=1)
    base = world_from_base(motion)
    if base is not None:
        known &= np.all(np.isfinite(base[:, :3, 3]), axis=1)
    return np.flatnonzero(known)


def _base_at(motion: Motion, rows: np.ndarray) -> np.ndarray | None:
    base = world_from_base(motion)
    return None if base is None else base[rows]


def link_series(machine: Machine, motion: Motion) -> LinkSeries:
    """Each link's pose in the world at every frame with known joints."""
    rows = known_rows(motion)
    world_from_link = machine.link_poses(motion.joints[rows], _base_at(motion, rows))  # (R, L, 4, 4)
    return LinkSeries(rows, world_from_link[..., :3, :3], world_from_link[..., :3, 3])


def model_markers(machine: Machine, links: LinkSeries) -> np.ndarray:
    """The model's marker positions (R, M, 3) at the frames of `links`."""
    return links.points(machine.marker_links, machine.marker_positions)


def joint_display_units(machine: Machine) -> tuple[np.ndarray, tuple[str, ...]]:
    """(J,) factors from internal units to display units, and the unit names (deg or m)."""
    revolute = np.array([joint.type == REVOLUTE for joint in machine.joints], dtype=bool)
    return np.where(revolute, np.degrees(1.0), 1.0), tuple("deg" if r else "m" for r in revolute)


def tip_speed(motion: Motion, point: str) -> np.ndarray:
    """(F,) speed of a named point, m/s: the motion's ``<point>_speed`` column if it has one,
    else central differences of its positions over time (NaN next to unknown positions)."""
    column = motion.extra.get(f"{point}_speed")
    if column is not None:
        return np.asarray(column, dtype=float)
    xyz = motion.point(point)
    if len(xyz) < 2:
        return np.full(len(xyz), np.nan)
    velocity = np.gradient(xyz, motion.time, axis=0)
    return np.linalg.norm(velocity, axis=1)


@dataclass(frozen=True)
class PlotSeries:
    """One plotted series: its group under plots/, name, label with unit, values (F,)."""

    group: str
    name: str
    label: str
    values: np.ndarray


def _extra_unit(name: str) -> tuple[str, str]:
    """A plot group and label for an extra motion column, from its name's unit suffix."""
    for suffix, unit in (("_acceleration", "m/s²"), ("_px", "px"), ("_deg", "deg"), ("_m", "m")):
        if name.endswith(suffix):
            return f"extra_{name}", f"{name} ({unit})"
    if name == "observations":
        return "extra_observations", "observations (count)"
    if name == "filled":
        return "extra_filled", "filled (1: predicted across a gap)"
    return f"extra_{name}", name


def plot_series(machine: Machine, motion: Motion, tip: str | None) -> list[PlotSeries]:
    """The motion's per-frame columns in display units, grouped so that one plot holds one
    unit: joints (deg; prismatic ones in joints_m, m), the bucket angle (deg, group bucket),
    speeds (m/s; the tip's computed if the file has none), uncertainty (SDs in deg,
    uncertainty_m in m), base (position columns) and one group per other column."""
    scale, units = joint_display_units(machine)
    out = [
        PlotSeries("joints" if units[j] == "deg" else "joints_m", name, f"{name} ({units[j]})",
                   motion.joints[:, j] * scale[j])
        for j, name in enumerate(motion.joint_names)
    ]
    out.append(PlotSeries("bucket", "bucket_angle", "bucket angle (deg)", np.degrees(motion.bucket_angle)))
    if tip is not None:
        out.append(PlotSeries("speed", tip, f"{tip} speed (m/s)", tip_speed(motion, tip)))
    if motion.joints_sd is not None:
        out += [
            PlotSeries("uncertainty" if units[j] == "deg" else "uncertainty_m", f"{name}_sd",
                       f"{name} sd ({units[j]})", motion.joints_sd[:, j] * scale[j])
            for j, name in enumerate(motion.joint_names)
        ]
    if motion.bucket_angle_sd is not None:
        sd = np.degrees(motion.bucket_angle_sd)
        out.append(PlotSeries("uncertainty", "bucket_angle_sd", "bucket angle sd (deg)", sd))
    if motion.points_sd is not None:
        out += [
            PlotSeries("uncertainty_m", f"{name}_sd", f"{name} sd (m)", motion.points_sd[:, k])
            for k, name in enumerate(motion.point_names)
        ]
    speeds = {f"{p}_speed": p for p in motion.point_names}
    for name, values in motion.extra.items():
        if name in BASE_POSITION:
            out.append(PlotSeries("base", name, f"{name} (m)", values))
        elif name in BASE_ANGLES:
            out.append(PlotSeries("base_angles", name, f"{name} (deg)", values))
        elif name in speeds and speeds[name] != tip:
            out.append(PlotSeries("speed", speeds[name], f"{speeds[name]} speed (m/s)", values))
        elif name not in speeds:
            group, label = _extra_unit(name)
            out.append(PlotSeries(group, name, label, values))
    return out


PHASES = ("dig", "swing loaded", "dump", "swing back")


def phase_series(motion: Motion, starts: np.ndarray, ends: np.ndarray, phases: np.ndarray) -> np.ndarray:
    """The dig-cycle phase of every motion frame (F,): 1 dig, 2 swing loaded, 3 dump,
    4 swing back, NaN outside the cycles or where not known. Cycles [start, end] (K,)
    motion frames; phases (K, 4) the frames where each phase begins, -1 where not known."""
    out = np.full(len(motion), np.nan)
    frame = motion.frame
    for start, end, begins in zip(starts, ends, phases):
        for p, begin in enumerate(begins):
            if begin < 0:
                continue
            later = [b for b in begins[p + 1:] if b >= 0]
            stop = min(later[0] - 1 if later else end, end)
            out[(frame >= begin) & (frame <= stop)] = p + 1
    return out


def working_view(motion: Motion, tip: str | None) -> tuple[np.ndarray, np.ndarray] | None:
    """Eye position and look target (3,) m that frame the machine's working range — the
    swing axis and everywhere the tip went — from the side, a little behind and above;
    None without a known tip position."""
    if tip is None:
        return None
    xyz = motion.point(tip)
    xyz = xyz[np.all(np.isfinite(xyz), axis=1)]
    if len(xyz) == 0:
        return None
    box = np.vstack([xyz, np.zeros((1, 3))])
    low, high = box.min(axis=0), box.max(axis=0)
    target = 0.5 * (low + high)
    extent = max(float(np.linalg.norm(high - low)), 1.0)
    direction = np.array([-0.2, -1.0, 0.3])  # from the side, a little behind and above
    return target + 1.8 * extent * direction / np.linalg.norm(direction), target


@dataclass(frozen=True)
class Trail:
    """The bucket tip's path in one dig cycle, drawn as segments that accumulate.

    frame (S,) and time (S,) s of the motion frame at which each segment ends; segments
    (S, 2, 3) from the previous frame's tip to this frame's, metres; first_frame and
    first_time the cycle's first motion frame; label the dig class, "" if not known.
    """

    name: str
    first_frame: int
    first_time: float
    frame: np.ndarray
    time: np.ndarray
    segments: np.ndarray
    label: str = ""

    def __post_init__(self) -> None:
        s = len(self.frame)
        if np.shape(self.time) != (s,) or np.shape(self.segments) != (s, 2, 3):
            raise ValueError(f"Trail {self.name!r}: expected time ({s},), segments ({s}, 2, 3)")

    def __len__(self) -> int:
        return len(self.frame)


def trails(motion: Motion, point: str, starts: np.ndarray, ends: np.ndarray, names, labels=()) -> list[Trail]:
    """One trail per cycle [start, end] (motion frames, inclusive), with its dig class from
    `labels` (K,) if given; segments touching an unknown tip position are left out. Cycles
    with no motion frame are left out."""
    xyz = motion.point(point)
    known = np.all(np.isfinite(xyz), axis=1)
    out = []
    labels = tuple(labels) or ("",) * len(starts)
    for name, start, end, label in zip(names, starts, ends, labels):
        rows = np.flatnonzero((motion.frame >= start) & (motion.frame <= end))
        if len(rows) == 0:
            continue
        ends_at = rows[1:]
        ok = known[ends_at] & known[ends_at - 1]
        ends_at = ends_at[ok]
        segments = np.stack([xyz[ends_at - 1], xyz[ends_at]], axis=1)
        out.append(
            Trail(
                str(name),
                int(motion.frame[rows[0]]),
                float(motion.time[rows[0]]),
                motion.frame[ends_at],
                motion.time[ends_at],
                segments.reshape(-1, 2, 3),
                str(label),
            )
        )
    return out


def camera_pose(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """The camera's world_from_cam: translation (3,) = its centre, rotation (3, 3)."""
    world_from_cam = camera.cam_from_world.inverse()
    return world_from_cam.translation, world_from_cam.rotation


def rerun_intrinsics(camera: Camera) -> np.ndarray:
    """K (3, 3) for Rerun's pixel grid: the principal point moved by half a pixel."""
    matrix = camera.matrix.copy()
    matrix[:2, 2] += RERUN_FROM_OPENCV_PIXEL
    return matrix


def camera_time(frames: np.ndarray, fps: float, offset: float) -> np.ndarray:
    """Times (s) shown by a camera's own frames (N,)."""
    return np.asarray(frames, dtype=float) / fps + offset


def reference_frames(times: np.ndarray, fps: float, offset: float) -> np.ndarray:
    """The reference camera's frame numbers (N,) nearest to times (N,) s."""
    return np.rint((np.asarray(times, dtype=float) - offset) * fps).astype(np.int64)


@dataclass(frozen=True)
class TrackSeries:
    """One camera's 2-D tracks grouped by frame, for a column-wise log.

    frame (G,) reference frames; time (G,) s; counts (G,) rows per group;
    xy (R, 2) Rerun pixels; marker (R,) marker index into the machine's markers.
    """

    frame: np.ndarray
    time: np.ndarray
    counts: np.ndarray
    xy: np.ndarray
    marker: np.ndarray


def track_series(
    tracks: Tracks,
    camera: str,
    marker_names: tuple[str, ...],
    fps: float,
    offset: float,
    reference_fps: float,
    reference_offset: float,
) -> TrackSeries:
    """The rows of `camera` with a known marker name, on the reference clock."""
    lookup = {name: i for i, name in enumerate(marker_names)}
    rows = tracks.of_camera(camera)
    marker = np.array([lookup.get(name, -1) for name in rows.marker], dtype=np.int64)
    keep = marker >= 0
    frames, xy, marker = rows.frame[keep], rows.xy[keep], marker[keep]
    order = np.argsort(frames, kind="stable")
    frames, xy, marker = frames[order], xy[order], marker[order]
    groups, first, counts = np.unique(frames, return_index=True, return_counts=True)
    times = camera_time(groups, fps, offset)
    return TrackSeries(
        reference_frames(times, reference_fps, reference_offset),
        times,
        counts,
        xy + RERUN_FROM_OPENCV_PIXEL,
        marker,
    )


def video_frame_rows(
    motion: Motion, n_video_frames: int, fps: float, offset: float
) -> tuple[np.ndarray, np.ndarray]:
    """For each motion frame, the camera's own video frame showing that moment.

    Returns rows (R,) motion rows whose moment the video holds, and frames (R,) the video's
    frame indices (0 .. n_video_frames - 1).
    """
    frames = np.rint((motion.time - offset) * fps).astype(np.int64)
    rows = np.flatnonzero((frames >= 0) & (frames < n_video_frames))
    return rows, frames[rows]
