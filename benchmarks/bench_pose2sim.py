"""Pose2Sim's demo, data the project did not make (`tests/data/pose2sim`, from the PyPI wheel
pose2sim 0.4.15): four Qualisys-calibrated cameras, a person's OpenPose keypoints over 100
frames, and Pose2Sim's own 3-D of them (the peer, its TRC).

mocap triangulates the keypoints with Pose2Sim's calibration (anipose TOML), keypoints below
0.3 confidence dropped (the demo's own likelihood threshold). The table compares, on the
same keypoints: each camera's reprojection error of mocap's points and of Pose2Sim's (both
projected by the same cameras), and the 3-D distance between the two, raw and after
Pose2Sim's own gap filling and filter (4th-order Butterworth, 6 Hz) applied to mocap's.

    .venv/bin/python benchmarks/bench_pose2sim.py
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from scipy.signal import butter, filtfilt

import mocap
from mocap.io.trc import load_trc
from mocap.reconstruct.outliers import noise_from_fits

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
    try:
        mocap.triangulate(cams, kept)
        print("mocap triangulate with its defaults: ran")
    except mocap.InputError as error:
        print(f"mocap triangulate with its defaults: refused ({str(error).split(':')[0]})")

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


if __name__ == "__main__":
    main()
