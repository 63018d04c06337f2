"""`mocap live` on a synthetic session played in real time, against the truth and the
offline chain on the same videos.

Writes a session with `mocap synth` (the default look, `--cameras` cameras at `--size`), then
for 1 .. N of its cameras: the videos played as their cameras delivered them
(`--realtime`) for `--duration` seconds through `mocap live` (`mocap.live.run.run_live`):
rows out per second of the run, frames dropped, latency p50 / p99 /
max (from the reference frame's arrival to its row written, the smoother's lag included),
the process's CPU time per row (all its threads: decoding, tracking, fitting); beside it the decode-only rate of the same
streams (the tracker's own grey decoding, all the cameras' frames of that duration one
after another: the floor); and the bucket tip's RMSE against the truth, live and by the
offline chain (`mocap track` each camera, then `mocap fit`, over the whole videos) over the
same frames; and the same live chain reading the files as fast as they are tracked (no frame
dropped, no time limit per frame) for the same time, against the offline chain on its rows;
and `--view`'s cost: the process's CPU per row (Rerun's sending thread included) logging the
as-fast run's rows to an .rrd file, and the main thread's time per row inside the run.

    python benchmarks/bench_live.py [--size 960x540] [--cameras 3] [--duration 20] [--seed 7] [--lag 1] [--fixed-base]
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from mocap import cli
from mocap.io.cameras_toml import load_calibration
from mocap.io.machine_toml import load_machine
from mocap.io.motion_csv import load_motion
from mocap.io.video import Video
from mocap.live.run import LiveRequest, run_live
from mocap.live.sources import parse_source
from mocap.reconstruct.kinfit import FitOptions
from mocap.reconstruct.smooth import SmoothOptions
from mocap.reconstruct.stage import run_fit
from mocap.tracking.stage import TrackRequest, run_track

MACHINE = "hitachi_ex3500"


def make_session(root: Path, size: str, cameras: int, seed: int) -> Path:
    session = root / f"live_{size}_{cameras}_{seed}"
    if not (session / "COMPLETE").exists():
        assert cli.main(["synth", "--machine", MACHINE, "--cameras", str(cameras), "--cycles", "1", "--seed",
                         str(seed), "--size", size, "--hold", "0.5", "--out", str(session)]) == 0
    return session


def tip_rmse(frames: np.ndarray, tips: np.ndarray, truth) -> float:
    error = np.linalg.norm(tips - truth.point("bucket_tip")[frames], axis=1)
    return float(np.sqrt(np.nanmean(error**2)))


def decode_rate(videos: list[Path], frames: list[int]) -> float:
    """Frames per second decoding every camera's first frames one after another (grey)."""
    started, total = time.perf_counter(), 0
    for video, n in zip(videos, frames):
        for _ in Video(video).frames(gray=True, stop=n):
            total += 1
    return total / (time.perf_counter() - started)


def live_run(session: Path, names: list[str], duration: float, lag: int, out: Path, base_motion: bool,
             realtime: bool = True, view: str | None = None, follow_clocks: bool = False):
    request = LiveRequest(MACHINE, session / "truth" / "cameras.toml",
                          tuple(parse_source(f"{n}={session / 'videos' / f'{n}.mp4'}") for n in names), out,
                          realtime=realtime, duration=duration, lag=lag, view=view,
                          follow_clocks=follow_clocks,
                          fit_options=FitOptions(base_motion=base_motion))
    cpu = time.process_time()
    report = run_live(request)
    return report, time.process_time() - cpu


def read_tips(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The rows' frames (R,) and bucket tips (R, 3)."""
    rows = np.genfromtxt(path, delimiter=",", names=True, dtype=None, encoding="utf-8")
    frames = np.atleast_1d(rows["frame"]).astype(int)
    return frames, np.stack([np.atleast_1d(rows[f"bucket_tip_{a}"]).astype(float) for a in "xyz"], 1)


def offline(session: Path, names: list[str], work: Path):
    """The offline chain's motion (`mocap track` each whole video, `mocap fit`)."""
    tracks = []
    for name in names:
        path = work / f"{name}.csv"
        run_track(TrackRequest(session / "videos" / f"{name}.mp4", MACHINE, session / "truth" / "cameras.toml", name,
                               path))
        tracks.append(path)
    out = work / "motion.csv"
    run_fit(MACHINE, session / "truth" / "cameras.toml", tracks, out, FitOptions(), SmoothOptions())
    return load_motion(out, load_machine(MACHINE))


def offline_rmse(motion, frames: np.ndarray, truth) -> float:
    """The offline motion's tip RMSE over `frames` (those it has)."""
    index = {int(f): k for k, f in enumerate(motion.frame)}
    keep = np.array([f for f in frames if f in index])
    return tip_rmse(keep, motion.point("bucket_tip")[[index[f] for f in keep]], truth)


def view_cpu(rows_path: Path, calibration, out: Path) -> float:
    """The process's CPU (ms) per row logging the rows of `rows_path` through `LiveView` to an
    .rrd file, flushed (Rerun's own thread included)."""
    from mocap.live.pose import Pose
    from mocap.live.view import LiveView, live_blueprint, open_stream
    from mocap.viewer.scene import joint_display_units

    machine = load_machine(MACHINE)
    rows = np.genfromtxt(rows_path, delimiter=",", names=True, dtype=None, encoding="utf-8")
    scale, _ = joint_display_units(machine)
    joints = np.stack([rows[n].astype(float) for n in machine.joint_names], 1) / scale
    points = np.stack([np.stack([rows[f"{p}_{a}"].astype(float) for a in "xyz"], 1) for p in machine.point_names], 1)
    angle = np.radians(rows["bucket_angle_deg"].astype(float))
    cpu = time.process_time()
    view = LiveView(open_stream(str(out), live_blueprint(machine)), machine, calibration)
    for k, frame in enumerate(rows["frame"]):
        view.log(int(frame), frame / 30.0, Pose(joints[k], joints[k] * 0, points[k], np.zeros(len(points[k])),
                                                float(angle[k]), 0.0, False, {}))
    view.close()
    return 1000 * (time.process_time() - cpu) / len(joints)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", default="960x540")
    parser.add_argument("--cameras", type=int, default=3)
    parser.add_argument("--duration", type=float, default=20.0)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--lag", type=int, default=1)
    parser.add_argument("--fixed-base", action="store_true",
                        help="fit live with the base fixed (default: its pose per frame, --base-motion: the "
                        "synthetic machine bounces, and the offline fit finds that it does)")
    parser.add_argument("--follow-clocks", action="store_true",
                        help="follow the clocks in the real-time runs: each other camera's newest offset against its "
                        "true one (the synthetic cameras keep their stated rates: the estimate's noise) and the CPU "
                        "per re-estimate")
    parser.add_argument("--work", help="folder for the session (default: a temporary one)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.work or tmp)
        session = make_session(root, args.size, args.cameras, args.seed)
        calibration = load_calibration(session / "truth" / "cameras.toml")
        truth = load_motion(session / "truth" / "motion.csv", load_machine(MACHINE))
        print(f"{args.size}, {args.duration:g} s of video played in real time, smoother lag {args.lag} frame(s), "
              f"{'fixed base' if args.fixed_base else 'base pose per frame'}")
        print(f"{'cams':>4} {'rows/s':>7} {'dropped':>8} {'p50 ms':>7} {'p99 ms':>7} {'max ms':>7} {'cpu ms/row':>10} "
              f"{'decode fps':>10} {'need fps':>8} {'tip RMSE live':>13} {'offline':>8} {'as fast':>10} {'offline':>8} "
              f"{'view cpu ms/row':>15} {'in loop':>7}")
        for n in range(1, args.cameras + 1):
            names = list(calibration.names[:n])
            work = root / f"run{n}"
            work.mkdir(exist_ok=True)
            report, cpu = live_run(session, names, args.duration, args.lag, work / "poses.csv", not args.fixed_base,
                                   follow_clocks=args.follow_clocks and n > 1)
            frames, tips = read_tips(work / "poses.csv")
            fast, _ = live_run(session, names, args.duration, args.lag, work / "fast.csv", not args.fixed_base,
                               realtime=False, view=str(work / "fast.rrd"))
            view_ms = view_cpu(work / "fast.csv", calibration, work / "view.rrd")
            fast_frames, fast_tips = read_tips(work / "fast.csv")
            fps = calibration.fps()[:n]
            offsets = calibration.time_offsets[:n]
            stops = [max(int((args.duration - max(o, 0.0)) * f), 1) for f, o in zip(fps, offsets)]
            decode = decode_rate([session / "videos" / f"{c}.mp4" for c in names], stops)
            motion = offline(session, names, work)
            dropped = sum(c.dropped for c in report.cameras)
            read = sum(c.read for c in report.cameras)
            p50, p99 = np.percentile(report.latency_ms, [50, 99])
            print(f"{n:>4} {report.rows / args.duration:>7.1f} {f'{dropped}/{read}':>8} {p50:>7.0f} {p99:>7.0f} "
                  f"{report.latency_ms.max():>7.0f} {1000 * cpu / max(report.rows, 1):>10.1f} {decode:>10.0f} {fps.sum():>8.1f} "
                  f"{tip_rmse(frames, tips, truth):>13.3f} {offline_rmse(motion, frames, truth):>8.3f} "
                  f"{tip_rmse(fast_frames, fast_tips, truth):>10.3f} {offline_rmse(motion, fast_frames, truth):>8.3f} "
                  f"{view_ms:>15.2f} {fast.view_ms:>7.2f}",
                  flush=True)
            for name, offset, at, _ in report.clocks:
                true = calibration.time_offsets[calibration.names.index(name)]
                print(f"     {name}: offset followed to {offset:+.4f} s around its frame {at:.0f}, true {true:+.4f} s "
                      f"({(offset - true) * fps[0]:+.2f} frames); {report.clock_update_ms:.0f} ms CPU per re-estimate "
                      "of all the offsets", flush=True)
        print("rows/s: rows written per second of the run (the reference camera delivers "
              f"{calibration.fps()[0]:g}); need fps: the frames the cameras deliver per second, beside the decode-only "
              "rate; RMSE in metres over the rows live and over the same frames offline; as fast: the files read as "
              "fast as they are tracked for the same time (no frame dropped), and offline over its rows' frames")


if __name__ == "__main__":
    main()
