"""Accuracy, convergence and speed of the model-based calibration, on generated scenes and
on a real chessboard, and a check that aniposelib reads the calibration files we write.

    python benchmarks/bench_calibration.py [--quick] [--only PART ...]

1. Accuracy against the Cramér–Rao bound: Hitachi EX3500 scenes (cameras 30–60 m away,
   1920 x 1080, 0.5 px noise per axis), 1, 2 and 3 cameras. Each scene is fixed and
   observed with many noise draws; the RMS errors of camera centre, rotation, focal length
   and joint values over the draws are set beside the bound sigma^2 (J^T J)^-1 evaluated at
   the truth and propagated to centre and rotation angle.
2. Convergence with no initial guess: random poses inside the limits, 1–3 cameras at
   20–80 m with random fields of view; a scene is solved when every parameter lies within
   5 sigma of the truth (sigma from the fit's own covariance at the known 0.5 px noise) and
   the residuals pass a chi-square test at 1e-4. A fit far from the truth that explains the
   pixels as well as the truth does (a fit started there) is named ambiguous: the
   observations cannot decide that scene.
3. Speed: the whole `calibrate` (start, fit, covariance) of one camera seeing 15 EX3500
   markers on all links, and on the rigid cube pair side by side with OpenCV's solvePnP
   (ITERATIVE, SQPNP) that is given the true intrinsics.
4. Real data: the OpenCV sample chessboard pairs (Debian package opencv-doc), each camera
   calibrated from one view of the board as a one-link rigid machine, against OpenCV's
   calibrateCamera over all views of the same camera; and the DLT's refusal of a plane.
5. aniposelib's CameraGroup.load on the files `mocap calibrate --out` and
   save_calibration write, run in aniposelib's own environment (benchmarks/.envs/).
6. Starts: the cube pair (test 1 of the paper, one camera, 0.3 px noise) calibrated from 500
   reasonable guesses (angles off by up to 30 deg, position by 30 %, focal length by a factor
   of 2): every start must reach the solution found with no guess, within 0.1 mm
   (tests/test_calibration.py holds the first 50 of the same starts to it).

Times are CPU times of this process (time.process_time): per scene the least over a few
repeats (the least disturbed by other processes on a shared machine), then the median over
scenes. Seeds are fixed: a run repeats the same scenes.
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import glob
import gzip
import io
import json
import os
import pstats
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.stats import chi2

from mocap import cli
from mocap.calibration import CalibrationOptions, Guess, Observations, calibrate, identify, initial
from mocap.calibration.dlt import dlt_camera
from mocap.calibration.problem import Layout, Problem
from mocap.calibration.solve import template_camera
from mocap.core.calibration import Calibration
from mocap.core.camera import Camera, intrinsic_matrix
from mocap.core.geometry import Rigid, matrix_to_rotvec, rotation_angle_between, rotvec_to_matrix
from mocap.errors import InputError
from mocap.io.cameras_toml import load_calibration, save_calibration
from mocap.io.machine_toml import load_machine, machine_from_dict, save_machine
from mocap.io.tracks_csv import save_tracks
from mocap.synthetic.bounds import numeric_jacobian
from mocap.synthetic.scenes import observe, random_joints, ring_of_cameras

HERE = Path(__file__).resolve().parent
NOISE_PX = 0.5
SIZE = (1920, 1080)
CHESSBOARD_DIR = Path("/usr/share/doc/opencv-doc/examples/data")
BOARD = (9, 6)  # inner corners per row, per column; OpenCV's stereo_calib default square 1.0
ANIPOSE_ENV = HERE / ".envs" / "aniposelib"
PARTS = ("accuracy", "convergence", "speed", "chessboard", "aniposelib", "starts")
SPEED_MARKERS = ("U1", "U2", "U3", "U5", "U7", "H1", "H2", "H4", "B1", "B2", "A1", "A2", "K1", "K2", "K4")


@dataclass(frozen=True)
class Sizes:
    crb_scenes: int
    crb_draws: int
    convergence: int
    speed_scenes: int
    speed_repeats: int
    starts: int


FULL = Sizes(crb_scenes=4, crb_draws=75, convergence=1000, speed_scenes=30, speed_repeats=5, starts=500)
QUICK = Sizes(crb_scenes=1, crb_draws=8, convergence=40, speed_scenes=5, speed_repeats=3, starts=50)
STARTS_BOUND_M = 1e-4


# --- scenes --------------------------------------------------------------------------------
def templates_of(cameras: list[Camera]) -> list[Camera]:
    return [template_camera(c.name, c.size) for c in cameras]


def true_observations(cameras: list[Camera], machine, joints: np.ndarray, markers=None) -> Observations:
    """Noise-free pixels of the markers (all, or the indices `markers`) inside each image."""
    world = machine.markers(joints[None])[0]
    index = np.arange(len(world)) if markers is None else np.asarray(markers)
    camera, marker, xy = [], [], []
    for c, cam in enumerate(cameras):
        uv = cam.project(world[index])
        w, h = cam.size
        seen = np.all(np.isfinite(uv), axis=1) & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1)
        seen &= (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
        camera.append(np.full(np.sum(seen), c))
        marker.append(index[seen])
        xy.append(uv[seen])
    return Observations(np.concatenate(camera), np.concatenate(marker), np.concatenate(xy))


def with_noise(obs: Observations, rng, noise_px: float = NOISE_PX) -> Observations:
    return Observations(obs.camera, obs.marker, obs.xy + rng.normal(0.0, noise_px, obs.xy.shape))


def ex3500_scene(machine, n_cameras: int, rng, distance=(30.0, 60.0), fov_deg=(25.0, 45.0), markers=None):
    """A random pose and `n_cameras` aimed at the posed machine; the noise-free pixels."""
    joints = random_joints(machine, 1, rng)[0]
    centre = machine.markers(joints[None])[0].mean(axis=0)
    cameras = ring_of_cameras(n_cameras, centre, distance, rng, size=SIZE, fov_deg=fov_deg)
    return cameras, joints, true_observations(cameras, machine, joints, markers)


# --- 1. accuracy against the Cramér–Rao bound ---------------------------------------------
def crb_variances(machine, cameras, joints, obs: Observations) -> dict:
    """Per quantity the bound on the mean squared error: camera centre (m^2, summed over
    x, y, z), rotation angle (rad^2, summed over the three small-angle components), focal
    (px^2), per camera; joint values (rad^2) per joint."""
    layout = Layout(len(cameras), machine.n_joints)
    x = layout.pack(cameras, joints)
    jac = Problem(machine, obs, layout, templates_of(cameras)).jacobian(x)
    cov = NOISE_PX**2 * np.linalg.inv(jac.T @ jac)
    out = {"centre": [], "rotation": [], "focal": []}
    for c, camera in enumerate(cameras):
        s = layout.camera_slice(c)
        block, sigma = x[s], cov[s, s]
        truth = camera.cam_from_world.rotation

        def centre(b):
            return -rotvec_to_matrix(b[:3]).T @ b[3:6]

        def rotation_error(b):
            return matrix_to_rotvec(rotvec_to_matrix(b[:3]) @ truth.T)

        g_centre = numeric_jacobian(centre, block)
        g_rotation = numeric_jacobian(rotation_error, block)
        out["centre"].append(np.trace(g_centre @ sigma @ g_centre.T))
        out["rotation"].append(np.trace(g_rotation @ sigma @ g_rotation.T))
        out["focal"].append(sigma[6, 6])
    out["joints"] = np.diag(cov)[layout.joint_slice(0)]
    return out


def bench_crb(machine, sizes: Sizes) -> list[dict]:
    rows = []
    for n_cameras in (1, 2, 3):
        # per quantity, per fitted value: (squared error, its bound)
        pairs = {key: [] for key in ("centre", "rotation", "focal", *machine.joint_names)}
        failures, scenes = 0, 0
        rng = np.random.default_rng(1000 + n_cameras)
        while scenes < sizes.crb_scenes:
            cameras, joints, clean = ex3500_scene(machine, n_cameras, rng)
            if len(clean) < n_cameras * len(machine.marker_names):
                continue  # keep scenes where every camera sees every marker
            scenes += 1
            crb = crb_variances(machine, cameras, joints, clean)
            for _ in range(sizes.crb_draws):
                try:
                    result = calibrate(machine, with_noise(clean, rng), templates_of(cameras))
                except InputError:
                    failures += 1
                    continue
                for c, (fit, cam) in enumerate(zip(result.cameras, cameras)):
                    angle = rotation_angle_between(fit.cam_from_world.rotation, cam.cam_from_world.rotation)
                    pairs["centre"].append((np.sum((fit.center - cam.center) ** 2), crb["centre"][c]))
                    pairs["rotation"].append((angle**2, crb["rotation"][c]))
                    pairs["focal"].append(((fit.focal - cam.focal) ** 2, crb["focal"][c]))
                for j, name in enumerate(machine.joint_names):
                    pairs[name].append(((result.joints[j] - joints[j]) ** 2, crb["joints"][j]))
        for key, values in pairs.items():
            squared, bound = np.array(values).T
            unit, scale = {"centre": ("m", 1.0), "focal": ("px", 1.0)}.get(key, ("deg", np.degrees(1.0)))
            label = f"{key} ({unit})" if key in ("centre", "rotation", "focal") else f"joint {key} ({unit})"
            normalised = squared / bound
            mean = float(np.mean(normalised))
            rows.append(dict(
                cameras=n_cameras, quantity=label, failures=failures,
                rms=scale * np.sqrt(np.mean(squared)), crb=scale * np.sqrt(np.mean(bound)),
                ratio=np.sqrt(mean), se=np.std(normalised) / np.sqrt(len(normalised)) / (2 * np.sqrt(mean)),
            ))
    print_table(
        f"1. Accuracy vs the Cramér–Rao bound: EX3500, {sizes.crb_scenes} scene(s) x "
        f"{sizes.crb_draws} noise draws per camera count, {NOISE_PX} px noise. Centre and rotation: "
        "the error's length. RMS and CRB pooled over the draws; ratio = sqrt(mean of error^2 / "
        "bound^2), each draw against its own scene's bound, ± its standard error",
        ["cameras", "quantity", "RMS error", "CRB", "ratio", "failed fits"],
        [
            [r["cameras"], r["quantity"], f"{r['rms']:.4g}", f"{r['crb']:.4g}",
             f"{r['ratio']:.3f} ± {r['se']:.3f}", r["failures"]]
            for r in rows
        ],
    )
    return rows


# --- 2. convergence with no initial guess --------------------------------------------------
def bench_convergence(machine, sizes: Sizes) -> dict:
    solved, failures, refused, draw = 0, [], {}, 0
    by_cameras = {1: [0, 0], 2: [0, 0], 3: [0, 0]}
    false_outliers, tried, ambiguous, optimum = 0, 0, [], []
    while tried < sizes.convergence:
        rng = np.random.default_rng(50_000 + draw)
        draw += 1
        n_cameras = int(rng.integers(1, 4))
        cameras, joints, clean = ex3500_scene(machine, n_cameras, rng, distance=(20.0, 80.0), fov_deg=(20.0, 60.0))
        obs = with_noise(clean, rng)
        names = [c.name for c in cameras]
        try:
            identify.check_counts(machine, names, obs.camera, obs.marker, False, 7)
        except InputError as exc:
            key = re.sub(r"'cam\d+'|\d+", "#", exc.detail.split(";")[0])  # the kind of refusal
            refused[key] = refused.get(key, 0) + 1
            continue
        tried += 1
        by_cameras[n_cameras][1] += 1
        seen = [int(np.sum(obs.camera == c)) for c in range(n_cameras)]
        verdict, why, n_false = check_solution(machine, cameras, joints, obs)
        false_outliers += n_false
        record = dict(draw=draw - 1, cameras=n_cameras, seen=seen, why=why)
        if verdict in ("solved", "optimum"):
            solved += 1
            by_cameras[n_cameras][0] += 1
            if verdict == "optimum":
                optimum.append(record)
        elif verdict == "ambiguous":
            ambiguous.append(record)
        else:
            record["distance"] = [float(np.linalg.norm(c.center - machine.markers(joints[None])[0].mean(axis=0))) for c in cameras]
            record.update(focal=[c.focal for c in cameras], joints=np.degrees(joints))
            failures.append(record)
    decidable = tried - len(ambiguous)
    rate = 100.0 * solved / max(decidable, 1)
    print_table(
        f"2. Convergence with no initial guess: {tried} random EX3500 scenes (1-3 cameras at "
        "20-80 m, fields of view 20-60 deg, poses inside the limits); solved: every parameter "
        "within 5 sigma of the truth, the residuals within the noise (chi-square, 1e-4) and "
        "nothing dropped, or else the same solution as a fit started at the truth",
        ["cameras", "scenes", "solved", "rate"],
        [[n, t, s, f"{100.0 * s / max(t, 1):.1f} %"] for n, (s, t) in by_cameras.items()]
        + [["all", tried, solved, f"{100.0 * solved / max(tried, 1):.1f} %"]],
    )
    print(f"   of the solved, outside the criteria but the same solution as a fit started at the truth: {len(optimum)}")
    for a in optimum:
        print(f"     draw {a['draw']}: {a['cameras']} camera(s) seeing {a['seen']} markers: {a['why']}")
    print(f"   ambiguous scenes (another solution explains the pixels as well as the truth): {len(ambiguous)}")
    for a in ambiguous:
        print(f"     draw {a['draw']}: {a['cameras']} camera(s) seeing {a['seen']} markers: {a['why']}")
    print(f"   rate over the scenes the observations decide: {solved} of {decidable} = {rate:.1f} %")
    print(f"   draws refused before the fit by the counting rules (not counted): {sum(refused.values())}")
    for key, count in sorted(refused.items(), key=lambda kv: -kv[1]):
        print(f"     {count:5d}  {key}")
    print(f"   correct observations wrongly named outliers: {false_outliers}")
    if failures:
        print("   failures:")
        for f in failures:
            print(
                f"     draw {f['draw']}: {f['cameras']} camera(s) seeing {f['seen']} markers at "
                f"{np.round(f['distance'], 1).tolist()} m, f {np.round(f['focal']).tolist()} px, "
                f"joints {np.round(f['joints'], 1).tolist()} deg: {f['why']}"
            )
    return dict(rate=rate, tried=tried, decidable=decidable, failures=failures)


def check_solution(machine, cameras, joints, obs: Observations) -> tuple[str, str, int]:
    """Calibrate `obs` with no guess. Returns the verdict, the reason and the number of
    correct observations named outliers. Verdicts: "solved" (every parameter within 5 sigma
    of the truth, residuals within the noise, nothing dropped); "optimum" (a criterion missed,
    but the fit is the one a fit started at the truth reaches: the miss is the noise draw's);
    "ambiguous" (another solution explains the pixels as well as the truth's); "failed"."""
    try:
        result = calibrate(machine, obs, templates_of(cameras))
    except InputError as exc:
        return "failed", f"refused: {exc}", 0
    layout = Layout(len(cameras), machine.n_joints)
    std = result.std * NOISE_PX / result.sigma_px  # the fit's covariance at the known noise
    z = np.abs(result.parameters - aligned(layout, layout.pack(cameras, joints), result.parameters)) / std
    chi_square, dof = chi_square_of(result)
    fits_noise = dof <= 0 or chi2.sf(chi_square, dof) >= 1e-4
    reasons = []
    if np.max(z) >= 5.0:
        k = int(np.argmax(z))
        reasons.append(f"{result.parameter_names[k]} off by {z[k]:.1f} sigma")
    if not fits_noise:
        reasons.append(f"rms {result.rms_px:.2f} px beyond the noise (chi2 {chi_square:.0f} for {dof} dof)")
    n_false = len(result.outliers)
    if n_false:
        reasons.append(f"{n_false} correct observation(s) dropped as outliers")
    if not reasons:
        return "solved", "", 0
    guess = Guess({c.name: c.to_paper() for c in cameras}, joints)
    at_truth = calibrate(machine, obs, templates_of(cameras), guess=guess)
    truth_chi_square, _ = chi_square_of(at_truth)
    same = np.max(np.abs(result.parameters - aligned(layout, at_truth.parameters, result.parameters)) / std)
    reason = "; ".join(reasons)
    if same < 0.01 and not n_false:
        return "optimum", f"{reason}; the fit started at the truth reaches the same solution", 0
    if fits_noise and abs(truth_chi_square - chi_square) < 9.0:
        return "ambiguous", (f"{reason}; the fit started at the truth explains the pixels as well "
                             f"(chi2 {truth_chi_square:.1f} vs {chi_square:.1f})"), n_false
    return "failed", f"{reason}; the fit started at the truth has chi2 {truth_chi_square:.1f} vs {chi_square:.1f}", n_false


def chi_square_of(result) -> tuple[float, int]:
    """Sum of squared inlier residuals over the known noise variance, and its degrees of freedom."""
    inliers = [r for r in result.residuals if not r.outlier]
    chi_square = sum(float(np.sum(r.residual**2)) for r in inliers) / NOISE_PX**2
    return chi_square, 2 * len(inliers) - len(result.parameters)


def aligned(layout: Layout, x: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """`x` with each camera's Rodrigues vector the one nearest `reference`'s (a rotation
    near 180 deg has two)."""
    x = x.copy()
    for c in range(layout.n_cameras):
        s = layout.camera_slice(c).start
        x[s : s + 3] = closest_rotvec(x[s : s + 3], reference[s : s + 3])
    return x


def closest_rotvec(rotvec: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """The Rodrigues vector of the same rotation as `rotvec` (angle a or a - 2 pi about the
    same axis) nearest to `reference`."""
    angle = np.linalg.norm(rotvec)
    if angle == 0:
        return rotvec
    other = rotvec * (1.0 - 2.0 * np.pi / angle)
    return other if np.linalg.norm(other - reference) < np.linalg.norm(rotvec - reference) else rotvec


# --- 3. speed ------------------------------------------------------------------------------
def cpu_time_per_call(function, repeats: int, calls: int = 1) -> float:
    """CPU seconds per call: the least over `repeats` timings of `calls` calls each (the
    least is the time least disturbed by other processes on a shared machine)."""
    best = np.inf
    for _ in range(repeats):
        start = time.process_time()
        for _ in range(calls):
            function()
        best = min(best, (time.process_time() - start) / calls)
    return best


def bench_speed_ex3500(machine, sizes: Sizes) -> dict:
    markers = machine.marker_index(list(SPEED_MARKERS))
    rng = np.random.default_rng(7)
    times, scenes, failed = [], [], 0
    while len(scenes) < sizes.speed_scenes:
        cameras, joints, clean = ex3500_scene(machine, 1, rng, markers=markers)
        if len(clean) < len(markers):
            continue
        scenes.append((cameras, with_noise(clean, rng)))
    for cameras, obs in scenes:
        templates = templates_of(cameras)
        try:
            calibrate(machine, obs, templates)
        except InputError:
            failed += 1
            continue
        times.append(cpu_time_per_call(lambda: calibrate(machine, obs, templates), sizes.speed_repeats))
    median = 1e3 * float(np.median(times))
    print_table(
        f"3a. Speed: calibrate() of one camera, {len(markers)} EX3500 markers on all 5 links, 4 "
        f"unknown joints, focal unknown ({len(times)} scenes; CPU time per call, the least of "
        f"{sizes.speed_repeats} repeats per scene; median, min and max over scenes; load average "
        f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)",
        ["median ms", "min ms", "max ms", "target ms", "failed"],
        [[f"{median:.1f}", f"{1e3 * min(times):.1f}", f"{1e3 * max(times):.1f}", "20", failed]],
    )
    profile_calibrate(machine, scenes[: min(10, len(scenes))], median)
    return dict(median_ms=median)


def profile_calibrate(machine, scenes, median_ms: float) -> None:
    """Where calibrate()'s time goes: the shares of its parts' cumulative time under
    cProfile, and those shares of the unprofiled median time."""
    profiler = cProfile.Profile()
    profiler.enable()
    for cameras, obs in scenes:
        calibrate(machine, obs, templates_of(cameras))
    profiler.disable()
    stats = pstats.Stats(profiler, stream=io.StringIO()).stats
    parts = {
        "start: place_camera (PnP over focal lengths)": ("initial.py", "place_camera"),
        "start: joints_along_chain (beam search)": ("initial.py", "joints_along_chain"),
        "fit: least_squares (all calls)": ("fit.py", "_least_squares"),
        "  of which residuals + Jacobian": ("problem.py", "_evaluate"),
        "check_jacobian (SVD)": ("identify.py", "check_jacobian"),
        "paper-parameter sd (finite differences)": ("fit.py", "_paper_sd"),
    }
    total = sum(v[3] for k, v in stats.items() if k[2] == "calibrate" and k[0].endswith("solve.py"))
    rows = []
    for label, (file, function) in parts.items():
        cum = sum(v[3] for k, v in stats.items() if k[2] == function and k[0].endswith(file))
        rows.append([label, f"{100 * cum / total:.0f} %", f"{median_ms * cum / total:.1f}"])
    rows.append(["total calibrate()", "100 %", f"{median_ms:.1f}"])
    print_table("   where the time goes (cProfile shares; ms = share x the unprofiled median)",
                ["part", "share", "~ms"], rows)


def pose_with_known_focal(machine, obs: Observations, template: Camera) -> Camera:
    """Ours with the focal length given: the PnP start at that focal length, then the
    least-squares fit of the six pose parameters with the calibration's own residuals and
    analytic Jacobian (no covariance, no outlier step)."""
    camera, _ = initial.place_camera(machine.marker_positions[obs.marker], obs.xy, template, template.focal)
    layout = Layout(1, 0)
    problem = Problem(machine, obs, layout, [template])
    focal = np.array([template.focal])
    fit = least_squares(
        lambda p: problem.residuals(np.r_[p, focal]),
        layout.pack([camera], np.zeros(0))[:6],
        jac=lambda p: problem.jacobian(np.r_[p, focal])[:, :6],
        x_scale="jac",
        method="trf",
    )
    return layout.unpack(np.r_[fit.x, focal], [template])[0][0]


def bench_speed_cube(cube, sizes: Sizes) -> dict:
    rest = cube.marker_positions
    extent = np.ptp(rest, axis=0).max()
    rng = np.random.default_rng(11)
    scenes = []
    while len(scenes) < sizes.speed_scenes:
        cameras = ring_of_cameras(1, rest.mean(axis=0), (2.5 * extent, 4.0 * extent), rng, size=SIZE,
                                  height=(0.3 * extent, 0.8 * extent))
        clean = true_observations(cameras, cube, np.zeros(0))
        if len(clean) == len(rest):
            scenes.append((cameras[0], with_noise(clean, rng)))

    def opencv(flag):
        def run(camera, obs):
            points = rest[obs.marker]
            ok, rvec, tvec = cv2.solvePnP(points, obs.xy, camera.matrix, None, flags=flag)
            return Camera(camera.name, camera.size, camera.matrix, np.zeros(5), Rigid.from_rotvec(rvec.ravel(), tvec.ravel()))
        return run

    methods = {
        "OpenCV solvePnP ITERATIVE (K known)": (opencv(cv2.SOLVEPNP_ITERATIVE), 20),
        "OpenCV solvePnP SQPNP (K known)": (opencv(cv2.SOLVEPNP_SQPNP), 20),
        "ours calibrate() (f unknown)": (
            lambda camera, obs: calibrate(cube, obs, [template_camera(camera.name, camera.size)]).cameras[0],
            1,
        ),
        "ours, f known (PnP start + pose LM)": (
            lambda camera, obs: pose_with_known_focal(cube, obs, replace(camera, cam_from_world=Rigid.identity())),
            4,
        ),
    }
    rows, out = [], {}
    for label, (method, n) in methods.items():
        times, centre, rms = [], [], []
        for camera, obs in scenes:
            fitted = method(camera, obs)
            times.append(cpu_time_per_call(lambda: method(camera, obs), sizes.speed_repeats, n))
            centre.append(np.linalg.norm(fitted.center - camera.center))
            rms.append(np.sqrt(np.mean(np.sum((fitted.project(rest[obs.marker]) - obs.xy) ** 2, axis=1))))
        out[label] = 1e3 * float(np.median(times))
        rows.append([label, f"{out[label]:.3f}", None, f"{np.sqrt(np.mean(np.square(centre))):.4f}",
                     f"{np.max(centre):.4f}", f"{np.median(rms):.3f}"])
    sqpnp = out["OpenCV solvePnP SQPNP (K known)"]
    for row in rows:
        row[2] = f"{float(row[1]) / sqpnp:.1f}x"
    print_table(
        f"3b. Speed and accuracy on the cube pair (8 markers, camera {2.5 * extent:.0f}-"
        f"{4 * extent:.0f} m away, {NOISE_PX} px noise, {len(scenes)} scenes; CPU ms per call, "
        "the least of the repeats, median over scenes; ratio to SQPNP)",
        ["method", "ms", "ratio", "centre RMS m", "centre max m", "reproj rms px (median)"],
        rows,
    )
    return out


# --- 4. real chessboard --------------------------------------------------------------------
def chessboard_images() -> dict[str, list[Path]] | None:
    if not CHESSBOARD_DIR.is_dir():
        return None
    found = {}
    for side in ("left", "right"):
        paths = sorted(glob.glob(str(CHESSBOARD_DIR / f"{side}[0-9][0-9].jpg*")))
        if paths:
            found[side] = [Path(p) for p in paths]
    return found or None


def read_image(path: Path) -> np.ndarray:
    data = gzip.decompress(path.read_bytes()) if path.suffix == ".gz" else path.read_bytes()
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)


def board_machine(folder: Path):
    """The board as a one-link rigid machine, written as a machine TOML and loaded back."""
    corners = [(i % BOARD[0], i // BOARD[0], 0.0) for i in range(BOARD[0] * BOARD[1])]
    data = {
        "name": "OpenCV sample chessboard",
        "source": "9 x 6 inner corners of unit squares (OpenCV samples/data left*.jpg, right*.jpg)",
        "links": [{"name": "board"}],
        "markers": [{"name": f"C{i:02d}", "link": "board", "position": list(p)} for i, p in enumerate(corners)],
    }
    path = folder / "chessboard.toml"
    save_machine(machine_from_dict(data, path), path)
    return load_machine(path)


def detect_corners(image: np.ndarray) -> np.ndarray | None:
    found, corners = cv2.findChessboardCorners(image, BOARD, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not found:
        return None
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)
    return cv2.cornerSubPix(image, corners, (11, 11), (-1, -1), criteria).reshape(-1, 2).astype(float)


def bench_chessboard() -> dict | None:
    images = chessboard_images()
    if images is None:
        print(f"\n4. Real chessboard: skipped, {CHESSBOARD_DIR} not found (apt-get install opencv-doc)")
        return None
    out = {}
    with tempfile.TemporaryDirectory() as folder:
        board = board_machine(Path(folder))
    objp = board.marker_positions.astype(np.float32)
    for side, paths in images.items():
        views, names, size = [], [], None
        for path in paths:
            image = read_image(path)
            size = (image.shape[1], image.shape[0])
            corners = detect_corners(image)
            if corners is not None:
                views.append(corners)
                names.append(path.name)
        opencv = opencv_calibrations(objp, views, size)
        rows, ratios, ratios_k1, dlt_message = [], [], [], None
        for name, corners, rvec, tvec in zip(names, views, *opencv["full"][2:]):
            reference = Rigid.from_rotvec(rvec.ravel(), tvec.ravel())
            obs = Observations(np.zeros(len(corners), int), np.arange(len(corners)), corners)
            row = [name]
            for options in (CalibrationOptions(), CalibrationOptions(distortion="k1")):
                try:
                    result = calibrate(board, obs, [template_camera(side, size)], options)
                except InputError as exc:
                    row += [f"refused: {exc.detail[:50]}", "", "", ""]
                    continue
                fit = result.cameras[0]
                centre = np.linalg.norm(fit.center - reference.inverse().translation)
                angle = rotation_angle_between(fit.cam_from_world.rotation, reference.rotation)
                row += [f"{fit.focal:.1f} ± {result.std[6]:.1f}", f"{centre:.2f}", f"{angle:.2f}", f"{result.rms_px:.2f}"]
                if options.distortion == "none":
                    ratios.append(fit.focal / opencv["same"][0][0, 0] - 1)
                else:
                    ratios_k1.append(fit.focal / np.mean(np.diag(opencv["full"][0])[:2]) - 1)
            rows.append(row)
            try:
                dlt_camera(side, size, board.marker_positions, corners)
            except InputError as exc:
                dlt_message = str(exc)
        full_k, full_dist = opencv["full"][0], opencv["full"][1].ravel()
        same_k = opencv["same"][0]
        print(
            f"\n4. Real chessboard, {side} camera ({len(views)} views of {len(paths)} with the board "
            f"found, {size[0]}x{size[1]}, unit squares)\n"
            f"   OpenCV calibrateCamera, all views, full model: fx {full_k[0, 0]:.1f} fy {full_k[1, 1]:.1f} "
            f"cx {full_k[0, 2]:.1f} cy {full_k[1, 2]:.1f} k1 {full_dist[0]:.3f} k2 {full_dist[1]:.3f}, rms "
            f"{opencv['full_rms']:.3f} px\n"
            f"   OpenCV calibrateCamera, all views, our model (f only, principal point at the centre, no "
            f"distortion): f {same_k[0, 0]:.1f}, rms {opencv['same_rms']:.3f} px"
        )
        print_table(
            "   ours from ONE view (f unknown, principal point at the centre); pose vs OpenCV's full "
            "model per view (centre in squares, rotation in deg)",
            ["view", "f px", "centre d", "rot d", "rms px", "f (k1 fit)", "centre d", "rot d", "rms px"],
            rows,
        )
        if ratios:
            print(f"   ours (no distortion) vs OpenCV same-model f: median {100 * np.median(ratios):+.1f} %, "
                  f"range {100 * min(ratios):+.1f} .. {100 * max(ratios):+.1f} %")
        if ratios_k1:
            print(f"   ours (k1 fitted) vs OpenCV full-model f: median {100 * np.median(ratios_k1):+.1f} %, "
                  f"range {100 * min(ratios_k1):+.1f} .. {100 * max(ratios_k1):+.1f} %")
        print(f"   DLT on the same views: {'refused: ' + dlt_message if dlt_message else 'NOT refused'}")
        out[side] = dict(median_f=float(np.median(ratios)) if ratios else float("nan"),
                         median_f_k1=float(np.median(ratios_k1)) if ratios_k1 else float("nan"),
                         opencv_f=float(same_k[0, 0]), dlt_refused=dlt_message is not None)
    return out


def opencv_calibrations(objp: np.ndarray, views: list[np.ndarray], size) -> dict:
    object_points = [objp] * len(views)
    image_points = [v.astype(np.float32).reshape(-1, 1, 2) for v in views]
    rms, k, dist, rvecs, tvecs = cv2.calibrateCamera(object_points, image_points, size, None, None)
    guess = intrinsic_matrix(k[0, 0], ((size[0] - 1) / 2, (size[1] - 1) / 2))
    flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_ASPECT_RATIO
             | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3)
    same_rms, same_k, *_ = cv2.calibrateCamera(object_points, image_points, size, guess, np.zeros(5), flags=flags)
    return {"full": (k, dist, rvecs, tvecs), "full_rms": rms, "same": (same_k,), "same_rms": same_rms}


# --- 5. aniposelib reads our files ---------------------------------------------------------
def anipose_python() -> Path | None:
    python = ANIPOSE_ENV / "bin" / "python"
    if python.exists():
        return python
    print(f"   creating {ANIPOSE_ENV} (python -m venv; pip install aniposelib)")
    try:
        subprocess.run([sys.executable, "-m", "venv", str(ANIPOSE_ENV)], check=True)
        subprocess.run([str(python), "-m", "pip", "install", "--quiet", "aniposelib>=0.5,<0.6", "numpy<2.3"], check=True)
    except (subprocess.CalledProcessError, OSError) as exc:
        print(f"   could not create it: {exc}")
        return None
    return python


def bench_aniposelib(machine) -> dict | None:
    print("\n5. aniposelib CameraGroup.load on our calibration files")
    python = anipose_python()
    if python is None:
        print("   skipped: no aniposelib environment")
        return None
    rng = np.random.default_rng(3)
    cameras, joints, _ = ex3500_scene(machine, 3, rng)
    tracks = observe(cameras, machine, joints[None], rng, noise_px=NOISE_PX)
    worst = {}
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        save_tracks(tracks, folder / "tracks.csv")
        written = folder / "cameras.toml"
        with contextlib.redirect_stdout(io.StringIO()):
            status = cli.main(["calibrate", "hitachi_ex3500", str(folder / "tracks.csv"),
                               "--size", f"{SIZE[0]}x{SIZE[1]}", "--out", str(written)])
        if status != 0:
            print(f"   mocap calibrate failed with status {status}")
            return None
        ours = load_calibration(written)
        distorted = folder / "distorted.toml"
        coefficients = np.array([-0.12, 0.03, 1e-3, -5e-4, -4e-3])
        save_calibration(
            Calibration(tuple(replace(c, distortion=coefficients * (1 + 0.1 * k)) for k, c in enumerate(ours.cameras)),
                        ours.extras, ours.metadata),
            distorted,
        )
        points = machine.markers(ours.joints(machine)[None])[0]
        np.save(folder / "points.npy", points)
        rows = []
        for label, path in (("mocap calibrate --out", written), ("save_calibration, with distortion", distorted)):
            target = folder / "anipose.json"
            run = subprocess.run([str(python), str(HERE / "peers" / "aniposelib_load.py"), str(path),
                                  str(folder / "points.npy"), str(target)], capture_output=True, text=True)
            if run.returncode != 0:
                rows.append([label, "aniposelib failed: " + run.stderr.strip().splitlines()[-1], "", "", ""])
                worst[label] = np.inf
                continue
            theirs = json.loads(target.read_text())["cameras"]
            mine = load_calibration(path).cameras
            for camera, read in zip(mine, theirs):
                pixels = camera.project(points)
                diff = float(np.max(np.abs(np.asarray(read["pixels"]) - pixels)))
                same = (read["name"] == camera.name and tuple(read["size"]) == camera.size
                        and np.allclose(read["matrix"], camera.matrix, rtol=0, atol=0)
                        and np.allclose(read["distortion"], camera.distortion, rtol=0, atol=0))
                rows.append([label, read["name"], f"{read['size'][0]}x{read['size'][1]}",
                             "identical" if same else "DIFFERENT", f"{diff:.2e}"])
                worst[label] = max(worst.get(label, 0.0), diff)
            if len(theirs) != len(mine):
                rows.append([label, f"aniposelib read {len(theirs)} cameras of {len(mine)}", "", "", ""])
                worst[label] = np.inf
    print_table(f"   {len(points)} marker positions projected by aniposelib (cv2.projectPoints) and by mocap",
                ["file", "camera", "size", "matrix, distortion", "max |d pixel| px"], rows)
    return worst


# --- output --------------------------------------------------------------------------------
def bench_starts(cube, sizes: Sizes) -> dict:
    """Part 6: the cube pair from `sizes.starts` seeded reasonable guesses; the worst distance
    of the fitted camera centre from the no-guess solution's."""
    sys.path.insert(0, str(HERE.parent / "tests"))
    from conftest import reasonable_guess, scene

    cameras, _, obs, _ = scene(cube, 1, 3, noise_px=0.3, distance=(2.5, 4.0))
    camera = cameras[0]
    reference = calibrate(cube, obs, templates_of([camera])).cameras[0].to_paper()
    truth = camera.to_paper()
    rng = np.random.default_rng(5)
    worst = 0.0
    for _ in range(sizes.starts):
        guess = reasonable_guess(truth, rng)
        result = calibrate(cube, obs, templates_of([camera]), guess=Guess({camera.name: guess}))
        worst = max(worst, float(np.linalg.norm(result.cameras[0].to_paper().position - reference.position)))
    return {"starts": sizes.starts, "worst_m": worst}


def print_table(title: str, header: list[str], rows: list[list]) -> None:
    cells = [[str(c) for c in header]] + [[str(c) for c in row] for row in rows]
    widths = [max(len(r[i]) for r in cells if i < len(r)) for i in range(len(header))]
    print(f"\n{title}")
    for k, row in enumerate(cells):
        print("   " + "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths))))
        if k == 0:
            print("   " + "  ".join("-" * w for w in widths))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="small sizes, a smoke check")
    parser.add_argument("--only", action="append", choices=PARTS, help="run only this part (repeatable)")
    args = parser.parse_args(argv)
    sizes = QUICK if args.quick else FULL
    ex3500 = load_machine("hitachi_ex3500")
    cube = load_machine("cube_pair")
    started = time.perf_counter()

    run = set(args.only or PARTS)
    crb = bench_crb(ex3500, sizes) if "accuracy" in run else None
    convergence = bench_convergence(ex3500, sizes) if "convergence" in run else None
    speed = bench_speed_ex3500(ex3500, sizes) if "speed" in run else None
    cube_speed = bench_speed_cube(cube, sizes) if "speed" in run else None
    board = bench_chessboard() if "chessboard" in run else None
    anipose = bench_aniposelib(ex3500) if "aniposelib" in run else None
    starts = bench_starts(cube, sizes) if "starts" in run else None

    summary = []
    if crb is not None:
        worst_ratio = max(r["ratio"] for r in crb)
        best_ratio = min(r["ratio"] for r in crb)
        met = "yes" if worst_ratio <= 1.2 else "NO"
        if max(r["se"] for r in crb) > 0.1:
            met = "too few draws to tell"
        summary.append(["accuracy: error / CRB, over all quantities", "<= 1.2",
                        f"{best_ratio:.2f} .. {worst_ratio:.2f}", met])
    if convergence is not None:
        summary.append(["convergence with no guess (scenes the pixels decide)", "100 %",
                        f"{convergence['rate']:.1f} % of {convergence['decidable']}",
                        "yes" if convergence["rate"] == 100.0 else "NO"])
    if speed is not None:
        ratio = cube_speed["ours calibrate() (f unknown)"] / cube_speed["OpenCV solvePnP SQPNP (K known)"]
        summary += [
            ["calibrate(), 1 camera, 15 markers, 4 joints", "<= 20 ms", f"{speed['median_ms']:.1f} ms",
             "yes" if speed["median_ms"] <= 20.0 else "NO"],
            ["  cube pair: ours (f unknown) vs OpenCV SQPNP (K known)", "-", f"{ratio:.0f}x its time", "-"],
        ]
    if "chessboard" in run and board is None:
        summary.append(["chessboard, one view vs calibrateCamera", "-", "skipped (no opencv-doc)", "-"])
    for side, b in (board or {}).items():
        summary.append([f"chessboard {side}: median f vs OpenCV (same model)", "-", f"{100 * b['median_f']:+.1f} %", "-"])
        summary.append([f"chessboard {side}: median f with k1 vs OpenCV (full)", "-", f"{100 * b['median_f_k1']:+.1f} %", "-"])
        summary.append([f"chessboard {side}: DLT refuses the plane", "refuses", "refuses" if b["dlt_refused"] else "accepts",
                        "yes" if b["dlt_refused"] else "NO"])
    if "aniposelib" in run and anipose is None:
        summary.append(["aniposelib reads our files", "<= 1e-6 px", "skipped", "-"])
    elif anipose is not None:
        worst = max(anipose.values())
        summary.append(["aniposelib reads our files: projection difference", "<= 1e-6 px", f"{worst:.1e} px",
                        "yes" if worst <= 1e-6 else "NO"])
    if starts is not None:
        summary.append([f"cube pair from {starts['starts']} guesses: worst centre off the no-guess fit",
                        f"< {STARTS_BOUND_M:g} m", f"{starts['worst_m']:.1e} m",
                        "yes" if starts["worst_m"] < STARTS_BOUND_M else "NO"])
    print_table(f"Summary ({'quick' if args.quick else 'full'} run, {time.perf_counter() - started:.0f} s wall)",
                ["what", "target", "measured", "met"], summary)
    return 1 if starts is not None and starts["worst_m"] >= STARTS_BOUND_M else 0


if __name__ == "__main__":
    sys.exit(main())
