"""Real data the project did not make: Pose2Sim's demo (PyPI wheel pose2sim 0.4.15, BSD-3;
`tests/data/pose2sim`, written by `benchmarks/pose2sim_extract.py`). A person filmed by four
1088x1920 cameras at 60 Hz calibrated by a Qualisys system, OpenPose's BODY_25B keypoints
per camera and frame, and Pose2Sim's own 3-D result (a TRC in metres, y up).

The truth it carries: the Qualisys calibration the TOML was converted from (camera
positions in mm, rotation matrices, intrinsics in 1/64 px), and the peer's triangulation of
the same keypoints. Keypoints whose OpenPose confidence is below 0.3 (the demo's own
`likelihood_threshold`) are dropped; the rest count alike."""

import subprocess
import sys
import tomllib
import xml.etree.ElementTree as ET
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.signal import butter, filtfilt

import mocap
from mocap.core.camera import project_cam
from mocap.io.trc import load_trc
from mocap.reconstruct.outliers import noise_from_fits

DATA = Path(__file__).parent / "data" / "pose2sim"
MIN_SCORE = 0.3  # Config.toml [triangulation] likelihood_threshold
FPS, CUTOFF_HZ, ORDER = 60.0, 6.0, 4  # Config.toml: frame_rate, [filtering.butterworth]
MAX_NOISE_PX = 30.0  # the keypoints' views disagree by ~14 px (measured below): a person is no rigid marker


def qualisys_cameras() -> list[dict]:
    """The demo's Qualisys calibration: per camera, world_from_cam-like rows `r`, position (m),
    focal lengths and principal point (px; Qualisys stores them in 1/64 px)."""
    cameras = []
    for element in ET.parse(DATA / "Calib.qca.txt").getroot().iter("camera"):
        t, i = element.find("transform").attrib, element.find("intrinsic").attrib
        cameras.append({
            "r": np.array([[float(t[f"r{a}{b}"]) for b in "123"] for a in "123"]),
            "position": np.array([float(t[k]) for k in "xyz"]) / 1000.0,
            "f": np.array([float(i["focalLengthU"]), float(i["focalLengthV"])]) / 64.0,
            "c": np.array([float(i["centerPointU"]), float(i["centerPointV"])]) / 64.0,
        })
    return cameras


def peer_points() -> tuple[tuple[str, ...], np.ndarray]:
    """Pose2Sim's 3-D (F, M, 3) in the calibration's world frame: its TRC turns z-up into
    y-up by (x, y, z) -> (y, z, x), undone here."""
    table = load_trc(DATA / "Demo_0-100.trc")
    assert table.frame[0] == 0 and table.rate == FPS
    return table.names, table.xyz[..., [2, 0, 1]]


@pytest.fixture(scope="module")
def demo():
    cams = mocap.read_calibration(DATA / "Calib_qualisys.toml")
    tracks = mocap.read_tracks(DATA / "keypoints.csv")
    tracks = tracks.select(tracks.score >= MIN_SCORE)
    names, peer = peer_points()
    points = mocap.triangulate(cams, tracks, max_noise_px=MAX_NOISE_PX).points
    marker = np.array([names.index(m) for m in points.marker])
    pixels = tracks.dense(list(cams.names), list(names), np.arange(len(peer)))  # (C, F, M, 2)
    sigma = noise_from_fits(points.error_px**2 * points.views, 2 * points.views - 3)
    return cams, names, peer, points, marker, pixels, sigma


def test_pose2sim_calibration_is_the_qualisys_one():
    cams = mocap.read_calibration(DATA / "Calib_qualisys.toml")
    file = tomllib.loads((DATA / "Calib_qualisys.toml").read_text())
    assert cams.names == ("cam_01", "cam_02", "cam_03", "cam_04")
    for camera, qualisys in zip(cams.cameras, qualisys_cameras(), strict=True):
        assert camera.size == (1088, 1920)
        cam_from_world = camera.cam_from_world
        # aniposelib's rotation/translation are world->camera: the centre is -R^T t
        assert np.allclose(-cam_from_world.rotation.T @ cam_from_world.translation, qualisys["position"], atol=1e-9)
        # Qualisys's camera looks down its -z with y up: OpenCV's axes are its rows with y, z negated
        assert np.allclose(cam_from_world.rotation, np.diag([1.0, -1.0, -1.0]) @ qualisys["r"], atol=1e-9)
        rotation_in_file = cv2.Rodrigues(np.array(file[camera.name]["rotation"]))[0]
        assert np.allclose(rotation_in_file, cam_from_world.rotation, atol=1e-12)
        assert np.allclose(np.diag(camera.matrix)[:2], qualisys["f"], atol=1e-6)
        assert np.allclose(camera.matrix[:2, 2], qualisys["c"], atol=1e-6)
        # four coefficients in the file (no k3): read as k1, k2, p1, p2 and k3 = 0
        assert np.array_equal(camera.distortion, np.r_[file[camera.name]["distortions"], 0.0])


def test_keypoints_triangulate_as_far_from_each_view_as_their_noise(demo):
    cams, names, peer, points, marker, pixels, sigma = demo
    # the keypoints' own frame-to-frame jitter (robust, second differences) is a floor for
    # the views' disagreement, which adds each view's own idea of where a joint is
    steps = np.diff(pixels, 2, axis=1)
    steps = steps[np.isfinite(steps)]
    jitter = 1.4826 * np.median(np.abs(steps - np.median(steps))) / np.sqrt(6.0)
    assert 1.0 < jitter < sigma
    assert len(points) >= 0.95 * np.isfinite(peer[..., 0]).sum()
    for c, camera in enumerate(cams.cameras):
        seen = pixels[c, points.frame, marker]
        errors = np.linalg.norm(camera.project(points.xyz) - seen, axis=1)
        errors = errors[np.isfinite(errors)]
        # a 2-D Gaussian's radial median is 1.18 sigma; one camera may carry more of the disagreement
        assert np.median(errors) < 1.6 * sigma, camera.name


def predicted_sd(cams, points, marker, pixels, sigma) -> np.ndarray:
    """(N,) the 3-D SD (root of the covariance's trace, m) of each point from `sigma` px per
    axis in every view that saw it: sigma^2 (sum of J^T J)^-1."""
    information = np.zeros((len(points), 3, 3))
    for c, camera in enumerate(cams.cameras):
        seen = np.isfinite(pixels[c, points.frame, marker, 0])
        _, jacobian = project_cam(camera.cam_from_world.apply(points.xyz), camera.matrix, camera.distortion,
                                  with_jacobian=True)
        jacobian = jacobian[seen] @ camera.cam_from_world.rotation  # d pixel / d world point
        information[seen] += np.einsum("nki,nkj->nij", jacobian, jacobian)
    return sigma * np.sqrt(np.trace(np.linalg.inv(information), axis1=1, axis2=2))


def test_points_agree_with_pose2sim_within_their_noise(demo):
    cams, names, peer, points, marker, pixels, sigma = demo
    sd = predicted_sd(cams, points, marker, pixels, sigma)
    distance = np.linalg.norm(points.xyz - peer[points.frame, marker], axis=1)
    # the peer's points are filtered (Butterworth, 6 Hz): nearly noise-free against ours
    assert 0.5 < np.sqrt(np.mean((distance / sd) ** 2)) < 1.25
    # ours through the peer's own gap filling and filter: the noise left is the filter's
    # share of white noise, (cut-off / Nyquist)^0.5 = 0.45 of the raw SD
    ours = np.full_like(peer, np.nan)
    ours[points.frame, marker] = points.xyz
    frames = np.arange(len(peer))
    for m in range(len(names)):
        seen = np.isfinite(ours[:, m, 0])
        ours[:, m] = np.stack([np.interp(frames, frames[seen], ours[seen, m, k]) for k in range(3)], axis=1)
    b, a = butter(ORDER, CUTOFF_HZ / (FPS / 2))
    filtered = filtfilt(b, a, ours, axis=0)
    assert np.median(np.linalg.norm(filtered - peer, axis=2)) < np.sqrt(CUTOFF_HZ / (FPS / 2)) * np.median(sd)


def test_cli_triangulates_the_demo(tmp_path):
    tracks = mocap.read_tracks(DATA / "keypoints.csv")
    mocap.write_tracks(tracks.select(tracks.score >= MIN_SCORE), tmp_path / "keypoints.csv")
    out = tmp_path / "points.csv"
    run = subprocess.run([sys.executable, "-m", "mocap", "triangulate", str(DATA / "Calib_qualisys.toml"),
                          str(tmp_path / "keypoints.csv"), "--out", str(out), "--max-noise-px", str(MAX_NOISE_PX)],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    points = mocap.read_points(out).points
    names, peer = peer_points()
    distance = np.linalg.norm(points.xyz - peer[points.frame, [names.index(m) for m in points.marker]], axis=1)
    assert len(points) > 2000 and np.median(distance) < 0.03


def test_api_max_noise_px_guard():
    with pytest.raises(mocap.InputError, match="max_noise_px -1"):
        mocap.triangulate(mocap.read_calibration(DATA / "Calib_qualisys.toml"),
                          mocap.read_tracks(DATA / "keypoints.csv"), max_noise_px=-1)


# The demo's intrinsic images: a 4x7 chessboard of 60 mm squares shown to each camera alone
# (6 images each; corners found by OpenCV as Pose2Sim finds them). mocap calibrates each camera
# from one image and refines it over all six (the board's pose per image, lens and principal
# point freed); the peer is Pose2Sim's own intrinsic calibration, OpenCV's calibrateCamera.
BOARD = mocap.load_machine(DATA / "board.toml")


@pytest.fixture(scope="module")
def board_lenses(tmp_path_factory):
    from mocap.reconstruct.refine import RefineOptions

    corners = mocap.read_tracks(DATA / "board_corners.csv")
    out = tmp_path_factory.mktemp("board")
    lenses = {}
    for name in corners.cameras:
        seen = corners.of_camera(name)
        one = mocap.calibrate(BOARD, seen, size=(1088, 1920))
        refined = mocap.refine(BOARD, one, seen, options=RefineOptions(distortion="auto", fit_principal_point=True,
                                                                       base_motion=True))
        refined.cameras.write(out / f"{name}.toml")
        lenses[name] = (one, mocap.read_calibration(out / f"{name}.toml"), seen)
    return lenses


def opencv_focal(seen) -> float:
    """Pose2Sim's intrinsics: cv2.calibrateCamera on the same corners (its default model)."""
    objp = BOARD.marker_positions.astype(np.float32)
    images = [seen.of_frame(f) for f in seen.frames]
    pixels = [image.xy[[BOARD.marker_names.index(m) for m in image.marker]].astype(np.float32) for image in images]
    assert all(len(p) == len(objp) for p in pixels)
    matrix = cv2.calibrateCamera([objp] * len(pixels), pixels, (1088, 1920), None, None)[1]
    return float(matrix[0, 0])


def test_board_focal_lengths_meet_qualisys_no_worse_than_opencv(board_lenses):
    for (name, (_, refined, seen)), qualisys in zip(board_lenses.items(), qualisys_cameras(), strict=True):
        focal, sd = refined.cameras[0].matrix[0, 0], refined.extras[0]["sd"]["focal_px"]
        ours, peer = abs(focal - qualisys["f"][0]), abs(opencv_focal(seen) - qualisys["f"][0])
        # the board and the Qualisys wand are separate calibrations: each within 1 %, and ours
        # no further from Qualisys's than OpenCV's beyond our own SD
        assert ours < 0.01 * qualisys["f"][0] and ours < peer + 3 * sd, (name, focal, qualisys["f"][0], peer)


def test_refined_file_describes_the_refined_cameras(board_lenses):
    """refine's file once kept the one-frame calibration's per-camera numbers: a `paper`
    focal of 1759 px beside a refined matrix of 1672 px, its residual and SDs."""
    for name, (one, refined, _) in board_lenses.items():
        camera, extra = refined.cameras[0], refined.extras[0]
        assert extra["paper"]["focal_px"] == pytest.approx(camera.matrix[0, 0])
        assert extra["paper"]["position"] == pytest.approx(camera.center.tolist())
        # the residual RMS (px, of the distances) over every corner of the six images: one
        # camera, so the file's RMS per coordinate times sqrt(2)
        assert extra["error"] == pytest.approx(np.sqrt(2) * refined.metadata["error"], rel=1e-9)
        assert extra["error"] != one.extras[0]["error"]
        # the covariance's SDs, not the one frame's
        covariance = refined.metadata["camera_covariance"]
        f = covariance["parameters"].index(f"{name}.f")
        assert extra["sd"]["focal_px"] == pytest.approx(np.sqrt(covariance["matrix"][f][f]))
        assert extra["sd"]["focal_px"] < one.extras[0]["sd"]["focal_px"]


def test_defaults_judge_the_keypoints_by_what_explains_their_disagreement():
    """With its defaults, triangulate writes every keypoint of the demo (their views
    disagree beyond the 5 px prior, in directions no camera's move explains) and names the
    disagreement; with the keypoints of confidence 0.3 and more it names cam_01, whose
    share a small move explains, as the chessboard's focal length does (table 3 of the
    benchmark)."""
    cams = mocap.read_calibration(DATA / "Calib_qualisys.toml")
    tracks = mocap.read_tracks(DATA / "keypoints.csv")
    written = mocap.triangulate(cams, tracks)
    assert len(written.points) > 2000 and "the views disagree by" in written.report
    with pytest.raises(mocap.InputError, match=r"moving camera cam_01 \(\d+ %\) a little explains"):
        mocap.triangulate(cams, tracks.select(tracks.score >= MIN_SCORE))
