"""Tracking and synchronisation on a rendered synthetic session, against its truth.

Renders a session with `mocap synth` (clutter, motion blur, dust, noise, occlusion by the
machine's own links), then per camera: two decode floors, OpenCV reading every frame in
colour (`decode s`, the peer a user would write) and the tracker's own grey decoding alone
(`grey s`: the same decoder and settings), detection + labelling + tracking of the same
video (decoding included; the least of `--repeat` interleaved runs of each) and its ratio to
each floor; then CPU time, which a loaded machine disturbs far less than wall time: `dec cpu`
the process's for OpenCV's decoding (all its threads), `cpu s` for the tracking (both
threads, decoding included) and `cpu ratio` the one over the other; and the labels and
centres against the true tracks; then the cameras' time offsets from the tracks against the
truth. A marker counts
as visible when all of its painted square is in view (the true tracks' score is 1).

    python benchmarks/bench_tracking.py [--size 1920x1080] [--cameras 3] [--cycles 1] [--seed 7]

`--processes` also times, per camera, `mocap track` of the video against a process that only
reads it with OpenCV, both as whole processes run in turn (wall and CPU seconds, the CPU of
all of a process's threads: the tracker decodes on a thread of its own beside the tracking),
and prints the load average: on a shared machine the wall clock says how busy it is.

    python benchmarks/bench_tracking.py --session DIR --cameras 1 --repeat 3 --processes

With `--looks N`: N sessions, each in its own random look (`mocap.synthetic.looks`:
machine paint, light, marker paint, haze, defocus, compression, noise, size, lens, shake,
rolling shutter: the truth then each marker where it is when its own row is read),
the first `--frames` frames of each camera rendered, encoded at the look's quality and
tracked from the true calibration without a labels file; in every camera the picture is
wholly covered (a flat grey board before the lens) for `--hide` frames from a third of the
way in, and "found again" is the frames from the cover's end to the first frame in which
at least half of the wholly visible markers are labelled right. Labelled share (the
covered frames not counted as visible; a label in them is wrong), also of those whose disk
is at least 3 px across its narrowest way (`>=3 px`: a disk turned far from the camera is a
sliver), wrong labels, centre
errors and found again per look and camera and overall, and the worst look printed with
its settings.

    python benchmarks/bench_tracking.py --looks 20 [--frames 120] [--hide 30] [--size 960x540] [--seed 1] [--fast]

`--fast` takes, in each camera, the `--frames` frames in which its visible markers move most
(the swing: where motion blur smears the markers and a rolling shutter moves them most)
instead of the first ones, tracked from the true joints at the first of them. `--readout
SHARE` gives every look that rolling shutter (0: a global shutter), to compare the same looks.
With `--diggers N`: machines nobody designed, N random diggers
(`mocap.synthetic.machines.random_digger`, seeds 1..N) filmed by `--cameras` cameras in the
default look, the first `--frames` frames rendered (not encoded) at `--size` (960x540) and
tracked from the true calibration without a labels file; a camera whose first frame cannot
be labelled (too few markers in view) is counted apart, and of those the ones whose first
frame shows at least a fit's markers (5) wholly.

    python benchmarks/bench_tracking.py --diggers 12 [--cameras 3] [--frames 120]

`--shapes meshes` (with `--looks` or `--diggers`) draws the links as solids the tracker does
not assume (`mocap.synthetic.meshes`: tapered and kinked links, cab and counterweight beyond
its guessed boxes, hoses, markers on plates turned 10-40 degrees from the boxes' faces), the
truth's visibility computed against them. Both modes print, beside the mean, the worst
camera-marker pair: among the markers clearly visible in at least half of a camera's frames
(wholly in view; with `--looks` also >= 3 px across), the share of those frames in which the
marker is labelled right, its mean, the worst pair and how many are below 90 %. With `--looks`
also the markers' normals learned from their disks' ellipses (`mocap.tracking.normals`, a
look's cameras pooled) against the truth's, beside the boxes' guess.

`--keep DIR` renders each look's clips once into DIR (a folder per look, named by a hash of
the settings that change the render) and tracks the kept clips on later runs: for comparing
tracking code on the same clips (a change to the renderer is not in the key: use a new DIR).
"""

from __future__ import annotations

import argparse
import hashlib
import os
import resource
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from mocap.io.cameras_toml import load_calibration
from mocap.io.machine_toml import load_machine
from mocap.io.tracks_csv import load_tracks
from mocap.io.video import Video
from mocap.clocks.align import joint_curves, synchronise
from mocap.synthetic import make_session
from mocap.synthetic.effects import EffectOptions
from mocap.synthetic.encode import video_writer
from mocap.synthetic.looks import random_look
from mocap.synthetic.machines import random_digger
from mocap.synthetic.render import RenderOptions
from mocap.synthetic.videos import renderer_for
from mocap.synthetic.session import SHAPES, marker_sizes
from mocap.tracking import CameraModel, track_frames
from mocap.tracking.tracker import TrackOptions
from mocap.tracking.normals import NormalEvidence


WIDE_PX = 3.0  # px: disks at least this wide across their narrowest way are also counted apart
WIDTH_BINS_PX = (0.0, 1.0, 2.0, 3.0, np.inf)  # the labelled share by the disk's narrowest width


def decode_floor(path: Path) -> tuple[float, float, int]:
    """Seconds OpenCV takes to read (decode, to colour) every frame, wall and the process's
    CPU (all of its decoding threads), and the frame count."""
    capture = cv2.VideoCapture(str(path))
    start, cpu, count = time.perf_counter(), time.process_time(), 0
    while capture.read()[0]:
        count += 1
    capture.release()
    return time.perf_counter() - start, time.process_time() - cpu, count


def grey_floor(video: Video) -> float:
    """Seconds the tracker's own decoding takes alone: every frame's grey image from the
    decoder's luma plane (`Video.frames`, the same decoder and settings, no tracking)."""
    start = time.perf_counter()
    for _ in video.frames(prefetch=4):
        pass
    return time.perf_counter() - start


_DECODE_ONLY = """import sys, cv2
capture = cv2.VideoCapture(sys.argv[1])
while capture.read()[0]:
    pass
"""


def _child_run(command: list[str]) -> tuple[float, float]:
    """Wall and CPU seconds (user + system, all of its threads) of one child process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def whole_processes(root: Path, machine: str, camera: str, repeat: int, out: Path) -> dict[str, float]:
    """`mocap track` of one camera's video against a process that only reads the same video
    with OpenCV (`cv2.VideoCapture`, colour, its default threads), both whole processes (the
    interpreter's start and the imports included), run in turn `repeat` times: the least wall
    and CPU seconds of each and the medians of the pairs' ratios."""
    video = root / "videos" / f"{camera}.mp4"
    track = [sys.executable, "-m", "mocap.cli", "track", str(video), "--machine", machine, "--calibration",
             str(root / "truth" / "cameras.toml"), "--camera", camera, "--out", str(out)]
    decode = [sys.executable, "-c", _DECODE_ONLY, str(video)]
    _child_run(decode)  # warm: the file in the page cache, the compiled kernels loaded once
    _child_run(track)
    tracks, decodes = [], []
    for _ in range(repeat):
        tracks.append(_child_run(track))
        decodes.append(_child_run(decode))
    t, d = np.array(tracks), np.array(decodes)
    return {"track wall": t[:, 0].min(), "track cpu": t[:, 1].min(), "decode wall": d[:, 0].min(),
            "decode cpu": d[:, 1].min(), "wall ratio": float(np.median(t[:, 0] / d[:, 0])),
            "cpu ratio": float(np.median(t[:, 1] / d[:, 1]))}


def score(truth, tracks):
    """Labelled fraction of the wholly visible markers (true score 1: all of the square in
    view), wrong-label fraction (the detection lies nearer another visible marker's true
    centre than its own, or 5 px or more from it, or its marker is not in view at all),
    centre errors (px) of the right labels of wholly visible markers, and the (frame,
    marker) pairs of those labels. A right label of a partly covered marker counts neither way."""
    true_xy = {(int(f), m): (xy, s) for f, m, xy, s in zip(truth.frame, truth.marker, truth.xy, truth.score)}
    by_frame = {int(f): (truth.xy[truth.frame == f], truth.marker[truth.frame == f]) for f in np.unique(truth.frame)}
    errors, wrong, right = [], 0, set()
    for f, m, xy in zip(tracks.frame, tracks.marker, tracks.xy):
        own, cover = true_xy.get((int(f), m), (None, 0.0))
        e = np.inf if own is None else float(np.linalg.norm(xy - own))
        others, names = by_frame.get(int(f), (np.full((1, 2), np.inf), np.array([m])))
        other = np.linalg.norm(others[names != m] - xy, axis=1)
        if e >= 5.0 or (len(other) and other.min() < e):
            wrong += 1
        elif cover >= 1.0:
            errors.append(e)
            right.add((int(f), m))
    whole = max(int(np.sum(truth.score >= 1.0)), 1)
    return len(errors) / whole, wrong / max(len(tracks), 1), np.array(errors), right


def pair_shares(truth, right, clear=None, least: float = 0.5) -> dict[str, float]:
    """Per marker, the share of the frames in which it is clearly visible (true score 1, and
    where `clear` (N,) over the score-1 rows is given, those of its rows) that it is labelled
    right (`right` the (frame, marker) pairs of `score`), for the markers clearly visible in at
    least `least` of the frames of `truth` (one camera's); {marker: share}."""
    whole = truth.select(truth.score >= 1.0)
    n_frames = max(len(np.unique(truth.frame)), 1)
    if clear is not None:
        whole = whole.select(clear)
    shares = {}
    for m in np.unique(whole.marker):
        frames = whole.frame[whole.marker == m]
        if len(frames) >= least * n_frames:
            shares[str(m)] = sum((int(f), m) in right for f in frames) / len(frames)
    return shares


def worst_pair_line(pairs: list[tuple[str, str, float]], what: str = "wholly visible") -> str:
    """'camera-marker pairs: mean, worst (which)' over (camera, marker, share) triples."""
    if not pairs:
        return f"camera-marker pairs: none {what} in most frames"
    shares = np.array([p[2] for p in pairs])
    k = int(np.argmin(shares))
    below = int(np.sum(shares < 0.9))
    return (f"{len(pairs)} camera-marker pairs {what} in most frames: labelled in {shares.mean():.2%} of "
            f"those frames on average, worst {shares[k]:.2%} ({pairs[k][0]} {pairs[k][1]}), {below} below 90 %")


def _degrees(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


def normals_line(errors: list[tuple[np.ndarray, np.ndarray, int]]) -> str:
    """The normals learned from the disks' ellipses (each look's cameras pooled) against the
    truth's, beside the boxes' guess, over (learned errors, guess errors, markers) per look."""
    learned = np.concatenate([e[0] for e in errors] + [np.zeros(0)])
    guess = np.concatenate([e[1] for e in errors] + [np.zeros(0)])
    total = sum(e[2] for e in errors)
    if not len(learned):
        return f"normals learned from the disks' ellipses: none of {total} settled"
    return (f"normals learned from the disks' ellipses (a look's cameras pooled): {len(learned)} of {total} settled, "
            f"off the truth's by median {np.median(learned):.2f} deg, "
            f"95th percentile {np.percentile(learned, 95):.2f}, "
            f"most {learned.max():.2f} (the boxes' guess: median {np.median(guess):.1f}, most {guess.max():.1f})")


def disk_widths(session, field, truth, diameter_m: float) -> np.ndarray:
    """(N,) the width (px) of each truth row's disk image across its narrowest way: the
    disk's diameter at its distance times the cosine of its face's turn from the line of
    sight (a disk of 2 px radius turned 80 degrees is 0.7 px wide). Lens distortion is left out."""
    machine = session.machine
    frames = np.unique(truth.frame)
    times = field.times(frames)
    joints, world_from_base = session.plan.joints(times), session.plan.world_from_base(times)
    cams = field.cam_from_world(times)  # (F, 4, 4)
    rotation = cams[:, None, :3, :3] @ machine.link_poses(joints, world_from_base)[:, machine.marker_links, :3, :3]
    centre = np.einsum("fij,fmj->fmi", cams[:, :3, :3], machine.markers(joints, world_from_base)) + cams[:, None, :3, 3]
    normal = np.einsum("fmij,mj->fmi", rotation, session.normals)  # in the camera frame
    facing = np.abs(np.sum(normal * centre, axis=-1)) / np.linalg.norm(centre, axis=-1)
    width = field.camera.matrix[0, 0] * diameter_m * facing / centre[..., 2]
    column = {name: i for i, name in enumerate(machine.marker_names)}
    return width[np.searchsorted(frames, truth.frame), [column[m] for m in truth.marker]]


def found_again(truth, tracks, end: int) -> int | None:
    """Frames from `end` to the first frame at or after it in which at least half of the
    wholly visible markers are labelled within 2 px of their true centres (None: never)."""
    true_xy = {(int(f), m): xy for f, m, xy, s in zip(truth.frame, truth.marker, truth.xy, truth.score) if s >= 1.0}
    right = np.zeros(int(truth.frame.max()) + 1 if len(truth) else 0, dtype=int)
    for f, m, xy in zip(tracks.frame, tracks.marker, tracks.xy):
        own = true_xy.get((int(f), m))
        if own is not None and f < len(right) and np.linalg.norm(xy - own) < 2.0:
            right[int(f)] += 1
    whole = np.bincount(truth.frame[truth.score >= 1.0].astype(int), minlength=len(right))
    found = np.flatnonzero((right >= 0.5 * whole) & (whole > 0) & (np.arange(len(right)) >= end))
    return int(found[0] - end) if len(found) else None


def covered(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The picture of a flat grey board held before the lens (sensor noise only)."""
    return np.clip(110.0 + rng.normal(0.0, 2.5, image.shape), 0, 255).astype(np.uint8)


def fastest_window(session, field, count: int) -> int:
    """The first of the `count` frames of `field` in which its visible markers move most
    (the swing, at the bucket's full reach)."""
    uv, seen, _ = session.observe(field, np.arange(field.frames))
    step = np.linalg.norm(np.diff(uv, axis=0), axis=-1)
    fastest = np.nanmax(np.where(seen[1:] & seen[:-1], step, np.nan), axis=1, initial=0.0)
    return int(np.argmax(np.convolve(np.nan_to_num(fastest), np.ones(count), "valid")))


def kept_clips(args, k: int, names: list[str]) -> tuple[Path, bool]:
    """The folder of look `k`'s clips under `args.keep`, keyed on every setting that changes
    what is rendered (the look's seed and index, its shutter, the size, the cameras, the
    window, the cover and the shapes), and whether all of its cameras' clips are there. The cameras of
    a look share one random stream, so a look's clips are rendered all together or not at all."""
    key = repr((args.machine, args.size, args.cameras, args.seed, k, args.readout, args.fast, args.frames, args.hide)
               + ((args.shapes,) if args.shapes != "boxes" else ()))
    folder = Path(args.keep) / f"look{k}-{hashlib.sha1(key.encode()).hexdigest()[:12]}"
    return folder, all((folder / f"{name}.mp4").is_file() for name in names)


def track_looks(args) -> int:
    """Tracking over `args.looks` random looks; see the module's docstring."""
    machine = load_machine(args.machine)
    width, height = (int(v) for v in args.size.lower().split("x"))
    header = (f"{'look':>4} {'camera':>6} {'size':>9} {'visible':>7} {'labelled':>8} {'>=3 px':>8} {'wrong':>7} {'median px':>9} "
              f"{'p95 px':>7} {'found again':>11}  look")
    print(header)
    print("-" * (len(header) + 40))
    results, pairs, normal_errors = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for k in ([args.look] if args.look is not None else range(args.looks)):
            look = random_look(np.random.default_rng([args.seed, k]), name=f"look {k}")
            if args.readout is not None:  # the same look with another shutter
                look = replace(look, readout=args.readout, name=f"{look.name[:-1]}; readout set to {args.readout:g})")
            size = (round(width * look.scale / 2) * 2, round(height * look.scale / 2) * 2)
            session = make_session(machine, args.machine, n_cameras=args.cameras, n_cycles=1, seed=args.seed + k,
                                   size=size, distortion=look.distortion, shake_deg=look.shake_deg,
                                   readout=look.readout, shapes=args.shapes)
            options = RenderOptions(effects=EffectOptions(look.noise, look.blur, look.exposure, look.dust), look=look)
            rng = np.random.default_rng([args.seed, k, 1])
            look_rows, evidence = [], []
            folder, kept = (kept_clips(args, k, [f.name for f in session.cameras]) if args.keep
                            else (Path(tmp), False))
            folder.mkdir(parents=True, exist_ok=True)
            for c, field in enumerate(session.cameras):
                first = fastest_window(session, field, args.frames) if args.fast else 0
                frames = np.arange(first, min(first + args.frames, field.frames))
                hide = (first + len(frames) // 3, min(first + len(frames) // 3 + args.hide, frames[-1] + 1))
                path = folder / f"{field.name}.mp4"
                if not kept:
                    renderer = renderer_for(session, c, options, rng)
                    part = path.with_suffix(".part.mp4")  # renamed when whole: an interrupted render is not kept
                    with video_writer(part, size, field.fps, "h264", 0, look.crf) as write:
                        for f, image in renderer.frames(frames):
                            write(covered(image, rng) if hide[0] <= f < hide[1] else image)
                    part.replace(path)
                model = CameraModel(machine, field.camera)
                try:
                    video = ((first + i, grey) for i, grey in Video(path).frames(prefetch=4))
                    joints = session.plan.joints(field.times(np.array([first])))[0]
                    tracks, summary = track_frames(model, video, joints, None, field.fps)
                    evidence.append(summary.normals)
                except ValueError as exc:  # the first frame could not be labelled
                    print(f"{k:>4} {field.name:>6}: {exc}")
                    tracks = None
                truth = session.tracks.of_camera(field.name)
                truth = truth.select((truth.frame >= first) & (truth.frame <= frames[-1])
                                     & ~((truth.frame >= hide[0]) & (truth.frame < hide[1])))
                whole = int(np.sum(truth.score >= 1.0))
                seen = truth.select(truth.score >= 1.0)
                widths = disk_widths(session, field, seen, look.disk_ratio * marker_sizes(session.reach)[1])
                wide = widths >= WIDE_PX
                if tracks is None:
                    labelled, wrong, errors, again, right = 0.0, 0.0, np.zeros(0), None, set()
                else:
                    labelled, wrong, errors, right = score(truth, tracks)
                    again = found_again(truth, tracks, hide[1]) if hide[1] > hide[0] else 0
                pairs += [(f"look {k} {field.name}", m, v) for m, v in pair_shares(truth, right, wide).items()]
                hits = np.array([(int(f), m) in right for f, m in zip(seen.frame, seen.marker)], dtype=bool)
                wide_right = int(np.sum(hits & wide))
                width_bin = np.digitize(widths, WIDTH_BINS_PX[1:-1])
                by_width = (np.bincount(width_bin, minlength=len(WIDTH_BINS_PX) - 1),
                            np.bincount(width_bin[hits], minlength=len(WIDTH_BINS_PX) - 1))
                look_rows.append((whole, labelled, wrong, errors, again, int(wide.sum()), wide_right, by_width))
                wide_share = wide_right / max(int(wide.sum()), 1)
                print(f"{k:>4} {field.name:>6} {size[0]:>4}x{size[1]:<4} {whole:>7} {labelled:>8.2%} {wide_share:>8.2%} {wrong:>7.3%} "
                      f"{np.median(errors) if len(errors) else np.nan:>9.3f} "
                      f"{np.percentile(errors, 95) if len(errors) else np.nan:>7.3f} "
                      f"{'never' if again is None else again:>11}  {look.name if c == 0 else ''}")
                if not args.keep:
                    path.unlink()
            results.append((look, look_rows))
            if evidence:  # the look's cameras pooled
                guessed = CameraModel(machine, session.cameras[0].camera).normals
                learned = NormalEvidence.pooled(evidence).learn(guessed)
                settled = learned.learned & learned.resolved
                normal_errors.append((_degrees(learned.normals[settled], session.normals[settled]),
                                      _degrees(guessed[settled], session.normals[settled]), len(guessed)))
    share = [sum(r[1] * r[0] for r in rows) / max(sum(r[0] for r in rows), 1) for _, rows in results]
    visible = sum(r[0] for _, rows in results for r in rows)
    labelled = sum(r[1] * r[0] for _, rows in results for r in rows) / max(visible, 1)
    wrong = np.mean([r[2] for _, rows in results for r in rows])
    errors = np.concatenate([r[3] for _, rows in results for r in rows] + [np.zeros(0)])
    print("-" * (len(header) + 40))
    print(f"all {len(results)} looks x {args.cameras} cameras: {labelled:.2%} of {visible} visible markers labelled, "
          f"{wrong:.3%} wrong (mean over cameras), centre error median {np.median(errors):.3f} px, "
          f"95th percentile {np.percentile(errors, 95):.3f} px")
    wide = sum(r[5] for _, rows in results for r in rows)
    print(f"of the {wide} whose disk is at least {WIDE_PX:g} px across its narrowest way: "
          f"{sum(r[6] for _, rows in results for r in rows) / max(wide, 1):.2%} labelled")
    shown = sum(r[7][0] for _, rows in results for r in rows)
    found = sum(r[7][1] for _, rows in results for r in rows)
    print("labelled by the disk's width across its narrowest way: " + ", ".join(
        f"{low:g}-{high:g} px {found[k] / max(shown[k], 1):.2%} of {shown[k]}" if np.isfinite(high)
        else f">= {low:g} px {found[k] / max(shown[k], 1):.2%} of {shown[k]}"
        for k, (low, high) in enumerate(zip(WIDTH_BINS_PX[:-1], WIDTH_BINS_PX[1:]))))
    clear = shown[2:].sum()
    print(f"of the {clear} clearly visible (wholly in view and >= {WIDTH_BINS_PX[2]:g} px across its narrowest "
          f"way): {found[2:].sum() / max(clear, 1):.2%} labelled")
    print(worst_pair_line(pairs, f"wholly visible and >= {WIDE_PX:g} px across"))
    print(normals_line(normal_errors))
    worst = int(np.argmin(share))  # an index of `results`; the look's own number is in its name
    again = [r[4] for _, rows in results for r in rows]
    known = [a for a in again if a is not None]
    print(f"found again after {args.hide} covered frames: median {np.median(known) if known else np.nan:.0f}, "
          f"most {max(known) if known else np.nan} frames; never in {len(again) - len(known)} of {len(again)} cameras")
    print(f"worst: {results[worst][0].name.split(' (')[0]}, {share[worst]:.2%} labelled; its settings:")
    for key, value in results[worst][0].table().items():
        print(f"    {key} = {value}")
    return 0


def track_diggers(args) -> int:
    """Tracking machines nobody designed: `args.diggers` random diggers (seeds 1..N), each
    filmed by `args.cameras` cameras in the default look, the first `args.frames` frames
    rendered (not encoded) and tracked from the true calibration without a labels file."""
    width, height = (int(v) for v in args.size.lower().split("x"))
    print(f"{'seed':>4} {'camera':>6} {'markers':>7} {'visible':>7} {'labelled':>8} {'wrong':>7} {'median px':>9} {'p95 px':>7}")
    visible, started, refused, errors, wrongs, pairs = 0, 0, 0, [], [], []
    refused_seeing = 0  # refused cameras in whose first frame enough markers for a fit are wholly visible
    for seed in range(1, args.diggers + 1):
        machine = random_digger(np.random.default_rng(seed))
        session = make_session(machine, "random digger", n_cameras=args.cameras, n_cycles=1, seed=seed,
                               size=(width, height), shapes=args.shapes)
        for c, field in enumerate(session.cameras):
            renderer = renderer_for(session, c, RenderOptions(), np.random.default_rng(seed))
            frames = [(f, cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))
                      for f, image in renderer.frames(np.arange(min(args.frames, field.frames)))]
            truth = session.tracks.of_camera(field.name)
            truth = truth.select(truth.frame < len(frames))
            whole = int(np.sum(truth.score >= 1.0))
            try:
                tracks, _ = track_frames(CameraModel(machine, field.camera), iter(frames),
                                         session.plan.joints(field.times(np.array([0])))[0], None, field.fps)
            except ValueError as exc:  # the first frame could not be labelled
                shown = int(np.sum((truth.frame == 0) & (truth.score >= 1.0)))
                print(f"{seed:>4} {field.name:>6}: {exc} ({shown} wholly visible)")
                refused += 1
                refused_seeing += shown >= TrackOptions().min_markers
                continue
            labelled, wrong, error, right = score(truth, tracks)
            pairs += [(f"seed {seed} {field.name}", m, v) for m, v in pair_shares(truth, right).items()]
            started += 1
            visible += whole
            errors.append(error)
            wrongs.append(wrong)
            print(f"{seed:>4} {field.name:>6} {len(machine.marker_names):>7} {whole:>7} {labelled:>8.2%} {wrong:>7.3%} "
                  f"{np.median(error) if len(error) else np.nan:>9.3f} "
                  f"{np.percentile(error, 95) if len(error) else np.nan:>7.3f}")
    error = np.concatenate(errors + [np.zeros(0)])
    print(f"{started} cameras tracked, {refused} refused at the first frame ({refused_seeing} of them with at least "
          f"{TrackOptions().min_markers} markers wholly visible in it); of the tracked: "
          f"{len(error) / max(visible, 1):.2%} of {visible} visible markers labelled, "
          f"{np.mean(wrongs) if wrongs else np.nan:.3%} wrong (mean over cameras), centre error median "
          f"{np.median(error) if len(error) else np.nan:.3f} px, 95th percentile "
          f"{np.percentile(error, 95) if len(error) else np.nan:.3f} px")
    print(worst_pair_line(pairs))
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", default="1920x1080")
    parser.add_argument("--cameras", type=int, default=3)
    parser.add_argument("--cycles", type=int, default=1)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--machine", default="hitachi_ex3500")
    parser.add_argument("--session", help="use this rendered session folder instead of rendering one")
    parser.add_argument("--repeat", type=int, default=2, help="timed runs per camera (the least counts)")
    parser.add_argument("--processes", action="store_true",
                        help="also time `mocap track` and an OpenCV decode of each video as whole processes")
    parser.add_argument("--looks", type=int, default=0, help="track over this many random looks instead")
    parser.add_argument("--frames", type=int, default=120, help="with --looks: frames per camera")
    parser.add_argument("--hide", type=int, default=30, help="with --looks: frames the picture is covered")
    parser.add_argument("--readout", type=float, help="with --looks: every look's rolling shutter (0: global)")
    parser.add_argument("--keep", metavar="DIR",
                        help="with --looks: render each look's clips once into DIR and reuse them on later runs")
    parser.add_argument("--look", type=int, metavar="K",
                        help="with --looks: track look K of the series alone (the same clips as in the whole run)")
    parser.add_argument("--fast", action="store_true",
                        help="with --looks: the frames in which the markers move most instead of the first ones")
    parser.add_argument("--shapes", choices=SHAPES, default="boxes",
                        help="with --looks or --diggers: the links drawn as the tracker's boxes or as other solids")
    parser.add_argument("--diggers", type=int, default=0,
                        help="track this many random diggers (machines nobody designed) instead")
    args = parser.parse_args()
    if args.diggers:
        if args.size == "1920x1080":
            args.size = "960x540"
        return track_diggers(args)
    if args.looks:
        if args.size == "1920x1080":
            args.size = "960x540"
        return track_looks(args)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.session) if args.session else Path(tmp) / "session"
        if not args.session:
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "mocap.cli", "synth", "--machine", args.machine, "--cameras",
                            str(args.cameras), "--cycles", str(args.cycles), "--seed", str(args.seed), "--size",
                            args.size, "--out", str(root)], check=True)
            print(f"rendered {root.name} in {time.perf_counter() - t0:.0f} s")
        machine = load_machine(args.machine)
        truth_cal = load_calibration(root / "truth" / "cameras.toml")
        truth = load_tracks(root / "truth" / "tracks.csv")
        header = (f"{'camera':>7} {'frames':>6} {'decode s':>8} {'grey s':>6} {'track s':>8} {'ratio':>6} {'/ grey':>6} "
                  f"{'dec cpu':>7} {'cpu s':>6} {'cpu ratio':>9} {'labelled':>8} {'wrong':>7} {'median px':>9} {'p95 px':>7}")
        print(header)
        print("-" * len(header))
        curves, all_errors = [], []
        for k, camera in enumerate(truth_cal.cameras):
            video_path = root / "videos" / f"{camera.name}.mp4"
            video = Video(video_path)
            model = CameraModel(machine, camera)
            floors, floor_cpus, greys, tooks, cpus = [], [], [], [], []
            for _ in range(args.repeat):  # interleaved, the least of each: the machine is shared
                floor, floor_cpu, count = decode_floor(video_path)
                floor_cpus.append(floor_cpu)
                greys.append(grey_floor(video))
                t0, cpu0 = time.perf_counter(), time.process_time()
                tracks, _ = track_frames(model, video.frames(prefetch=4), truth_cal.joints(machine), None,
                                         video.info.fps)
                floors.append(floor)
                tooks.append(time.perf_counter() - t0)
                cpus.append(time.process_time() - cpu0)
            floor, floor_cpu, grey, took, cpu = min(floors), min(floor_cpus), min(greys), min(tooks), min(cpus)
            labelled, wrong, errors, _ = score(truth.of_camera(camera.name), tracks)
            all_errors.append(errors)
            print(f"{camera.name:>7} {count:>6} {floor:>8.2f} {grey:>6.2f} {took:>8.2f} {took / floor:>6.2f} "
                  f"{took / grey:>6.2f} {floor_cpu:>7.2f} {cpu:>6.2f} {cpu / floor_cpu:>9.2f} {labelled:>8.2%} "
                  f"{wrong:>7.3%} {np.median(errors):>9.3f} {np.percentile(errors, 95):>7.3f}")
            frames = np.arange(tracks.frame.max() + 1)
            pixels = tracks.dense([camera.name], machine.marker_names, frames)[0]
            curves.append(joint_curves(machine, camera, frames, pixels, truth_cal.joints(machine)))
        if args.processes:
            load = os.getloadavg()[0]
            print(f"\nwhole processes, `mocap track` against OpenCV reading the same video, {args.repeat} runs each "
                  f"in turn (least seconds; ratios the medians of the pairs'); load average {load:.1f} on "
                  f"{os.cpu_count()} cores before")
            print(f"{'camera':>7} {'decode wall':>11} {'track wall':>10} {'wall ratio':>10} {'decode cpu':>10} "
                  f"{'track cpu':>9} {'cpu ratio':>9}")
            for camera in truth_cal.cameras:
                r = whole_processes(root, args.machine, camera.name, args.repeat, Path(tmp) / f"{camera.name}.csv")
                print(f"{camera.name:>7} {r['decode wall']:>11.2f} {r['track wall']:>10.2f} {r['wall ratio']:>10.2f} "
                      f"{r['decode cpu']:>10.2f} {r['track cpu']:>9.2f} {r['cpu ratio']:>9.2f}")
            print(f"load average {os.getloadavg()[0]:.1f} after (the wall ratios hold on a quiet machine only)\n")
        errors = np.concatenate(all_errors)
        print(f"all cameras: centre error median {np.median(errors):.3f} px, 95th percentile {np.percentile(errors, 95):.3f} px")
        fps = truth_cal.fps()
        result = synchronise(curves, fps)
        true_offsets = truth_cal.time_offsets
        print(f"{'camera':>7} {'fps':>6} {'true offset s':>13} {'found s':>9} {'error frames':>12}")
        for k, camera in enumerate(truth_cal.cameras):
            err = (result.offsets[k] - true_offsets[k]) * fps[0]
            print(f"{camera.name:>7} {fps[k]:>6.2f} {true_offsets[k]:>13.4f} {result.offsets[k]:>9.4f} {err:>12.3f}"
                  + (f"  ({result.reasons[k]})" if result.reasons[k] else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
