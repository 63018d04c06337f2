"""`mocap batch` throughput: N small synthetic sessions through the whole chain.

Side by side in one run, each on fresh copies of the same sessions:
  1. one after the other: `mocap run SESSION --no-view` for each session (the peer);
  2. `mocap batch` on an embedded local cluster of 2 single-threaded workers;
  3. `mocap batch --scheduler` against `dask scheduler` and two `dask worker`s started here
     as separate processes, as a person would by hand;
  4. `mocap batch` again on the sessions of 2: nothing changed, so no stage runs.
It prints the wall and CPU times (of every process each run started, so "cores busy" =
CPU / wall tells how much of the machine a run could use), the throughput ratio of 2 to 1
(target >= 1.6), and whether the results of 1, 2 and 3 (calibration, tracks, points,
motion) are identical byte for byte.

    .venv/bin/python benchmarks/bench_batch.py [--sessions 8] [--scale 0.25] [--work DIR]
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mocap.io.session import Session  # noqa: E402
from mocap.orchestration.demo import digitise_first_frame  # noqa: E402

RESULTS = ("calibration/cameras.toml", "tracks/cam1.csv", "tracks/cam2.csv", "tracks/cam3.csv",
           "results/points.csv", "results/motion.csv")


def cpu_seconds() -> float:
    """User + system CPU time of this process's finished children (and theirs)."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def mocap(*args, **kwargs) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "mocap.cli", *map(str, args)], env=env, cwd=ROOT,
                          capture_output=True, text=True, **kwargs)


def make_sessions(work: Path, n: int, scale: float) -> list[Path]:
    """N sessions of one dig cycle each (seeds 1..N), with the first frame's labels; kept in
    `work`/sources between runs."""
    roots = []
    for seed in range(1, n + 1):
        root = work / "sources" / f"session_{seed:02d}"
        if not (root / "calibration" / "labels.csv").is_file():
            shutil.rmtree(root, ignore_errors=True)
            done = mocap("synth", "--machine", "hitachi_ex3500", "--cycles", 1, "--seed", seed, "--scale", scale,
                         "--codec", "mp4v", "--out", root)
            if done.returncode:
                sys.exit(done.stderr)
            digitise_first_frame(Session.open(root), np.random.default_rng(seed))
        roots.append(root)
    return roots


def fresh_copies(sources: list[Path], folder: Path) -> list[Path]:
    shutil.rmtree(folder, ignore_errors=True)
    copies = []
    for source in sources:
        target = folder / source.name
        shutil.copytree(source, target)
        copies.append(target)
    return copies


def digests(roots: list[Path]) -> dict[str, str]:
    out = {}
    for root in roots:
        for name in RESULTS:
            path = root / name
            out[f"{root.name}/{name}"] = hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else "missing"
    return out


def fleet_rows(out: Path) -> list[dict]:
    with open(out / "fleet.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def timed_batch(paths, out: Path, *extra) -> tuple[float, list[dict]]:
    start = time.perf_counter()
    done = mocap("batch", *paths, "--out", out, *extra)
    seconds = time.perf_counter() - start
    if done.returncode not in (0, 1):
        sys.exit(done.stderr)
    return seconds, fleet_rows(out)


class HandStartedCluster:
    """`dask scheduler` and two `dask worker` processes, as started by hand."""

    def __init__(self, folder: Path, workers: int = 2):
        self.folder = folder
        self.workers = workers
        self.processes: list[subprocess.Popen] = []

    def __enter__(self) -> str:
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        dask = [sys.executable, "-m", "dask"]
        scheduler_file = self.folder / "scheduler.json"
        scheduler_file.unlink(missing_ok=True)
        logs = open(self.folder / "cluster.log", "w")
        self.processes.append(subprocess.Popen(
            [*dask, "scheduler", "--port", "0", "--dashboard-address", ":0", "--scheduler-file", str(scheduler_file)],
            env=env, stdout=logs, stderr=logs))
        for _ in range(300):
            if scheduler_file.is_file() and scheduler_file.stat().st_size:
                break
            time.sleep(0.1)
        for k in range(self.workers):
            self.processes.append(subprocess.Popen(
                [*dask, "worker", "--scheduler-file", str(scheduler_file), "--nthreads", "1", "--nworkers", "1",
                 "--dashboard-address", ":0", "--name", f"hand-{k}"], env=env, stdout=logs, stderr=logs, cwd=ROOT))
        import json

        address = json.loads(scheduler_file.read_text())["address"]
        from distributed import Client

        with Client(address, timeout="30s") as client:
            client.wait_for_workers(self.workers, timeout=60)
        return address

    def cpu_seconds(self) -> float:
        """CPU time of the scheduler and workers and their processes so far."""
        import psutil

        total = 0.0
        for process in self.processes:
            try:
                family = [psutil.Process(process.pid)] + psutil.Process(process.pid).children(recursive=True)
            except psutil.NoSuchProcess:
                continue
            for member in family:
                try:
                    times = member.cpu_times()
                except psutil.NoSuchProcess:
                    continue
                total += times.user + times.system
        return total

    def __exit__(self, *exc) -> None:
        for process in reversed(self.processes):
            process.terminate()
        for process in self.processes:
            try:
                process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                process.kill()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sessions", type=int, default=8)
    parser.add_argument("--scale", type=float, default=0.25, help="image scale of the synthetic videos")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "mocap-bench-batch")
    args = parser.parse_args()
    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    print(f"making {args.sessions} sessions in {work}/sources (kept for later runs) ...", flush=True)
    sources = make_sessions(work, args.sessions, args.scale)

    rows = []
    sequential = fresh_copies(sources, work / "sequential")
    start, cpu = time.perf_counter(), cpu_seconds()
    failed = sum(mocap("run", root, "--no-view").returncode != 0 for root in sequential)
    t_sequential = time.perf_counter() - start
    rows.append(("one after the other (mocap run)", t_sequential, cpu_seconds() - cpu,
                 f"{len(sources) - failed}/{len(sources)} ok"))

    local = fresh_copies(sources, work / "local")
    cpu = cpu_seconds()
    t_local, fleet = timed_batch([work / "local"], work / "local_fleet", "--workers", args.workers)
    rows.append((f"mocap batch, local cluster of {args.workers}", t_local, cpu_seconds() - cpu,
                 f"{sum(r['status'] == 'ok' for r in fleet)}/{len(fleet)} ok"))

    hand = fresh_copies(sources, work / "hand")
    cluster = HandStartedCluster(work, args.workers)
    with cluster as address:
        cpu = cpu_seconds() + cluster.cpu_seconds()
        t_hand, fleet_hand = timed_batch([work / "hand"], work / "hand_fleet", "--scheduler", address)
        cpu_hand = cpu_seconds() + cluster.cpu_seconds() - cpu
    rows.append(("mocap batch --scheduler (dask scheduler + 2 dask worker)", t_hand, cpu_hand,
                 f"{sum(r['status'] == 'ok' for r in fleet_hand)}/{len(fleet_hand)} ok"))

    cpu = cpu_seconds()
    t_again, fleet_again = timed_batch([work / "local"], work / "local_fleet", "--workers", args.workers)
    ran = sum(int(r["stages_run"]) for r in fleet_again)
    rows.append(("mocap batch again, nothing changed", t_again, cpu_seconds() - cpu, f"{ran} stages run"))

    print(f"\n{len(sources)} sessions (EX3500, 3 cameras, 1 cycle, scale {args.scale}), {os.cpu_count()} cores\n")
    print(f"| {'run':58s} | {'wall s':>7s} | {'CPU s':>7s} | cores busy | {'sessions/h':>10s} | result |")
    print(f"|{'-' * 60}|{'-' * 9}|{'-' * 9}|------------|{'-' * 12}|--------|")
    for name, seconds, cpu, result in rows:
        print(f"| {name:58s} | {seconds:7.1f} | {cpu:7.1f} | {cpu / seconds:10.2f} | "
              f"{3600 * len(sources) / seconds:10.0f} | {result} |")
    d_seq, d_local, d_hand = digests(sequential), digests(local), digests(hand)
    print(f"\nthroughput, local cluster / one after the other: {t_sequential / t_local:.2f}x (target >= 1.6); "
          f"CPU per session {rows[0][2] / len(sources):.1f} s one after the other, {rows[1][2] / len(sources):.1f} s "
          f"in the batch; the machine's load average now {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    print(f"results identical, hand-started cluster vs local cluster: {d_hand == d_local} "
          f"({sum(d_hand[k] == d_local[k] for k in d_local)}/{len(d_local)} files)")
    print(f"results identical, local cluster vs one after the other: {d_seq == d_local} "
          f"({sum(d_seq[k] == d_local[k] for k in d_local)}/{len(d_local)} files)")
    print(f"re-run with nothing changed: {ran} stages run in {t_again:.1f} s")


if __name__ == "__main__":
    main()
