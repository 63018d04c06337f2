"""Are the fit's stated SDs honest? The bucket tip's error over its stated SD (RMS over a
scene's frames, then over scenes) with the true cameras, the one-frame calibration (frame 0)
and that calibration refined over the scene's frames, on random clean and field scenes.
An honest SD scores 1; a camera's error is common to a scene's frames, so each scene gives
one ratio, and the RMS over a dozen scenes is uncertain by a few tenths (the column
`RMS 90 %`, by resampling the scenes); on field scenes most of a scene's error is the
markers' offsets', common to its frames, and a hundred scenes tell an honest SD within
±0.1. `with camera covariance` adds the calibration's covariance to the fit's
(mocap.reconstruct.camera_share), `pixel noise only` is the fit's covariance alone.
The triangulation's columns do the same for the markers' points as `mocap triangulate`
makes them (`triangulate_tracks`, the pixel noise estimated from the points' residuals):
the RMS over a scene's points and coordinates of error / stated SD, with the cameras'
covariance propagated through the triangulation (`point_covariance`) and without.

    .venv/bin/python benchmarks/bench_honesty.py --scenes 8
    .venv/bin/python benchmarks/bench_honesty.py --scenes 8 --kind field --no-refine
    .venv/bin/python benchmarks/bench_honesty.py --scenes 100 --kind field --true-only --jobs 2
"""

from __future__ import annotations

import argparse
import logging
import multiprocessing

import numpy as np

from mocap.calibration import CalibrationOptions, calibrate, template_camera
from mocap.core.machine import Tolerance
from mocap.errors import DegenerateError, InputError
from mocap.reconstruct.camera_share import CameraCovariance, camera_share, point_covariance
from mocap.reconstruct.kinfit import FitOptions, fit_joints
from mocap.reconstruct.offsets import fit_with_offsets
from mocap.reconstruct.outliers import noise_from_fits
from mocap.reconstruct.refine import RefineOptions, refine
from mocap.reconstruct.timing import tracks_on_reference_clock
from mocap.reconstruct.triangulate import triangulate_tracks
from mocap.reconstruct.uncertainty import point_quantities
from mocap.synthetic.machines import SceneOptions, random_scene

FRAMES = 40


def on_clock(scene) -> np.ndarray:
    names = [c.name for c in scene.cameras]
    ones = np.ones(len(names))
    return tracks_on_reference_clock(scene.tracks, names, scene.machine.marker_names, 30.0 * ones, 0.0 * ones).pixels


def one_scene(seed: int, field: bool, with_refine: bool, calibrated: bool = True) -> dict:
    rng = np.random.default_rng(seed)
    options = SceneOptions.field() if field else SceneOptions()
    try:
        scene = random_scene(rng, options, n_frames=FRAMES)
    except DegenerateError:
        return {"seed": seed}
    machine, cameras = scene.machine, list(scene.cameras)
    out = {"seed": seed, "cameras": len(cameras)}
    if not (machine.n_joints and machine.point_names):
        return out
    pixels = on_clock(scene) if field else scene.pixels()
    truth = machine.points(scene.joints)[:, 0]
    tolerance = Tolerance(options.tolerance) if field else None
    fit_options = FitOptions(tolerance=tolerance)

    def ratios(key: str, cameras_used, covariance: CameraCovariance | None, model=scene.model,
               estimated: bool = False) -> None:
        if estimated:  # the markers estimated with the cameras: their uncertainty is in the covariance
            fit = fit_joints(model, cameras_used, pixels, options=FitOptions(tolerance=Tolerance()))
            shared, fitted = 0.0, model
        elif field:
            result = fit_with_offsets(model, cameras_used, pixels, options=fit_options)
            fit, shared, fitted = result.fit, result.shared, result.offsets.apply(model)
        else:
            fit, shared, fitted = fit_joints(model, cameras_used, pixels, options=fit_options), 0.0, model
        ok = fit.valid & fit.explained
        for suffix, extra in (("", camera_share(fitted, cameras_used, fit, covariance)), ("_pixels", 0.0)):
            tip = point_quantities(scene.model, np.nan_to_num(fit.joints), fit.covariance + shared + extra)
            error = np.linalg.norm(tip.points[:, 0] - truth, axis=1)
            z = (error / tip.points_sd[:, 0])[ok]
            z = z[np.isfinite(z)]
            if len(z):
                out[key + suffix] = float(np.sqrt(np.mean(z**2)))

    def triangulated(key: str, cameras_used, covariance: CameraCovariance | None) -> None:
        if len(cameras_used) < 2:
            return
        points = triangulate_tracks(cameras_used, pixels)
        xyz, used = points.xyz.reshape(-1, 3), points.used.reshape(len(cameras_used), -1)
        ok = np.isfinite(xyz[:, 0])
        if not ok.any():
            return
        views, error = points.views.reshape(-1)[ok], points.error_px.reshape(-1)[ok]
        noise = noise_from_fits(error**2 * views, 2 * views - 3)
        truth = machine.markers(scene.joints).reshape(-1, 3)[ok]
        for suffix, carried in (("", covariance), ("_pixels", None)):
            spread = point_covariance(cameras_used, xyz[ok], used[:, ok], noise, carried)
            z = (xyz[ok] - truth) / np.sqrt(np.diagonal(spread, axis1=1, axis2=2))
            out["points_" + key + suffix] = float(np.sqrt(np.mean(z[np.isfinite(z)] ** 2)))

    ratios("true", cameras, None)
    triangulated("true", cameras, None)
    if not calibrated:
        return out
    try:
        templates = [template_camera(c.name, c.size) for c in cameras]
        result = calibrate(scene.model, scene.observations(), templates, CalibrationOptions(tolerance=tolerance))
    except InputError as exc:
        out["refused"] = str(exc)[:80]
        return out
    covariance = CameraCovariance.of_cameras(result.parameter_names, result.covariance, result.cameras)
    ratios("one_frame", list(result.cameras), covariance)
    triangulated("one_frame", list(result.cameras), covariance)
    if with_refine:
        try:
            refined = refine(scene.model, list(result.cameras), pixels, RefineOptions(frames=FRAMES, tolerance=tolerance))
        except InputError as exc:
            out["refine_refused"] = str(exc)[:80]
            return out
        ratios("refined", list(refined.cameras), refined.camera_covariance, refined.machine, field)
        triangulated("refined", list(refined.cameras), refined.camera_covariance)
    return out


def interval(values: np.ndarray, draws: int = 2000) -> tuple[float, float]:
    """The 90 % interval of the RMS over scenes, by resampling the scenes (bootstrap): a
    scene's ratio is one draw of the error common to its frames (its cameras', its markers'
    offsets), so a dozen scenes leave the RMS uncertain by a few tenths."""
    picks = np.random.default_rng(0).integers(0, len(values), (draws, len(values)))
    rms = np.sqrt(np.mean(values[picks] ** 2, axis=1))
    return float(np.percentile(rms, 5)), float(np.percentile(rms, 95))


def row(name: str, values: list[float]) -> str:
    v = np.array([x for x in values if np.isfinite(x)])
    if not len(v):
        return f"{name:<34} {'-':>6}"
    low, high = interval(v)
    return (f"{name:<34} {len(v):>6} {np.median(v):>8.2f} {np.percentile(v, 90):>8.2f} {np.sqrt(np.mean(v**2)):>8.2f}"
            f" {f'{low:.2f}-{high:.2f}':>10} {np.mean((v >= 0.8) & (v <= 1.25)):>8.0%}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=8)
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--kind", choices=("clean", "field"), default="clean")
    parser.add_argument("--no-refine", action="store_true")
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument("--rows", action="store_true", help="also print every scene's ratios")
    parser.add_argument("--true-only", action="store_true", help="only the true cameras (quick: many scenes)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    seeds = range(args.first, args.first + args.scenes)
    jobs = [(s, args.kind == "field", not args.no_refine, not args.true_only) for s in seeds]
    if args.jobs > 1:
        with multiprocessing.Pool(args.jobs) as pool:
            rows = pool.starmap(one_scene, jobs)
    else:
        rows = [one_scene(*j) for j in jobs]
    print(f"bucket tip: RMS over a scene's frames of error / stated SD; {args.kind} scenes, seeds {seeds.start}-{seeds.stop - 1}")
    print(f"{'cameras, SDs':<34} {'scenes':>6} {'median':>8} {'p90':>8} {'RMS':>8} {'RMS 90 %':>10} {'in 0.8-1.25':>8}")
    for key, label in (("true", "true"), ("one_frame", "one-frame"), ("refined", "refined")):
        print(row(f"{label}, with camera covariance", [r.get(key, np.nan) for r in rows]))
        print(row(f"{label}, pixel noise only", [r.get(key + "_pixels", np.nan) for r in rows]))
    print(f"\nmarkers' points (mocap triangulate): RMS over a scene's points and coordinates of error / stated SD")
    print(f"{'cameras, SDs':<34} {'scenes':>6} {'median':>8} {'p90':>8} {'RMS':>8} {'RMS 90 %':>10} {'in 0.8-1.25':>8}")
    for key, label in (("true", "true"), ("one_frame", "one-frame"), ("refined", "refined")):
        print(row(f"{label}, with camera covariance", [r.get("points_" + key, np.nan) for r in rows]))
        print(row(f"{label}, pixel noise only", [r.get("points_" + key + "_pixels", np.nan) for r in rows]))
    if args.rows:
        print(f"\nper scene (bucket tip, with camera covariance): seed, cameras, true, one-frame, refined")
        for r in rows:
            if any(k in r for k in ("true", "one_frame", "refined")):
                print(f"  {r['seed']:>5} {r['cameras']:>2} " + " ".join(f"{r.get(k, np.nan):6.2f}"
                                                                 for k in ("true", "one_frame", "refined")))
    for r in rows:
        if "refused" in r or "refine_refused" in r:
            print(f"seed {r['seed']}: {r.get('refused') or r.get('refine_refused')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
