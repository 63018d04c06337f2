"""How close a processed synthetic session came to its ground truth (truth/ of `mocap synth`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mocap.core.geometry import rotation_angle_between
from mocap.io.cameras_toml import load_calibration
from mocap.io.motion_csv import load_motion
from mocap.io.points_csv import load_points
from mocap.io.session import Session
from mocap.io.tracks_csv import load_tracks

MATCH_PX = 2.0  # a tracked marker within this of its true centre is labelled right


@dataclass(frozen=True)
class CameraScore:
    name: str
    centre_m: float  # calibrated from one frame
    rotation_deg: float
    focal_pct: float
    refined_centre_m: float  # after the bundle adjustment over the session (NaN if none)
    offset_frames: float
    labelled_pct: float  # of the truly visible marker-frames
    wrong_pct: float  # of the tracked marker-frames
    centre_median_px: float
    centre_p95_px: float


@dataclass(frozen=True)
class SessionScore:
    cameras: tuple[CameraScore, ...]
    calibration_joints_deg: float  # worst joint error at the calibration frame
    tip_rmse_m: float
    bucket_angle_rmse_deg: float
    joints_rmse_deg: np.ndarray  # (J,)
    points_rmse_m: float
    frames_fitted_pct: float


def score_session(root) -> SessionScore:
    session = Session.open(root)
    machine = session.machine()
    truth_dir = session.truth_dir
    truth_cal = load_calibration(truth_dir / "cameras.toml")
    fitted_cal = load_calibration(session.calibration_path)
    refined = session.refined_calibration_path
    refined_cal = load_calibration(refined) if refined.exists() else None
    truth_tracks = load_tracks(truth_dir / "tracks.csv")
    cameras = []
    for k, name in enumerate(truth_cal.names):
        true_camera, camera = truth_cal.camera(name), fitted_cal.camera(name)
        k_fit = fitted_cal.names.index(name)
        offset = (fitted_cal.time_offsets[k_fit] - truth_cal.time_offsets[k]) * truth_cal.fps()[k]
        tracked = load_tracks(session.tracks_path(name))
        labelled, wrong, errors = _labelling(truth_tracks.of_camera(name), tracked)
        cameras.append(CameraScore(
            name,
            float(np.linalg.norm(camera.center - true_camera.center)),
            float(np.degrees(rotation_angle_between(camera.cam_from_world.rotation, true_camera.cam_from_world.rotation))),
            float(100 * abs(camera.focal - true_camera.focal) / true_camera.focal),
            float(np.linalg.norm(refined_cal.camera(name).center - true_camera.center)) if refined_cal else np.nan,
            float(offset),
            labelled,
            wrong,
            float(np.median(errors)) if len(errors) else np.nan,
            float(np.percentile(errors, 95)) if len(errors) else np.nan,
        ))
    truth_motion = load_motion(truth_dir / "motion.csv", machine)
    motion = load_motion(session.motion_path, machine)
    at = np.searchsorted(truth_motion.frame, motion.frame)
    good = np.isfinite(motion.joints).all(axis=1)
    tip = machine.point_names.index("bucket_tip") if "bucket_tip" in machine.point_names else 0
    tip_error = np.linalg.norm(motion.points[good, tip] - truth_motion.points[at[good], tip], axis=1)
    angle_error = np.degrees(motion.bucket_angle[good] - truth_motion.bucket_angle[at[good]])
    joint_error = np.degrees(_wrap(motion.joints[good] - truth_motion.joints[at[good]]))
    calibration_joints = fitted_cal.joints(machine)
    first = np.degrees(np.abs(_wrap(calibration_joints - truth_motion.joints[0]))).max() if calibration_joints is not None else np.nan
    points_rmse = np.nan
    if session.points_path.exists():
        points, true_points = load_points(session.points_path), load_points(truth_dir / "markers.csv")
        lookup = {(f, m): xyz for f, m, xyz in zip(true_points.frame, true_points.marker, true_points.xyz)}
        d = [np.linalg.norm(xyz - lookup[(f, m)]) for f, m, xyz in zip(points.frame, points.marker, points.xyz) if (f, m) in lookup]
        points_rmse = float(np.sqrt(np.mean(np.square(d)))) if d else np.nan
    return SessionScore(
        tuple(cameras),
        float(first),
        float(np.sqrt(np.mean(tip_error**2))),
        float(np.sqrt(np.mean(angle_error**2))),
        np.sqrt(np.mean(joint_error**2, axis=0)),
        points_rmse,
        float(100 * good.mean()),
    )


def _labelling(truth, tracked) -> tuple[float, float, np.ndarray]:
    """Percent of the wholly visible true marker-frames (true score 1, or no score)
    labelled, percent of tracked ones wrong (not within MATCH_PX of their marker's true
    centre, partly covered markers included), and the centre errors (px) of the right
    labels of wholly visible markers."""
    whole = ~(truth.score < 1.0)  # NaN (no score): whole
    true_xy = {(f, m): (xy, w) for f, m, xy, w in zip(truth.frame, truth.marker, truth.xy, whole)}
    frames = set(tracked.frame.tolist())
    in_range = [key for key, (_, w) in true_xy.items() if w and (key[0] in frames or not frames)]
    right, right_whole, errors = 0, 0, []
    for f, m, xy in zip(tracked.frame, tracked.marker, tracked.xy):
        expected, w = true_xy.get((f, m), (None, False))
        if expected is not None and np.linalg.norm(xy - expected) <= MATCH_PX:
            right += 1
            if w:
                right_whole += 1
                errors.append(np.linalg.norm(xy - expected))
    total = max(len(in_range), 1)
    wrong = len(tracked) - right
    return 100 * right_whole / total, 100 * wrong / max(len(tracked), 1), np.array(errors)


def _wrap(angles: np.ndarray) -> np.ndarray:
    return (angles + np.pi) % (2 * np.pi) - np.pi


def format_score(score: SessionScore, machine) -> str:
    lines = [
        "         one-frame calibration       refined",
        "camera  centre m  rot deg  focal %  centre m  sync frames  labelled %  wrong %  centre px (median / 95th)",
    ]
    for c in score.cameras:
        lines.append(
            f"{c.name:<7} {c.centre_m:8.3f} {c.rotation_deg:8.3f} {c.focal_pct:8.2f} {c.refined_centre_m:9.3f} "
            f"{c.offset_frames:+12.3f} "
            f"{c.labelled_pct:11.2f} {c.wrong_pct:8.3f}  {c.centre_median_px:.3f} / {c.centre_p95_px:.3f}"
        )
    lines.append(f"joints at the calibration frame: worst error {score.calibration_joints_deg:.3f} deg")
    lines.append(
        f"bucket tip RMSE {score.tip_rmse_m:.3f} m, bucket angle RMSE {score.bucket_angle_rmse_deg:.3f} deg, "
        f"frames fitted {score.frames_fitted_pct:.1f} %"
    )
    lines.append("joint RMSE (deg): " + ", ".join(
        f"{name} {v:.3f}" for name, v in zip(machine.joint_names, score.joints_rmse_deg)))
    if np.isfinite(score.points_rmse_m):
        lines.append(f"triangulated markers RMSE {score.points_rmse_m:.3f} m")
    return "\n".join(lines)
