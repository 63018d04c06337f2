"""Measurement on machines nobody designed: random articulated machines (0-6 moving links,
revolute and prismatic joints, flipped frames, axes of either sign, 1-4 markers per link)
seen by 1-4 random cameras at 10-90 m, every error divided by its Cramér–Rao bound at the
truth. Prints the distribution of error / bound per stage and the worst scenes.

    .venv/bin/python benchmarks/bench_robustness.py                 # 1000 scenes, a few minutes
    .venv/bin/python benchmarks/bench_robustness.py --scenes 100    # a quicker look

Clean scenes: 0.5 px noise, exact model. Field scenes: 0.8 px, 15 % occlusion, 2 % wild
pixels (10-100 px), every marker coordinate off by up to ±5 % (the paper's tape measure),
the tolerance stated to calibrate and fit; their bound counts that model error (the
markers' offsets marginalised). The peer: a plain least-squares fit (scipy, no robust
loss, no outlier rule, no tolerance) started from the truth perturbed by 2 %.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np
from scipy.optimize import least_squares

from mocap.calibration import CalibrationOptions, calibrate, template_camera
from mocap.calibration.problem import Layout, Problem
from mocap.errors import InputError
from mocap.machine import Tolerance
from mocap.reconstruct.kinfit import FitOptions, fit_joints
from mocap.reconstruct.timing import tracks_on_reference_clock
from mocap.reconstruct.triangulate import triangulate
from mocap.reconstruct.uncertainty import point_quantities
from mocap.synthetic.bounds import calibration_centre_sd, fit_point_sd, triangulation_sd
from mocap.synthetic.machines import SceneOptions, random_scene

FIELD = SceneOptions.field()
FRAMES = 40


def centres_error(cameras, truth) -> np.ndarray:
    return np.array([np.linalg.norm(a.center - b.center) for a, b in zip(cameras, truth)])


def naive_calibration(scene, rng) -> np.ndarray:
    """Camera centre errors of plain least squares from the truth perturbed by 2 %."""
    layout = Layout(len(scene.cameras), scene.machine.n_joints)
    templates = [template_camera(c.name, c.size) for c in scene.cameras]
    truth = layout.pack(list(scene.cameras), scene.joints[0])
    problem = Problem(scene.model, scene.observations(), layout, templates)
    solution = least_squares(problem.residuals, truth * (1 + rng.normal(0, 0.02, truth.shape)), jac=problem.jacobian,
                             x_scale="jac")
    return centres_error(layout.unpack(solution.x, templates)[0], scene.cameras)


def pixels_without_wild(scene) -> np.ndarray:
    good = scene.pixels()
    names = [c.name for c in scene.cameras]
    rows = scene.outlier
    good[[names.index(c) for c in scene.tracks.camera[rows]], scene.tracks.frame[rows],
         scene.machine.marker_index(scene.tracks.marker[rows])] = np.nan
    return good


def on_clock(scene) -> np.ndarray:
    names = [c.name for c in scene.cameras]
    ones = np.ones(len(names))
    return tracks_on_reference_clock(scene.tracks, names, scene.machine.marker_names, 30.0 * ones, 0.0 * ones).pixels


def model_sd(scene) -> np.ndarray | None:
    tolerance = scene.options.tolerance
    return tolerance * np.abs(scene.machine.marker_positions) / np.sqrt(3) if tolerance else None


def one_scene(seed: int, field: bool) -> dict:
    rng = np.random.default_rng(seed)
    options = FIELD if field else SceneOptions()
    scene = random_scene(rng, options, n_frames=FRAMES)
    machine, cameras = scene.machine, list(scene.cameras)
    out = dict(seed=seed, joints=machine.n_joints, cameras=len(cameras), markers=len(machine.marker_names))
    sd = model_sd(scene)
    noise = options.noise_px
    templates = [template_camera(c.name, c.size) for c in cameras]
    calibration_options = CalibrationOptions(tolerance=Tolerance(options.tolerance) if field else None)
    try:
        bound = calibration_centre_sd(machine, cameras, scene.joints[0], scene.observations(inliers_only=True), noise, sd)
        result = calibrate(scene.model, scene.observations(), templates, calibration_options)
        out["calibration"] = float(np.median(centres_error(result.cameras, cameras) / bound))
        out["dropped_good"] = int(sum(r.outlier and not w for r, w in zip(result.residuals, scene.outlier[scene.tracks.frame == 0])))
        if field:
            out["naive_calibration"] = float(np.median(naive_calibration(scene, rng) / bound))
    except InputError as exc:
        out["refused"] = str(exc).split(";")[0][:90]
    if machine.n_joints and machine.point_names:
        fit = fit_joints(scene.model, cameras, on_clock(scene) if field else scene.pixels(),
                         options=FitOptions(tolerance=Tolerance(options.tolerance) if field else None))
        tip = point_quantities(scene.model, np.nan_to_num(fit.joints), fit.covariance)
        error = np.linalg.norm(tip.points[:, 0] - machine.points(scene.joints)[:, 0], axis=1)
        seen = np.isfinite(pixels_without_wild(scene)[..., 0])
        bound = fit_point_sd(machine, cameras, scene.joints, seen, noise, sd)[:, 0]
        out["fit"] = float(np.sqrt(np.mean(error**2) / np.mean(bound**2)))
        out["fit_sds"] = float(np.max(error / tip.points_sd[:, 0]))
        out["unexplained"] = int((~fit.explained).sum())
    if len(cameras) >= 2:
        result = triangulate(cameras, on_clock(scene) if field else scene.pixels())
        truth = machine.markers(scene.joints).reshape(-1, 3)
        seen = np.isfinite(pixels_without_wild(scene)[..., 0]).reshape(len(cameras), -1)
        bound = triangulation_sd(cameras, truth, seen, noise)
        error = np.linalg.norm(result.xyz.reshape(-1, 3) - truth, axis=1)
        ok = np.isfinite(bound) & np.isfinite(error)
        if ok.any():
            out["triangulation"] = float(np.sqrt(np.mean(error[ok] ** 2) / np.mean(bound[ok] ** 2)))
            out["lost_points"] = float(1 - ok.sum() / max(np.isfinite(bound).sum(), 1))
    return out


def distribution(rows: list[dict], key: str) -> list:
    values = np.array([r[key] for r in rows if key in r], dtype=float)
    if not len(values):
        return [key, 0, "", "", "", ""]
    return [key, len(values), f"{np.median(values):.2f}", f"{np.percentile(values, 90):.2f}",
            f"{np.percentile(values, 99):.2f}", f"{values.max():.2f}"]


def table(title: str, header: list[str], rows: list[list]) -> None:
    print(f"\n{title}")
    widths = [max(len(str(x)) for x in column) for column in zip(header, *rows)]
    for row in [header, ["-" * w for w in widths], *rows]:
        print("  ".join(str(x).rjust(w) for x, w in zip(row, widths)))


def report(name: str, rows: list[dict], keys: list[str]) -> None:
    table(f"{name}: {len(rows)} scenes, error / bound", ["stage", "scenes", "median", "90 %", "99 %", "worst"],
          [distribution(rows, k) for k in keys])
    refused = [r for r in rows if "refused" in r]
    print(f"  calibration refused (one clear error, no answer): {len(refused)}")
    for r in refused[:5]:
        print(f"    seed {r['seed']}: {r['cameras']} camera(s), {r['markers']} markers: {r['refused']}")
    print(f"  good observations dropped as outliers by calibrate: {sum(r.get('dropped_good', 0) for r in rows)}")
    print(f"  frames left unexplained by the fit: {sum(r.get('unexplained', 0) for r in rows)}")
    if any("fit_sds" in r for r in rows):
        print(f"  fit: scenes with a frame's tip beyond 5 of its stated SDs: {sum(r.get('fit_sds', 0) > 5 for r in rows)}")
    if any("lost_points" in r for r in rows):
        print(f"  triangulation: share of the points seen twice that were dropped, median "
              f"{100 * np.median([r['lost_points'] for r in rows if 'lost_points' in r]):.1f} %")
    for key in ("calibration", "fit", "triangulation"):
        worst = sorted((r for r in rows if key in r), key=lambda r: -r[key])[:3]
        print(f"  worst {key}: " + "; ".join(
            f"seed {r['seed']} ({r['joints']} joints, {r['cameras']} cameras) {r[key]:.1f}" for r in worst))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", type=int, default=1000, help="random scenes of each kind (default 1000)")
    args = parser.parse_args(argv)
    for field, name, keys in ((False, "Clean scenes", ["calibration", "fit", "fit_sds", "triangulation"]),
                              (True, "Field scenes", ["calibration", "naive_calibration", "fit", "triangulation"])):
        started = time.process_time()
        rows = [one_scene(seed + (10**6 if field else 0), field) for seed in range(args.scenes)]
        report(name, rows, keys)
        print(f"  CPU time {time.process_time() - started:.0f} s")
        if field:
            ours = np.array([r.get("calibration", np.inf) for r in rows])
            naive = np.array([r.get("naive_calibration", np.inf) for r in rows])
            both = np.isfinite(ours) & np.isfinite(naive)
            print(f"  calibration beside the peer (plain least squares from a perturbed truth), median of "
                  f"the ratio ours / peer: {np.median(ours[both] / naive[both]):.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
