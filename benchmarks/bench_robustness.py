"""Measurement on machines nobody designed: random articulated machines (0-6 moving links,
revolute and prismatic joints, flipped frames, axes of either sign, 1-4 markers per link)
seen by 1-4 random cameras at 10-90 m, every error divided by its Cramér–Rao bound at the
truth. Prints the distribution of error / bound per stage and the worst scenes.

    .venv/bin/python benchmarks/bench_robustness.py --jobs 2        # 1000 scenes of each kind, ~30 min
    .venv/bin/python benchmarks/bench_robustness.py --scenes 100    # a quicker look
    .venv/bin/python benchmarks/bench_robustness.py --kind field --first 500 --scenes 100 --jobs 2 --rows out.jsonl

Clean scenes: 0.5 px noise, exact model. Field scenes: 0.8 px, 15 % occlusion, 2 % wild
pixels (10-100 px), every marker coordinate off by up to ±5 % (the paper's tape measure),
the tolerance stated to calibrate and fit (with `--unstated` told to neither: the fit uses the
tolerance the calibration estimated, as `mocap refine` and `mocap fit` read it from the
calibration file, and where it estimated none, the paper's ±5 % if the exact model's fit
leaves three markers or more off in every frame, `mocap.reconstruct.offsets.markers_off`,
as `mocap fit` does); their bound counts that model error (the
markers' offsets marginalised). The peer: a plain least-squares fit (scipy, no robust
loss, no outlier rule, no tolerance) started from the truth perturbed by 2 %.

Rows: `calibration` the median over a scene's cameras of centre error / bound, the bound
inverted after scaling (a plain pseudo-inverse drops a far camera's distance);
`calibration_at_bound` what an estimator exactly at the bound would score on the same
scenes (one draw from the bound's covariance: a single camera's error lies along its line
of sight, |N(0, 1)|, 2.58 at 99 %); `calibration_worst_camera` the worst camera's ratio;
`calibration_unflagged` the scenes whose calibration carries no warning (a camera its
markers hardly fix, or one that lost a fifth of its pixels as outliers);
on field scenes `calibration_from_truth` the same calibration given the truth as its
initial guess (where it ends as far off as ours, the error is the estimator's minimum's,
not a start's), `calibration_stated_prior` the same error over the bound with the prior the
calibration is told (the tape tolerance, `mocap.reconstruct.offsets.tape_sd`) and
`calibration_exact_model` over the bound of an exact model (what the offsets cost: the
excess of the first row over this one no estimator removes). A refusal is counted wrong
when every camera's own bound lies below a fifth of its distance (an estimator could place
it). `--calibration-only` skips the fit and the triangulation.
`fit` the tip's RMS error / RMS bound over the frames whose markers show the tip's joints
(on field scenes with the markers' offsets estimated over the scene's frames,
`mocap.reconstruct.offsets`; `fit_weighted_only` the per-frame fit that only weighs the
tolerance, as before);
`fit_unambiguous` the same over the scenes where the fit finds no second solution that
explains the pixels as well (`mocap.reconstruct.ambiguity`; the others are reported by the
fit itself, not hidden); `fit_sds` the worst frame's tip error in its stated SDs.
`triangulation` the markers' RMS error over the RMS bound of their good views, as `mocap
triangulate` makes them (each marker's 3-D track asked, `triangulate_tracks`), and
`triangulation_per_frame` the same per frame alone (`triangulate`);
`triangulation_at_bound` what an estimator exactly at the triangulation bound would score
(one draw of every point's error from its bound covariance). `--triangulation-only` skips
the calibration and the fit; `--wild` and `--occlusion` set the field scenes' shares of
wild pixels and hidden markers:

    .venv/bin/python benchmarks/bench_robustness.py --kind field --scenes 1600 --triangulation-only --jobs 2
    .venv/bin/python benchmarks/bench_robustness.py --kind field --scenes 600 --triangulation-only --wild 0.06 --occlusion 0.3

With `--refined N`, N clean scenes of `REFINED_FRAMES` frames go through the chain a user
runs without surveyed cameras: the one-frame calibration (frame 0), `refine` over the
scene's frames, then the per-frame fit; the tip's RMS error over the bound with the true
cameras, beside the same fit with the true cameras and with the cameras refined from the truth
(what the scene's frames can fix of the cameras at best).

With `--long N`, N clean scenes of `LONG_FRAMES` frames are fitted with the true cameras:
the tip's RMS error over the bound and the frames whose tip lies beyond 5 of its stated SDs
(a stretch of frames on a wrong minimum), beside the peer, a plain per-frame least squares
warm-started from the frame before (the first from the truth), and both fits' times.

    .venv/bin/python benchmarks/bench_robustness.py --scenes 0 --long 40 --jobs 2
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import multiprocessing
import time
from contextlib import nullcontext
from dataclasses import replace

import numpy as np
from scipy.optimize import least_squares

from mocap.calibration import CalibrationOptions, Guess, calibrate, template_camera
from mocap.calibration.problem import Layout, Problem
from mocap.core.camera import project
from mocap.core.machine import Tolerance
from mocap.errors import DegenerateError, InputError
from mocap.reconstruct.ambiguity import second_solutions
from mocap.reconstruct.kinfit import FitOptions, fit_joints
from mocap.reconstruct.offsets import ASSUMED_TOLERANCE, SHOWN_MARKERS, fit_with_offsets, markers_off, tape_sd
from mocap.reconstruct.refine import RefineOptions, refine
from mocap.reconstruct.timing import tracks_on_reference_clock
from mocap.reconstruct.triangulate import triangulate, triangulate_tracks
from mocap.reconstruct.uncertainty import point_quantities
from mocap.synthetic.bounds import calibration_centre_covariance, fit_point_sd, triangulation_covariance
from mocap.synthetic.machines import SceneOptions, random_scene

FIELD = SceneOptions.field()
CALIBRATION_KEYS = ["calibration", "calibration_at_bound", "calibration_worst_camera", "calibration_unflagged"]
FIELD_CALIBRATION_KEYS = [*CALIBRATION_KEYS, "calibration_from_truth", "calibration_stated_prior",
                          "calibration_exact_model"]
TRIANGULATION_KEYS = ["triangulation", "triangulation_per_frame", "triangulation_at_bound"]
CLEAN_KEYS = [*CALIBRATION_KEYS, "fit", "fit_unambiguous", "fit_sds", *TRIANGULATION_KEYS]
FIELD_KEYS = [*FIELD_CALIBRATION_KEYS, "naive_calibration", "fit", "fit_unambiguous", "fit_sds", "fit_weighted_only",
              *TRIANGULATION_KEYS]
FRAMES = 40
REFINED_FRAMES = 120  # a session's refinement sees many frames; 40 leave the cameras a few tenths of the bound
LONG_FRAMES = 3000  # a session's length at which a wrong stretch of frames has room to form
PLACEABLE = 0.2  # a camera whose bound is below this share of its distance can be placed


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


def from_truth(out: dict, scene, templates, options, ours, bound) -> None:
    """The same calibration started from the truth: where it ends in another minimum that
    explains the frame better (a lower residual SD), ours kept a wrong one;
    where it ends as far from the truth as ours, the error is the estimator's own."""
    guess = Guess({c.name: c.to_paper() for c in scene.cameras}, scene.joints[0])
    try:
        other = calibrate(scene.model, scene.observations(), templates, options, guess)
    except InputError:
        return
    out["calibration_from_truth"] = float(np.median(centres_error(other.cameras, scene.cameras) / bound))
    out["from_truth_better_by"] = float(ours.sigma_px / other.sigma_px)


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


def rms_over_bound(error: np.ndarray, bound: np.ndarray) -> float:
    """RMS error over RMS bound (SD) of the same points or frames."""
    return float(np.sqrt(np.mean(error**2) / np.mean(bound**2)))


def at_bound(covariance: np.ndarray, rng) -> float:
    """What an estimator exactly at the bound would score: the median over cameras of one
    draw of each centre's error from its bound covariance (C, 3, 3), over its bound. A
    camera whose error lies along one direction (a single camera's distance) has the tail
    of |N(0, 1)|: 2.58 at 99 %, whatever the estimator."""
    values, vectors = np.linalg.eigh(covariance)
    draws = np.einsum("cij,cj->ci", vectors, np.sqrt(np.maximum(values, 0)) * rng.normal(size=values.shape))
    return float(np.median(np.linalg.norm(draws, axis=1) / np.sqrt(np.trace(covariance, axis1=1, axis2=2))))


def one_scene(seed: int, field: bool, stages: str = "all", field_options: SceneOptions = FIELD,
              stated: bool = True) -> dict:
    """One scene's rows; `stages`: all, calibration or triangulation; `stated`: the field
    scenes' tolerance told to the calibration (else it estimates one where the residuals show it)."""
    rng = np.random.default_rng(seed)
    options = field_options if field else SceneOptions()
    try:
        scene = random_scene(rng, options, n_frames=FRAMES)
    except DegenerateError:  # much occlusion (`--occlusion`) can leave no scene a camera fixes
        return dict(seed=seed, joints=0, cameras=0, markers=0, skipped=True)
    machine, cameras = scene.machine, list(scene.cameras)
    out = dict(seed=seed, joints=machine.n_joints, cameras=len(cameras), markers=len(machine.marker_names))
    sd = model_sd(scene)
    noise = options.noise_px
    if stages == "triangulation":
        return {**out, **triangulation_rows(scene, seed, field, noise)}
    templates = [template_camera(c.name, c.size) for c in cameras]
    calibration_options = CalibrationOptions(tolerance=Tolerance(options.tolerance) if field and stated else None)
    # the fit's tolerance: the stated one, else the one the calibration estimated (as refine and fit read it)
    fit_tolerance = Tolerance(options.tolerance) if field and stated else None
    try:
        covariance = calibration_centre_covariance(machine, cameras, scene.joints[0],
                                                   scene.observations(inliers_only=True), noise, sd)
        bound = np.sqrt(np.trace(covariance, axis1=1, axis2=2))
        distance = np.array([np.linalg.norm(c.center - scene.machine.markers(scene.joints[:1])[0].mean(axis=0))
                             for c in cameras])
        out["bound_over_distance"] = float(np.max(bound / distance))
        result = calibrate(scene.model, scene.observations(), templates, calibration_options)
        ratio = centres_error(result.cameras, cameras) / bound
        out["calibration"] = float(np.median(ratio))
        out["calibration_worst_camera"] = float(np.max(ratio))
        out["calibration_at_bound"] = at_bound(covariance, np.random.default_rng(seed + 7))
        out["flagged"] = len(result.warnings)
        if field and not stated and result.estimated_tolerance is not None:
            fit_tolerance = Tolerance(result.estimated_tolerance)
            out["estimated_tolerance"] = float(result.estimated_tolerance)
        if not result.warnings:
            out["calibration_unflagged"] = out["calibration"]
        out["dropped_good"] = int(sum(r.outlier and not w for r, w in zip(result.residuals, scene.outlier[scene.tracks.frame == 0])))
        if field:
            out["naive_calibration"] = float(np.median(naive_calibration(scene, rng) / bound))
            from_truth(out, scene, templates, calibration_options, result, bound)
            inliers = scene.observations(inliers_only=True)
            for key, prior in (("calibration_stated_prior", tape_sd(Tolerance(options.tolerance),
                                                                    scene.model.marker_positions)),
                               ("calibration_exact_model", None)):
                other = calibration_centre_covariance(machine, cameras, scene.joints[0], inliers, noise, prior)
                out[key] = float(np.median(centres_error(result.cameras, cameras)
                                           / np.sqrt(np.trace(other, axis1=1, axis2=2))))
    except InputError as exc:
        out["refused"] = str(exc).split(";")[0][:90]
    if stages == "calibration":
        return out
    if machine.n_joints and machine.point_names:
        pixels = on_clock(scene) if field else scene.pixels()
        seen = np.isfinite(pixels_without_wild(scene)[..., 0])
        bound = fit_point_sd(machine, cameras, scene.joints, seen, noise, sd)[:, 0]
        shown = np.isfinite(bound)  # frames whose markers show the tip's joints at all
        truth = machine.points(scene.joints)[:, 0]

        def tip_ratio(fit, shared=0.0) -> tuple[float, float]:
            tip = point_quantities(scene.model, np.nan_to_num(fit.joints), fit.covariance + shared)
            error = np.linalg.norm(tip.points[:, 0] - truth, axis=1)
            return (rms_over_bound(error[shown], bound[shown]),
                    float(np.max(error[shown] / tip.points_sd[shown, 0])))

        if field and not fit_tolerance:  # none stated nor estimated: as `mocap fit`, the exact fit's residuals tell
            if markers_off(fit_joints(scene.model, cameras, pixels)).sum() >= SHOWN_MARKERS:
                fit_tolerance = ASSUMED_TOLERANCE
                out["fit_assumed_tolerance"] = True
        fit_options = FitOptions(tolerance=fit_tolerance)
        fitted_model, ambiguity_options = scene.model, fit_options
        if fit_tolerance:  # the markers' offsets estimated over the session; beside it the fit that only weighs them
            weighted = fit_joints(scene.model, cameras, pixels, options=fit_options)
            result = fit_with_offsets(scene.model, cameras, pixels, options=fit_options)
            fit, shared = result.fit, result.shared
            fitted_model = result.offsets.apply(scene.model)
            ambiguity_options = replace(fit_options, tolerance=Tolerance())
            if shown.any():
                out["fit_weighted_only"] = tip_ratio(weighted)[0]
        else:
            fit, shared = fit_joints(scene.model, cameras, pixels, options=fit_options), 0.0
        if shown.any():
            out["fit"], out["fit_sds"] = tip_ratio(fit, shared)
        out["unexplained"] = int((~fit.explained).sum())
        ambiguity = second_solutions(fitted_model, cameras, pixels, fit, ambiguity_options)
        out["fit_ambiguous"] = bool(ambiguity.ambiguous.any())
        if shown.any() and not ambiguity.ambiguous.any():
            out["fit_unambiguous"] = out["fit"]
    return {**out, **triangulation_rows(scene, seed, field, noise)}


def triangulation_rows(scene, seed: int, field: bool, noise: float) -> dict:
    """The markers' RMS error over the bound of the good views, as `mocap triangulate` does
    it (the tracks asked) and per frame alone, what an estimator at the bound scores, and
    the share of the points the good views fix that were dropped."""
    cameras, out = list(scene.cameras), {}
    if len(cameras) < 2:
        return out
    pixels = on_clock(scene) if field else scene.pixels()
    truth = scene.machine.markers(scene.joints).reshape(-1, 3)
    seen = np.isfinite(pixels_without_wild(scene)[..., 0]).reshape(len(cameras), -1)
    covariance = triangulation_covariance(cameras, truth, seen, noise)
    bound = np.sqrt(np.trace(covariance, axis1=1, axis2=2))
    wild = np.isfinite(pixels[..., 0]).reshape(len(cameras), -1) & ~seen
    for key, result in (("triangulation", triangulate_tracks(cameras, pixels)),
                        ("triangulation_per_frame", triangulate(cameras, pixels))):
        error = np.linalg.norm(result.xyz.reshape(-1, 3) - truth, axis=1)
        ok = np.isfinite(bound) & np.isfinite(error)
        if not ok.any():
            return out
        out[key] = rms_over_bound(error[ok], bound[ok])
        out[key + "_wild_kept"] = int((result.used.reshape(len(cameras), -1) & wild & np.isfinite(error)).sum())
        if key == "triangulation":
            values, vectors = np.linalg.eigh(covariance[ok])  # one draw of each point's error at the bound
            draws = np.einsum("nij,nj->ni", vectors, np.sqrt(np.maximum(values, 0))
                              * np.random.default_rng(seed + 11).normal(size=values.shape))
            out["triangulation_at_bound"] = float(np.sqrt(np.mean((draws**2).sum(1)) / np.mean(bound[ok] ** 2)))
            out["lost_points"] = float(1 - ok.sum() / max(np.isfinite(bound).sum(), 1))
            out["contradicted"] = int(result.contradicted.sum())
    return out


def refined_scene(seed: int) -> dict:
    """A clean scene through calibrate (frame 0), refine (every frame) and fit: the tip's
    error over the bound with the true cameras, and the same fit with the true cameras."""
    rng = np.random.default_rng(seed)
    options = SceneOptions()
    scene = random_scene(rng, options, n_frames=REFINED_FRAMES)
    machine, cameras, pixels = scene.machine, list(scene.cameras), scene.pixels()
    out = dict(seed=seed, joints=machine.n_joints, cameras=len(cameras), markers=len(machine.marker_names))
    if not (machine.n_joints and machine.point_names):
        return out
    bound = fit_point_sd(machine, cameras, scene.joints, np.isfinite(pixels[..., 0]), options.noise_px, None)[:, 0]
    shown = np.isfinite(bound)
    truth = machine.points(scene.joints)[:, 0]
    if not shown.any():
        return out

    def tip_ratio(cameras_used) -> float:
        fit = fit_joints(scene.model, cameras_used, pixels)
        error = np.linalg.norm(machine.points(np.nan_to_num(fit.joints))[:, 0] - truth, axis=1)
        return rms_over_bound(error[shown], bound[shown])

    try:
        templates = [template_camera(c.name, c.size) for c in cameras]
        calibrated = list(calibrate(scene.model, scene.observations(), templates, CalibrationOptions()).cameras)
        refined = list(refine(scene.model, calibrated, pixels, RefineOptions(frames=REFINED_FRAMES)).cameras)
    except InputError as exc:
        out["refused"] = str(exc).split(";")[0][:90]
        return out
    out["fit_known_cameras"] = tip_ratio(cameras)
    out["fit_calibrated"] = tip_ratio(calibrated)
    out["fit_refined"] = tip_ratio(refined)
    out["fit_refined_over_known"] = out["fit_refined"] / out["fit_known_cameras"]
    # the same refinement started from the true cameras: where it ends as far, the frames do not fix the cameras better
    out["fit_refined_from_truth"] = tip_ratio(list(refine(scene.model, cameras, pixels,
                                                          RefineOptions(frames=REFINED_FRAMES)).cameras))
    return out


def naive_per_frame_fit(machine, cameras, pixels: np.ndarray, start: np.ndarray) -> np.ndarray:
    """The peer of the fit: plain least squares (scipy, no robust loss, no restart) frame by
    frame, each frame started from the previous frame's solution, the first from `start`."""
    joints = np.empty((pixels.shape[1], machine.n_joints))
    q = start
    for f in range(pixels.shape[1]):
        seen = np.isfinite(pixels[:, f, :, 0])
        if seen.any():
            def residuals(x, seen=seen, f=f):
                return (project(cameras, machine.markers(x[None])[0])[seen] - pixels[:, f][seen]).ravel()
            q = least_squares(residuals, q, x_scale="jac").x
        joints[f] = q
    return joints


def long_session(seed: int) -> dict:
    """A clean scene of `LONG_FRAMES` frames fitted with the true cameras: the tip's RMS error
    over the bound, the frames whose tip lies beyond 5 of its stated SDs (a wrong stretch),
    the fit's time; beside the peer, a per-frame least squares warm-started from the frame before."""
    rng = np.random.default_rng(seed)
    scene = random_scene(rng, SceneOptions(), n_frames=LONG_FRAMES)
    machine, cameras, pixels = scene.machine, list(scene.cameras), scene.pixels()
    out = dict(seed=seed, joints=machine.n_joints, cameras=len(cameras), markers=len(machine.marker_names))
    if not (machine.n_joints and machine.point_names):
        return out
    bound = fit_point_sd(machine, cameras, scene.joints, np.isfinite(pixels[..., 0]), scene.options.noise_px, None)[:, 0]
    shown = np.isfinite(bound)
    if not shown.any():
        return out
    truth = machine.points(scene.joints)[:, 0]

    def ratio(joints) -> float:
        error = np.linalg.norm(machine.points(np.nan_to_num(joints))[:, 0] - truth, axis=1)
        return rms_over_bound(error[shown], bound[shown])

    started = time.perf_counter()
    fit = fit_joints(scene.model, cameras, pixels)
    out["long_fit_seconds"] = time.perf_counter() - started
    out["long_fit"] = ratio(fit.joints)
    tip = point_quantities(scene.model, np.nan_to_num(fit.joints), fit.covariance)
    error = np.linalg.norm(tip.points[:, 0] - truth, axis=1)
    out["long_frames_beyond_5sd"] = int((error[shown] > 5 * tip.points_sd[shown, 0]).sum())
    started = time.perf_counter()
    naive = naive_per_frame_fit(machine, cameras, pixels, scene.joints[0])
    out["long_naive_seconds"] = time.perf_counter() - started
    out["long_naive"] = ratio(naive)
    return out


def distribution(rows: list[dict], key: str) -> list:
    values = np.array([r[key] for r in rows if key in r], dtype=float)
    values = values[~np.isnan(values)]  # a frame whose fit states no SD (nothing seen) has no ratio
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
    """The stages the rows hold (`--calibration-only` and `--triangulation-only` hold one)."""
    if any(r.get("skipped") for r in rows):
        print(f"\n{name}: {sum(r.get('skipped', False) for r in rows)} seeds drew no scene a camera fixes (skipped)")
        rows = [r for r in rows if not r.get("skipped")]
    table(f"{name}: {len(rows)} scenes, error / bound", ["stage", "scenes", "median", "90 %", "99 %", "worst"],
          [d for d in (distribution(rows, k) for k in keys) if d[1]])
    if any("calibration" in r or "refused" in r for r in rows):
        refused = [r for r in rows if "refused" in r]
        placeable = [r for r in refused if r.get("bound_over_distance", np.inf) < PLACEABLE]
        print(f"  calibration refused (one clear error, no answer): {len(refused)}, of which {len(placeable)} wrongly "
              f"(every camera's own bound below {PLACEABLE} of its distance: an estimator could place it)")
        for r in placeable + [r for r in refused if r not in placeable][:max(0, 5 - len(placeable))]:
            print(f"    seed {r['seed']}: {r['cameras']} camera(s), {r['markers']} markers, worst bound / distance "
                  f"{r.get('bound_over_distance', np.nan):.2f}: {r['refused']}")
        print(f"  good observations dropped as outliers by calibrate: {sum(r.get('dropped_good', 0) for r in rows)}")
        print(f"  calibrations returned with a warning (a camera hardly fixed or doubtful): "
              f"{sum(r.get('flagged', 0) > 0 for r in rows)}")
    if any("fit_ambiguous" in r for r in rows):
        print(f"  frames left unexplained by the fit: {sum(r.get('unexplained', 0) for r in rows)}")
        print(f"  fits the fit itself calls ambiguous (a second solution as good, far away): "
              f"{sum(r.get('fit_ambiguous', False) for r in rows)} of {sum('fit_ambiguous' in r for r in rows)}")
    if any("fit_sds" in r for r in rows):
        print(f"  fit: scenes with a frame's tip beyond 5 of its stated SDs: {sum(r.get('fit_sds', 0) > 5 for r in rows)}")
    if any("lost_points" in r for r in rows):
        print(f"  triangulation: share of the points seen twice that were dropped, median "
              f"{100 * np.median([r['lost_points'] for r in rows if 'lost_points' in r]):.1f} %; views the "
              f"markers' 3-D tracks contradicted {sum(r.get('contradicted', 0) for r in rows)}; wild views kept "
              f"{sum(r.get('triangulation_wild_kept', 0) for r in rows)} (per frame alone "
              f"{sum(r.get('triangulation_per_frame_wild_kept', 0) for r in rows)})")
    for key in ("calibration", "fit", "triangulation", "triangulation_per_frame"):
        worst = sorted((r for r in rows if key in r), key=lambda r: -r[key])[:3]
        if worst:
            print(f"  worst {key}: " + "; ".join(
                f"seed {r['seed']} ({r['joints']} joints, {r['cameras']} cameras) {r[key]:.1f}" for r in worst))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", type=int, default=1000, help="random scenes of each kind (default 1000)")
    parser.add_argument("--kind", choices=("both", "clean", "field"), default="both", help="which scenes (default both)")
    parser.add_argument("--first", type=int, default=0, help="the first scene's seed (default 0)")
    parser.add_argument("--jobs", type=int, default=1, help="processes to run scenes in (default 1)")
    parser.add_argument("--calibration-only", action="store_true", help="only the one-frame calibration (quicker)")
    parser.add_argument("--triangulation-only", action="store_true", help="only the triangulation (seconds for 1,000 scenes)")
    parser.add_argument("--wild", type=float, default=FIELD.outliers,
                        help=f"field scenes' share of wild pixels (default {FIELD.outliers:g})")
    parser.add_argument("--occlusion", type=float, default=FIELD.occlusion,
                        help=f"field scenes' share of hidden markers (default {FIELD.occlusion:g})")
    parser.add_argument("--unstated", action="store_true",
                        help="field scenes' tolerance not told to the calibration (it estimates one from the "
                        "residuals) nor to the fit (it uses the calibration's estimate)")
    parser.add_argument("--rows", help="also write every scene's figures to this file (JSON lines)")
    parser.add_argument("--refined", type=int, default=0, metavar="N",
                        help="also N clean scenes through calibrate, refine and fit (default 0)")
    parser.add_argument("--long", type=int, default=0, metavar="N",
                        help=f"also N clean scenes of {LONG_FRAMES} frames fitted with the true cameras (default 0)")
    args = parser.parse_args(argv)
    if args.calibration_only and args.triangulation_only:
        parser.error("--calibration-only and --triangulation-only: choose one")
    stages = "calibration" if args.calibration_only else "triangulation" if args.triangulation_only else "all"
    field_options = replace(FIELD, outliers=args.wild, occlusion=args.occlusion)
    logging.getLogger("mocap").setLevel(logging.ERROR)  # the warnings are counted in the table instead
    kinds = [k for k in ((False, "Clean scenes", CLEAN_KEYS), (True, "Field scenes", FIELD_KEYS))
             if args.scenes and args.kind in ("both", "field" if k[0] else "clean")]
    everything = []
    for field, name, keys in kinds:
        started = time.perf_counter()
        seeds = [seed + (10**6 if field else 0) for seed in range(args.first, args.first + args.scenes)]
        with multiprocessing.Pool(args.jobs) if args.jobs > 1 else nullcontext() as pool:
            rows = (pool.starmap if pool else itertools.starmap)(
                one_scene, [(seed, field, stages, field_options, not args.unstated) for seed in seeds])
            rows = list(rows)
        everything += rows
        report(name, rows, keys)
        print(f"  wall time {time.perf_counter() - started:.0f} s ({args.jobs} process(es))")
        if field and stages != "triangulation":
            ours = np.array([r.get("calibration", np.inf) for r in rows])
            naive = np.array([r.get("naive_calibration", np.inf) for r in rows])
            both = np.isfinite(ours) & np.isfinite(naive)
            print(f"  calibration beside the peer (plain least squares from a perturbed truth), median of "
                  f"the ratio ours / peer: {np.median(ours[both] / naive[both]):.2f}")
            started_right = [r for r in rows if "calibration_from_truth" in r and "calibration" in r]
            print(f"  calibration started from the truth: {len(started_right)} scenes; ours beyond 1.5 of the bound: "
                  f"{sum(r['calibration'] > 1.5 for r in started_right)}, from the truth: "
                  f"{sum(r['calibration_from_truth'] > 1.5 for r in started_right)}; scenes where the truth's start "
                  f"ends nearer the truth and explains the frame better (residual SD 5 % lower): "
                  f"{sum(r['calibration_from_truth'] < r['calibration'] and r['from_truth_better_by'] > 1.05 for r in started_right)}")
    if args.refined:
        started = time.perf_counter()
        with multiprocessing.Pool(args.jobs) if args.jobs > 1 else nullcontext() as pool:
            rows = list((pool.map if pool else map)(refined_scene, range(args.first, args.first + args.refined)))
        everything += rows
        table(f"One-frame calibration, refined over {REFINED_FRAMES} frames, then fit: {len(rows)} clean scenes, "
              "tip error / bound with the true cameras", ["stage", "scenes", "median", "90 %", "99 %", "worst"],
              [distribution(rows, k) for k in ("fit_known_cameras", "fit_calibrated", "fit_refined",
                                                "fit_refined_over_known", "fit_refined_from_truth")])
        refused = [r for r in rows if "refused" in r]
        print(f"  calibration or refinement refused: {len(refused)}")
        worst = sorted((r for r in rows if "fit_refined" in r), key=lambda r: -r["fit_refined"])[:3]
        print("  worst refined: " + "; ".join(f"seed {r['seed']} ({r['joints']} joints, {r['cameras']} cameras) "
                                               f"{r['fit_refined']:.2f}" for r in worst))
        print(f"  wall time {time.perf_counter() - started:.0f} s ({args.jobs} process(es))")
    if args.long:
        started = time.perf_counter()
        with multiprocessing.Pool(args.jobs) if args.jobs > 1 else nullcontext() as pool:
            rows = list((pool.map if pool else map)(long_session, range(args.first, args.first + args.long)))
        everything += rows
        table(f"Sessions of {LONG_FRAMES} frames, true cameras: {len(rows)} clean scenes, tip error / bound",
              ["stage", "scenes", "median", "90 %", "99 %", "worst"],
              [distribution(rows, k) for k in ("long_fit", "long_naive", "long_frames_beyond_5sd")])
        fitted = [r for r in rows if "long_fit" in r]
        print(f"  scenes with a frame beyond 5 SDs: {sum(r['long_frames_beyond_5sd'] > 0 for r in fitted)} of "
              f"{len(fitted)}; beyond 1.3 times the bound: ours {sum(r['long_fit'] > 1.3 for r in fitted)}, "
              f"peer {sum(r['long_naive'] > 1.3 for r in fitted)}")
        print(f"  fit time per session, median: ours {np.median([r['long_fit_seconds'] for r in fitted]):.2f} s, peer "
              f"{np.median([r['long_naive_seconds'] for r in fitted]):.1f} s (ratio peer / ours "
              f"{np.median([r['long_naive_seconds'] / r['long_fit_seconds'] for r in fitted]):.0f})")
        worst = sorted(fitted, key=lambda r: -r["long_fit"])[:3]
        print("  worst: " + "; ".join(f"seed {r['seed']} ({r['joints']} joints, {r['cameras']} cameras) "
                                      f"{r['long_fit']:.2f} ({r['long_frames_beyond_5sd']} frames beyond 5 SDs)"
                                      for r in worst))
        print(f"  wall time {time.perf_counter() - started:.0f} s ({args.jobs} process(es))")
    if args.rows:
        with open(args.rows, "w") as out:
            out.writelines(json.dumps(r) + "\n" for r in everything)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
