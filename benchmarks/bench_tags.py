"""Tag detection on webcam-like video, beside OpenCV's own ArucoDetector on the same frames.

Boards of DICT_4X4_50 tags (cv2.aruco.generateImageMarker) seen through a lens with
k1 = -0.35, drifting across the view, rendered per condition (tag size, inverted print,
motion blur, rolling shutter, defocus), H.264-encoded and decoded as `mocap track` reads
them (luma). Per condition: the share of the wholly visible tags found (frames x tags) by
`mocap.detect.TagFinder` (one per video, as `mocap track` runs it) and by
`cv2.aruco.ArucoDetector` with its default settings (the peer), the tags the peer finds that
ours misses, the median distance between the two centres where both find a tag, each one's
centre error against the truth (median and 95th percentile), and the time per frame of each.

    python benchmarks/bench_tags.py [--frames 10] [--size 1280x720] [--seed 1]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from mocap.detect import TagFinder, diagonal_intersection, tag_dictionary
from mocap.io.video import Video
from mocap.synthetic.encode import video_writer
from mocap.synthetic.tag_board import BoardLook, render_board

CONDITIONS = {
    "12 px": dict(tag_px=12),
    "16 px": dict(tag_px=16),
    "24 px": dict(tag_px=24),
    "40 px": dict(tag_px=40),
    "12 px inverted": dict(tag_px=12, inverted=True),
    "24 px inverted": dict(tag_px=24, inverted=True),
    "16 px blur 3 px": dict(tag_px=16, speed=6.0, shutter=0.5),
    "24 px blur 3 px": dict(tag_px=24, speed=6.0, shutter=0.5),
    "24 px blur 6 px": dict(tag_px=24, speed=12.0, shutter=0.5),
    "24 px rolling shutter": dict(tag_px=24, speed=12.0, rolling_shutter=0.9),
    "16 px inv. blur + rolling": dict(tag_px=16, inverted=True, speed=6.0, shutter=0.5, rolling_shutter=0.9),
    "24 px defocus 1.2 px": dict(tag_px=24, defocus=1.2),
}


def opencv_tags(gray: np.ndarray, detector) -> dict[int, np.ndarray]:
    corners, ids, _ = detector.detectMarkers(gray)
    if ids is None:
        return {}
    return dict(zip(ids.reshape(-1).tolist(), diagonal_intersection(np.concatenate(corners).reshape(-1, 4, 2))))


def run_condition(look: BoardLook, n_frames: int, rng: np.random.Generator, tmp: Path) -> dict:
    board = render_board(look, n_frames, rng)
    h, w = board.frames.shape[1:]
    path = tmp / "board.mp4"
    with video_writer(path, (w, h), 30.0) as write:
        for gray in board.frames:
            write(cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR))
    frames = [gray for _, gray in Video(path).frames()]
    peer = cv2.aruco.ArucoDetector(tag_dictionary(look.dictionary), cv2.aruco.DetectorParameters())
    finder = TagFinder(look.dictionary)  # one per video, as `mocap track` uses it
    ids = board.ids.tolist()
    found = {"ours": 0, "opencv": 0}
    errors = {"ours": [], "opencv": []}
    times = {"ours": 0.0, "opencv": 0.0}
    differences, peer_only, wrong = [], 0, 0
    for f, gray in enumerate(frames):
        t0 = time.perf_counter()
        tags = finder(gray)
        t1 = time.perf_counter()
        theirs = opencv_tags(gray, peer)
        t2 = time.perf_counter()
        times["ours"] += t1 - t0
        times["opencv"] += t2 - t1
        ours = dict(zip(tags.ids.tolist(), tags.xy))
        for name, result in (("ours", ours), ("opencv", theirs)):
            for tag_id, xy in result.items():
                if tag_id not in ids:
                    wrong += name == "ours"
                    continue
                truth = board.xy[f, ids.index(tag_id)]
                if np.isfinite(truth[0]):
                    found[name] += 1
                    errors[name].append(np.linalg.norm(xy - truth))
        peer_only += len(set(theirs) - set(ours))
        differences += [np.linalg.norm(ours[t] - theirs[t]) for t in set(ours) & set(theirs)]
    visible = int(np.isfinite(board.xy[..., 0]).sum())
    return dict(visible=visible, found=found, errors=errors, times=times, n=len(frames),
                differences=np.array(differences), peer_only=peer_only, wrong=wrong)


def _stat(values, q) -> str:
    return f"{np.percentile(values, q):.3f}" if len(values) else "-"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=10, help="frames per condition")
    parser.add_argument("--size", default="1280x720")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.lower().split("x"))
    header = (f"{'condition':<26} {'tags':>5} {'ours':>7} {'OpenCV':>7} {'ratio':>6} {'missed':>6} {'wrong':>5} "
              f"{'diff med':>8} {'err ours med/p95':>16} {'err OpenCV med/p95':>18} {'ms ours':>7} {'ms OpenCV':>9}")
    print(header)
    print("-" * len(header))
    totals = {"visible": 0, "ours": 0, "opencv": 0, "peer_only": 0, "wrong": 0}
    all_diff, all_err = [], {"ours": [], "opencv": []}
    with tempfile.TemporaryDirectory() as tmp:
        for k, (name, settings) in enumerate(CONDITIONS.items()):
            look = BoardLook(size=size, **settings)
            r = run_condition(look, args.frames, np.random.default_rng(args.seed + k), Path(tmp))
            ours, theirs = r["found"]["ours"], r["found"]["opencv"]
            print(f"{name:<26} {r['visible']:>5} {ours / r['visible']:>7.1%} {theirs / r['visible']:>7.1%} "
                  f"{ours / max(theirs, 1):>6.2f} {r['peer_only']:>6} {r['wrong']:>5} {_stat(r['differences'], 50):>8} "
                  f"{_stat(r['errors']['ours'], 50):>8}/{_stat(r['errors']['ours'], 95):<7} "
                  f"{_stat(r['errors']['opencv'], 50):>10}/{_stat(r['errors']['opencv'], 95):<7} "
                  f"{1000 * r['times']['ours'] / r['n']:>7.1f} {1000 * r['times']['opencv'] / r['n']:>9.1f}")
            totals["visible"] += r["visible"]
            totals["ours"] += ours
            totals["opencv"] += theirs
            totals["peer_only"] += r["peer_only"]
            totals["wrong"] += r["wrong"]
            all_diff.append(r["differences"])
            for key in all_err:
                all_err[key] += r["errors"][key]
    diff = np.concatenate(all_diff)
    print("-" * len(header))
    print(f"{'all':<26} {totals['visible']:>5} {totals['ours'] / totals['visible']:>7.1%} "
          f"{totals['opencv'] / totals['visible']:>7.1%} {totals['ours'] / max(totals['opencv'], 1):>6.2f} "
          f"{totals['peer_only']:>6} {totals['wrong']:>5} {_stat(diff, 50):>8} "
          f"{_stat(all_err['ours'], 50):>8}/{_stat(all_err['ours'], 95):<7} "
          f"{_stat(all_err['opencv'], 50):>10}/{_stat(all_err['opencv'], 95):<7}")
    print("tags: frames x tags wholly in view; missed: tags OpenCV finds and ours does not; wrong: ids not on the "
          "board; diff: px between the two centres where both find a tag; err: px from the true centre")
    return 0


if __name__ == "__main__":
    sys.exit(main())
