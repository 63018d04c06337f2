"""Model-based calibration: cameras and the machine's joint values fitted together.

`calibrate` takes one frame's marker pixels from one or several cameras, finds a starting
point by itself (or takes the user's guess in the paper's parameters), fits all unknowns
with a robust loss, names the outliers, refits without them, checks identifiability and
returns the parameters with their standard deviations.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from mocap.calibration import doubts, identify, noise
from mocap.calibration.context import (
    CalibrationOptions,
    CalibrationResult,
    FitContext,
    Residual,
    robust_cost,
    vector,
)
from mocap.calibration.fit import first_fit, fit, free_parameters
from mocap.calibration.problem import Layout, Observations, Problem
from mocap.calibration.start import (
    chained_start,
    replaced_cameras,
    starting_point,
    swept_joints,
    wild_base_pixels,
    worst_links_markers,
)
from mocap.core.camera import Camera, default_principal_point, intrinsic_matrix
from mocap.core.guess import Guess
from mocap.core.machine import Machine, Tolerance
from mocap.errors import InputError
from mocap.reconstruct.offsets import tape_sd

__all__ = ["CalibrationOptions", "CalibrationResult", "Residual", "calibrate", "template_camera"]

log = logging.getLogger(__name__)


def calibrate(
    machine: Machine,
    observations: Observations,
    templates: list[Camera],
    options: CalibrationOptions = CalibrationOptions(),
    guess: Guess | None = None,
) -> CalibrationResult:
    """Fit cameras and joint values to one frame's marker pixels.

    observations: N rows of (camera index into `templates`, marker index, pixel).
    templates: one Camera per camera giving name and image size (and the principal point
    and distortion used when they are not fitted).

    With no tolerance stated (neither in `options` nor in the model), where the residuals
    show model error (many markers off beyond the pixel noise, more the farther they reach:
    `noise.model_error_fraction`), the tolerance is estimated from them and the frame
    calibrated again within it (`estimated_tolerance` in the result); an explicit
    tolerance, an exact one (``Tolerance()``) too, is used as stated.
    """
    result = _calibrate(machine, observations, templates, options, guess)
    if options.tolerance is not None or machine.tolerance:  # a tolerance stated (an exact model too) wins
        return result
    fraction = _shown_tolerance(machine, observations, templates, options, result)
    if fraction is None:
        return result
    log.info("the residuals show the markers' positions off by about %.1f %% (no tolerance stated): calibrated "
             "again within it", 100 * fraction)
    try:
        again = _calibrate(machine, observations, templates, replace(options, tolerance=Tolerance(fraction)), guess)
    except InputError as failure:
        log.info("the calibration within the estimated tolerance failed (%s): the exact model's kept", failure)
        return result
    return replace(again, estimated_tolerance=fraction)


def _shown_tolerance(machine: Machine, observations: Observations, templates: list[Camera],
                     options: CalibrationOptions, result: CalibrationResult) -> float | None:
    """The tolerance the residuals of an exact model's calibration show
    (`noise.model_error_fraction`), each residual standardised by the share of its variance
    the fit leaves (its leverage among the inliers the fit saw; an outlier's residual is
    from a fit without it)."""
    if result.per_camera:
        return None
    index = {c.name: k for k, c in enumerate(result.cameras)}
    camera = np.array([index[r.camera] for r in result.residuals])
    marker = machine.marker_index([r.marker for r in result.residuals])
    squared = np.array([np.sum(r.residual**2) for r in result.residuals])
    inlier = np.array([not r.outlier for r in result.residuals])
    layout = Layout(len(templates), machine.n_joints, False, options.fit_principal_point, options.distortion,
                    fixed_intrinsics=options.fixed_intrinsics)
    problem = Problem(machine, observations.select(inlier), layout, templates)
    jacobian = problem.jacobian(result.parameters)[:, free_parameters(layout, templates)]
    left = np.ones(len(squared))
    left[inlier] = 1.0 - noise.leverages(jacobian).reshape(-1, 2).mean(axis=1)
    spread = np.linalg.norm(tape_sd(Tolerance(0.5), machine.marker_positions), axis=1) / 0.5 / np.sqrt(3.0)  # (M,) m per axis, a fraction of 1
    depth = np.array([(c.cam_from_world.rotation @ result.markers_world[m] + c.cam_from_world.translation)[2]
                      for c, m in zip((result.cameras[k] for k in camera), marker)])
    focal = np.array([result.cameras[k].focal for k in camera])
    scale = focal * spread[marker] / np.maximum(np.abs(depth), 1e-6)
    return noise.model_error_fraction(squared, scale, marker, options.noise_px, result.sigma_px, left, ~inlier)


def _calibrate(machine, observations, templates, options, guess) -> CalibrationResult:
    names = [t.name for t in templates]
    tolerance = machine.tolerance if options.tolerance is None else options.tolerance
    layout = Layout(
        len(templates), machine.n_joints, options.per_camera, options.fit_principal_point, options.distortion,
        n_markers=len(machine.marker_names) if tolerance else 0, fixed_intrinsics=options.fixed_intrinsics,
    )
    identify.check_counts(
        machine, names, observations.camera, observations.marker, options.per_camera, layout.camera_size
    )
    if guess is not None and guess.cameras:
        missing = [n for n in names if n not in guess.cameras]
        if missing:
            raise InputError(f"the initial guess lacks camera(s) {', '.join(missing)}")
    marker_sd = tape_sd(tolerance, machine.marker_positions) if tolerance else None  # as the fit reads it
    context = FitContext(machine, observations, layout, templates, options, guess, marker_sd)
    x0 = starting_point(context)
    wild = wild_base_pixels(context) if guess is None else []
    try:
        result = _from_start(context, x0)
    except InputError as failure:
        if not wild:
            raise
        result, first_failure = None, failure
    if wild:
        # a wild pixel among a camera's base markers bends its placement, and the start with
        # it: the start is found again without those pixels (the fit still sees them all)
        kept = np.ones(len(observations), dtype=bool)
        kept[wild] = False
        again = starting_point(context.select(kept))
        try:
            other = _from_start(context, again)
        except InputError:
            if result is None:
                raise first_failure from None
            return result
        if result is None or robust_cost(other, options) < robust_cost(result, options):
            log.info("the start without the wild base pixel(s) explains the pixels better: kept")
            result = other
    return result


def _from_start(context: FitContext, x0: np.ndarray) -> CalibrationResult:
    """The calibration from the start x0 (P,), and if it fails, from the joints searched
    again with every camera placed (`start.chained_start`)."""
    try:
        return _calibrated(context, x0)
    except InputError as failure:
        # a camera that sees too few base markers is placed at the joint values the others
        # found alone, which can be far off: the joints are searched again with every camera
        # placed, and those cameras placed again
        again = None if context.guess is not None or context.options.per_camera else chained_start(context, x0)
        if again is None:
            raise
        log.info("the fit from the first start failed (%s); the joints searched again with every camera", failure)
        try:
            return _calibrated(context, again)
        except InputError:
            raise failure from None


def _calibrated(context: FitContext, x0: np.ndarray) -> CalibrationResult:
    """The calibration from the start x0 (P,): the first fit, new starts where it named
    outliers or left residuals above the stated noise; refused (DegenerateError) when a
    camera stays unfixed."""
    options, layout = context.options, context.layout
    result = first_fit(context, x0)
    starts, swept = [], np.zeros(0, int)
    if result.outliers:
        # pixels named outliers may be a wrong minimum's doing: the start is found again
        # without them, and the cameras that lost many are placed again on all their markers
        # at the fitted pose; the fit from each is kept if it explains the pixels better
        kept = np.array([not r.outlier for r in result.residuals])
        starts.append(lambda: starting_point(context.select(kept)))
        doubtful = doubts.doubtful_cameras(result)
        if doubtful:
            starts.append(lambda: layout.pack(replaced_cameras(context, result, doubtful), result.joints))
        swept = context.observations.marker[~kept]
    if result.sigma_px > options.noise_px:
        # residuals above the pixels' stated noise: a joint may sit in a mirror minimum (the
        # cameras' focal lengths and places bent to suit it); that of the link whose markers
        # the fit explains worst is searched across its range
        log.info("residual noise %.2f px above the stated %.2f px: the worst-fitted link's joint searched",
                 result.sigma_px, options.noise_px)
        swept = np.union1d(swept, worst_links_markers(context, result))
    if not result.per_camera:
        starts += swept_joints(context, result, swept)
    for start in starts:
        try:
            again = fit(context, start())
        except (InputError, np.linalg.LinAlgError) as exc:  # a start the solver cannot leave
            log.info("a new start did not converge: %s", exc)
            continue
        if robust_cost(again, options) < robust_cost(result, options):
            log.info("a new start explains the pixels better: kept")
            result = again
    if result.sigma_px > options.noise_px:
        result = _without_worst(context, result)
    if context.marker_sd is not None:  # the offsets can absorb perspective: a weak camera may slide to the orthographic limit
        doubts.refuse_unfixed(result)
    return replace(result, warnings=doubts.warnings(result))


def _without_worst(context: FitContext, result: CalibrationResult, tries: int = 3) -> CalibrationResult:
    """Residuals still above the stated noise after every start: a wrong answer or a wild
    pixel the outlier rule let through (judged against a noise that the wild pixel itself,
    drawing its neighbours off, had raised). The fit without each of the `tries` worst-fitted
    observations in turn; one that this fit predicts beyond the outlier rule (`outlier_px`,
    else 5 sigma and 4 px) is named an outlier where the fit explains all the pixels better
    (robust cost)."""
    observations, options = context.observations, context.options
    error = np.array([-1.0 if r.outlier else np.linalg.norm(r.residual) for r in result.residuals])
    for k in np.argsort(-error)[:tries]:
        if error[k] <= 4.0:
            break
        kept = np.ones(len(observations), dtype=bool)
        kept[k] = False
        try:
            again = fit(context.select(kept), vector(result))
        except (InputError, np.linalg.LinAlgError):  # the others alone do not fix the cameras
            continue
        left_out = context.problem(observations.select(~kept), again.sigma_px)
        residual = left_out.residuals(vector(again))[:2]
        rule = options.outlier_px if options.outlier_px is not None else max(4.0, 5.0 * again.sigma_px)
        if np.linalg.norm(residual) <= rule:
            continue
        residuals = np.empty(len(observations), dtype=object)
        residuals[kept] = again.residuals
        residuals[k] = replace(result.residuals[k], residual=residual, outlier=True)
        merged = replace(again, residuals=tuple(residuals))
        if robust_cost(merged, options, rule) < robust_cost(result, options, rule):
            log.info("camera %s, marker %s: %.1f px from the fit of the others, whose residuals fall to %.2f px "
                     "(from %.2f): an outlier", residuals[k].camera, residuals[k].marker, np.linalg.norm(residual),
                     again.sigma_px, result.sigma_px)
            result = merged
    return result


def template_camera(name: str, size: tuple[int, int]) -> Camera:
    """A camera with only name and size known: principal point at the centre, no distortion."""
    return Camera(name, size, intrinsic_matrix(float(size[0]), default_principal_point(size)))
