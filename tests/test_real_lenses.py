"""Real lenses, data the project did not make: OpenCV's sample stereo pairs (Debian's
opencv-doc, left01-right14: two webcams of 640x480 with barrel distortion, a 9x6
chessboard moved by hand), their corners found by OpenCV's own detector
(`tests/data/opencv_stereo`, written by `benchmarks/bench_lenses.py --save-corners`).
The truth is the board itself: adjacent corners lie one square apart. The peer is OpenCV
from end to end on the same corners: `calibrateCamera` per camera, `stereoCalibrate`,
`undistortPoints` and `triangulatePoints`."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from mocap import cli
from mocap.io.cameras_toml import load_calibration
from mocap.io.machine_toml import load_machine
from mocap.io.points_csv import load_points
from mocap.io.tracks_csv import load_tracks

DATA = Path(__file__).parent / "data" / "opencv_stereo"
COLUMNS, ROWS = 9, 6  # inner corners; the board's squares are its unit of length
SIZE = (640, 480)
NAMES = ["left", "right"]
BOARD = load_machine(DATA / "board.toml")  # corner C00..C53 row by row at (column, row, 0) squares


def corner_pixels() -> np.ndarray:
    """(C=2, K, M=54, 2) the detected corners, NaN where a corner was not found."""
    tracks = load_tracks(DATA / "corners.csv")
    return tracks.dense(NAMES, BOARD.marker_names, tracks.frames)


def adjacent_rmse(xyz: np.ndarray) -> float:
    """RMS error, in squares, of the distance between adjacent corners of (K, M, 3) points."""
    grid = xyz.reshape(len(xyz), ROWS, COLUMNS, 3)
    steps = np.r_[np.linalg.norm(np.diff(grid, axis=2), axis=-1).ravel(),
                  np.linalg.norm(np.diff(grid, axis=1), axis=-1).ravel()]
    return float(np.sqrt(np.nanmean((steps - 1.0) ** 2)))


def opencv_points(pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV alone: (K, M, 3) corners in the left camera's frame, and (K, M) their RMS
    reprojection error in px over both views."""
    objp = BOARD.marker_positions.astype(np.float32)
    views = [[p.astype(np.float32) for p in camera] for camera in pixels]
    lenses = [cv2.calibrateCamera([objp] * len(v), v, SIZE, None, None)[1:3] for v in views]
    (k0, d0), (k1, d1) = lenses
    out = cv2.stereoCalibrate([objp] * len(views[0]), views[0], views[1], k0, d0, k1, d1, SIZE,
                              flags=cv2.CALIB_FIX_INTRINSIC)
    right_from_left = np.c_[out[5], out[6]]
    flat = pixels.reshape(2, -1, 2)
    normalised = [cv2.undistortPoints(flat[c][:, None], k, d).reshape(-1, 2) for c, (k, d) in enumerate(lenses)]
    homogeneous = cv2.triangulatePoints(np.eye(3, 4), right_from_left, normalised[0].T, normalised[1].T)
    xyz = (homogeneous[:3] / homogeneous[3]).T
    errors = []
    for (k, d), cam_from_left, seen in zip(lenses, (np.eye(3, 4), right_from_left), flat):
        rvec = cv2.Rodrigues(cam_from_left[:, :3])[0]
        projected = cv2.projectPoints(xyz, rvec, cam_from_left[:, 3], k, d)[0].reshape(-1, 2)
        errors.append(np.sum((projected - seen) ** 2, axis=1))
    return xyz.reshape(pixels.shape[1], -1, 3), np.sqrt(np.mean(errors, axis=0)).reshape(pixels.shape[1:3])


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    """calibrate (one frame) -> refine (every frame, the board's pose per frame, lens and
    principal point freed) -> triangulate, from the command line as a user runs them."""
    out = tmp_path_factory.mktemp("real")
    board, corners = str(DATA / "board.toml"), str(DATA / "corners.csv")
    assert cli.main(["calibrate", board, corners, "--size", "640x480", "--out", str(out / "one.toml")]) == 0
    assert cli.main(["refine", board, str(out / "one.toml"), corners, "--base-motion", "--fit-principal-point",
                     "--out", str(out / "refined.toml")]) == 0
    assert cli.main(["triangulate", str(out / "refined.toml"), corners, "--out", str(out / "points.csv")]) == 0
    return out


def ours_points(chain, pixels) -> np.ndarray:
    points = load_points(chain / "points.csv")
    xyz = np.full(pixels.shape[1:3] + (3,), np.nan)
    xyz[points.frame, [BOARD.marker_names.index(m) for m in points.marker]] = points.xyz
    return xyz


def test_real_pairs_measure_the_board_as_well_as_opencv_end_to_end(chain):
    pixels = corner_pixels()
    assert pixels.shape == (2, 13, 54, 2)
    peer, _ = opencv_points(pixels)
    ours = ours_points(chain, pixels)
    seen_twice = np.isfinite(pixels[..., 0]).all(0)
    assert np.isnan(ours[seen_twice, 0]).mean() < 0.015  # few views dropped (6 of 702 here)
    assert adjacent_rmse(ours) <= 1.02 * adjacent_rmse(peer)  # 0.0130 against OpenCV's 0.0156 squares
    assert adjacent_rmse(peer) < 0.02  # the peer itself measures the board to 2 % of a square
    calibration = load_calibration(chain / "refined.toml")
    assert [c.name for c in calibration.cameras] == NAMES
    assert all(c.distortion[0] < -0.2 for c in calibration.cameras)  # the barrel the lenses have (OpenCV: -0.27)


def test_real_pairs_drop_only_views_opencv_also_finds_off(chain):
    """The views `mocap triangulate` drops on the real corners are corners OpenCV's own
    calibration cannot explain either: far above its median reprojection error."""
    pixels = corner_pixels()
    _, peer_error = opencv_points(pixels)
    dropped = np.isnan(ours_points(chain, pixels)[..., 0]) & np.isfinite(pixels[..., 0]).all(0)
    assert 0 < dropped.sum()
    assert np.min(peer_error[dropped]) > 4 * np.nanmedian(peer_error)
