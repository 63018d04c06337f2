"""The reconstruction stages: load -> compute -> save -> a short report. The only part of
`mocap.reconstruct` that touches files; the commands only parse options and call these.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from mocap.errors import InputError
from mocap.io.cameras_toml import Calibration, load_calibration, save_calibration
from mocap.io.intrinsics import load_intrinsics, with_known_intrinsics
from mocap.io.machine_toml import load_machine, save_machine
from mocap.io.motion_csv import save_motion
from mocap.io.points_csv import Points, save_points
from mocap.io.tracks_csv import SPARSE_SPAN, Tracks, check_in_images, load_tracks
from mocap.machine import Machine, Tolerance
from mocap.progress import progress
from mocap.reconstruct.outliers import noise_from_fits
from mocap.reconstruct.timing import Resampled, tracks_on_reference_clock
from mocap.reconstruct.triangulate import TRACK_FRAMES, TriangulateOptions, triangulate_tracks

if TYPE_CHECKING:  # the fit and the refinement are imported by the stages that use them
    from mocap.reconstruct.kinfit import FitOptions
    from mocap.reconstruct.refine import RefineOptions
    from mocap.reconstruct.smooth import SmoothOptions

log = logging.getLogger(__name__)

_CHUNK_FRAMES = 2000  # frames triangulated per batch (memory, progress)


def load_inputs(calibration_path, tracks_paths, machine: Machine | None = None):
    """Calibration, tracks and their marker names; raises InputError for cameras or
    markers that do not match."""
    calibration = load_calibration(calibration_path)
    tracks = load_tracks(tracks_paths)
    if not len(tracks):
        raise InputError("no observations in the tracks file(s)", path=", ".join(map(str, tracks_paths)))
    unknown = sorted(set(tracks.cameras) - set(calibration.names))
    if unknown:
        raise InputError(
            f"tracks name camera(s) {unknown} that the calibration lacks (it has "
            f"{list(calibration.names)}); calibrate them or rename the tracks' camera column",
            path=calibration_path,
        )
    check_in_images(tracks, {c.name: c.size for c in calibration.cameras}, ", ".join(map(str, tracks_paths)))
    if machine is None:
        markers = tracks.markers
    else:
        strange = sorted(set(tracks.markers) - set(machine.marker_names))
        if strange:
            raise InputError(
                f"marker(s) {strange[:5]}{' …' if len(strange) > 5 else ''} are not in the machine "
                f"model {machine.name!r}; check the model or the tracks' marker names",
                path=", ".join(map(str, tracks_paths)),
            )
        markers = machine.marker_names
    return calibration, tracks, markers


def on_reference_clock(calibration: Calibration, tracks: Tracks, markers, path=None) -> Resampled:
    offsets = calibration.time_offsets
    missing_fps = [n for n, e in zip(calibration.names, calibration.extras) if "fps" not in e]
    if missing_fps and np.any(offsets != 0):
        log.warning("camera(s) %s have no fps in the calibration; assuming 30", missing_fps)
    _check_clock_span(calibration, tracks, path)
    return tracks_on_reference_clock(tracks, calibration.names, markers, calibration.fps(), offsets)


def _check_clock_span(calibration: Calibration, tracks: Tracks, path) -> None:
    """The cameras' recordings placed on the reference clock by their time offsets must not
    spread over far more reference frames than they hold (the resampling allocates by the
    span): time offsets hours apart on seconds of tracks are refused."""
    fps, offsets = calibration.fps(), calibration.time_offsets - calibration.time_offsets[0]
    starts, ends, held = [], [], 0
    for name, rate, offset in zip(calibration.names, fps, offsets):
        frames = tracks.frame[tracks.rows_of_camera(name)]
        if len(frames):
            starts.append(frames.min() / rate + offset)
            ends.append(frames.max() / rate + offset)
            held += int(frames.max() - frames.min()) + 1
    span = (max(ends) - max(min(starts), 0.0)) * fps[0] if starts else 0.0
    if span > SPARSE_SPAN and span > 10 * held:
        raise InputError(
            f"the cameras' tracks, placed on the reference clock by their time offsets, spread over "
            f"{span:,.0f} frames but cover {held:,}: check each camera's time_offset and fps", path=path)


MAX_NOISE_PX = 5.0  # tracks that lie further than this from any consistent answer: refused


def run_triangulate(calibration_path, tracks_paths, out, options: TriangulateOptions,
                    max_noise_px: float = MAX_NOISE_PX) -> str:
    calibration, tracks, markers = load_inputs(calibration_path, tracks_paths)
    if options.min_views > len(calibration.cameras):
        raise InputError(f"--min-views {options.min_views}: the calibration has only {len(calibration.cameras)} "
                         "cameras", path=calibration_path)
    clock = on_reference_clock(calibration, tracks, markers, calibration_path)
    cameras = list(calibration.cameras)
    rows, contradicted, n_frames = [], 0, len(clock.frame)
    for start in progress(range(0, n_frames, _CHUNK_FRAMES), desc="triangulate", unit="chunk"):
        # each chunk with the frames its edges' tracks predict from; the points of its own frames kept
        first, stop = max(start - TRACK_FRAMES, 0), min(start + _CHUNK_FRAMES + TRACK_FRAMES, n_frames)
        part = triangulate_tracks(cameras, clock.pixels[:, first:stop], options)
        own = np.arange(start - first, min(start + _CHUNK_FRAMES, n_frames) - first)
        f, m = np.nonzero(np.isfinite(part.xyz[own, :, 0]))
        f = own[f]
        rows.append((clock.frame[first + f], np.asarray(markers, dtype=object)[m], part.xyz[f, m], part.error_px[f, m], part.views[f, m]))
        contradicted += int(part.contradicted[own].sum())
    if not sum(len(r[0]) for r in rows):
        raise InputError(
            "no marker is seen by two cameras at the same time; check the time offsets and "
            "that the tracks' camera names match the calibration",
            path=calibration_path,
        )
    points = Points(*(np.concatenate([r[k] for r in rows]) for k in range(5)))
    noise = noise_from_fits(points.error_px**2 * points.views, 2 * points.views - 3)
    if noise > max_noise_px:
        worst = _worst(points.marker, points.error_px)
        raise InputError(
            f"the cameras' views of the markers disagree by {noise:.1f} px (the pixel noise they imply; most: "
            f"{worst}): the calibration, the time offsets or the labels do not match the tracks; nothing "
            f"written (check them, or raise --max-noise-px {max_noise_px:g})", path=calibration_path)
    save_points(points, out)
    seen = int(np.isfinite(clock.pixels[..., 0]).any(0).sum())
    return (
        f"{len(points)} points in {_count_distinct(points.frame)} frames written to {out}; "
        f"median reprojection error {np.median(points.error_px):.2f} px; "
        f"{seen - len(points)} marker-frames seen by fewer than 2 cameras or by two that disagree"
        + (f"; {contradicted} view(s) dropped that the markers' 3-D tracks contradict" if contradicted else "")
        + _dropped(clock)
    )


def _count_distinct(values: np.ndarray) -> int:
    """The number of distinct values (N,): by their steps where they are sorted (as the
    chunks write them), else by sorting."""
    if len(values) and np.all(values[1:] >= values[:-1]):
        return int(np.count_nonzero(values[1:] != values[:-1])) + 1
    return len(np.unique(values))


def run_fit(machine_path, calibration_path, tracks_paths, out, fit_options: FitOptions,
            smooth_options: SmoothOptions | None, max_noise_px: float = MAX_NOISE_PX, out_machine=None,
            choose_base: bool = True) -> str:
    """Fit the machine to the tracks and write the motion; the report line. With
    `choose_base` a fixed base (fit_options) is fitted per frame when the data say it moves."""
    from mocap.reconstruct.motion import reconstruct_motion

    machine = load_machine(machine_path)
    if out_machine is not None and not fit_options.tolerance_of(machine):
        raise InputError("--out-machine needs the markers' tolerance (--tolerance, or `tolerance` in the model file): "
                         "without it the markers are taken as exact and not moved", path=machine_path)
    calibration, tracks, markers = load_inputs(calibration_path, tracks_paths, machine)
    clock = on_reference_clock(calibration, tracks, markers, calibration_path)
    if machine.n_joints == 0 and not fit_options.base_motion:
        log.info("%s is rigid (no joints): fitting its pose per frame", machine.name)
        fit_options = replace(fit_options, base_motion=True)
    result = reconstruct_motion(
        machine, list(calibration.cameras), clock.frame, clock.time, clock.pixels,
        fit_options=fit_options, smooth_options=smooth_options, smoothing=smooth_options is not None,
        choose_base=choose_base,
    )
    fit = result.fit
    if fit.noise_px > max_noise_px:
        seen = np.isfinite(fit.residuals[..., 0])
        length = np.linalg.norm(np.nan_to_num(fit.residuals), axis=-1)
        camera, _, marker = np.nonzero(seen)
        labels = np.array([f"{calibration.names[c]}:{machine.marker_names[m]}" for c, m in zip(camera, marker)])
        raise InputError(
            f"the tracks lie {fit.noise_px:.1f} px (the pixel noise they imply) from the best pose of the model "
            f"{machine.name!r} (most: {_worst(labels, length[seen])}): the machine model, the labels or the "
            f"calibration do not match the tracks; nothing written (check them, or raise --max-noise-px "
            f"{max_noise_px:g})", path=", ".join(map(str, tracks_paths)))
    save_motion(result.motion, machine, out)
    report = (
        f"{len(result.motion)} frames written to {out}; {int(fit.valid.sum())} fitted, "
        f"median residual {np.nanmedian(fit.rms_px):.2f} px, pixel noise {fit.noise_px:.2f} px"
    )
    unexplained = int((fit.valid & ~fit.explained).sum())
    if unexplained:
        report += (f"; {unexplained} frame(s) that no joint values explain within the noise (column "
                   "unexplained: wrong labels, a wrong model or calibration there; the smoother skips them)")
    if result.smoothed is not None:
        report += f"; {int(result.smoothed.filled.sum())} frames filled by the smoother"
    if result.offsets is not None:  # the fit is of the model with its markers moved by them
        report += _offsets(result.offsets)
        machine = result.offsets.apply(machine)
        if out_machine is not None:
            save_machine(machine, out_machine)
            report += f"; the model with its markers there written to {out_machine}"
        fit_options = replace(fit_options, tolerance=Tolerance())
    check = result.base_check
    if check is not None and check.moves:
        fit_options = replace(fit_options, base_motion=True)
        report += (f"; the base moves: a base pose per frame leaves {check.moving_noise_px:.2f} px of noise where the "
                   f"fixed base leaves {check.fixed_noise_px:.2f} px ({check.frames} frames tried; the machine "
                   "bounces, or the cameras moved since the calibration), so it was fitted per frame (columns "
                   "base_*; --fixed-base keeps it fixed)")
    return report + _ambiguity(machine, list(calibration.cameras), clock.pixels, fit, fit_options) + _dropped(clock)


def _offsets(offsets) -> str:
    """A sentence for the report on the markers' estimated offsets (each is in the log)."""
    size = np.linalg.norm(offsets.offsets, axis=1)
    largest = int(np.argmax(size))
    return (f"; marker offsets estimated over the session ({int(offsets.fixed.sum())} of {len(size)} markers fixed "
            f"by the data, the others kept near their measured positions): largest {size[largest]:.3f} m "
            f"({offsets.names[largest]}, SD {np.linalg.norm(offsets.sd[largest]):.3f} m)")


def _ambiguity(machine: Machine, cameras, pixels, fit, fit_options: FitOptions) -> str:
    """A sentence for the report when sampled frames have a second solution that explains
    their pixels as well as the fit's, far from it (empty otherwise)."""
    from mocap.reconstruct.ambiguity import second_solutions

    found = second_solutions(machine, cameras, pixels, fit, fit_options)
    if not found.ambiguous.any():
        return ""
    frames = np.nonzero(found.ambiguous)[0]
    if machine.point_names:
        apart = np.linalg.norm(machine.points(found.alternative[frames]) - machine.points(fit.joints[frames]), axis=-1)
        gap = f"{machine.point_names[int(np.argmax(apart.max(0)))]} up to {apart.max():.2f} m apart"
    else:
        gap = "markers moved"
    line = (f"; {len(frames)} of {int(found.checked.sum())} frames checked have a second solution that explains the "
            f"pixels as well ({gap}, e.g. frame {frames[0]}): the cameras see too little of the moving links to "
            "tell them apart; add a camera or markers on those links")
    log.warning("%s", line[2:])
    return line


def _worst(names: np.ndarray, errors: np.ndarray, count: int = 3) -> str:
    """The `count` names whose median error is largest, with it: 'cam2:U3 41.0 px, …'."""
    unique, inverse = np.unique(names, return_inverse=True)
    medians = np.array([np.median(errors[inverse == k]) for k in range(len(unique))])
    order = np.argsort(-medians)[:count]
    return ", ".join(f"{unique[k]} {medians[k]:.1f} px" for k in order)


def _dropped(clock: Resampled) -> str:
    return f"; {clock.dropped} pixel(s) dropped that their own tracks contradict" if clock.dropped else ""


def run_refine(machine_path, calibration_path, tracks_paths, out_calibration, out_machine,
               options: RefineOptions, intrinsics_path=None) -> str:
    from mocap.reconstruct.refine import refine

    machine = load_machine(machine_path)
    calibration, tracks, markers = load_inputs(calibration_path, tracks_paths, machine)
    cameras = list(calibration.cameras)
    if intrinsics_path is not None:  # known intrinsics: used and kept
        known = load_intrinsics(intrinsics_path)
        cameras = with_known_intrinsics(cameras, known, intrinsics_path)
        options = replace(options, fixed_intrinsics=frozenset(c.name for c in cameras if c.name in known))
    clock = on_reference_clock(calibration, tracks, markers, calibration_path)
    result = refine(machine, cameras, clock.pixels, options)
    refined = Calibration(result.cameras, calibration.extras, {
        **calibration.metadata, "refined_frames": int(len(result.frames)), "error": float(result.rms_after),
    })
    save_calibration(refined, out_calibration)
    report = (
        f"cameras refined over {len(result.frames)} frames: residual RMS {result.rms_before:.2f} -> "
        f"{result.rms_after:.2f} px, written to {out_calibration}; the tracks lie "
        + ", ".join(f"{c.name} {m:.2f}" for c, m in zip(result.cameras, result.median_px))
        + f" px (median) from the refined cameras, noise estimated {result.noise_px:.2f} px per coordinate"
    )
    if result.criterion:
        tried = ", ".join(f"{name} {value:.0f}" for name, value in result.criterion.items())
        report += f"; lens distortion chosen by the data: {result.distortion} (BIC {tried})"
    elif result.distortion != "none":
        report += f"; lens distortion {result.distortion} freed"
    if options.fixed_intrinsics:
        report += f"; intrinsics of {', '.join(sorted(options.fixed_intrinsics))} kept as given"
    if out_machine is not None:
        save_machine(result.machine, out_machine)
        moved = np.linalg.norm(result.machine.marker_positions - machine.marker_positions, axis=1)
        report += f"; markers moved by up to {moved.max():.3f} m, model written to {out_machine}"
    return report
