"""Speed and size of the Rerun replay: column-wise `send_columns` (mocap.viewer) against the
naive loop that calls `rr.log` for every entity at every frame, on the same data.

    python benchmarks/bench_view.py [--hours 2] [--naive-minutes 5]

Two sessions: 300 frames before 3 cameras with H.264 videos, 2-D tracks, triangulated
points and 2 dig cycles; and a long one (2 h at 30 fps by default) of motion only, with a
dig cycle every 30 s. The naive loop on the long session runs on its first minutes only and
is scaled to the whole, as its time grows linearly with the frames.
"""

from __future__ import annotations

import argparse
import tempfile
import time
import uuid
from dataclasses import replace
from pathlib import Path

import numpy as np
import rerun as rr
from scipy.interpolate import CubicSpline

from mocap.core.calibration import Calibration
from mocap.core.motion import Motion
from mocap.core.points import Points
from mocap.io.machine_toml import load_machine
from mocap.synthetic.encode import video_writer
from mocap.synthetic.scenes import observe, random_joints, ring_of_cameras
from mocap.viewer import Cycles, Replay, Sinks, run_replay
from mocap.viewer import record, scene
from mocap.viewer.replay import frustum_depth
from mocap.viewer.video import load_video

FPS = 30.0


def make_motion(machine, n_frames: int, rng) -> Motion:
    n_keys = max(4, n_frames // 90)
    time_ = np.arange(n_frames) / FPS
    joints = CubicSpline(np.linspace(0.0, time_[-1], n_keys), random_joints(machine, n_keys, rng))(time_)
    return Motion(
        machine.joint_names,
        machine.point_names,
        np.arange(n_frames),
        time_,
        joints,
        machine.points(joints),
        machine.bucket_angles(joints),
        joints_sd=np.full_like(joints, np.radians(0.2)),
        points_sd=np.full((n_frames, len(machine.point_names)), 0.02),
    )


def encode_video(path: Path, n_frames: int, size=(320, 240)) -> Path:
    with video_writer(path, size, FPS) as write:
        for i in range(n_frames):
            write(np.full((size[1], size[0], 3), (3 * i) % 256, dtype=np.uint8))
    return path


def short_session(folder: Path, rng) -> Replay:
    machine = load_machine("hitachi_ex3500")
    motion = make_motion(machine, 300, rng)
    cameras = ring_of_cameras(3, [6.0, 0.0, 4.0], (30.0, 45.0), rng)
    calibration = Calibration(tuple(cameras), tuple({"fps": FPS} for _ in cameras))
    tracks = observe(cameras, machine, motion.joints, rng, miss_fraction=0.1)
    truth = machine.markers(motion.joints)
    f, m = np.nonzero(np.ones(truth.shape[:2], dtype=bool))
    points = Points(f, np.asarray(machine.marker_names, dtype=object)[m], truth[f, m], np.zeros(len(f)), np.full(len(f), 3))
    videos = {c.name: encode_video(folder / f"{c.name}.mp4", 300) for c in cameras}
    cycles = Cycles(("1", "2"), np.array([0, 150]), np.array([149, 299]))
    return Replay(machine, calibration, motion, calibration.fps(), points, tracks, videos, cycles)


def long_session(hours: float, rng) -> Replay:
    machine = load_machine("hitachi_ex3500")
    n_frames = int(hours * 3600 * FPS)
    motion = make_motion(machine, n_frames, rng)
    cameras = ring_of_cameras(3, [6.0, 0.0, 4.0], (30.0, 45.0), rng)
    calibration = Calibration(tuple(cameras), tuple({"fps": FPS} for _ in cameras))
    starts = np.arange(0, n_frames, int(30 * FPS))
    cycles = Cycles(tuple(str(k + 1) for k in range(len(starts))), starts, np.r_[starts[1:] - 1, n_frames - 1])
    return Replay(machine, calibration, motion, calibration.fps(), cycles=cycles)


def naive_replay(replay: Replay, path: Path) -> None:
    """The peer: the same content, one `rr.log` per entity per frame."""
    rec = rr.RecordingStream("mocap-naive", recording_id=uuid.uuid4())
    rec.save(path)
    machine, motion, calibration = replay.machine, replay.motion, replay.calibration
    record.log_world(rec, machine)
    record.log_cameras(rec, calibration, frustum_depth(calibration))
    series = scene.link_series(machine, motion)
    quaternion = series.quaternions()
    markers = scene.model_markers(machine, series)
    tip = motion.point("bucket_tip")
    scale, _ = scene.joint_display_units(machine)
    cycle_of = np.searchsorted(replay.cycles.start, motion.frame, side="right") - 1
    videos = {}
    for k, camera in enumerate(calibration.cameras):
        video = load_video(replay.videos[camera.name], camera.name) if camera.name in replay.videos else None
        if video is not None:
            rec.log(record.camera_path(camera.name) + "/video", video.asset, static=True)
            videos[camera.name] = video
    track_rows = {}
    if replay.tracks is not None:
        for camera in calibration.names:
            rows = replay.tracks.of_camera(camera)
            track_rows[camera] = (rows, {f: np.flatnonzero(rows.frame == f) for f in np.unique(rows.frame)})
    point_rows = {}
    if replay.points is not None:
        lookup = {n: i for i, n in enumerate(machine.marker_names)}
        ids = np.array([lookup[n] for n in replay.points.marker])
        point_rows = {f: (replay.points.xyz[replay.points.frame == f], ids[replay.points.frame == f]) for f in np.unique(replay.points.frame)}
    for r, frame in enumerate(motion.frame):
        rec.set_time("frame", sequence=int(frame))
        rec.set_time("time", duration=float(motion.time[r]))
        for i, link in enumerate(machine.link_names):
            rec.log(record.link_path(link), rr.Transform3D(translation=series.translation[r, i], quaternion=quaternion[r, i]))
        rec.log("world/markers/model", rr.Points3D(markers[r], class_ids=np.arange(len(machine.marker_names))))
        if frame in point_rows:
            rec.log("world/markers/observed", rr.Points3D(point_rows[frame][0], class_ids=point_rows[frame][1]))
        rec.log("world/bucket_tip", rr.Points3D([tip[r]]))
        if r and cycle_of[r] == cycle_of[r - 1]:
            rec.log(record.trail_path(replay.cycles.name[cycle_of[r]]), rr.LineStrips3D([tip[r - 1 : r + 1]]))
        for name, video in videos.items():
            if frame < len(video):
                rec.log(record.camera_path(name) + "/video", rr.VideoFrameReference(nanoseconds=int(video.timestamps_ns[frame])))
        for name, (rows, index) in track_rows.items():
            if frame in index:
                at = index[frame]
                rec.log(record.camera_path(name) + "/tracks", rr.Points2D(rows.xy[at] + 0.5))
        for j, joint in enumerate(motion.joint_names):
            rec.log(f"plots/joints/{joint}", rr.Scalars(motion.joints[r, j] * scale[j]))
        rec.log("plots/bucket_angle", rr.Scalars(np.degrees(motion.bucket_angle[r])))
    rec.flush()
    rec.disconnect()


def first_frames(replay: Replay, n: int) -> Replay:
    motion = replay.motion
    cut = Motion(
        motion.joint_names, motion.point_names, motion.frame[:n], motion.time[:n], motion.joints[:n],
        motion.points[:n], motion.bucket_angle[:n], motion.joints_sd[:n], motion.points_sd[:n],
    )
    return replace(replay, motion=cut)


def timed(fn, *args) -> float:
    start = time.perf_counter()
    fn(*args)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hours", type=float, default=2.0, help="length of the long session")
    parser.add_argument("--naive-minutes", type=float, default=5.0, help="naive loop on this much of it")
    args = parser.parse_args()
    rng = np.random.default_rng(3)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        short = short_session(tmp, rng)
        ours = timed(run_replay, short, Sinks(save=tmp / "short.rrd"))
        naive = timed(naive_replay, short, tmp / "short_naive.rrd")
        rows.append(("300 frames, 3 cameras + H.264 video", 300, ours, (tmp / "short.rrd").stat().st_size, naive, (tmp / "short_naive.rrd").stat().st_size, 1.0))

        long = long_session(args.hours, rng)
        n_long = len(long.motion)
        ours = timed(run_replay, long, Sinks(save=tmp / "long.rrd"))
        n_naive = min(n_long, int(args.naive_minutes * 60 * FPS))
        naive = timed(naive_replay, first_frames(long, n_naive), tmp / "long_naive.rrd")
        share = n_naive / n_long
        size_naive = (tmp / "long_naive.rrd").stat().st_size / share
        rows.append((f"{args.hours:g} h at 30 fps, motion only", n_long, ours, (tmp / "long.rrd").stat().st_size, naive / share, size_naive, share))

    print(f"{'session':38} {'frames':>8} {'send_columns s':>15} {'.rrd MB':>8} {'naive rr.log s':>15} {'.rrd MB':>8} {'speed-up':>9}")
    for name, frames, ours, size, naive, size_naive, share in rows:
        note = "" if share == 1.0 else f"   (naive: first {share:.1%}, scaled)"
        print(
            f"{name:38} {frames:8d} {ours:15.2f} {size / 1e6:8.1f} {naive:15.2f} {size_naive / 1e6:8.1f} {naive / ours:8.1f}x{note}"
        )


if __name__ == "__main__":
    main()
