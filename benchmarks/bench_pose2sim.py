"""Pose2Sim's demo, data the project did not make (`tests/data/pose2sim`, from the PyPI wheel
pose2sim 0.4.15): four Qualisys-calibrated cameras, a person's OpenPose keypoints over 100
frames, and Pose2Sim's own 3-D of them (the peer, its TRC).

mocap triangulates the keypoints with Pose2Sim's calibration (anipose TOML), keypoints below
0.3 confidence dropped (the demo's own likelihood threshold). The table compares, on the
same keypoints: each camera's reprojection error of mocap's points and of Pose2Sim's (both
projected by the same cameras), and the 3-D distance between the two, raw and after
Pose2Sim's own gap filling and filter (4th-order Butterworth, 6 Hz) applied to mocap's.

Then the demo's intrinsic images (a 4x7 chessboard of 60 mm squares shown to each camera
alone): mocap's lens (one image, then refine over the six with the board's pose per image,
lens and principal point freed) and Pose2Sim's (OpenCV's calibrateCamera, the peer) against
the Qualisys calibration's, on the same corners.

    .venv/bin/python benchmarks/bench_pose2sim.py
"""

from __future__ import annotations

import time
import xml.etree.ElementTree as ET
from pathlib import Path

import cv2
import numpy as np
from scipy.signal import butter, filtfilt

import mocap
from mocap.io.trc import load_trc
from mocap.reconstruct.outliers import noise_from_fits
from mocap.reconstruct.refine import RefineOptions

DATA = Path(__file__).parent.parent / "tests" / "data" / "pose2sim"
MIN_SCORE, FPS, CUTOFF_HZ, ORDER = 0.3, 60.0, 6.0, 4  # the demo's Config.toml


def filled_and_filtered(xyz: np.ndarray) -> np.ndarray:
    """(F, M, 3) with each marker's gaps filled linearly, then Pose2Sim's Butterworth filter."""
    frames = np.arange(len(xyz))
    filled = np.empty_like(xyz)
    for m in range(xyz.shape[1]):
        seen = np.isfinite(xyz[:, m, 0])
        filled[:, m] = np.stack([np.interp(frames, frames[seen], xyz[seen, m, k]) for k in range(3)], axis=1)
    b, a = butter(ORDER, CUTOFF_HZ / (FPS / 2))
    return filtfilt(b, a, filled, axis=0)


def main() -> None:
    cams = mocap.read_calibration(DATA / "Calib_qualisys.toml")
    tracks = mocap.read_tracks(DATA / "keypoints.csv")
    kept = tracks.select(tracks.score >= MIN_SCORE)
    table = load_trc(DATA / "Demo_0-100.trc")
    names, peer = list(table.names), table.xyz[..., [2, 0, 1]]  # the TRC is y-up: (x, y, z) written as (y, z, x)
    pixels = kept.dense(list(cams.names), names, np.arange(len(peer)))  # (C, F, M, 2)

    print(f"Pose2Sim's demo: {len(cams.names)} cameras, {len(peer)} frames, {len(names)} keypoints; "
          f"{len(tracks)} keypoints found, {len(kept)} of confidence >= {MIN_SCORE}")
    for label, given in (("every keypoint", tracks), (f"confidence >= {MIN_SCORE}", kept)):
        try:
            report = mocap.triangulate(cams, given).report
            print(f"mocap triangulate with its defaults, {label}: written; {report[report.find('the views disagree'):]}")
        except mocap.InputError as error:
            print(f"mocap triangulate with its defaults, {label}: refused: {str(error).split(' (most:')[0]}")

    start = time.process_time()
    result = mocap.triangulate(cams, kept, max_noise_px=30.0)
    cpu = time.process_time() - start
    points = result.points
    marker = np.array([names.index(m) for m in points.marker])
    ours = np.full_like(peer, np.nan)
    ours[points.frame, marker] = points.xyz
    noise = noise_from_fits(points.error_px**2 * points.views, 2 * points.views - 3)
    steps = np.diff(pixels, 2, axis=1)
    steps = steps[np.isfinite(steps)]
    jitter = 1.4826 * np.median(np.abs(steps - np.median(steps))) / np.sqrt(6.0)
    print(f"mocap triangulate --max-noise-px 30: {result.report} ({cpu:.2f} s CPU)")
    print(f"keypoint noise: views disagree by {noise:.1f} px (residuals), frame-to-frame jitter {jitter:.1f} px")

    both = np.isfinite(ours[..., 0]) & np.isfinite(peer[..., 0])
    print(f"\n1. Reprojection error on the keypoints of confidence >= {MIN_SCORE}, px, "
          f"over the {both.sum()} marker-frames both triangulated (Pose2Sim's: its filtered TRC)")
    print(f"{'camera':>7} {'keypoints':>9} {'mocap median':>12} {'Pose2Sim median':>15} {'ratio':>6} "
          f"{'mocap RMS':>9} {'Pose2Sim RMS':>12} {'ratio':>6}")
    for c, camera in enumerate(cams.cameras):
        seen = both & np.isfinite(pixels[c, ..., 0])
        mine = np.linalg.norm(camera.project(ours[seen]) - pixels[c][seen], axis=1)
        theirs = np.linalg.norm(camera.project(peer[seen]) - pixels[c][seen], axis=1)
        med, peer_med = np.median(mine), np.median(theirs)
        rms, peer_rms = np.sqrt(np.mean(mine**2)), np.sqrt(np.mean(theirs**2))
        print(f"{camera.name:>7} {seen.sum():>9} {med:>12.1f} {peer_med:>15.1f} {med / peer_med:>6.2f} "
              f"{rms:>9.1f} {peer_rms:>12.1f} {rms / peer_rms:>6.2f}")

    print(f"\n2. 3-D distance from Pose2Sim's points, mm ({both.sum()} of {np.isfinite(peer[..., 0]).sum()} "
          "marker-frames triangulated by mocap)")
    print(f"{'mocap':>28} {'median':>7} {'p95':>7} {'max':>7}")
    for label, xyz in (("raw", ours), ("gaps filled, Butterworth 6 Hz", filled_and_filtered(ours))):
        distance = np.linalg.norm(xyz - peer, axis=2)[np.isfinite(xyz[..., 0])] * 1e3
        print(f"{label:>28} {np.median(distance):>7.1f} {np.percentile(distance, 95):>7.1f} {distance.max():>7.1f}")

    board_table(cams)


def qualisys_lenses() -> list[tuple[float, float, float, float, float]]:
    """Per camera: focal (px), principal point (px), k1, k2 as Qualisys wrote them (its
    pixel values in 1/64 px; its radial coefficients unscaled, unlike Pose2Sim 0.4's TOML)."""
    out = []
    for element in ET.parse(DATA / "Calib.qca.txt").getroot().iter("camera"):
        i = {k: float(v) for k, v in element.find("intrinsic").attrib.items()}
        out.append((i["focalLengthU"] / 64, i["centerPointU"] / 64, i["centerPointV"] / 64,
                    i["radialDistortion1"], i["radialDistortion2"]))
    return out


def board_table(cams) -> None:
    board = mocap.load_machine(DATA / "board.toml")
    corners = mocap.read_tracks(DATA / "board_corners.csv")
    objp = board.marker_positions.astype(np.float32)
    print("\n3. Lenses from the demo's chessboard images (6 per camera), against the Qualisys calibration: "
          "focal length px, principal point px, k1, k2")
    print(f"{'camera':>7} {'source':>22} {'focal':>8} {'|df|':>6} {'cx':>6} {'cy':>6} {'k1':>7} {'k2':>7} {'CPU s':>6}")
    for name, (f_q, cx_q, cy_q, k1_q, k2_q) in zip(cams.names, qualisys_lenses(), strict=True):
        seen = corners.of_camera(name)
        start = time.process_time()
        one = mocap.calibrate(board, seen, size=(1088, 1920))
        refined = mocap.refine(board, one, seen, options=RefineOptions(distortion="auto", fit_principal_point=True,
                                                                       base_motion=True))
        ours_s = time.process_time() - start
        lens = refined.cameras.cameras[0]
        sd = refined.cameras.extras[0]["sd"]["focal_px"]
        images = [seen.of_frame(f) for f in seen.frames]
        pixels = [i.xy[[board.marker_names.index(m) for m in i.marker]].astype(np.float32) for i in images]
        start = time.process_time()
        _, matrix, distortion, _, _ = cv2.calibrateCamera([objp] * len(pixels), pixels, (1088, 1920), None, None)
        peer_s = time.process_time() - start
        rows = (("Qualisys", f_q, cx_q, cy_q, k1_q, k2_q, None),
                (f"mocap (SD {sd:.1f} px)", lens.matrix[0, 0], *lens.matrix[:2, 2], *lens.distortion[:2], ours_s),
                ("Pose2Sim (OpenCV)", matrix[0, 0], *matrix[:2, 2], *distortion.ravel()[:2], peer_s))
        for source, f, cx, cy, k1, k2, cpu in rows:
            print(f"{name:>7} {source:>22} {f:>8.1f} {abs(f - f_q):>6.1f} {cx:>6.1f} {cy:>6.1f} {k1:>7.3f} {k2:>7.3f} "
                  + (f"{cpu:>6.2f}" if cpu is not None else f"{'':>6}"))


if __name__ == "__main__":
    main()
