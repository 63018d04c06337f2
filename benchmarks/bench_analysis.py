"""Dig-cycle analysis benchmarks: accuracy against the synthetic truth and speed.

    OMP_NUM_THREADS=1 python benchmarks/bench_analysis.py [--quick] [--only accuracy|machines|long]

Table (1): synthetic sessions of 12 cycles with all three classes, operator redirections
and scaling (`mocap synth --no-video`), analysed on the truth motion and on the motion
`mocap fit` reconstructs from the true 2-D marker centres plus 0.5 px of pixel noise with
the true cameras; the EX3500 front shovel and the Bobcat 225 compact excavator (whose
synthetic digs are planned like a shovel's, so the rules fit them). The peer is the
simplest segmentation — the dig is the whole dwell at the face, from the return swing's
stop to the loaded swing's start — with the ratio of its median dig-bound error to ours.
Table (2): the same truth sessions played backwards (a dig that pulls the bucket down and
towards the machine, as a backhoe's does): the share of digs reported `other`.
Table (4): machines nobody designed — random diggers (`mocap.synthetic.machines.random_digger`:
boom-arm-bucket linkages of random proportions, frames, joint senses and limits) driven
through their own inverse kinematics, digging like a shovel (classes by the rules) and like
a backhoe (dragging towards the machine: `other`), and the Bobcat 225 digging like a
backhoe; on the truth motion and with reconstruction-sized noise added.
Table (3): a 2-hour session (216,000 frames at 30 fps, about 290 cycles) built by
concatenating planned truth sessions, analysed end to end (`mocap analyze`: CSV read,
analysis, report, templates) and the analysis alone; CPU seconds of one thread.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from mocap import cli
from mocap.analysis.core import analyze
from mocap.analysis.score import planned_truth, score_analysis
from mocap.analysis.series import tip_series
from mocap.analysis.stage import run_analyze
from mocap.io.cycles_csv import load_cycle_table
from mocap.io.machine_toml import load_machine
from mocap.io.motion_csv import Motion, load_motion, save_motion
from mocap.io.tracks_csv import Tracks, load_tracks, save_tracks
from mocap.errors import InputError
from mocap.synthetic.machines import random_digger
from mocap.synthetic.motion import plan_session
from mocap.synthetic.paths import BACKHOE, CLASSES

SESSIONS = [("hitachi_ex3500", 3), ("hitachi_ex3500", 5), ("hitachi_ex3500", 8),
            ("bobcat_225", 3), ("bobcat_225", 5), ("bobcat_225", 7)]
PIXEL_NOISE = 0.5
# about twice the tip error (0.05 % of the reach) and the 0.2 deg of bucket angle `mocap fit` leaves
NOISE_TIP, NOISE_ANGLE_DEG = 0.001, 0.3


def table(title, header, rows):
    print(f"\n## {title}\n")
    print("| " + " | ".join(header) + " |")
    print("|" + "|".join("---" for _ in header) + "|")
    for row in rows:
        print("| " + " | ".join(f"{v:.3g}" if isinstance(v, float) else str(v) for v in row) + " |")


def dwell_peer(a, truth) -> tuple[float, float]:
    """Median dig start and end errors (s) of the peer: the dig is the whole face dwell."""
    t = a.series.time
    swings = a.segments.swings
    stops, starts = t[swings[:, 1]], t[swings[:, 0]]
    errors = []
    for s0, s1 in zip(truth["dig_start_time"].astype(float), truth["dig_end_time"].astype(float)):
        before, after = stops[stops <= s0 + 2.0], starts[starts >= s1 - 2.0]
        start = before[-1] if len(before) else t[0]
        end = after[0] if len(after) else t[-1]
        errors.append((abs(start - s0), abs(end - s1)))
    e = np.array(errors)
    return float(np.median(e[:, 0])), float(np.median(e[:, 1]))


def purity(a) -> float:
    """The share of grouped digs (outliers left out) whose group's most common class is their own."""
    groups, labels = a.grouping.groups, a.table["class"]
    hits = 0
    for g in np.unique(groups[groups > 0]):
        _, counts = np.unique(labels[groups == g], return_counts=True)
        hits += counts.max()
    return hits / max(int((groups > 0).sum()), 1)


def noisy_tracks(source: Path, target: Path, rng: np.random.Generator) -> None:
    t = load_tracks(source)
    save_tracks(Tracks.from_rows(t.camera, t.frame, t.marker, t.xy + rng.normal(0, PIXEL_NOISE, t.xy.shape),
                                 time=t.time), target)


def accuracy(root: Path, quick: bool) -> None:
    rows, backwards, pooled = [], [], {"truth": [], "fitted": []}
    for name, seed in SESSIONS[:2] if quick else SESSIONS:
        folder = root / f"{name}_{seed}"
        assert cli.main(["synth", "--machine", name, "--cycles", "12", "--seed", str(seed), "--no-video",
                         "--out", str(folder)]) == 0
        truth = load_cycle_table(folder / "truth" / "cycles.csv")
        noisy_tracks(folder / "truth" / "tracks.csv", folder / "noisy.csv", np.random.default_rng(seed))
        assert cli.main(["fit", name, str(folder / "truth" / "cameras.toml"), str(folder / "noisy.csv"),
                         "--out", str(folder / "fitted.csv")]) == 0
        machine = load_machine(name)
        for label, path in (("truth", folder / "truth" / "motion.csv"), ("fitted", folder / "fitted.csv")):
            a = analyze(tip_series(load_motion(path, machine)))
            score = score_analysis(a.table, truth)
            pooled[label].append(score)
            r = score.row()
            peer = dwell_peer(a, truth)
            rows.append([name, seed, label, r["true"], r["found"], r["missed"], r["extra"],
                         r["start_med_s"], r["start_p95_s"], r["end_med_s"], r["end_p95_s"], r["class_acc"],
                         r["redir_precision"], r["redir_recall"], r["redir_kind_acc"], r["scale_med"],
                         r["scale_within_5pct"], r["scale_within_5pct_plain"], f"{peer[0]:.2f}/{peer[1]:.2f}",
                         f"{peer[0] / max(r['start_med_s'], 1e-3):.1f}/{peer[1] / max(r['end_med_s'], 1e-3):.1f}",
                         a.grouping.count, int((a.grouping.groups == 0).sum()), purity(a)])
            if label == "truth":
                motion = load_motion(path, machine)
                order = np.arange(len(motion))[::-1]
                reverse = replace(motion, joints=motion.joints[order], points=motion.points[order],
                                  bucket_angle=motion.bucket_angle[order], extra={})
                b = analyze(tip_series(reverse))
                backwards.append([name, seed, len(b), float(np.mean(b.table["class"] == "other")) if len(b) else 1.0])
    table("(1) accuracy against the truth (errors in s; scale error as a share, relative to each class's size)",
          ["machine", "seed", "motion", "true", "found", "missed", "extra", "start med", "start p95", "end med",
           "end p95", "class acc", "redir P", "redir R", "redir kind", "scale err med", "scale <=5%",
           "scale <=5% (no redirection)", "peer start/end med", "peer / ours", "groups", "outliers", "group purity"],
          rows)
    summary = []
    for label, scores in pooled.items():
        start = np.abs(np.concatenate([s.start_errors for s in scores]))
        end = np.abs(np.concatenate([s.end_errors for s in scores]))
        errors = np.abs(np.concatenate([s.scale_errors for s in scores]))
        redirected = np.concatenate([s.scale_redirected for s in scores])
        tp, fp, fn = (sum(getattr(s, k) for s in scores) for k in ("redirect_tp", "redirect_fp", "redirect_fn"))
        true = sum(s.true for s in scores)
        summary.append([label, true, sum(s.found for s in scores), sum(s.missed for s in scores),
                        sum(s.extra for s in scores), float(np.median(start)), float(np.percentile(start, 95)),
                        float(np.median(end)), float(np.percentile(end, 95)),
                        sum(s.class_correct for s in scores) / true, tp / max(tp + fp, 1), tp / max(tp + fn, 1),
                        float(np.mean(errors <= 0.05)), float(np.mean(errors[~redirected] <= 0.05))])
    table("(1b) all sessions of (1) pooled",
          ["motion", "true", "found", "missed", "extra", "start med", "start p95", "end med", "end p95", "class acc",
           "redir P", "redir R", "scale <=5%", "scale <=5% (no redirection)"], summary)
    table("(2) the same digs played backwards (pulling towards the machine)",
          ["machine", "seed", "digs found", "share other"], backwards)


def reconstruction_noise(motion, rng: np.random.Generator, reach: float):
    """The motion with noise of the size `mocap fit` leaves (NOISE_TIP of the reach on every
    point, NOISE_ANGLE_DEG on the bucket angle, white per frame)."""
    points = motion.points + rng.normal(0.0, NOISE_TIP * reach, motion.points.shape)
    angle = motion.bucket_angle + np.radians(rng.normal(0.0, NOISE_ANGLE_DEG, len(motion)))
    return replace(motion, points=points, bucket_angle=angle)


def other_machines(n: int) -> None:
    """Random diggers digging like shovels, and backhoe digs of random diggers and the Bobcat."""
    rows = []
    bobcat = load_machine("bobcat_225")
    for kind, classes in (("random digger, shovel digs", CLASSES), ("random digger, backhoe digs", (BACKHOE,)),
                          ("Bobcat 225, backhoe digs", (BACKHOE,))):
        for noisy in (False, True):
            scores, refused, other, machines = [], 0, [], 0
            for seed in range(n):
                machine = bobcat if kind.startswith("Bobcat") else random_digger(np.random.default_rng(seed))
                try:
                    plan = plan_session(machine, 12, np.random.default_rng(1000 + seed), classes=classes)
                except InputError:  # a linkage that cannot dig so: the planner says so
                    refused += 1
                    continue
                machines += 1
                motion, truth = planned_truth(machine, plan)
                if noisy:
                    motion = reconstruction_noise(motion, np.random.default_rng(seed), plan_reach(plan))
                a = analyze(tip_series(motion))
                scores.append(score_analysis(a.table, truth))
                other.append(np.mean(a.table["class"] == "other") if len(a) else 1.0)
            start = np.abs(np.concatenate([s.start_errors for s in scores]))
            end = np.abs(np.concatenate([s.end_errors for s in scores]))
            true = sum(s.true for s in scores)
            rows.append([kind, "noisy" if noisy else "truth", machines, refused, true, sum(s.found for s in scores),
                         sum(s.missed for s in scores), sum(s.extra for s in scores),
                         float(np.median(start)), float(np.percentile(start, 95)), float(np.median(end)),
                         float(np.percentile(end, 95)), sum(s.class_correct for s in scores) / max(true, 1),
                         float(np.mean(other))])
    table(f"(4) machines nobody designed: {n} sessions of 12 cycles each (truth motion, and with "
          f"{NOISE_TIP:.1%} of the reach and {NOISE_ANGLE_DEG} deg of white noise)",
          ["machines, digs", "motion", "sessions", "refused by the planner", "true", "found", "missed", "extra",
           "start med", "start p95", "end med", "end p95", "class acc", "share other"], rows)


def plan_reach(plan) -> float:
    return float(np.linalg.norm(plan.chain.offsets, axis=1).sum())


def azimuth(motion, k: int) -> float:
    tip = motion.point("bucket_tip")[k]
    return float(np.arctan2(tip[1], tip[0]))


def turned(motion, machine, angle: float):
    """The motion turned by `angle` (rad) about the swing axis."""
    c, s = np.cos(angle), np.sin(angle)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    joints = motion.joints.copy()
    joints[:, machine.joint_names.index("swing")] += angle
    return replace(motion, joints=joints, points=motion.points @ rotation.T)


def two_hours(root: Path) -> None:
    machine = load_machine("hitachi_ex3500")
    parts, truths, offset, seed = [], [], 0.0, 100
    while offset < 7200.0:
        seed += 1
        try:
            motion, truth = planned_truth(machine, plan_session(machine, 6, np.random.default_rng(seed)))
        except ValueError:
            continue
        if parts:  # turn the session about the swing axis to carry on where the last one stopped
            motion = turned(motion, machine, azimuth(parts[-1][0], -1) - azimuth(motion, 0))
        parts.append((motion, offset))
        truths.append({k: (v + offset if k.endswith("_time") else v) for k, v in truth.items()})
        offset += motion.time[-1] + 1.0 / 30.0
    n = 216_000
    time_ = np.concatenate([m.time + o for m, o in parts])[:n]
    cat = lambda name: np.concatenate([getattr(m, name) for m, _ in parts])[:n]  # noqa: E731
    motion = Motion(machine.joint_names, machine.point_names, np.arange(n), time_, cat("joints"), cat("points"),
                    cat("bucket_angle"))
    truth = {k: np.concatenate([t[k] for t in truths]) for k in truths[0]}
    inside = truth["dig_end_time"] < time_[-1]
    truth = {k: v[inside] for k, v in truth.items()}
    path = root / "two_hours.csv"
    save_motion(motion, machine, path)
    start = time.process_time()
    loaded = load_motion(path, machine)
    read = time.process_time() - start
    start = time.process_time()
    a = analyze(tip_series(loaded))
    analysis = time.process_time() - start
    start = time.process_time()
    run_analyze("hitachi_ex3500", path, root / "two_hours")
    whole = time.process_time() - start
    r = score_analysis(a.table, truth).row()
    table("(3) a 2-hour session, CPU seconds of one thread (target <= 10 s)",
          ["frames", "true cycles", "found", "missed", "extra", "start med", "end med", "class acc", "redir P",
           "redir R", "groups", "outliers", "group purity", "read CSV s", "analysis s",
           "mocap analyze s (read, analyse, report, templates)"],
          [[n, r["true"], r["found"], r["missed"], r["extra"], r["start_med_s"], r["end_med_s"], r["class_acc"],
            r["redir_precision"], r["redir_recall"], a.grouping.count, int((a.grouping.groups == 0).sum()), purity(a),
            read, analysis, whole]])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="two sessions instead of six, 5 random machines "
                        "instead of 30, no 2-hour session")
    parser.add_argument("--only", choices=("accuracy", "machines", "long"), help="one part only")
    args = parser.parse_args()
    if os.environ.get("OMP_NUM_THREADS") != "1":
        print("note: set OMP_NUM_THREADS=1 for one-thread figures")
    with tempfile.TemporaryDirectory() as tmp:
        if args.only in (None, "accuracy"):
            accuracy(Path(tmp), args.quick)
        if args.only in (None, "machines"):
            other_machines(5 if args.quick else 30)
        if args.only in (None, "long") and not args.quick:
            two_hours(Path(tmp))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
