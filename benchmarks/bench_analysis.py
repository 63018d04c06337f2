"""Dig-cycle analysis benchmarks: accuracy against the synthetic truth and speed.

    OMP_NUM_THREADS=1 python benchmarks/bench_analysis.py [--quick] [--only accuracy|machines|long]
    OMP_NUM_THREADS=1 python benchmarks/bench_analysis.py --only accuracy --accuracy-seeds 10-29   # table 1, 40 sessions

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
backhoe; on the truth motion, with reconstruction-sized noise added, and on the motion
`mocap fit` reconstructs from 2-3 random cameras of the robustness scenes
(`mocap.synthetic.machines.random_cameras`: 10-90 m away, the machine filling 40-90 % of
the image) seeing every marker in view (no part of the machine hides one) plus 0.5 px of
pixel noise, with the true cameras (the same fit as table 1's).
Table (5) (`--only seeds`): redirections and scales over many planned truth sessions of 12
cycles (seeds `--seeds A-B` of each machine, no cameras, no fit): pooled precision and
recall, how many sessions fall below 0.9 in either, and for the redirections found with
the right kind (temporary or kept) the error of their lift (a share of the machine's
reach) and turn (deg).
Table (4b) (`--only machines-truth`): table 4's first 10 machines of each kind on the
truth motion alone (no cameras, no fit).
Table (6) (`--only endings --seeds A-B`): dig start and end errors on planned truth sessions
of 12 cycles of the EX3500 and of random diggers whose digs end in other ways: a rest before
the lift-out, the swing starting before the dig ends, redirections late in the dig, more
reactive noise, and all of these; on the truth motion and with reconstruction-sized noise
(and with `--fitted` on the motion `mocap fit` gives, table 4's cameras).
Table (3): a 2-hour session (216,000 frames at 30 fps, about 290 cycles) built by
concatenating planned truth sessions, analysed end to end (`mocap analyze`: CSV read,
analysis, report, templates) and the analysis alone; CPU seconds of one thread.
"""

from __future__ import annotations

import argparse
import contextlib
import io
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
from mocap.core.calibration import Calibration
from mocap.core.motion import Motion
from mocap.core.tracks import Tracks, concatenate
from mocap.errors import InputError
from mocap.io.cameras_toml import save_calibration
from mocap.io.cycles_csv import load_cycle_table
from mocap.io.machine_toml import load_machine, save_machine
from mocap.io.motion_csv import load_motion, save_motion
from mocap.io.tracks_csv import load_tracks, save_tracks
from mocap.synthetic.machines import SceneOptions, random_cameras, random_digger
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


def fitted_motion(machine: str | Path, cameras: Path, tracks: Path, folder: Path, rng: np.random.Generator,
                  quiet: bool = False) -> Path | None:
    """`mocap fit` of the true tracks plus PIXEL_NOISE of pixel noise with the true cameras:
    the fitted motion CSV, or None when the fit refuses (exit 2)."""
    noisy_tracks(tracks, folder / "noisy.csv", rng)
    with contextlib.redirect_stdout(io.StringIO()) if quiet else contextlib.nullcontext():
        code = cli.main(["fit", str(machine), str(cameras), str(folder / "noisy.csv"),
                         "--out", str(folder / "fitted.csv")])
    return folder / "fitted.csv" if code == 0 else None


def accuracy(root: Path, sessions: list[tuple[str, int]]) -> None:
    rows, backwards, pooled = [], [], {"truth": [], "fitted": []}
    for name, seed in sessions:
        folder = root / f"{name}_{seed}"
        assert cli.main(["synth", "--machine", name, "--cycles", "12", "--seed", str(seed), "--no-video",
                         "--out", str(folder)]) == 0
        truth = load_cycle_table(folder / "truth" / "cycles.csv")
        fitted = fitted_motion(name, folder / "truth" / "cameras.toml", folder / "truth" / "tracks.csv", folder,
                               np.random.default_rng(seed))
        assert fitted is not None
        machine = load_machine(name)
        for label, path in (("truth", folder / "truth" / "motion.csv"), ("fitted", fitted)):
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
        counts, bounds, class_acc, redirections, scales = pool(scores)
        summary.append([label, *counts, *bounds, class_acc, *redirections, *scales])
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


def filmed(machine, plan, times: np.ndarray, folder: Path, rng: np.random.Generator) -> tuple[Path, Path, Path]:
    """The machine model, 2-3 random cameras of the robustness scenes (`random_cameras`) and
    the true pixels of every marker in view at `times` (s, 30 fps), written to `folder`:
    (machine.toml, cameras.toml, tracks.csv). No part of the machine hides a marker."""
    world = machine.markers(plan.joints(times), plan.world_from_base(times))  # (F, M, 3)
    cameras = random_cameras(world, SceneOptions(cameras=(2, 3)), rng)
    folder.mkdir(parents=True, exist_ok=True)
    save_machine(machine, folder / "machine.toml")
    save_calibration(Calibration(cameras, tuple({"fps": 30.0, "time_offset": 0.0} for _ in cameras)),
                     folder / "cameras.toml")
    names, parts = np.asarray(machine.marker_names, dtype=object), []
    for camera in cameras:
        uv = camera.project(world)
        w, h = camera.size
        seen = np.isfinite(uv).all(axis=-1) & (uv >= 1).all(axis=-1) & (uv[..., 0] <= w - 2) & (uv[..., 1] <= h - 2)
        f, m = np.nonzero(seen)
        parts.append(Tracks.from_rows(np.full(len(f), camera.name, dtype=object), f, names[m], uv[f, m],
                                      time=times[f]))
    save_tracks(concatenate(parts), folder / "tracks.csv")
    return folder / "machine.toml", folder / "cameras.toml", folder / "tracks.csv"


MOTIONS = ("truth", "noisy", "fitted")


def other_machines(n: int, root: Path) -> None:
    """Random diggers digging like shovels, and backhoe digs of random diggers and the Bobcat:
    on the truth motion, with reconstruction-sized white noise, and as `mocap fit` gives it."""
    rows = []
    bobcat = load_machine("bobcat_225")
    for kind, classes in (("random digger, shovel digs", CLASSES), ("random digger, backhoe digs", (BACKHOE,)),
                          ("Bobcat 225, backhoe digs", (BACKHOE,))):
        scores = {label: [] for label in MOTIONS}
        other = {label: [] for label in MOTIONS}
        lifts = {label: [] for label in MOTIONS}
        refused, fit_refused, machines = 0, 0, 0
        for seed in range(n):
            machine = bobcat if kind.startswith("Bobcat") else random_digger(np.random.default_rng(seed))
            try:
                plan = plan_session(machine, 12, np.random.default_rng(1000 + seed), classes=classes)
            except InputError:  # a linkage that cannot dig so: the planner says so
                refused += 1
                continue
            machines += 1
            motion, truth = planned_truth(machine, plan)
            motions = {"truth": motion,
                       "noisy": reconstruction_noise(motion, np.random.default_rng(seed), plan_reach(plan))}
            folder = root / f"{kind.split(',')[0].replace(' ', '_')}_{len(classes)}_{seed}"
            files = filmed(machine, plan, motion.time, folder, np.random.default_rng([2, seed]))
            fitted = fitted_motion(files[0], files[1], files[2], folder, np.random.default_rng([3, seed]), quiet=True)
            if fitted is None:
                fit_refused += 1
            else:
                motions["fitted"] = load_motion(fitted, machine)
            for label, m in motions.items():
                a = analyze(tip_series(m))
                scores[label].append(score_analysis(a.table, truth))
                other[label].append(np.mean(a.table["class"] == "other") if len(a) else 1.0)
                lifts[label].append(np.abs(scores[label][-1].lift_errors) / plan_reach(plan))
        for label in MOTIONS:
            rows.append(machine_row(kind, label, machines, refused, fit_refused if label == "fitted" else 0,
                                    scores[label], other[label], lifts[label]))
    table(f"(4) machines nobody designed: {n} sessions of 12 cycles each (truth motion; with "
          f"{NOISE_TIP:.1%} of the reach and {NOISE_ANGLE_DEG} deg of white noise; and as `mocap fit` gives it "
          f"from 2-3 random cameras with {PIXEL_NOISE} px of pixel noise)",
          ["machines, digs", "motion", "sessions", "refused by the planner", "refused by the fit", "true", "found",
           "missed", "extra", "start med", "start p95", "end med", "end p95", "class acc", "share other",
           "redir P", "redir R", "scale <=5%", "scale <=5% (no redirection)", "lift err med (reach)",
           "lift err p90"], rows)


def machines_truth(n: int) -> None:
    """Table (4b): table (4)'s first `n` machines of each kind on the truth motion alone (no
    cameras, no fit): a quick look at the scales and redirections."""
    rows = []
    bobcat = load_machine("bobcat_225")
    for kind, classes in (("random digger, shovel digs", CLASSES), ("random digger, backhoe digs", (BACKHOE,)),
                          ("Bobcat 225, backhoe digs", (BACKHOE,))):
        scores, other, refused, lifts = [], [], 0, []
        for seed in range(n):
            machine = bobcat if kind.startswith("Bobcat") else random_digger(np.random.default_rng(seed))
            try:
                plan = plan_session(machine, 12, np.random.default_rng(1000 + seed), classes=classes)
            except InputError:
                refused += 1
                continue
            motion, truth = planned_truth(machine, plan)
            a = analyze(tip_series(motion))
            scores.append(score_analysis(a.table, truth))
            other.append(np.mean(a.table["class"] == "other") if len(a) else 1.0)
            lifts.append(np.abs(scores[-1].lift_errors) / plan_reach(plan))
        rows.append(machine_row(kind, "truth", len(scores), refused, 0, scores, other, lifts))
    table(f"(4b) machines nobody designed, the first {n} of each kind, truth motion only",
          ["machines, digs", "motion", "sessions", "refused by the planner", "refused by the fit", "true", "found",
           "missed", "extra", "start med", "start p95", "end med", "end p95", "class acc", "share other",
           "redir P", "redir R", "scale <=5%", "scale <=5% (no redirection)", "lift err med (reach)",
           "lift err p90"], rows)


def machine_row(kind: str, label: str, machines: int, refused: int, fit_refused: int, scores: list,
                other: list, lifts: list) -> list:
    """One row of table (4): the sessions' scores pooled; `lifts` the sessions' lift errors
    of the redirections found with the right kind, as shares of the machine's reach."""
    counts, bounds, class_acc, redirections, scales = pool(scores)
    lifts = np.concatenate(lifts) if lifts else np.zeros(0)
    spread = (float(np.median(lifts)), float(np.percentile(lifts, 90))) if len(lifts) else (np.nan, np.nan)
    return [kind, label, machines, refused, fit_refused, *counts, *bounds, class_acc, float(np.mean(other)),
            *redirections, *scales, *spread]


def pool(scores: list) -> tuple:
    """Sessions' scores pooled: (true, found, missed, extra); dig start and end median and
    95th (s); class accuracy over the true digs; redirection precision and recall; the
    shares of scale errors within 5 %, of all digs and of those without a redirection."""
    start = np.abs(np.concatenate([s.start_errors for s in scores]))
    end = np.abs(np.concatenate([s.end_errors for s in scores]))
    errors = np.abs(np.concatenate([s.scale_errors for s in scores]))
    redirected = np.concatenate([s.scale_redirected for s in scores])
    tp, fp, fn = (sum(getattr(s, k) for s in scores) for k in ("redirect_tp", "redirect_fp", "redirect_fn"))
    true = sum(s.true for s in scores)
    counts = (true, *(sum(getattr(s, k) for s in scores) for k in ("found", "missed", "extra")))
    bounds = (float(np.median(start)), float(np.percentile(start, 95)), float(np.median(end)),
              float(np.percentile(end, 95)))
    class_acc = sum(s.class_correct for s in scores) / max(true, 1)
    return (counts, bounds, class_acc, (tp / max(tp + fp, 1), tp / max(tp + fn, 1)),
            (float(np.mean(errors <= 0.05)), float(np.mean(errors[~redirected] <= 0.05))))


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


def seed_sweep(first: int, last: int) -> None:
    """Table (5): redirections and scales over planned truth sessions `first`..`last` of each machine."""
    rows = []
    for name in ("hitachi_ex3500", "bobcat_225"):
        machine = load_machine(name)
        scores, below, lifts = [], 0, []
        for seed in range(first, last + 1):
            plan = plan_session(machine, 12, np.random.default_rng(seed))
            motion, truth = planned_truth(machine, plan)
            score = score_analysis(analyze(tip_series(motion)).table, truth)
            r = score.row()
            below += int(r["redir_precision"] < 0.9 or r["redir_recall"] < 0.9)
            scores.append(score)
            lifts.append(np.abs(score.lift_errors) / plan_reach(plan))
        counts, _, class_acc, redirections, scales = pool(scores)
        tp, fp, fn = (sum(getattr(s, k) for s in scores) for k in ("redirect_tp", "redirect_fp", "redirect_fn"))
        lifts, turns = np.concatenate(lifts), np.abs(np.concatenate([s.turn_errors for s in scores]))
        rows.append([name, f"{first}-{last}", len(scores), counts[0], class_acc, tp + fn, fp, fn, *redirections,
                     below, *scales, len(lifts), float(np.median(lifts)), float(np.percentile(lifts, 90)),
                     float(np.median(turns)), float(np.percentile(turns, 90))])
    table(f"(5) redirections over planned truth sessions, seeds {first}-{last} of each machine",
          ["machine", "seeds", "sessions", "digs", "class acc", "true redirections", "false", "missed", "redir P",
           "redir R", "sessions with P or R < 0.9", "scale <=5%", "scale <=5% (no redirection)",
           "right kind", "lift err med (reach)", "lift err p90", "turn err med (deg)", "turn err p90"], rows)


ENDINGS = (("default digs", {}),
           ("a rest of 0.5-3 s before the lift-out", {"end_pause": (0.5, 3.0)}),
           ("the swing starting up to 0.9 s before the dig ends", {"swing_lead": (-0.3, 0.4)}),
           ("redirections at 0.7-0.92 of the dig (4 in 5 digs)", {"redirect_at": (0.7, 0.92), "redirect_probability": 0.8}),
           ("reactive noise x2.5", {"reactive": 2.5}),
           ("all of these", {"end_pause": (0.5, 3.0), "swing_lead": (-0.3, 0.4), "redirect_at": (0.7, 0.92),
                             "redirect_probability": 0.8, "reactive": 2.5}))


def endings(first: int, last: int, root: Path, fit: bool = False) -> None:
    """Table (6): dig bounds on digs that end in other ways, planned truth sessions of 12
    cycles (seeds `first`..`last`) of the EX3500 and of random diggers digging like shovels;
    on the truth motion, with reconstruction-sized white noise (noisy) and, when `fit`, as
    `mocap fit` gives it from 2-3 random cameras (table 4's)."""
    rows = []
    ex3500 = load_machine("hitachi_ex3500")
    for kind in ("EX3500", "random diggers"):
        for name, options in ENDINGS:
            scores = {"truth": [], "noisy": [], **({"fitted": []} if fit else {})}
            peer, refused = [], 0
            for seed in range(first, last + 1):
                machine = ex3500 if kind == "EX3500" else random_digger(np.random.default_rng(seed))
                try:
                    plan = plan_session(machine, 12, np.random.default_rng([6, seed]), **options)
                except InputError:
                    refused += 1
                    continue
                motion, truth = planned_truth(machine, plan)
                motions = {"truth": motion,
                           "noisy": reconstruction_noise(motion, np.random.default_rng([7, seed]), plan_reach(plan))}
                if fit:
                    folder = root / f"endings_{kind.split()[0]}_{seed}"
                    files = filmed(machine, plan, motion.time, folder, np.random.default_rng([2, seed]))
                    fitted = fitted_motion(*files, folder, np.random.default_rng([3, seed]), quiet=True)
                    assert fitted is not None, "the fit refused an endings session"
                    motions["fitted"] = load_motion(fitted, machine)
                for label, m in motions.items():
                    a = analyze(tip_series(m))
                    scores[label].append(score_analysis(a.table, truth))
                    if label == "truth":
                        peer.append(dwell_peer(a, truth)[1])
            for label, pooled in scores.items():
                counts, bounds, *_ = pool(pooled)
                worst = float(np.abs(np.concatenate([s.end_errors for s in pooled])).max())
                rows.append([kind, name, label, len(pooled), refused, *counts, *bounds, worst,
                             float(np.median(peer)) if label == "truth" else ""])
    table(f"(6) dig bounds on digs that end in other ways, seeds {first}-{last} (truth motion; with "
          f"{NOISE_TIP:.1%} of the reach and {NOISE_ANGLE_DEG} deg of white noise; fitted with --fitted)",
          ["machines", "digs", "motion", "sessions", "refused", "true", "found", "missed", "extra", "start med",
           "start p95", "end med", "end p95", "end max", "peer's end med (dwell)"], rows)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="two sessions instead of six, 5 random machines "
                        "instead of 30, no 2-hour session")
    parser.add_argument("--only", choices=("accuracy", "machines", "long", "seeds", "machines-truth", "endings"),
                        help="one part only (seeds: table 5, machines-truth: table 4b, endings: table 6, run "
                        "only when asked)")
    parser.add_argument("--seeds", default="1-60", help="table 5's seeds, A-B (default 1-60)")
    parser.add_argument("--accuracy-seeds", metavar="A-B",
                        help="table 1 on seeds A-B of each machine instead of its six sessions")
    parser.add_argument("--fitted", action="store_true", help="table 6 on the fitted motion too (a fit a session)")
    args = parser.parse_args()
    sessions = SESSIONS[:2] if args.quick else SESSIONS
    if args.accuracy_seeds:
        first, _, last = args.accuracy_seeds.partition("-")
        sessions = [(name, seed) for name in dict(SESSIONS) for seed in range(int(first), int(last or first) + 1)]
    if os.environ.get("OMP_NUM_THREADS") != "1":
        print("note: set OMP_NUM_THREADS=1 for one-thread figures")
    with tempfile.TemporaryDirectory() as tmp:
        if args.only in (None, "accuracy"):
            accuracy(Path(tmp), sessions)
        if args.only in (None, "machines"):
            other_machines(5 if args.quick else 30, Path(tmp))
        if args.only in (None, "long") and not args.quick:
            two_hours(Path(tmp))
        if args.only == "machines-truth":
            machines_truth(10)
        if args.only == "endings":
            first, _, last = args.seeds.partition("-")
            endings(int(first), int(last or first), Path(tmp), args.fitted)
        if args.only == "seeds":
            first, _, last = args.seeds.partition("-")
            seed_sweep(int(first), int(last or first))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
