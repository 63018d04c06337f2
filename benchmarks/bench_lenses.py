"""Self-calibration on real lenses: a chessboard moved through the view of webcams with
strong barrel distortion (k1 = -0.35), calibrated from one frame by `calibrate` and
refined over the session by `refine` (lens model chosen by the data, principal point
freed, the board's pose followed every frame), against OpenCV's `calibrateCamera` per
camera plus `stereoCalibrate` over all the same frames (the peer), in the same run. Then
the same on OpenCV's real sample stereo pairs (Debian package opencv-doc), skipped with a
message when they are absent.

The measure is gauge-free: every corner of every frame triangulated (linear, then
Gauss-Newton, no view dropped) through each calibration, and the RMS error of the
distance between adjacent corners against the board's square.

    python benchmarks/bench_lenses.py [--scenes 5] [--frames 60]
    python benchmarks/bench_lenses.py --save-corners tests/data/opencv_stereo   # the tests' real corners

`--save-corners DIR` writes the sample pairs' detected corners (`corners.csv`, tracks
format: cameras `left` and `right`, frame = pair, marker = corner C00-C53) and the board's
model (`board.toml`, unit squares) instead: the real-lens data the tests run on.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # the solvers' small products: threads only contend

import argparse  # noqa: E402
import glob  # noqa: E402
import logging  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from mocap.calibration import CalibrationOptions, Observations, calibrate  # noqa: E402
from mocap.calibration.solve import template_camera  # noqa: E402
from mocap.core.camera import Camera  # noqa: E402
from mocap.core.geometry import Rigid, rotvec_to_matrix  # noqa: E402
from mocap.core.tracks import Tracks  # noqa: E402
from mocap.io.machine_toml import save_machine  # noqa: E402
from mocap.io.tracks_csv import save_tracks  # noqa: E402
from mocap.reconstruct.refine import RefineOptions, refine  # noqa: E402
from mocap.reconstruct.triangulate import TriangulateOptions, triangulate  # noqa: E402
from mocap.synthetic.lens_scene import board_scene, chessboard  # noqa: E402

SAMPLES = Path("/usr/share/doc/opencv-doc/examples/data")
BOARD = (9, 6)


def adjacent_rmse(cameras, pixels, square: float) -> float:
    """RMS error of adjacent corners' distance (along rows and columns) against `square`."""
    xyz = triangulate(list(cameras), pixels, TriangulateOptions(max_error_px=1e6)).xyz
    grid = xyz.reshape(xyz.shape[0], BOARD[1], BOARD[0], 3)
    steps = np.r_[np.linalg.norm(np.diff(grid, axis=2), axis=-1).ravel(), np.linalg.norm(np.diff(grid, axis=1), axis=-1).ravel()]
    return float(np.sqrt(np.nanmean((steps - square) ** 2)))


def ours(board, pixels, size, names):
    """calibrate from the best-seen frame, then refine over all frames."""
    k = int(np.argmax(np.isfinite(pixels[..., 0]).sum((0, 2))))
    c, m = np.nonzero(np.isfinite(pixels[:, k, :, 0]))
    templates = [template_camera(name, size) for name in names]
    one = calibrate(board, Observations(c, m, pixels[c, k, m]), templates, CalibrationOptions()).cameras
    order = np.r_[k, np.delete(np.arange(pixels.shape[1]), k)]  # the world stays the board in that frame
    result = refine(board, list(one), pixels[:, order], RefineOptions(
        frames=pixels.shape[1], distortion="auto", fit_principal_point=True, base_motion=True, max_median_px=2.0))
    return one, result


def opencv_peer(board, pixels, size, names):
    """calibrateCamera per camera (OpenCV's default five coefficients) over every frame it
    sees whole, then stereoCalibrate of each camera with the first over the frames both see
    whole, intrinsics fixed; the world is the first camera."""
    objp = board.marker_positions.astype(np.float32)
    whole = np.isfinite(pixels[..., 0]).all(-1)  # (C, K)
    intrinsics = []
    for c in range(len(names)):
        views = [pixels[c, k].astype(np.float32) for k in np.nonzero(whole[c])[0]]
        _, matrix, dist, _, _ = cv2.calibrateCamera([objp] * len(views), views, size, None, None)
        intrinsics.append((matrix, dist.ravel()[:5]))
    cameras = [Camera(names[0], size, intrinsics[0][0], intrinsics[0][1], Rigid(np.eye(3), np.zeros(3)))]
    for c in range(1, len(names)):
        both = np.nonzero(whole[0] & whole[c])[0]
        out = cv2.stereoCalibrate([objp] * len(both), [pixels[0, k].astype(np.float32) for k in both],
                                  [pixels[c, k].astype(np.float32) for k in both], intrinsics[0][0], intrinsics[0][1],
                                  intrinsics[c][0], intrinsics[c][1], size, flags=cv2.CALIB_FIX_INTRINSIC)
        rotation, translation = out[5], out[6]
        cameras.append(Camera(names[c], size, intrinsics[c][0], intrinsics[c][1], Rigid(rotation, translation.ravel())))
    return cameras


def synthetic(n_scenes: int, n_frames: int) -> list[float]:
    print(f"\n1. Synthetic: 9x6 chessboard (40 mm) moved by hand through 4 webcams 1280x720, k1 = -0.35, "
          f"0.3 px noise, {n_frames} frames")
    print(f"{'seed':>4} {'one frame mm':>12} {'ours mm':>8} {'model':>6} {'k1 err':>7} {'OpenCV mm':>9} "
          f"{'ours/OpenCV':>11} {'ours s':>7} {'OpenCV s':>8}")
    ratios = []
    for seed in range(n_scenes):
        scene = board_scene(np.random.default_rng(100 + seed), n_frames=n_frames)
        names = [c.name for c in scene.cameras]
        size = scene.cameras[0].size
        t0 = time.perf_counter()
        one, result = ours(scene.board, scene.pixels, size, names)
        t1 = time.perf_counter()
        peer = opencv_peer(scene.board, scene.pixels, size, names)
        t2 = time.perf_counter()
        e_one, e_ours, e_peer = (1000 * adjacent_rmse(c, scene.pixels, 0.04) for c in (one, result.cameras, peer))
        k1 = max(abs(a.distortion[0] - b.distortion[0]) for a, b in zip(result.cameras, scene.cameras))
        ratios.append(e_ours / e_peer)
        print(f"{seed:>4} {e_one:>12.3f} {e_ours:>8.3f} {result.distortion:>6} {k1:>7.3f} {e_peer:>9.3f} "
              f"{e_ours / e_peer:>11.2f} {t1 - t0:>7.1f} {t2 - t1:>8.2f}")
    print(f"median ours / OpenCV: {np.median(ratios):.2f}, worst {max(ratios):.2f}")
    return ratios


def sample_pairs():
    """(2, K, 54, 2) corners of the sample stereo pairs both of whose images show the whole board."""
    lefts = sorted(glob.glob(str(SAMPLES / "left[0-9][0-9].jpg")))
    pixels, size = [], None
    for left in lefts:
        pair = []
        for path in (left, left.replace("left", "right")):
            image = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
            if image is None:
                break
            size = (image.shape[1], image.shape[0])
            found, corners = cv2.findChessboardCorners(image, BOARD, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
            if not found:
                break
            corners = cv2.cornerSubPix(image, corners, (11, 11), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3))
            pair.append(corners.reshape(-1, 2).astype(float))
        if len(pair) == 2:
            pixels.append(pair)
    return np.transpose(np.array(pixels), (1, 0, 2, 3)), size


def real() -> float | None:
    if not (SAMPLES / "left01.jpg").exists():
        print(f"\n2. OpenCV's sample stereo pairs: skipped, {SAMPLES}/left01.jpg not found (apt-get install opencv-doc)")
        return None
    pixels, size = sample_pairs()
    board = chessboard(*BOARD, square=1.0)
    names = ["left", "right"]
    one, result = ours(board, pixels, size, names)
    peer = opencv_peer(board, pixels, size, names)
    e_one, e_ours, e_peer = (adjacent_rmse(c, pixels, 1.0) for c in (one, result.cameras, peer))
    print(f"\n2. OpenCV's sample stereo pairs ({pixels.shape[1]} pairs, 9x6 board, unit squares, {size[0]}x{size[1]})")
    print(f"{'':>20} {'adjacent RMSE (squares)':>24} {'k1 left / right':>16}")
    print(f"{'calibrate, 1 frame':>20} {e_one:>24.4f} {'':>16}")
    print(f"{'+ refine (' + result.distortion + ')':>20} {e_ours:>24.4f} "
          f"{result.cameras[0].distortion[0]:>7.3f} / {result.cameras[1].distortion[0]:.3f}")
    print(f"{'OpenCV':>20} {e_peer:>24.4f} {peer[0].distortion[0]:>7.3f} / {peer[1].distortion[0]:.3f}")
    print(f"ours / OpenCV: {e_ours / e_peer:.2f}; refine residual {result.rms_after:.3f} px, BIC "
          + ", ".join(f"{k} {v:.0f}" for k, v in result.criterion.items()))
    return e_ours / e_peer


def save_corners(folder: Path) -> None:
    """The sample pairs' corners as tracks and the board as a machine model, in `folder`."""
    if not (SAMPLES / "left01.jpg").exists():
        raise SystemExit(f"{SAMPLES}/left01.jpg not found (apt-get install opencv-doc)")
    pixels, size = sample_pairs()
    board = chessboard(*BOARD, square=1.0)
    c, k, m = np.nonzero(np.isfinite(pixels[..., 0]))
    folder.mkdir(parents=True, exist_ok=True)
    save_tracks(Tracks.from_rows(np.array(["left", "right"])[c], k, np.array(board.marker_names)[m],
                                 np.round(pixels[c, k, m], 4)), folder / "corners.csv")
    save_machine(board, folder / "board.toml")
    print(f"{folder}: {pixels.shape[1]} pairs of {size[0]}x{size[1]} images, {len(c)} corners")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", type=int, default=5)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--save-corners", type=Path, metavar="DIR",
                        help="write the sample pairs' corners and the board's model to DIR, and stop")
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    if args.save_corners:
        save_corners(args.save_corners)
        return
    synthetic(args.scenes, args.frames)
    real()


if __name__ == "__main__":
    main()
