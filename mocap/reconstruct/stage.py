"""The reconstruction stages: load -> compute -> save -> a short report. The only part of
`mocap.reconstruct` that touches files; the commands only parse options and call these.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from mocap.core.calibration import Calibration
from mocap.core.machine import Machine, Tolerance
from mocap.core.points import Points
from mocap.core.tracks import Tracks
from mocap.errors import InputError, Report
from mocap.io.cameras_toml import load_calibration, save_calibration
from mocap.io.intrinsics import load_intrinsics, with_known_intrinsics
from mocap.io.machine_toml import load_machine, save_machine
from mocap.io.motion_csv import save_motion
from mocap.io.points_csv import save_points
from mocap.io.tracks_csv import load_tracks
from mocap.progress import progress
from mocap.reconstruct.outliers import noise_from_fits
from mocap.reconstruct.timing import on_reference_clock
from mocap.reconstruct.triangulate import TRACK_FRAMES, TriangulateOptions, triangulate_tracks

if TYPE_CHECKING:  # the fit and the refinement are imported by the stages that use them
    from mocap.reconstruct.kinfit import FitOptions
    from mocap.reconstruct.refine import RefineOptions
    from mocap.reconstruct.smooth import SmoothOptions

log = logging.getLogger(__name__)

_CHUNK_FRAMES = 2000  # frames triangulated per batch (memory, progress)
_CHUNK_POINTS = 20_000  # points whose covariance is computed at once (memory: K camera parameters each)
# a fit is partial (exit status 3) when frames no joint values explain make a stretch of a
# second or more, or more than a tenth of the fitted frames: a few scattered ones are not
PARTIAL_STRETCH_S = 1.0
PARTIAL_SHARE = 0.1


def load_inputs(calibration_path, tracks_paths, machine: Machine | None = None):
    """Calibration, tracks and their marker names; raises InputError for cameras or
    markers that do not match."""
    calibration = load_calibration(calibration_path)
    tracks = load_tracks(tracks_paths)
    markers = tracks.checked_against(calibration, machine, calibration_path, ", ".join(map(str, tracks_paths)))
    return calibration, tracks, markers


MAX_NOISE_PX = 5.0  # tracks that lie further than this from any consistent answer: refused
VIEWS_RATIO = 10.0  # views disagreeing this many times beyond the tracks' own noise (and MAX_NOISE_PX): refused
POSE_EXPLAINS = 0.5  # ... or this share of one camera's disagreement explained by moving it a little: refused
DISAGREE_RATIO, DISAGREE_FLOOR_PX = 2.0, 1.0  # views disagreeing beyond both are named in the report


@dataclass(frozen=True)
class Triangulation:
    """`triangulate`'s result: the points and what the report says of them."""

    points: Points
    seen: int  # marker-frames seen by any camera
    contradicted: int  # views dropped that the markers' 3-D tracks contradict
    dropped: int  # pixels dropped that their own tracks contradict
    noise_px: float = float("nan")  # the pixel noise the views imply
    own_noise_px: float = float("nan")  # the noise the 2-D tracks show by themselves

    def report(self, out) -> str:
        points = self.points
        return (
            f"{len(points)} points in {_count_distinct(points.frame)} frames{_written(out)}; "
            f"median reprojection error {np.median(points.error_px):.2f} px; "
            f"{self.seen - len(points)} marker-frames seen by fewer than 2 cameras or by two that disagree"
            + (f"; {self.contradicted} view(s) dropped that the markers' 3-D tracks contradict"
               if self.contradicted else "")
            + _dropped(self.dropped)
            + self._disagreement()
        )

    def _disagreement(self) -> str:
        """The report's warning when the views disagree well beyond the tracks' own noise
        (within what `views_contradiction` refuses): "" otherwise."""
        if not self.noise_px > max(DISAGREE_RATIO * self.own_noise_px, DISAGREE_FLOOR_PX):
            return ""
        return (f"; the views disagree by {self.noise_px:.1f} px, {self.noise_px / self.own_noise_px:.1f} times the "
                f"noise the tracks show by themselves ({self.own_noise_px:.1f} px): points that are not one physical "
                "point in every view (keypoints), or a calibration or clocks a little off; the points' SDs carry it")


def run_triangulate(calibration_path, tracks_paths, out, options: TriangulateOptions,
                    max_noise_px: float | None = None) -> str:
    calibration, tracks, markers = load_inputs(calibration_path, tracks_paths)
    result = triangulate(calibration, tracks, options, max_noise_px, markers, calibration_path)
    save_points(result.points, out)
    return result.report(out)


def triangulate(calibration: Calibration, tracks: Tracks, options: TriangulateOptions = TriangulateOptions(),
                max_noise_px: float | None = None, markers=None, calibration_path=None) -> Triangulation:
    """Every marker in every reference frame seen by `options.min_views` cameras or more.
    `markers`: the names to triangulate (default: the tracks'); `calibration_path` names
    the calibration in messages.

    Refused (InputError) for a contradiction the data show (`views_contradiction`): a
    camera whose disagreement moving it explains, or views that disagree far beyond the
    noise the tracks show by themselves. `max_noise_px`, when given, is the user's own
    limit on the pixel noise the views imply, in place of those checks."""
    if markers is None:
        markers = tracks.checked_against(calibration, None, calibration_path)
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
        rows.append((clock.frame[first + f], np.asarray(markers, dtype=object)[m], part.xyz[f, m], part.error_px[f, m],
                     part.views[f, m], part.used[:, f, m], first + f, m))
        contradicted += int(part.contradicted[own].sum())
    if not sum(len(r[0]) for r in rows):
        raise InputError(
            "no marker is seen by two cameras at the same time; check the time offsets and "
            "that the tracks' camera names match the calibration",
            path=calibration_path,
        )
    points = Points(*(np.concatenate([r[k] for r in rows]) for k in range(5)))
    noise = noise_from_fits(points.error_px**2 * points.views, 2 * points.views - 3)
    if max_noise_px is not None and noise > max_noise_px:
        worst = _worst(points.marker, points.error_px)
        raise InputError(
            f"the cameras' views of the markers disagree by {noise:.1f} px (the pixel noise they imply; most: "
            f"{worst}), beyond --max-noise-px {max_noise_px:g}: the calibration, the time offsets or the labels "
            f"do not match the tracks; nothing written", path=calibration_path)
    from mocap.reconstruct.refine import track_noise

    own_noise = track_noise(clock.pixels)
    at = np.concatenate([r[6] for r in rows]), np.concatenate([r[7] for r in rows])
    views = clock.pixels[:, at[0], at[1]]
    if max_noise_px is None and (why := views_contradiction(cameras, points.xyz, views, noise, own_noise)):
        worst = _worst(points.marker, points.error_px)
        raise InputError(f"{why} (most: {worst}); nothing written", path=calibration_path)
    used = np.concatenate([r[5] for r in rows], axis=1)
    covariance = covariance_of(calibration, calibration_path)
    points = replace(points, sd=_points_sd(cameras, points.xyz, used, noise, covariance))
    seen = int(np.isfinite(clock.pixels[..., 0]).any(0).sum())
    return Triangulation(points, seen, contradicted, clock.dropped, noise, own_noise)


def views_contradiction(cameras, xyz: np.ndarray, pixels: np.ndarray, noise_px: float, own_noise_px: float) -> str:
    """The contradiction the views show, or "": `pixels` (C, N, 2) each camera's view of
    the triangulated points xyz (N, 3) (NaN where unseen), `noise_px` the pixel noise the
    views imply, `own_noise_px` the noise the 2-D tracks show by themselves (`track_noise`).

    Views within MAX_NOISE_PX (the prior, made for painted markers) are never refused.
    Beyond it: a camera whose disagreement a small move of that camera explains
    (POSE_EXPLAINS of its squared distances): the calibration is off; or views that
    disagree VIEWS_RATIO times beyond the tracks' own noise (the calibration, the clocks
    or the labels as a whole). Points that are not one physical point in every view (a body's
    keypoints, each view placing a joint on the outline it sees) disagree by several times
    their jitter, in directions no camera's move explains, and are written with the noise
    they show."""
    if not noise_px > MAX_NOISE_PX:
        return ""
    explained = np.array([_pose_explains(camera, xyz, view) for camera, view in zip(cameras, pixels)])
    moved = [f"{cameras[c].name} ({100 * explained[c]:.0f} %)" for c in np.argsort(-explained)
             if explained[c] >= POSE_EXPLAINS]
    if moved:
        return (f"the cameras' views of the markers disagree by {noise_px:.1f} px (the pixel noise they imply), and "
                f"moving camera {' or '.join(moved)} a little explains that much of its share: the calibration does "
                "not match the tracks (run `mocap refine`, or check it)")
    if np.isfinite(own_noise_px) and noise_px > VIEWS_RATIO * own_noise_px:
        return (f"the cameras' views of the markers disagree by {noise_px:.1f} px (the pixel noise they imply), "
                f"{noise_px / own_noise_px:.0f} times the noise the tracks show by themselves ({own_noise_px:.2f} px): "
                "the calibration, the time offsets or the labels do not match the tracks")
    return ""


def _pose_explains(camera, xyz: np.ndarray, pixels: np.ndarray) -> float:
    """The share (0-1) of the squared distances of `camera`'s pixels (N, 2) from its view
    of the points xyz (N, 3) that a small change of its pose (3 rotations, 3 translations,
    linearised, least squares over every point it sees) explains; 0 where it sees fewer
    than 4 points."""
    from dataclasses import replace as replaced

    from mocap.core.geometry import Rigid, rotvec_to_matrix

    seen = np.isfinite(pixels[:, 0])
    if np.count_nonzero(seen) < 4:
        return 0.0
    xyz, pixels = xyz[seen], pixels[seen]
    pose = camera.cam_from_world
    residual = (pixels - camera.project(xyz)).ravel()
    depth = float(np.median((xyz @ pose.rotation.T + pose.translation)[:, 2]))
    columns = []
    for k in range(6):  # numeric derivatives: 0.1 mrad and 0.1 mm per metre of depth
        step = np.zeros(6)
        step[k] = 1e-4 if k < 3 else 1e-4 * depth
        moved = Rigid(rotvec_to_matrix(step[:3]) @ pose.rotation, pose.translation + step[3:])
        columns.append((replaced(camera, cam_from_world=moved).project(xyz).ravel() - camera.project(xyz).ravel()) / 1e-4)
    jacobian = np.stack(columns, axis=1)
    delta = np.linalg.lstsq(jacobian, residual, rcond=None)[0]
    before = float(residual @ residual)
    after = float(np.sum((residual - jacobian @ delta) ** 2))
    return 1.0 - after / before if before > 0 else 0.0


def _points_sd(cameras, xyz: np.ndarray, used: np.ndarray, noise: float, covariance) -> np.ndarray:
    """(N, 3) each coordinate's SD of the points xyz (N, 3) from their views `used` (C, N):
    the pixel noise's and the calibration's covariance's (None: the pixel noise's alone)."""
    from mocap.reconstruct.camera_share import point_covariance

    sd = np.empty(xyz.shape)
    for start in range(0, len(xyz), _CHUNK_POINTS):
        part = slice(start, start + _CHUNK_POINTS)
        sd[part] = np.sqrt(np.diagonal(point_covariance(cameras, xyz[part], used[:, part], noise, covariance),
                                       axis1=1, axis2=2))
    return sd


def _count_distinct(values: np.ndarray) -> int:
    """The number of distinct values (N,): by their steps where they are sorted (as the
    chunks write them), else by sorting."""
    if len(values) and np.all(values[1:] >= values[:-1]):
        return int(np.count_nonzero(values[1:] != values[:-1])) + 1
    return len(np.unique(values))


@dataclass(frozen=True)
class Fitted:
    """`fit_motion`'s result: the motion, the model it was fitted with (its markers moved by
    the estimated offsets, if any) and the figures of the report."""

    motion: object  # mocap.core.motion.Motion
    machine: Machine
    result: object  # mocap.reconstruct.motion.MotionResult
    ambiguity: str  # the report's sentence on second solutions ("" if none)
    dropped: int  # pixels dropped that their own tracks contradict

    def report(self, out, out_machine=None) -> str:
        result, fit = self.result, self.result.fit
        report = (
            f"{len(result.motion)} frames{_written(out)}; {int(fit.valid.sum())} fitted, "
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
            if out_machine is not None:
                report += f"; the model with its markers there written to {out_machine}"
        check = result.base_check
        if check is not None and check.moves:
            report += (f"; the base moves: a base pose per frame leaves {check.moving_noise_px:.2f} px of noise where "
                       f"the fixed base leaves {check.fixed_noise_px:.2f} px ({check.frames} frames tried; the machine "
                       "bounces, or the cameras moved since the calibration), so it was fitted per frame (columns "
                       "base_*; --fixed-base keeps it fixed)")
        return report + self.ambiguity + _dropped(self.dropped)

    def partial(self, out=None) -> str:
        """One line when a stretch of frames was left unexplained (a run of them lasting
        PARTIAL_STRETCH_S or more, or more than PARTIAL_SHARE of the fitted frames), else ''."""
        fit, motion = self.result.fit, self.result.motion
        unexplained = np.asarray(fit.valid & ~fit.explained, dtype=bool)
        count = int(unexplained.sum())
        if not count:
            return ""
        first, last = _longest_run(unexplained)
        time = np.asarray(motion.time, dtype=float)
        step = float(np.median(np.diff(time))) if len(time) > 1 else 0.0
        seconds = float(time[last] - time[first]) + step
        fitted = max(int(fit.valid.sum()), 1)
        if seconds < PARTIAL_STRETCH_S and count <= PARTIAL_SHARE * fitted:
            return ""
        filled = "; the smoother filled them" if self.result.smoothed is not None else ""
        return (f"{count} of {fitted} fitted frames unexplained (no joint values explain them within the noise), "
                f"the longest stretch frames {int(motion.frame[first])}-{int(motion.frame[last])} ({seconds:.1f} s)"
                f"{filled}; the motion{_written(out)} (column unexplained)")


def _longest_run(flags: np.ndarray) -> tuple[int, int]:
    """First and last index of the longest run of True in `flags` (at least one True)."""
    edges = np.diff(np.r_[0, flags.astype(np.int8), 0])
    starts, ends = np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]
    k = int(np.argmax(ends - starts))
    return int(starts[k]), int(ends[k] - 1)


def run_fit(machine_path, calibration_path, tracks_paths, out, fit_options: FitOptions,
            smooth_options: SmoothOptions | None, max_noise_px: float = MAX_NOISE_PX, out_machine=None,
            choose_base: bool = True) -> str:
    """Fit the machine to the tracks and write the motion; the report line. With
    `choose_base` a fixed base (fit_options) is fitted per frame when the data say it moves."""
    machine = load_machine(machine_path)
    if out_machine is not None and not fit_options.tolerance_of(machine):
        raise InputError("--out-machine needs the markers' tolerance (--tolerance, or `tolerance` in the model file): "
                         "without it the markers are taken as exact and not moved", path=machine_path)
    calibration, tracks = load_calibration(calibration_path), load_tracks(tracks_paths)
    fitted = fit_motion(machine, calibration, tracks, fit_options, smooth_options, max_noise_px, choose_base,
                        calibration_path, ", ".join(map(str, tracks_paths)))
    save_motion(fitted.motion, machine, out)
    if fitted.result.offsets is not None and out_machine is not None:
        save_machine(fitted.machine, out_machine)
    return Report(fitted.report(out, out_machine), fitted.partial(out))


def fit_motion(machine: Machine, calibration: Calibration, tracks: Tracks, fit_options: FitOptions | None = None,
               smooth_options: SmoothOptions | None = None, max_noise_px: float = MAX_NOISE_PX,
               choose_base: bool = True, calibration_path=None, tracks_where=None) -> Fitted:
    """The machine's motion from every camera's tracks: the per-frame fit, smoothed unless
    `smooth_options` is None. The paths name the inputs in messages."""
    from mocap.reconstruct.kinfit import FitOptions
    from mocap.reconstruct.motion import reconstruct_motion

    fit_options = FitOptions() if fit_options is None else fit_options
    if fit_options.tolerance is None and not machine.tolerance:
        fit_options = replace(fit_options, tolerance=estimated_tolerance(calibration))
    markers = tracks.checked_against(calibration, machine, calibration_path, tracks_where)
    clock = on_reference_clock(calibration, tracks, markers, calibration_path)
    if machine.n_joints == 0 and not fit_options.base_motion:
        log.info("%s is rigid (no joints): fitting its pose per frame", machine.name)
        fit_options = replace(fit_options, base_motion=True)
    result = reconstruct_motion(
        machine, list(calibration.cameras), clock.frame, clock.time, clock.pixels,
        fit_options=fit_options, smooth_options=smooth_options, smoothing=smooth_options is not None,
        choose_base=choose_base, camera_covariance=covariance_of(calibration, calibration_path),
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
            f"{max_noise_px:g})", path=tracks_where)
    fitted_machine = machine
    if result.offsets is not None:  # the fit is of the model with its markers moved by them
        fitted_machine = result.offsets.apply(machine)
        fit_options = replace(fit_options, tolerance=Tolerance())
    check = result.base_check
    if check is not None and check.moves:
        fit_options = replace(fit_options, base_motion=True)
    ambiguity = _ambiguity(fitted_machine, list(calibration.cameras), clock.pixels, fit, fit_options)
    return Fitted(result.motion, fitted_machine, result, ambiguity, clock.dropped)


def estimated_tolerance(calibration: Calibration) -> Tolerance | None:
    """The markers' tolerance that calibrate estimated from its residuals where none was
    stated (``estimated_tolerance`` in the calibration's metadata, kept by refine), or None:
    refine and fit use it where neither the command nor the model file states one."""
    fraction = calibration.metadata.get("estimated_tolerance")
    if fraction is None:
        return None
    log.info("the markers' tolerance: %.1f %%, estimated by the calibration (none stated)", 100 * float(fraction))
    return Tolerance(float(fraction))


def covariance_of(calibration: Calibration, path=None):
    """The calibration file's covariance of its cameras (``[metadata.camera_covariance]``,
    as calibrate and refine write it), or None where the file has none."""
    from mocap.reconstruct.camera_share import CameraCovariance

    table = calibration.metadata.get("camera_covariance")
    if table is None:
        return None
    try:
        return CameraCovariance.from_table(table)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"[metadata.camera_covariance] must hold 'parameters' (K names) and 'matrix' (K x K "
                         f"numbers) ({exc}); fix or delete it", path=path) from None


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


def _written(out, comma: str = "") -> str:
    """ " written to OUT" for a report, or nothing for a result kept in memory (out None)."""
    return "" if out is None else f"{comma} written to {out}"


def _dropped(dropped: int) -> str:
    return f"; {dropped} pixel(s) dropped that their own tracks contradict" if dropped else ""


@dataclass(frozen=True)
class Refinement:
    """`refine_cameras`' result: the refined calibration and model, and the refinement's figures."""

    calibration: Calibration
    machine: Machine
    result: object  # mocap.reconstruct.refine.RefineResult
    fixed_intrinsics: frozenset

    def report(self, out_calibration, out_machine=None, before: Machine | None = None) -> str:
        result = self.result
        report = (
            f"cameras refined over {len(result.frames)} frames: residual RMS {result.rms_before:.2f} -> "
            f"{result.rms_after:.2f} px{_written(out_calibration, ',')}; the tracks lie "
            + ", ".join(f"{c.name} {m:.2f}" for c, m in zip(result.cameras, result.median_px))
            + f" px (median) from the refined cameras, noise estimated {result.noise_px:.2f} px per coordinate"
        )
        if result.criterion:
            tried = ", ".join(f"{name} {value:.0f}" for name, value in result.criterion.items())
            report += f"; lens distortion chosen by the data: {result.distortion} (BIC {tried})"
        elif result.distortion != "none":
            report += f"; lens distortion {result.distortion} freed"
        if self.fixed_intrinsics:
            report += f"; intrinsics of {', '.join(sorted(self.fixed_intrinsics))} kept as given"
        if out_machine is not None and before is not None:
            moved = np.linalg.norm(self.machine.marker_positions - before.marker_positions, axis=1)
            report += f"; markers moved by up to {moved.max():.3f} m, model written to {out_machine}"
        return report


def run_refine(machine_path, calibration_path, tracks_paths, out_calibration, out_machine,
               options: RefineOptions, intrinsics_path=None) -> str:
    machine = load_machine(machine_path)
    calibration, tracks = load_calibration(calibration_path), load_tracks(tracks_paths)
    tracks.checked_against(calibration, machine, calibration_path, ", ".join(map(str, tracks_paths)))
    known = load_intrinsics(intrinsics_path) if intrinsics_path is not None else None
    refined = refine_cameras(machine, calibration, tracks, options, known, intrinsics_path, calibration_path,
                             ", ".join(map(str, tracks_paths)))
    save_calibration(refined.calibration, out_calibration)
    if out_machine is not None:
        save_machine(refined.machine, out_machine)
    return refined.report(out_calibration, out_machine, machine)


def refine_cameras(machine: Machine, calibration: Calibration, tracks: Tracks, options: RefineOptions | None = None,
                   known_intrinsics: dict | None = None, intrinsics_path=None, calibration_path=None,
                   tracks_where=None) -> Refinement:
    """Bundle adjustment of the cameras (and, with `options.markers`, the marker positions)
    over the session's frames; `known_intrinsics` {camera: intrinsics} are used and kept."""
    from mocap.reconstruct.refine import RefineOptions, refine

    options = RefineOptions() if options is None else options
    if options.tolerance is None and not machine.tolerance:
        options = replace(options, tolerance=estimated_tolerance(calibration))
    markers = tracks.checked_against(calibration, machine, calibration_path, tracks_where)
    cameras = list(calibration.cameras)
    if known_intrinsics is not None:  # known intrinsics: used and kept
        cameras = with_known_intrinsics(cameras, known_intrinsics, intrinsics_path)
        options = replace(options, fixed_intrinsics=frozenset(c.name for c in cameras if c.name in known_intrinsics))
    clock = on_reference_clock(calibration, tracks, markers, calibration_path)
    result = refine(machine, cameras, clock.pixels, options)
    metadata = {k: v for k, v in calibration.metadata.items() if k != "camera_covariance"}  # the one-frame's
    metadata.update({"refined_frames": int(len(result.frames)), "error": float(result.rms_after)})
    if result.camera_covariance is not None:
        metadata["camera_covariance"] = result.camera_covariance.to_table()
    refined = Calibration(result.cameras, refined_extras(calibration.extras, result), metadata)
    return Refinement(refined, result.machine, result, frozenset(options.fixed_intrinsics))


def refined_extras(extras: tuple[dict, ...], result) -> tuple[dict, ...]:
    """Each camera's table after refine: its residual RMS (`error`), SDs (`sd`) and paper
    view (`paper`) are the refined camera's, from the bundle's residuals and covariance
    (the one-frame calibration's described the camera it started from); the rest (time
    offset, fps, joints) kept."""
    sd_of = {}
    if result.camera_covariance is not None:
        covariance = result.camera_covariance
        sd_of = dict(zip(covariance.names, np.sqrt(np.diag(covariance.matrix)).tolist()))
    tables = []
    for extra, camera, rms in zip(extras, result.cameras, result.rms_px, strict=True):
        own = {name.rsplit(".", 1)[1]: sd for name, sd in sd_of.items() if name.rsplit(".", 1)[0] == camera.name}
        table = {k: v for k, v in extra.items() if k not in ("error", "sd", "paper")}
        table["error"] = rms
        if all(k in own for k in ("rx", "ry", "rz", "tx", "ty", "tz")):
            sd = {"rotation": [own[f"r{a}"] for a in "xyz"], "translation": [own[f"t{a}"] for a in "xyz"]}
            table["sd"] = sd | {"focal_px" if k == "f" else k: v for k, v in own.items() if k[0] not in "rt"}
        paper = camera.to_paper()  # the paper's 7 parameters in file units (degrees, metres, px)
        table["paper"] = {"azimuth_deg": float(np.degrees(paper.azimuth)),
                          "elevation_deg": float(np.degrees(paper.elevation)),
                          "tilt_deg": float(np.degrees(paper.tilt)), "position": paper.position.tolist(),
                          "focal_px": float(paper.focal)}
        tables.append(table)
    return tuple(tables)
