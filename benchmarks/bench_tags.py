"""Tag detection on webcam-like video, beside OpenCV's own ArucoDetector on the same frames.

Boards of DICT_4X4_50 tags (cv2.aruco.generateImageMarker) seen through a lens with
k1 = -0.35, drifting across the view, rendered per condition (tag size, inverted print,
motion blur, rolling shutter, defocus), H.264-encoded and decoded as `mocap track` reads
them (luma). Per condition: the share of the wholly visible tags found (frames x tags) by
`mocap.tracking.detect.TagFinder` (one per video, as `mocap track` runs it) and by two peers:
`cv2.aruco.ArucoDetector` with its default settings ("OpenCV", as a new user runs it) and
with its corners refined on the tag's contour ("OpenCV contour": `cornerRefinementMethod =
CORNER_REFINE_CONTOUR`, OpenCV's most accurate refinement here), both given the picture
black on white (an inverted print's frames inverted for them; `detectInvertedMarker`
places corners differently, by 0.2 px at the centre); the tags either peer finds that
ours misses; the median distance between our centre and each peer's
where both find a tag; each one's centre error against the truth (median and 95th
percentile); and the time per frame of ours and of the default peer. A centre is the
crossing of the tag's diagonals (`mocap.tracking.detect.diagonal_intersection`) for all three.

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

from mocap.io.video import Video
from mocap.synthetic.encode import video_writer
from mocap.synthetic.tag_board import BoardLook, render_board
from mocap.tracking.detect import TagFinder, diagonal_intersection, tag_dictionary

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
    if ids is None or not len(ids):  # OpenCV 5 gives an empty array, 4 gave None
        return {}
    return dict(zip(ids.reshape(-1).tolist(), diagonal_intersection(np.concatenate(corners).reshape(-1, 4, 2))))


def contour_peer(dictionary: str):
    """OpenCV's ArucoDetector with corners refined on the tag's contour."""
    parameters = cv2.aruco.DetectorParameters()
    parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_CONTOUR
    return cv2.aruco.ArucoDetector(tag_dictionary(dictionary), parameters)


def run_condition(look: BoardLook, n_frames: int, rng: np.random.Generator, tmp: Path) -> dict:
    board = render_board(look, n_frames, rng)
    h, w = board.frames.shape[1:]
    path = tmp / "board.mp4"
    with video_writer(path, (w, h), 30.0) as write:
        for gray in board.frames:
            write(cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR))
    frames = [gray for _, gray in Video(path).frames()]
    peers = {"opencv": cv2.aruco.ArucoDetector(tag_dictionary(look.dictionary), cv2.aruco.DetectorParameters()),
             "contour": contour_peer(look.dictionary)}
    finder = TagFinder(look.dictionary)  # one per video, as `mocap track` uses it
    ids = board.ids.tolist()
    found = {"ours": 0, "opencv": 0, "contour": 0}
    errors = {"ours": [], "opencv": [], "contour": []}
    times = {"ours": 0.0, "opencv": 0.0}
    differences = {"opencv": [], "contour": []}
    peer_only, wrong = 0, 0
    for f, gray in enumerate(frames):
        t0 = time.perf_counter()
        tags = finder(gray)
        t1 = time.perf_counter()
        black_on_white = 255 - gray if look.inverted else gray
        results = {"ours": dict(zip(tags.ids.tolist(), tags.xy)), "opencv": opencv_tags(black_on_white, peers["opencv"])}
        t2 = time.perf_counter()
        results["contour"] = opencv_tags(black_on_white, peers["contour"])
        times["ours"] += t1 - t0
        times["opencv"] += t2 - t1
        ours = results["ours"]
        for name, result in results.items():
            for tag_id, xy in result.items():
                if tag_id not in ids:
                    wrong += name == "ours"
                    continue
                truth = board.xy[f, ids.index(tag_id)]
                if np.isfinite(truth[0]):
                    found[name] += 1
                    errors[name].append(np.linalg.norm(xy - truth))
        peer_only += len((set(results["opencv"]) | set(results["contour"])) - set(ours))
        for name in differences:
            differences[name] += [np.linalg.norm(ours[t] - results[name][t]) for t in set(ours) & set(results[name])]
    visible = int(np.isfinite(board.xy[..., 0]).sum())
    return dict(visible=visible, found=found, errors=errors, times=times, n=len(frames),
                differences={k: np.array(v) for k, v in differences.items()}, peer_only=peer_only, wrong=wrong)


def _stat(values, q) -> str:
    return f"{np.percentile(values, q):.3f}" if len(values) else "-"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=10, help="frames per condition")
    parser.add_argument("--size", default="1280x720")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.lower().split("x"))
    header = (f"{'condition':<26} {'tags':>5} {'ours':>7} {'OpenCV':>7} {'contour':>7} {'ratio':>6} {'missed':>6} "
              f"{'wrong':>5} {'diff/OCV':>8} {'diff/cnt':>8} {'err ours':>11} {'err OpenCV':>11} {'err contour':>11} "
              f"{'ms ours':>7} {'ms OCV':>6}")
    print(header)
    print("-" * len(header))
    totals = {"visible": 0, "ours": 0, "opencv": 0, "contour": 0, "peer_only": 0, "wrong": 0}
    all_diff = {"opencv": [], "contour": []}
    all_err = {"ours": [], "opencv": [], "contour": []}

    def row(name, visible, found, peer_only, wrong, diff, err, times=None) -> str:
        best_peer = max(found["opencv"], found["contour"], 1)
        line = (f"{name:<26} {visible:>5} {found['ours'] / visible:>7.1%} {found['opencv'] / visible:>7.1%} "
                f"{found['contour'] / visible:>7.1%} {found['ours'] / best_peer:>6.2f} {peer_only:>6} {wrong:>5} "
                f"{_stat(diff['opencv'], 50):>8} {_stat(diff['contour'], 50):>8} "
                + " ".join(f"{_stat(err[k], 50) + '/' + _stat(err[k], 95):>11}" for k in ("ours", "opencv", "contour")))
        if times is not None:
            line += f" {times[0]:>7.1f} {times[1]:>6.1f}"
        return line

    with tempfile.TemporaryDirectory() as tmp:
        for k, (name, settings) in enumerate(CONDITIONS.items()):
            look = BoardLook(size=size, **settings)
            r = run_condition(look, args.frames, np.random.default_rng(args.seed + k), Path(tmp))
            ms = (1000 * r["times"]["ours"] / r["n"], 1000 * r["times"]["opencv"] / r["n"])
            print(row(name, r["visible"], r["found"], r["peer_only"], r["wrong"], r["differences"], r["errors"], ms))
            totals["visible"] += r["visible"]
            totals["peer_only"] += r["peer_only"]
            totals["wrong"] += r["wrong"]
            for key in all_err:
                totals[key] += r["found"][key]
                all_err[key] += r["errors"][key]
            for key in all_diff:
                all_diff[key].append(r["differences"][key])
    print("-" * len(header))
    print(row("all", totals["visible"], totals, totals["peer_only"], totals["wrong"],
              {k: np.concatenate(v) for k, v in all_diff.items()}, all_err))
    print("tags: frames x tags wholly in view; OpenCV: ArucoDetector, default settings; contour: ArucoDetector with "
          "CORNER_REFINE_CONTOUR; both on the frames inverted for an inverted print; ratio: ours / the better peer; missed: tags a peer finds "
          "and ours does not; wrong: ids not on the board; diff: median px between our centre and the peer's where "
          "both find a tag; err: px from the true centre, median/p95")
    return 0


if __name__ == "__main__":
    sys.exit(main())
