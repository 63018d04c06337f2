"""Soak: `mocap batch` over N small sessions, some broken, with workers killed at random.

Truth-only synthetic sessions (no video: the truth tracks stand in for tracking, as in
tests/test_batch.py; sync, triangulate and fit are the real commands) are copied N times;
B of them are broken, each its own way (a lost calibration, a corrupt tracks file, a wrong
machine model, a session.toml that does not parse, no tracks of one camera). A seeded
choice of the good sessions' tasks SIGKILLs its worker process the first time it runs (as
the out-of-memory killer would); Dask gives the task to another worker. Printed:
completed, failed (each with its one-line reason), tasks re-run after a killed worker,
sessions identical to a serial run (the same stages one after the other in this process,
no Dask, no kills) byte for byte, and the peak memory of each worker process.

    .venv/bin/python benchmarks/bench_faults.py [--sessions 50] [--broken 5] [--kills 8] [--workers 2]

The kill soak instead: `mocap run` (--kill-run N) or `mocap batch` (--kill-batch N, over
--sessions M copies of one small session) SIGKILLed, with every process it started, at N
seeded random moments, each run taking up what the last one left; after each kill every
file a reader sees is checked (whole: as an uninterrupted run leaves it, or a state such a
run passes through), and the lock a killed run left is counted (the next run takes it
over); then the command runs to its end and its files are compared with an uninterrupted
`mocap run`'s, byte for byte:

    .venv/bin/python benchmarks/bench_faults.py --kill-run 20
    .venv/bin/python benchmarks/bench_faults.py --kill-batch 10 --sessions 4
"""

from __future__ import annotations

import argparse
import hashlib
import os
import resource
import shutil
import signal
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mocap import cli  # noqa: E402
from mocap.batch.plan import Stage, stage_from_command  # noqa: E402
from mocap.batch.run import run_stages  # noqa: E402
from mocap.batch.stage import BatchOptions, run_batch  # noqa: E402
from mocap.core.calibration import Calibration  # noqa: E402
from mocap.io.cameras_toml import load_calibration, save_calibration  # noqa: E402
from mocap.io.session import Session  # noqa: E402
from mocap.io.tracks_csv import load_tracks, save_tracks  # noqa: E402

RESULTS = ("calibration/cameras.toml", "tracks/cam1.csv", "tracks/cam2.csv", "results/points.csv",
           "results/motion.csv")
KILLS_DIR = "kills"  # beside the sessions: one file per task whose worker was killed


def prepare(root: Path) -> None:
    """The truth calibration without time offsets: sync must find them."""
    truth = load_calibration(root / "truth" / "cameras.toml")
    extras = tuple({**e, "time_offset": 0.0} for e in truth.extras)
    save_calibration(Calibration(truth.cameras, extras, truth.metadata), root / "calibration" / "cameras.toml")


def camera_tracks(root: Path, camera: str, kill_mark: Path | None = None) -> None:
    """One camera's truth tracks; with `kill_mark`, the first run kills its own worker."""
    if kill_mark is not None and not kill_mark.exists():
        kill_mark.parent.mkdir(parents=True, exist_ok=True)
        kill_mark.write_text(f"{root.name} {camera}\n")
        os.kill(os.getpid(), signal.SIGKILL)
    tracks = load_tracks(root / "truth" / "tracks.csv")
    if camera not in tracks.cameras:
        raise FileNotFoundError(f"{root / 'truth' / 'tracks.csv'}: no tracks of camera {camera}")
    save_tracks(tracks.of_camera(camera), root / "tracks" / f"{camera}.csv")


def chain(root: Path, killed: frozenset = frozenset(), kills: Path | None = None) -> list[Stage]:
    session = Session.open(root)
    config = session.config()
    calibration = root / "calibration" / "cameras.toml"
    tracks = [session.tracks_path(c) for c in session.camera_names]
    machine = str(session.machine_path())
    fps = [a for c in config.cameras for a in ("--fps", f"{c.name}={c.fps}")]
    made = {calibration, *tracks}

    def mark(camera):
        return kills / f"{root.name}-{camera}" if (root.name, camera) in killed else None
    return [
        Stage("prepare", (root / "truth" / "cameras.toml",), (calibration,), call=partial(prepare, root)),
        *[Stage(f"tracks {c}", (root / "truth" / "tracks.csv", calibration), (session.tracks_path(c),),
                call=partial(camera_tracks, root, c, mark(c)), camera=c) for c in session.camera_names],
        stage_from_command("sync", ["sync", str(calibration), *map(str, tracks), "--machine", machine, *fps,
                                    "--out", str(calibration)], made),
        stage_from_command("triangulate", ["triangulate", str(calibration), *map(str, tracks),
                                           "--out", str(session.points_path)], made),
        stage_from_command("fit", ["fit", machine, str(calibration), *map(str, tracks),
                                   "--out", str(session.motion_path)], made),
    ]


BREAKS = {  # how a session is broken: (what, spoil)
    "lost calibration": lambda r: (r / "truth" / "cameras.toml").unlink(),
    "corrupt tracks": lambda r: (r / "truth" / "tracks.csv").write_bytes(b"camera,frame,marker,x,y\ncam1,0,X\x00\n"),
    "wrong machine model": lambda r: (r / "session.toml").write_text(
        (r / "session.toml").read_text().replace('machine = "hitachi_ex3500"', 'machine = "bobcat_225"')),
    "session.toml not TOML": lambda r: (r / "session.toml").write_text("[[cameras]\nname = 1\n"),
    "one camera's tracks lost": lambda r: save_tracks(
        load_tracks(r / "truth" / "tracks.csv").of_camera("cam1"), r / "truth" / "tracks.csv"),
}


def make_fleet(work: Path, n: int, broken: int) -> tuple[list[Path], dict[str, str]]:
    base = work / "base"
    if not (base / "COMPLETE").exists():
        shutil.rmtree(base, ignore_errors=True)
        assert cli.main(["synth", "--machine", "hitachi_ex3500", "--cameras", "2", "--cycles", "1", "--no-video",
                         "--seed", "3", "--out", str(base)]) == 0
    roots, broken_how = [], {}
    kinds = list(BREAKS)
    for k in range(n):
        root = work / "fleet" / f"s{k:02d}"
        shutil.copytree(base, root)
        roots.append(root)
    for k, root in enumerate(roots[::max(1, n // broken)][:broken]):
        kind = kinds[k % len(kinds)]
        BREAKS[kind](root)
        broken_how[root.name] = kind
    return roots, broken_how


def digest(root: Path) -> str:
    h = hashlib.sha256()
    for name in RESULTS:
        path = root / name
        h.update(path.read_bytes() if path.exists() else b"-")
    return h.hexdigest()


def serial(roots: list[Path], broken: dict[str, str]) -> dict[str, str]:
    """The good sessions' results, stage after stage in this process (no Dask, no kills)."""
    out = {}
    for root in roots:
        if root.name in broken:
            continue
        stages = chain(root)
        result = run_stages(root, stages, [s.name for s in stages], [], True)
        assert not result.error, result.error
        out[root.name] = digest(root)
    return out


# --- the kill soak: `mocap run` / `mocap batch` killed at random moments -------------------------

sys.path.insert(0, str(ROOT / "tests"))
NOT_BATCH_RESULTS = ("results/session_report.html", "results/COMPLETE")  # `mocap run`'s, not the batch's


def kill_soak(command: str, kills: int, sessions: int, workers: int, seed: int, work: Path) -> None:
    from kills import make_small_session, run_killed, visible

    from mocap.io.lock import LOCK_NAME
    from mocap.orchestration.pipeline import RunOptions, session_steps

    small = work / "small" / "s"
    if not (small / "calibration" / "labels.csv").exists():
        shutil.rmtree(small.parent, ignore_errors=True)
        make_small_session(small)
    inputs = visible(small)
    for made in ("whole", "between", "killed"):
        shutil.rmtree(work / made, ignore_errors=True)
    whole_root = work / "whole" / "s"
    shutil.copytree(small, whole_root)
    start = time.perf_counter()
    assert run_killed(["run", str(whole_root), "--no-view"], work, 3600.0) == 0
    took = time.perf_counter() - start
    whole = visible(whole_root)
    between = work / "between" / "s"  # the calibration the calibrate stage writes, before sync rewrites it
    shutil.copytree(small, between)
    session_steps(Session.open(between), RunOptions(view=False))[0].call()
    passed_through = {"calibration/cameras.toml": visible(between)["calibration/cameras.toml"]}

    if command == "run":
        roots = [work / "killed" / "s"]
        argv = ["run", str(roots[0]), "--no-view"]
        expected = whole
        estimate = took
    else:
        roots = [work / "killed" / f"s{k:02d}" for k in range(sessions)]
        argv = ["batch", str(work / "killed"), "--workers", str(workers), "--out", str(work / "killed-out")]
        expected = {k: v for k, v in whole.items() if k not in NOT_BATCH_RESULTS}
        estimate = 5.0 + took * sessions / workers  # Dask's start, then the sessions side by side
    for root in roots:
        shutil.copytree(small, root)

    def results(root: Path) -> dict:
        return {k: v for k, v in visible(root).items() if not k.startswith("batch/")}

    rng = np.random.default_rng(seed)
    killed = checked = not_whole = stale = inputs_changed = ended = refused = ended_identical = 0
    for _ in range(kills):
        start = time.perf_counter()
        code = run_killed(argv, work, float(rng.uniform(0.05, 1.0)) * estimate)
        elapsed = time.perf_counter() - start
        killed += code is None
        ended += code == 0
        refused += code not in (None, 0)
        for root in roots:
            files = results(root)
            inputs_changed += any(files.get(k) != v for k, v in inputs.items())
            for name, digest in files.items():
                checked += 1
                not_whole += digest not in (whole.get(name), passed_through.get(name))
            stale += (root / LOCK_NAME).exists()  # a dead process's: the next run takes it over
        if code == 0 and command == "batch":  # all done (a re-run would skip every stage): afresh, and sooner
            ended_identical += all(results(r) == expected for r in roots)
            for root in roots:
                shutil.rmtree(root)
                shutil.copytree(small, root)
            estimate = min(estimate, elapsed)
    start = time.perf_counter()
    final = run_killed(argv, work, 3600.0)
    rerun_s = time.perf_counter() - start
    identical = sum({k: v for k, v in visible(r).items() if not k.startswith("batch/")} == expected for r in roots)
    skipped = ""
    if command == "batch" and (work / "killed-out" / "fleet.csv").exists():
        import csv

        with open(work / "killed-out" / "fleet.csv", newline="") as fh:
            rows = list(csv.DictReader(fh))
        skipped = (f"; the re-run: {sum(int(r['stages_run']) for r in rows)} stages run, "
                   f"{sum(int(r['stages_skipped']) for r in rows)} skipped (done before a kill)")
    print(f"kill soak of `mocap {command}`" + (f" over {sessions} sessions, {workers} workers" if command == "batch"
                                               else "") + f" (seed {seed}); an uninterrupted `mocap run` {took:.1f} s")
    print(f"runs {kills}: killed {killed}, ended before their moment {ended}"
          + (f" ({ended_identical} of them identical to an uninterrupted run, then started afresh)"
             if command == "batch" and ended else "") + f", refused {refused}; files checked "
          f"{checked}, files not whole {not_whole}, inputs changed {inputs_changed}, stale locks taken over {stale}")
    print(f"run again to its end: exit {final} in {rerun_s:.1f} s; identical to an uninterrupted run "
          f"{identical} of {len(roots)} session(s) ({'identical' if identical == len(roots) else 'NOT identical'})"
          + skipped)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sessions", type=int, default=None, help="sessions (default 50; the kill soak of batch 4)")
    parser.add_argument("--broken", type=int, default=5)
    parser.add_argument("--kills", type=int, default=8, help="tasks whose worker is killed the first time")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--work", type=Path, help="work folder (default: a temporary one)")
    parser.add_argument("--kill-run", type=int, metavar="N", help="the kill soak of `mocap run`: N kills")
    parser.add_argument("--kill-batch", type=int, metavar="N", help="the kill soak of `mocap batch`: N kills")
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_faults_"))
    if args.kill_run or args.kill_batch:
        command, kills = ("run", args.kill_run) if args.kill_run else ("batch", args.kill_batch)
        kill_soak(command, kills, args.sessions or 4, args.workers, args.seed, work)
        return
    args.sessions = args.sessions or 50
    shutil.rmtree(work / "fleet", ignore_errors=True)
    shutil.rmtree(work / "serial", ignore_errors=True)
    shutil.rmtree(work / KILLS_DIR, ignore_errors=True)
    roots, broken = make_fleet(work, args.sessions, args.broken)
    copies = [work / "serial" / r.name for r in roots]
    for root, copy in zip(roots, copies):
        shutil.copytree(root, copy)
    start = time.perf_counter()
    reference = serial(copies, broken)
    serial_s = time.perf_counter() - start

    rng = np.random.default_rng(args.seed)
    good = [r.name for r in roots if r.name not in broken]
    victims = rng.choice(len(good) * 2, size=min(args.kills, len(good) * 2), replace=False)
    killed = frozenset((good[v // 2], f"cam{v % 2 + 1}") for v in victims)
    kills = work / KILLS_DIR

    import dask
    from distributed import Client, LocalCluster

    peaks = {}
    start = time.perf_counter()
    settings = {"distributed.worker.profile.enabled": False, "distributed.scheduler.allowed-failures": 10}  # as batch's own
    with dask.config.set(settings), LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True,
                                                 dashboard_address=":0") as cluster:
        options = BatchOptions(scheduler=cluster.scheduler_address, out=work)
        report, failed = run_batch([work / "fleet"], options,
                                   chain_for=partial(chain, killed=killed, kills=kills))
        with Client(cluster) as client:
            peaks = client.run(lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    batch_s = time.perf_counter() - start
    reruns = len(list(kills.glob("*"))) if kills.exists() else 0
    identical = sum(digest(r) == reference[r.name] for r in roots if r.name in reference)
    failures = [line.strip() for line in report.splitlines() if line.startswith("  ")]
    lost = [line for line in failures if line.split(":")[0].split("/")[-1] not in broken]
    print(f"sessions {len(roots)}, broken {len(broken)}, workers {args.workers}, tasks whose worker was killed "
          f"{len(killed)} (seed {args.seed})")
    print(f"serial (in-process, no kills): {serial_s:.1f} s; batch under faults: {batch_s:.1f} s")
    print(f"completed {len(roots) - failed}, failed {failed}, re-run after a killed worker {reruns}, "
          f"identical to serial {identical} of {len(reference)}, good sessions lost {len(lost)}")
    for line in failures:
        name = line.split(":")[0]
        print(f"  failed {line}   [broken: {broken.get(name.split('/')[-1], 'NOT BROKEN')}]")
    print("peak memory per worker (the workers alive at the end; a restarted one counts from its restart):")
    for address, mb in sorted(peaks.items()):
        print(f"  {address}: {mb:.0f} MB")


if __name__ == "__main__":
    main()
