"""The calibration's outlier rule: observations whose residual is implausible against the
noise the residuals show, dropped worst first while the rest still fix every unknown."""

from __future__ import annotations

import logging

import numpy as np

from mocap.calibration import identify, noise
from mocap.calibration.context import (
    CalibrationOptions,
    FitContext,
    pixel_errors,
    robust_loss,
    weighed_prior,
)
from mocap.errors import DegenerateError

log = logging.getLogger(__name__)


def suspects(errors: np.ndarray, options: CalibrationOptions) -> np.ndarray:
    """(N,) observations whose residual (px) is implausible: beyond `outlier_px` if given,
    else beyond 5 sigma of the noise the residuals show and beyond 4 px."""
    if options.outlier_px is not None:
        return errors > options.outlier_px
    return errors > max(4.0, 5.0 * noise.robust_sigma(errors))


def without_outliers(context: FitContext, problem, final, x0: np.ndarray, bounds, least_squares_from):
    """A robust fit names the suspects (from x0 (P,) for an exact model; from the fit
    `final` with the markers' offsets, each residual judged with the offsets marginalised),
    they are dropped while the rest stay identifiable, and the least-squares fit repeated
    without them. Returns the problem, its fit and the inliers (N,) bool."""
    options, observations, marker_sd = context.options, context.observations, context.marker_sd
    if marker_sd is None:
        robust = least_squares_from(problem, x0, bounds, loss="soft_l1", f_scale=options.f_scale_px)
        errors = pixel_errors(robust.fun, problem)
        suspect = suspects(errors, options)
    else:
        # outliers judged against the noise with the markers' offsets marginalised: each
        # residual of the robust fit over sqrt(1 - its leverage), the share of its variance
        # the fit leaves; a wild pixel on a marker that only one camera sees is mostly
        # absorbed by that marker's offset, but its residual's variance is then small too
        robust = least_squares_from(problem, final.x, bounds, **robust_loss(problem, options))
        errors, _ = noise.standardised_errors(robust.fun, robust.jac, problem.n_pixel_rows)
        suspect = suspects(errors, options)
    inlier = drop_while_identifiable(context, suspect, errors)
    if np.all(inlier):
        final = least_squares_from(problem, robust.x, bounds)
    else:
        log.info("%d outlier(s) dropped", np.sum(~inlier))
        problem = context.problem(observations.select(inlier), problem.prior_px)
        final = least_squares_from(problem, robust.x, bounds)
    if marker_sd is not None:  # the noise again, without the outliers
        problem, final = weighed_prior(context.select(inlier), final, least_squares_from, bounds)
    return problem, final, inlier


def drop_while_identifiable(context: FitContext, suspect: np.ndarray, errors: np.ndarray) -> np.ndarray:
    """(N,) inliers: the suspects dropped worst first (by `errors` (N,)), each only while
    the rest still satisfy the counts (a camera's fourth base marker stays, its residual
    reported)."""
    machine, observations, layout, names = context.machine, context.observations, context.layout, context.names
    inlier = np.ones(len(observations), dtype=bool)
    for k in np.argsort(-errors):
        if not suspect[k]:
            break
        inlier[k] = False
        kept = observations.select(inlier)
        try:
            identify.check_counts(machine, names, kept.camera, kept.marker, layout.per_camera, layout.camera_size)
        except DegenerateError:
            inlier[k] = True
            log.warning("camera %s, marker %s: residual beyond the noise, kept (the fit needs it)",
                        names[observations.camera[k]], machine.marker_names[observations.marker[k]])
    return inlier
