"""Scale benchmarks: long sessions through the command line, beside a naive reference.

    python benchmarks/bench_scale.py [--frames 9000] [--long-frames 216000] [--skip-long]

A synthetic session of the EX3500 (`mocap synth --no-video --bounce 0`, truth tracks of 3
cameras and 18 markers; the base still, so that `mocap fit`, which would fit a bouncing base
per frame, and the reference fit the same model) is repeated end to end up to --frames reference frames (each camera repeats a
block of the same duration, so that the cameras' clocks stay as calibrated) and given 0.5 px
of pixel noise. Tables: (1) `mocap triangulate` and `mocap fit` wall time beside a naive
numpy/scipy reference run through its own small command line (the csv module, one
`scipy.optimize.least_squares` per point and per frame, the previous frame's joints as the
start), and the ratio; (2) tracks CSV parsing in rows/s (with pyarrow's own thread pool, as a
command runs, and with one thread), the columnar reader beside the
csv module's checked reader and pyarrow's bare read (no checks); (3) start time of
`mocap --help` and of a command's --help;
(4) a --long-frames session (216,000 frames: two hours at 30 fps, Parquet tracks) from
tracks to analysis as `mocap run` goes after tracking (sync, triangulate, fit, analyze):
each command's wall time, CPU time (user + system) and its own peak resident memory. Wall
times, so other work on the machine lengthens them (the CPU times much less). The naive reference ignores the cameras' time offsets (it
pairs equal frame numbers); that makes it faster, not slower.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from unittest import mock

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq

from mocap.cli import COMMANDS
from mocap.io.cameras_toml import load_calibration
from mocap.io import columnar
from mocap.io.tracks_csv import load_tracks

MACHINE = "hitachi_ex3500"
NOISE_PX = 0.5
TARGETS = {"triangulate": 10.0, "fit": 20.0}

NAIVE = r'''
"""The textbook way: the csv module, one least_squares per point / per frame."""
import csv, sys
import numpy as np
from scipy.optimize import least_squares
from mocap.io.cameras_toml import load_calibration
from mocap.io.machine_toml import load_machine

def read(path):
    frames = {}
    with open(path, newline="") as fh:
        for row in csv.DictReader(fh):
            frames.setdefault(int(row["frame"]), []).append((row["camera"], row["marker"], float(row["x"]), float(row["y"])))
    return frames

def triangulate(cal, tracks, out):
    cams = {c.name: c for c in load_calibration(cal).cameras}
    P = {n: c.matrix @ np.c_[c.cam_from_world.rotation, c.cam_from_world.translation] for n, c in cams.items()}
    rows = []
    for frame, obs in sorted(read(tracks).items()):
        by_marker = {}
        for cam, marker, x, y in obs:
            by_marker.setdefault(marker, []).append((cam, x, y))
        for marker, views in by_marker.items():
            if len(views) < 2:
                continue
            A = np.concatenate([[x * P[c][2] - P[c][0], y * P[c][2] - P[c][1]] for c, x, y in views])
            X = np.linalg.svd(A)[2][-1]
            uv = np.array([[x, y] for _, x, y in views])
            res = least_squares(lambda p: np.concatenate([cams[c].project(p) for c, _, _ in views]) - uv.ravel(), X[:3] / X[3])
            rows.append([frame, marker, *res.x])
    with open(out, "w", newline="") as fh:
        csv.writer(fh).writerows([["frame", "marker", "x", "y", "z"], *rows])

def fit(machine, cal, tracks, out):
    m = load_machine(machine)
    cams = {c.name: c for c in load_calibration(cal).cameras}
    index = {n: i for i, n in enumerate(m.marker_names)}
    q = np.clip(np.zeros(m.n_joints), m.joint_limits[:, 0], m.joint_limits[:, 1])
    rows = []
    for frame, obs in sorted(read(tracks).items()):
        groups = {}
        for cam, marker, x, y in obs:
            groups.setdefault(cam, ([], []))
            groups[cam][0].append(index[marker]); groups[cam][1].append((x, y))
        groups = {c: (np.array(i), np.array(uv)) for c, (i, uv) in groups.items()}

        def residual(joints):
            world = m.markers(joints[None])[0]
            return np.concatenate([(cams[c].project(world[i]) - uv).ravel() for c, (i, uv) in groups.items()])

        q = least_squares(residual, q, loss="huber", f_scale=2.0).x
        rows.append([frame, *q])
    with open(out, "w", newline="") as fh:
        csv.writer(fh).writerows([["frame", *m.joint_names], *rows])

if __name__ == "__main__":
    {"triangulate": triangulate, "fit": fit}[sys.argv[1]](*sys.argv[2:])
'''


def run(argv: list[str], cwd: Path) -> float:
    """Wall seconds of a child process; its failure stops the benchmark."""
    start = time.perf_counter()
    done = subprocess.run(argv, cwd=cwd, capture_output=True, text=True)
    if done.returncode:
        sys.exit(f"{' '.join(map(str, argv))} failed:\n{done.stderr[-2000:]}")
    return time.perf_counter() - start


def mocap(*args) -> list[str]:
    return [sys.executable, "-m", "mocap.cli", *map(str, args)]


def make_session(work: Path, root: Path, seed: int) -> Path:
    base = work / "base"
    if not (base / "truth" / "tracks.csv").exists():
        run(mocap("synth", "--machine", MACHINE, "--no-video", "--bounce", 0, "--seed", seed, "--out", base), root)
    return base / "truth"


def write_long_tracks(truth: Path, n_frames: int, path: Path, rng) -> int:
    """The truth tracks repeated end to end over `n_frames` reference frames, with pixel
    noise; rows. Each camera repeats a block of the same duration (a whole number of frames
    at every camera's rate: 3,003 frames at 30 fps are 3,000 at 29.97), so that the cameras'
    clocks stay as the calibration states them however long the session."""
    tracks = load_tracks(truth / "tracks.csv")
    calibration = load_calibration(truth / "cameras.toml")
    fps = calibration.fps()
    spans = [int(tracks.frame[tracks.camera == c].max()) + 1 for c in calibration.names]
    available = min(int(span * fps[0] / rate) for span, rate in zip(spans, fps))
    block = next((n for n in range(available, 0, -1)
                  if np.all(np.abs(n * fps / fps[0] - np.round(n * fps / fps[0])) < 1e-6)), available)
    columns = {name: [] for name in ("camera", "frame", "marker", "x", "y")}
    for name, rate in zip(calibration.names, fps):
        own = tracks.of_camera(name)
        own_block = int(round(block * rate / fps[0]))
        keep = own.frame < own_block
        frame0, xy0 = own.frame[keep], own.xy[keep]
        repeats = -(-int(n_frames * rate / fps[0]) // own_block)
        frame = (frame0[None] + own_block * np.arange(repeats)[:, None]).ravel()
        inside = frame < n_frames * rate / fps[0]
        xy = np.tile(xy0, (repeats, 1))[inside]
        xy += rng.normal(0, NOISE_PX, xy.shape)
        columns["camera"].append(np.full(int(inside.sum()), name))
        columns["frame"].append(frame[inside])
        columns["marker"].append(np.tile(own.marker[keep].astype(str), repeats)[inside])
        columns["x"].append(np.round(xy[:, 0], 4))
        columns["y"].append(np.round(xy[:, 1], 4))
    table = pa.table({k: np.concatenate(v) for k, v in columns.items()})
    if path.suffix == ".parquet":
        pq.write_table(table, path)
        return table.num_rows
    with open(path, "wb") as fh:
        fh.write(b"camera,frame,marker,x,y\n")
        pacsv.write_csv(table, fh, pacsv.WriteOptions(include_header=False, quoting_style="none"))
    return table.num_rows


def speed_table(work: Path, truth: Path, root: Path, tracks: Path) -> None:
    naive = work / "naive.py"
    naive.write_text(NAIVE)
    cal = truth / "cameras.toml"
    print("\n(1) through the command line: mocap vs the naive numpy/scipy reference")
    print(f"{'command':<12} {'mocap s':>9} {'naive s':>9} {'ratio':>7} {'target':>7}")
    for name, ours, theirs in [
        ("triangulate", mocap("triangulate", cal, tracks, "--out", work / "points.csv"),
         [sys.executable, naive, "triangulate", cal, tracks, work / "naive_points.csv"]),
        ("fit", mocap("fit", MACHINE, cal, tracks, "--out", work / "motion.csv"),
         [sys.executable, naive, "fit", MACHINE, cal, tracks, work / "naive_motion.csv"]),
    ]:
        a, b = run(ours, root), run(theirs, root)
        print(f"{name:<12} {a:9.2f} {b:9.2f} {b / a:6.1f}x {TARGETS[name]:6.0f}x")


def parse_table(tracks: Path) -> None:
    def best(fn) -> tuple[float, float, int]:
        """Least wall and least CPU seconds of 5 runs (the CPU time, all threads, does not
        count the time other work on a shared machine takes the cores), and rows."""
        walls, cpus, n = [], [], 0
        for _ in range(5):
            wall, cpu = time.perf_counter(), time.process_time()
            n = fn()
            walls.append(time.perf_counter() - wall)
            cpus.append(time.process_time() - cpu)
        return min(walls), min(cpus), n

    def checked() -> int:  # every value read as text by the csv module and checked one by one
        with mock.patch.object(columnar, "_typed", lambda *args: None):
            return len(load_tracks(tracks))

    def bare() -> int:  # pyarrow's own read of the same file: no checks, no Tracks
        return pacsv.read_csv(tracks).num_rows

    threads = os.cpu_count() or 1
    pa.set_cpu_count(threads)  # as a command runs (OMP_NUM_THREADS=1, set for table 1, sets pyarrow's pool to one)
    wall, cpu, n = best(lambda: len(load_tracks(tracks)))
    wall_bare, cpu_bare, _ = best(bare)
    pa.set_cpu_count(1)
    wall_1, cpu_1, _ = best(lambda: len(load_tracks(tracks)))
    wall_bare_1, cpu_bare_1, _ = best(bare)
    wall_csv, cpu_csv, _ = best(checked)
    print(f"\n(2) tracks CSV parsing, {n:,} rows (best of 5)")
    print(f"{'reader':<40} {'wall s':>7} {'M rows/s':>9} {'CPU s':>7} {'M rows/CPU s':>13}")
    for name, w, c, note in [
        (f"pyarrow (load_tracks), {threads} threads", wall, cpu, "target 5"),
        (f"pyarrow.csv.read_csv (bare), {threads} threads", wall_bare, cpu_bare, "(no checks: the floor)"),
        ("pyarrow (load_tracks), 1 thread", wall_1, cpu_1, ""),
        ("pyarrow.csv.read_csv (bare), 1 thread", wall_bare_1, cpu_bare_1, ""),
        ("csv module (checked)", wall_csv, cpu_csv, f"ratio {wall_csv / wall_1:.1f}x the 1-thread load_tracks"),
    ]:
        print(f"{name:<40} {w:7.3f} {n / w / 1e6:9.2f} {c:7.3f} {n / c / 1e6:13.2f}   {note}")


def start_table(root: Path) -> None:
    print("\n(3) start time, wall s (best of 5; target 0.3)")
    for args in [("--help",), *((command, "--help") for command in COMMANDS)]:
        best = min(run(mocap(*args), root) for _ in range(5))
        print(f"  mocap {' '.join(args):<20} {best:6.2f}")


LONG_STAGES = ("sync", "triangulate", "fit", "analyze")


def long_child(work: Path, truth: Path, root: Path, tracks: Path) -> None:
    """The long session from tracks to analysis as `mocap run` runs it after tracking (sync,
    triangulate, fit, analyze); print each command's wall time and peak resident memory."""
    out = work / "long"
    out.mkdir(exist_ok=True)
    cameras = out / "cameras.toml"
    commands = {
        "sync": mocap("sync", truth / "cameras.toml", tracks, "--machine", MACHINE, "--out", cameras),
        "triangulate": mocap("triangulate", cameras, tracks, "--out", out / "points.parquet"),
        "fit": mocap("fit", MACHINE, cameras, tracks, "--out", out / "motion.parquet"),
        "analyze": mocap("analyze", MACHINE, out / "motion.parquet", "--out", out / "analysis"),
    }
    result = {}
    for name in LONG_STAGES:
        start = time.perf_counter()
        child = subprocess.Popen(commands[name], cwd=root, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        stderr = child.stderr.read()
        _, status, usage = os.wait4(child.pid, 0)  # this command's own peak memory
        if status:
            sys.exit(f"{name} failed:\n{stderr.decode()[-2000:]}")
        result[name] = [time.perf_counter() - start, usage.ru_maxrss / 2**20,  # KiB -> GiB
                        usage.ru_utime + usage.ru_stime]
    print(json.dumps(result))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=9000)
    parser.add_argument("--long-frames", type=int, default=216_000)
    parser.add_argument("--skip-long", action="store_true")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--work", type=Path, help="folder to keep the files in (default: a temporary one)")
    parser.add_argument("--long-child", nargs=2, metavar=("WORK", "TRACKS"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    root = Path(__file__).resolve().parents[1]
    if args.long_child:
        work = Path(args.long_child[0])
        return long_child(work, work / "base" / "truth", root, Path(args.long_child[1]))
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        rng = np.random.default_rng(args.seed)
        truth = make_session(work, root, args.seed)
        tracks = work / "tracks.csv"
        rows = write_long_tracks(truth, args.frames, tracks, rng)
        print(f"session: {args.frames:,} frames x 3 cameras x 18 markers, {rows:,} track rows, {NOISE_PX} px noise")
        speed_table(work, truth, root, tracks)
        parse_table(tracks)
        start_table(root)
        if args.skip_long:
            return
        long_tracks = work / "long_tracks.parquet"
        rows = write_long_tracks(truth, args.long_frames, long_tracks, rng)
        done = subprocess.run([sys.executable, __file__, "--long-child", str(work), str(long_tracks)],
                              cwd=root, capture_output=True, text=True)
        if done.returncode:
            sys.exit(done.stdout[-2000:] + done.stderr[-2000:])
        result = json.loads(done.stdout.strip().splitlines()[-1])
        print(f"\n(4) {args.long_frames:,} frames ({rows:,} track rows, Parquet), tracks -> sync -> triangulate -> "
              "fit -> analyze (as mocap run after tracking)")
        print(f"{'command':<12} {'wall s':>8} {'CPU s':>8} {'peak GiB':>9}")
        for name in LONG_STAGES:
            print(f"{name:<12} {result[name][0]:8.1f} {result[name][2]:8.1f} {result[name][1]:9.2f}")
        total, cpu = sum(result[n][0] for n in LONG_STAGES), sum(result[n][2] for n in LONG_STAGES)
        peak = max(result[n][1] for n in LONG_STAGES)
        print(f"{'total':<12} {total:8.1f} {cpu:8.1f} {peak:9.2f}   targets 120 s, 4 GiB")


if __name__ == "__main__":
    main()
