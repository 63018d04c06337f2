"""`mocap live` on synthetic sessions played in real time, against the truth and the
offline chain on the same videos.

For each size of `--sizes` and seed of `--seeds`, writes a session with `mocap synth` (the
default look, or with `--look random` the seed's random look: paint, light, lens, noise ...;
the largest of `--cameras` cameras; the first camera at 30 fps, the others at 29.97), then for
each count of `--cameras`: the first N videos played as their cameras delivered them
(`--realtime`) for `--duration` seconds through `mocap live` (`mocap.live.run.run_live`): rows
out per second of the run (the session outlasts the run: its cameras deliver throughout), what
became of the reference camera's frames (a row each, or why not), frames dropped, latency p50 /
p99 / max (from the reference frame's arrival to its row written, the smoother's lag included)
and its parts' medians (the reference frame's tracking, the wait for the other cameras, the
fit, the smoother's lag); the process's CPU time per row (all its threads: decoding, tracking,
fitting: load-independent where the wall figures are upper bounds on a shared machine); its
resident memory after the first tenth of the run and at its end (flat?); beside it the
decode-only rate of the same streams (the tracker's own grey decoding, all the cameras' frames
of that duration one after another: the floor) and the frames the cameras deliver; and the
bucket tip's RMSE against the truth, live and by the offline chain (`mocap track` each camera,
then `mocap fit`, over the whole videos) over the same frames.

`--fault disconnect`: the last of the N cameras delivers nothing for 5 s from a third of the
run (its frames in that time never arrive, as from a camera unplugged and plugged back).
`--files`: instead, the whole videos read as fast as they are tracked (no frame dropped; not
a latency measurement; with `--fault disconnect` the last camera's frames of those 5 s on the
reference clock never come, and the offline chain like for like is beside it) and the rows' tip RMSE beside that of the same fits through the smoother
whose process noise is never raised (the peer: the estimate over 30 s alone) and the offline
chain's; with the worst second of the live rows; the tip SDs' coverage (the rows within 1, 2,
3 SDs of the truth, and the RMS of error / SD), live and unraised; the fit's and the
smoother's time per row; and the base's choice (`--base`: `recent`, chosen from the data on
the last frames as `mocap live` chooses it, the default; `choose`, the same test on a sample
spread over the whole run so far; or its pose per frame, or fixed; comma-separated, each run
on the same sessions one after the other, with the offline chain run once).
`--as-fast`: also the same live chain reading the files as fast as they are tracked (no
frame dropped) against the offline chain on its rows, and `--view`'s cost (the process's CPU
per row logging those rows to an .rrd file, and the main thread's time per row in the run).

    python benchmarks/bench_live.py [--sizes 960x540,1920x1080] [--cameras 1,2,3,4] [--duration 20]
        [--seeds 7] [--look random] [--lag 1] [--fault disconnect] [--base recent,choose,moving,fixed]
        [--as-fast] [--files]
"""

from __future__ import annotations

import argparse
import logging
import os
import tempfile
import threading
import time
import tomllib
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from mocap import cli
from mocap.errors import InputError
from mocap.io.cameras_toml import load_calibration
from mocap.io.machine_toml import load_machine
from mocap.io.motion_csv import load_motion
from mocap.io.video import Video
from mocap.live import run as live_module
from mocap.live.pose import BASE_WINDOW, FixedLagSmoother
from mocap.live.run import LiveRequest, run_live
from mocap.live.sources import SourceReader, parse_source
from mocap.reconstruct.kinfit import FitOptions
from mocap.reconstruct.smooth import SmoothOptions
from mocap.reconstruct.stage import run_fit
from mocap.tracking.stage import TrackRequest, run_track

MACHINE = "hitachi_ex3500"
BASES = {"recent": f"chosen from the last {BASE_WINDOW} frames", "choose": "chosen from the data over the whole run",
         "moving": "pose per frame", "fixed": "fixed"}


GAP_S = 5.0  # --fault disconnect: how long the camera delivers nothing


HOLD_S = 0.5  # the session's still start (`mocap synth --hold`)
FIRST_FRAMES = 180  # --files: the rows' SDs' coverage also over the frames up to this one (the scales not yet measured)


def machine_for(root: Path, name: str, seed: int) -> str:
    """The machine model of `seed`'s session: a shipped name or a file, or with `random` the
    seed's random digger (`mocap.synthetic.machines.random_digger`: random proportions, link
    frames, joint senses and limits), written to a model file under `root`."""
    if name != "random":
        return name
    from mocap.io.machine_toml import save_machine
    from mocap.synthetic.machines import random_digger

    path = root / f"digger_{seed}.toml"
    if not path.exists():
        save_machine(random_digger(np.random.default_rng(seed)), path)
    return str(path)


def session_machine(session: Path) -> str:
    """The model a session was drawn with: its session.toml's `machine`, a shipped name or
    a file beside it (`mocap synth` copies a model that is not shipped as machine.toml)."""
    entry = tomllib.loads((session / "session.toml").read_text(encoding="utf-8"))["machine"]
    return str(session / entry) if (session / entry).is_file() else entry


def cycles_for(duration: float, seed: int, machine_name: str = MACHINE) -> int:
    """The fewest dig cycles whose session (as `mocap synth` plans it for `seed`) outlasts a
    run of `duration` s by a second: the sources then deliver for the whole run (a session
    of 24 cycles lasts 588 s, not the 600 of a 10-minute run)."""
    from mocap.synthetic.motion import plan_session

    machine = load_machine(machine_name)
    cycles = 1
    while plan_session(machine, cycles, np.random.default_rng(seed), hold=HOLD_S).duration < duration + 1.0:
        cycles += 1
    return cycles


def make_session(root: Path, size: str, cameras: int, seed: int, look: str = "default", duration: float = 20.0,
                 machine: str = MACHINE) -> Path:
    cycles = cycles_for(duration, seed, machine)
    name = (("live_" if machine == MACHINE else f"live_{Path(machine).stem}_") + f"{size}_{cameras}_{seed}"
            + (f"_{look}" if look != "default" else "") + (f"_{cycles}c" if cycles > 1 else ""))
    session = root / name
    if not (session / "COMPLETE").exists():
        assert cli.main(["synth", "--machine", machine, "--cameras", str(cameras), "--cycles", str(cycles), "--seed",
                         str(seed), "--size", size, "--hold", str(HOLD_S), "--look", look, "--out", str(session)]) == 0
    return session


class _Silent(SourceReader):
    """A source whose camera `gap[0]` delivers nothing from `gap[1]` to `gap[2]` s after the
    start (with `gap[3]`, files read as fast as tracked: its frames of those times on the
    reference clock)."""

    gap: tuple[str, float, float, bool] | None = None

    def _deliver(self, frame) -> None:
        gap = _Silent.gap
        if gap is not None and self.spec.camera == gap[0]:
            at = frame.time if gap[3] else frame.arrived - self.clock_start
            if gap[1] <= at < gap[2]:
                return
        super()._deliver(frame)


@contextmanager
def silent(camera: str | None, start: float, by_time: bool = False):
    """While in it, `run_live`'s camera `camera` delivers nothing for `GAP_S` from `start` s
    (`by_time`: its frames of those times on the reference clock, for files read as fast as
    tracked)."""
    if camera is None:
        yield
        return
    _Silent.gap = (camera, start, start + GAP_S, by_time)
    live_module.SourceReader = _Silent
    try:
        yield
    finally:
        live_module.SourceReader = SourceReader
        _Silent.gap = None


class _Recording(FixedLagSmoother):
    """The live smoother, its inputs kept (`calls`) to be given again to another smoother."""

    calls: list[tuple] = []

    def push(self, time, fit):
        _Recording.calls.append(("push", time, fit))
        return super().push(time, fit)

    def revise(self, fit) -> None:
        _Recording.calls.append(("revise", fit))
        super().revise(fit)

    def flush(self):
        _Recording.calls.append(("flush",))
        return super().flush()


@contextmanager
def recording():
    """While in it, `run_live`'s smoother keeps its inputs in `_Recording.calls` (emptied first)."""
    _Recording.calls = []
    live_module.FixedLagSmoother = _Recording
    try:
        yield _Recording.calls
    finally:
        live_module.FixedLagSmoother = FixedLagSmoother


def replay(calls: list[tuple], machine_name: str, lag: int, base_motion: bool,
           pace_steps: int) -> tuple[np.ndarray, np.ndarray]:
    """(R, 3) the bucket tips of the rows a smoother with `pace_steps` gives from the same
    inputs, and (R,) their SDs."""
    machine = load_machine(machine_name)
    smoother = FixedLagSmoother(machine, lag, base_motion=base_motion, pace_steps=pace_steps)
    poses = []
    for call in calls:
        if call[0] == "push":
            poses += [p for p in [smoother.push(call[1], call[2])] if p is not None]
        elif call[0] == "revise":
            smoother.revise(call[1])
        else:
            poses += smoother.flush()
    tip = machine.point_names.index("bucket_tip")
    return np.array([p.points[tip] for p in poses]).reshape(-1, 3), np.array([p.points_sd[tip] for p in poses])


class Memory(threading.Thread):
    """The process's resident memory (MB) sampled every 0.2 s until `done` is set."""

    def __init__(self):
        super().__init__(daemon=True)
        self.samples: list[tuple[float, float]] = []
        self.done = threading.Event()
        self.page_mb = os.sysconf("SC_PAGE_SIZE") / 2**20

    def run(self) -> None:
        started = time.perf_counter()
        while not self.done.wait(0.2):
            with open("/proc/self/statm") as f:
                self.samples.append((time.perf_counter() - started, int(f.read().split()[1]) * self.page_mb))

    def at(self, share: float) -> float:
        """The RSS at `share` of the sampled time (the largest sample up to it)."""
        if not self.samples:
            return float("nan")
        end = self.samples[-1][0] * share
        return max(mb for t, mb in self.samples if t <= end or t == self.samples[0][0])


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


def live_run(session: Path, names: list[str], duration: float | None, lag: int, out: Path, base: str,
             realtime: bool = True, view: str | None = None, follow_clocks: bool = False):
    """The run's report, its CPU seconds (all threads) and its memory samples. `base`: recent
    (from the data, the last frames: live's default), choose (from the data, a sample over the
    whole run), moving (`--base-motion`) or fixed (`--fixed-base`)."""
    request = LiveRequest(session_machine(session), session / "truth" / "cameras.toml",
                          tuple(parse_source(f"{n}={session / 'videos' / f'{n}.mp4'}") for n in names), out,
                          realtime=realtime, duration=duration, lag=lag, view=view,
                          follow_clocks=follow_clocks,
                          fit_options=FitOptions(base_motion=base == "moving"),
                          choose_base=base in ("choose", "recent"),
                          base_window=None if base == "choose" else BASE_WINDOW)
    memory = Memory()
    memory.start()
    cpu = time.process_time()
    try:
        report = run_live(request)
    finally:
        memory.done.set()
        memory.join()
    return report, time.process_time() - cpu, memory


def read_tips(path: Path, sd: bool = False):
    """The rows' frames (R,) and bucket tips (R, 3) (and with `sd` their SDs (R,))."""
    rows = np.genfromtxt(path, delimiter=",", names=True, dtype=None, encoding="utf-8")
    frames = np.atleast_1d(rows["frame"]).astype(int)
    tips = np.stack([np.atleast_1d(rows[f"bucket_tip_{a}"]).astype(float) for a in "xyz"], 1)
    return (frames, tips, np.atleast_1d(rows["bucket_tip_sd"]).astype(float)) if sd else (frames, tips)


def coverage(frames: np.ndarray, tips: np.ndarray, sds: np.ndarray, truth) -> tuple[float, float, float, float]:
    """The shares of the rows whose tip is within 1, 2, 3 of its SDs of the truth, and the RMS
    of error / SD (1 when the SDs are honest: the SD is the RMS of the 3-D error's length)."""
    ratio = np.linalg.norm(tips - truth.point("bucket_tip")[frames], axis=1) / sds
    ratio = ratio[np.isfinite(ratio)]
    if not len(ratio):
        return (np.nan,) * 4
    return (*(float(np.mean(ratio <= k)) for k in (1, 2, 3)), float(np.sqrt(np.mean(ratio**2))))


def coverage_text(shares) -> str:
    return f"{' '.join(f'{100 * x:.0f}' for x in shares[:3]):>10} {shares[3]:>6.2f}"


def offline(session: Path, names: list[str], work: Path):
    """The offline chain's motion (`mocap track` each whole video, `mocap fit`)."""
    tracks = []
    for name in names:
        path = session.parent / f"{session.name}_tracks" / f"{name}.csv"  # the same for every count of cameras
        if not path.exists():
            path.parent.mkdir(exist_ok=True)
            run_track(TrackRequest(session / "videos" / f"{name}.mp4", session_machine(session),
                                   session / "truth" / "cameras.toml", name, path))
        tracks.append(path)
    return fitted(session, tracks, work / "motion.csv")


def fitted(session: Path, tracks: list[Path], out: Path):
    """`mocap fit` of `tracks` with the session's true cameras, written to `out` and read back."""
    machine = session_machine(session)
    run_fit(machine, session / "truth" / "cameras.toml", tracks, out, FitOptions(), SmoothOptions())
    return load_motion(out, load_machine(machine))


def offline_rmse(motion, frames: np.ndarray, truth) -> float:
    """The offline motion's tip RMSE over `frames` (those it has)."""
    index = {int(f): k for k, f in enumerate(motion.frame)}
    keep = np.array([f for f in frames if f in index])
    return tip_rmse(keep, motion.point("bucket_tip")[[index[f] for f in keep]], truth)


def offline_coverage(motion, frames: np.ndarray, truth):
    """`coverage` of the offline motion's tip SDs over `frames` (those it has)."""
    index = {int(f): k for k, f in enumerate(motion.frame)}
    rows = [index[f] for f in frames if f in index]
    sds = motion.points_sd[rows, motion.point_names.index("bucket_tip")]
    return coverage(motion.frame[rows], motion.point("bucket_tip")[rows], sds, truth)


def offline_without(session: Path, names: list[str], work: Path, camera: str, frames: np.ndarray, calibration):
    """The offline chain on the same tracks but with `camera`'s frames removed where the live
    rows `frames` (reference frames) went without it: each of its frames whose nearest
    reference frame is one of those (the like-for-like camera set)."""
    k = calibration.names.index(camera)
    fps, offset = calibration.fps()[k], calibration.time_offsets[k]
    reference_fps = calibration.fps()[calibration.names.index(names[0])]
    source = session.parent / f"{session.name}_tracks" / f"{camera}.csv"
    lines = source.read_text().splitlines()
    frame = np.array([int(line.split(",")[1]) for line in lines[1:]])
    nearest = np.round((frame / fps + offset) * reference_fps).astype(int)
    keep = ~np.isin(nearest, frames)
    path = work / f"{camera}_without.csv"
    path.write_text("\n".join([lines[0]] + [line for line, k in zip(lines[1:], keep) if k]) + "\n")
    tracks = [session.parent / f"{session.name}_tracks" / f"{n}.csv" if n != camera else path for n in names]
    return fitted(session, tracks, work / "motion_without.csv"), int(len(np.unique(frame[~keep])))


def view_cpu(rows_path: Path, calibration, out: Path, machine_name: str) -> float:
    """The process's CPU (ms) per row logging the rows of `rows_path` through `LiveView` to an
    .rrd file, flushed (Rerun's own thread included)."""
    from mocap.live.pose import Pose
    from mocap.live.view import LiveView, live_blueprint, open_stream
    from mocap.viewer.scene import joint_display_units

    machine = load_machine(machine_name)
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


def counts(text: str) -> list[int]:
    return [int(n) for n in text.split(",")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="960x540", help="image sizes, comma-separated (default 960x540)")
    parser.add_argument("--cameras", default="1,2,3", help="camera counts, comma-separated (default 1,2,3)")
    parser.add_argument("--duration", type=float, default=20.0, help="seconds of each run (600: the soak)")
    parser.add_argument("--seeds", default="7", help="sessions' seeds, comma-separated (the motion, and the look)")
    parser.add_argument("--look", choices=("default", "random"), default="default",
                        help="random: each seed's random look (mocap synth --look random)")
    parser.add_argument("--machine", default=MACHINE,
                        help=f"the machine model: a shipped name or a file (default {MACHINE}), or random: each "
                        "seed's random digger (random proportions, link frames, joint senses and limits)")
    parser.add_argument("--lag", type=int, default=1)
    parser.add_argument("--fault", choices=("none", "disconnect"), default="none",
                        help=f"disconnect: the last camera delivers nothing for {GAP_S:g} s from a third of the run")
    parser.add_argument("--base", default="recent",
                        help="live's base, comma-separated to run several: chosen from the data by mocap fit's test, "
                        "on the last frames (recent, the default, as mocap live) or on a sample over the whole run "
                        "(choose), its pose per frame (moving, --base-motion) or fixed (fixed, --fixed-base)")
    parser.add_argument("--follow-clocks", action="store_true",
                        help="follow the clocks in the real-time runs: each other camera's newest offset against its "
                        "true one (the synthetic cameras keep their stated rates: the estimate's noise) and the CPU "
                        "per re-estimate")
    parser.add_argument("--as-fast", action="store_true",
                        help="also the files read as fast as they are tracked, and the viewer's cost")
    parser.add_argument("--files", action="store_true",
                        help="instead of the real-time runs: the whole videos read as fast as they are tracked (no "
                        "frame dropped; not a latency measurement), the rows' tip RMSE against the same fits through "
                        "the smoother with its process noise as estimated over 30 s only (never raised), and offline")
    parser.add_argument("--work", help="folder for the sessions and runs (default: a temporary one); a session "
                        "found there complete is used again")
    args = parser.parse_args()
    bases = args.base.split(",")
    if not set(bases) <= set(BASES):
        parser.error(f"--base: {args.base!r}; give some of {', '.join(BASES)}, comma-separated")
    logging.basicConfig(level=logging.WARNING)
    cameras = counts(args.cameras)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.work or tmp)
        if args.files:
            files_table(args, root, cameras)
            return
        print(f"{args.duration:g} s of video played in real time, smoother lag {args.lag} frame(s), "
              f"base {' / '.join(BASES[b] for b in bases)}"
              + (f", the last camera silent for {GAP_S:g} s from {args.duration / 3:.0f} s" if args.fault != "none"
                 else "") + f"; load average {os.getloadavg()[0]:.2f} at the start")
        header = (f"{'size':>9} {'seed':>4} {'cams':>4} {'rows/s':>6} {'dropped':>8} {'p50 ms':>6} {'p99 ms':>6} "
                  f"{'max ms':>6} {'track':>5} {'wait':>5} {'fit':>5} {'lag':>5} {'cpu ms/row':>10} {'RSS MB':>9} "
                  f"{'decode fps':>10} {'need fps':>8} {'tip RMSE live':>13} {'offline':>7} {'ratio':>5}")
        if args.as_fast:
            header += f" {'as fast':>7} {'offline':>7} {'view cpu ms/row':>15} {'in loop':>7}"
        print(header, flush=True)
        ratios = []
        for size, seed, session, calibration, truth in sessions(args, root, cameras):
            print(f"{session.name}: " + ", ".join(f"{c} {f:.5g} fps" for c, f in zip(calibration.names,
                                                                                  calibration.fps())), flush=True)
            for n in cameras:
                for base in bases:
                    if len(bases) > 1:
                        print(f"  base {BASES[base]}:", flush=True)
                    ratios.append(bench_row(argparse.Namespace(**{**vars(args), "base": base}), root, session,
                                            calibration, truth, size, seed, n))
        loads = os.getloadavg()
        ratios = np.array(ratios)
        print("rows/s: rows written per second of the run (the reference camera delivers 30; each session's cameras' "
              "rates above); "
              "dropped: frames late, of those read; track / wait / fit / lag: the latency's parts' medians (ms: the "
              "reference frame's tracking, the wait for the other cameras, the fit, the smoother's lag to the row "
              "written); cpu ms/row: the process's CPU (all threads) per row; RSS MB: resident memory after a tenth "
              "of the run / at its end; need fps: the frames the cameras deliver per second, beside the decode-only "
              "rate; RMSE in metres over the rows live and over the same frames offline (ratio: live / offline)"
              + ("; as fast: the files read as fast as they are tracked for the same time (no frame dropped), and "
                 "offline over its rows' frames" if args.as_fast else ""))
        print(f"tip RMSE live / offline over {len(ratios)} runs: median {np.median(ratios):.2f}, worst "
              f"{ratios.max():.2f}; load average {loads[0]:.2f} at the end")


def sessions(args, root: Path, cameras: list[int]):
    """Each size and seed's session (made, or found complete under `root`): size, seed, its
    folder, the true calibration and the true motion."""
    for size in args.sizes.split(","):
        for seed in counts(args.seeds):
            machine = machine_for(root, args.machine, seed)
            session = make_session(root, size, max(cameras), seed, args.look, args.duration, machine)
            yield (size, seed, session, load_calibration(session / "truth" / "cameras.toml"),
                   load_motion(session / "truth" / "motion.csv", load_machine(machine)))


def files_table(args, root: Path, cameras: list[int]) -> None:
    """`--files`: per session and count of cameras, the whole videos read as fast as tracked."""
    bases = args.base.split(",")
    print(f"the whole videos read as fast as they are tracked, smoother lag {args.lag} frame(s), base "
          f"{' / '.join(f'{b}: {BASES[b]}' for b in bases)}; tip RMSE (m) over the rows: live, the same fits "
          "through the smoother whose process noise is never raised, and the offline chain over the same frames; "
          "the tip SDs' coverage")
    print(f"{'session':>28} {'cams':>4} {'base':>6} {'rows':>5} {'live':>7} {'unraised':>8} {'offline':>7} "
          f"{'live/off':>8} "
          f"{'unraised/off':>12} {'worst 1 s live':>14} {'unraised':>8} {'offline':>7} {'live 1/2/3 SD %':>15} "
          f"{'e/SD':>6} {'unraised':>10} {'e/SD':>6} {'fit ms':>6} {'smooth ms':>9} {'cpu ms/row':>10} {'choice':>12}",
          flush=True)
    ratios = {base: [] for base in bases}
    for size, seed, session, calibration, truth in sessions(args, root, cameras):
        for n in cameras:
            names = list(calibration.names[:n])
            work = root / f"files_{session.name}_{n}"
            work.mkdir(exist_ok=True)
            try:
                motion = offline(session, names, work)  # once for every base
            except InputError as exc:  # a random machine's camera may see too few markers to be tracked
                print(f"{session.name:>28} {n:>4} not compared: the offline chain refuses it: {exc}", flush=True)
                continue
            gap = names[-1] if args.fault == "disconnect" and n > 1 else None
            for base in bases:
                with silent(gap, args.duration / 3, by_time=True), recording() as calls:
                    report, cpu, _ = live_run(session, names, None, args.lag, work / "poses.csv", base,
                                              realtime=False)
                frames, tips, sds = read_tips(work / "poses.csv", sd=True)
                unraised, unraised_sds = replay(calls, session_machine(session), args.lag, base != "fixed", pace_steps=0)
                keep = frames < len(truth.frame)  # the truth's frames (a camera's last frames may outlast the first's)
                frames, tips, sds, unraised, unraised_sds = (x[keep] for x in (frames, tips, sds, unraised,
                                                                               unraised_sds))
                live, flat, off = (tip_rmse(frames, tips, truth), tip_rmse(frames, unraised, truth),
                                   offline_rmse(motion, frames, truth))
                # the second of rows where live is worst
                error = np.linalg.norm(tips - truth.point("bucket_tip")[frames], axis=1) ** 2
                start = (int(np.argmax(np.convolve(np.nan_to_num(error), np.ones(30), "valid")))
                         if len(frames) >= 30 else 0)
                worst = frames[start:start + 30]
                stages = np.median(report.stages_ms, axis=0) if len(report.stages_ms) else np.full(4, np.nan)
                tests = report.base_tests
                choice = ("-" if not tests else ("moving" if tests[-1][1] else "fixed")
                        + f" {sum(a[1] != b[1] for a, b in zip(((0, base != 'fixed'),) + tests[:-1], tests))}/{len(tests)}")
                print(f"{session.name:>28} {n:>4} {base:>6} {len(frames):>5} {live:>7.4f} {flat:>8.4f} {off:>7.4f} "
                      f"{live / off:>8.2f} {flat / off:>12.2f} "
                      f"{tip_rmse(worst, tips[start:start + 30], truth):>14.4f} "
                      f"{tip_rmse(worst, unraised[start:start + 30], truth):>8.4f} "
                      f"{offline_rmse(motion, worst, truth):>7.4f} "
                      f"{coverage_text(coverage(frames, tips, sds, truth)):>22} "
                      f"{coverage_text(coverage(frames, unraised, unraised_sds, truth)):>17} "
                      f"{stages[2]:>6.2f} {stages[3]:>9.1f} {1000 * cpu / max(report.rows, 1):>10.1f} {choice:>12}"
                      f"  (worst: frames {worst[0]}-{worst[-1]})", flush=True)
                first = frames <= FIRST_FRAMES
                print(f"{'':>34}{report.reference.text()}" + (f" (and {report.rows_of_others} rows of the other "
                                                               "cameras' frames)" if report.rows_of_others else "")
                      + f"; frames 0-{FIRST_FRAMES}: live 1/2/3 SD % "
                      f"{coverage_text(coverage(frames[first], tips[first], sds[first], truth)).strip()} (e/SD last)"
                      f"; offline over all rows 1/2/3 SD % "
                      f"{coverage_text(offline_coverage(motion, frames, truth)).strip()}",
                      flush=True)
                if gap is not None:
                    rows = np.genfromtxt(work / "poses.csv", delimiter=",", names=True, dtype=None,
                                         encoding="utf-8")
                    without = np.array([gap not in str(c).split(";") for c in np.atleast_1d(rows["cameras"])])
                    without = without[:len(keep)][keep]
                    alike, removed = offline_without(session, names, work, gap, frames[without], calibration)
                    like = offline_rmse(alike, frames, truth)
                    print(f"{'':>34}{without.sum()} rows without {gap}: tip RMSE "
                          f"{tip_rmse(frames[without], tips[without], truth):.4f} live, "
                          f"{offline_rmse(alike, frames[without], truth):.4f} offline without its {removed} frames "
                          f"there; all rows {like:.4f} offline like for like: live / offline {live / like:.2f}",
                          flush=True)
                ratios[base].append((live / off, flat / off))
    print("live 1/2/3 SD %: the rows whose tip is within 1, 2, 3 of its SDs of the truth (the SD is the RMS of the "
          "3-D error's length: honest SDs give e/SD, the RMS of error / SD, near 1, and within 1/2/3 SD between a "
          "1-D Gaussian's 68/95/99.7 % and an isotropic 3-D one's 61/99/100 %); fit ms: the median fit of a frame; "
          "smooth ms: the median from the fit to the row written (the smoother, files read as fast as tracked); "
          "choice: the last test's choice, the changes / the tests")
    for base in bases:
        shares = np.array(ratios[base])
        print(f"base {base}: live / offline over {len(shares)} runs: median {np.median(shares[:, 0]):.2f}, "
              f"worst {shares[:, 0].max():.2f}"
              f"; never raised: median {np.median(shares[:, 1]):.2f}, worst {shares[:, 1].max():.2f}")


def bench_row(args, root: Path, session: Path, calibration, truth, size: str, seed: int, n: int) -> float:
    """One count of cameras' line of the table; the live / offline tip RMSE ratio."""
    names = list(calibration.names[:n])
    work = root / f"run_{session.name}_{n}"
    work.mkdir(exist_ok=True)
    gap = names[-1] if args.fault == "disconnect" else None
    with silent(gap, args.duration / 3), recording() as calls:
        report, cpu, memory = live_run(session, names, args.duration, args.lag, work / "poses.csv",
                                       args.base, follow_clocks=args.follow_clocks and n > 1)
    frames, tips = read_tips(work / "poses.csv")
    fps = calibration.fps()[:n]
    offsets = calibration.time_offsets[:n]
    stops = [max(int((args.duration - max(o, 0.0)) * f), 1) for f, o in zip(fps, offsets)]
    decode = decode_rate([session / "videos" / f"{c}.mp4" for c in names], stops)
    motion = offline(session, names, work)
    dropped = sum(c.dropped for c in report.cameras)
    read = sum(c.read for c in report.cameras)
    p50, p99 = np.percentile(report.latency_ms, [50, 99]) if len(report.latency_ms) else (np.nan, np.nan)
    stages = np.median(report.stages_ms, axis=0) if len(report.stages_ms) else np.full(4, np.nan)
    live, off = tip_rmse(frames, tips, truth), offline_rmse(motion, frames, truth)
    unraised, _ = replay(calls, session_machine(session), args.lag, args.base != "fixed", pace_steps=0)
    width, height = calibration.cameras[0].size
    line = (f"{f'{width}x{height}':>9} {seed:>4} {n:>4} {report.rows / args.duration:>6.1f} {f'{dropped}/{read}':>8} "
            f"{p50:>6.0f} {p99:>6.0f} {report.latency_ms.max() if len(report.latency_ms) else np.nan:>6.0f} "
            + " ".join(f"{x:>5.1f}" for x in stages)
            + f" {1000 * cpu / max(report.rows, 1):>10.1f} {f'{memory.at(0.1):.0f}/{memory.at(1.0):.0f}':>9} "
            f"{decode:>10.0f} {fps.sum():>8.1f} {live:>13.4f} {off:>7.4f} {live / off:>5.2f}")
    if args.as_fast:
        fast, _, _ = live_run(session, names, args.duration, args.lag, work / "fast.csv", args.base,
                              realtime=False, view=str(work / "fast.rrd"))
        view_ms = view_cpu(work / "fast.csv", calibration, work / "view.rrd", session_machine(session))
        fast_frames, fast_tips = read_tips(work / "fast.csv")
        line += (f" {tip_rmse(fast_frames, fast_tips, truth):>7.4f} {offline_rmse(motion, fast_frames, truth):>7.4f} "
                 f"{view_ms:>15.2f} {fast.view_ms:>7.2f}")
    print(line, flush=True)
    print(f"     the same fits through the smoother that never raises its process noise: tip RMSE "
          + (f"{tip_rmse(frames, unraised, truth):.4f}" if len(unraised) == len(frames) else
             f"not compared ({len(unraised)} rows given again, {len(frames)} written)"), flush=True)
    account = report.reference
    print(f"     {account.text()}" + (f" (and {report.rows_of_others} rows of other cameras' frames)"
                                      if report.rows_of_others else "")
          + "".join(f"; {c.camera} labelled afresh {c.resumed}x after a gap" for c in report.cameras if c.resumed),
          flush=True)
    if gap is not None:
        rows = np.genfromtxt(work / "poses.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
        without = np.array([gap not in str(c).split(";") for c in np.atleast_1d(rows["cameras"])])
        print(f"     {without.sum()} rows without {gap} (its {GAP_S:g} s gap, and its first frames): tip RMSE "
              f"{tip_rmse(frames[without], tips[without], truth):.4f} live, "
              f"{offline_rmse(motion, frames[without], truth):.4f} offline (all cameras); the other "
              f"{(~without).sum()} rows: {tip_rmse(frames[~without], tips[~without], truth):.4f} live, "
              f"{offline_rmse(motion, frames[~without], truth):.4f} offline", flush=True)
        alike, removed = offline_without(session, names, work, gap, frames[without], calibration)
        like = offline_rmse(alike, frames, truth)
        print(f"     offline with the same camera set ({gap}'s {removed} frames of those rows removed from its "
              f"track): {offline_rmse(alike, frames[without], truth):.4f} over the rows without {gap}, "
              f"{like:.4f} over all rows; live / offline like for like {live / like:.2f}", flush=True)
    for name, offset, at, _ in report.clocks:
        true = calibration.time_offsets[calibration.names.index(name)]
        print(f"     {name}: offset followed to {offset:+.4f} s around its frame {at:.0f}, true {true:+.4f} s "
              f"({(offset - true) * fps[0]:+.2f} frames); {report.clock_update_ms:.0f} ms CPU per re-estimate "
              "of all the offsets", flush=True)
    return live / off


if __name__ == "__main__":
    main()
