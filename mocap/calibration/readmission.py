"""Observations the outlier rule dropped taken back where the fit of the others predicts
them within the rule: a wild pixel's pull on the robust fit can make its neighbours look
wild too."""

from __future__ import annotations

import logging

import numpy as np

from mocap.calibration import identify, noise
from mocap.calibration.context import CalibrationOptions, FitContext, max_rms, pixel_rms, weighed_prior
from mocap.calibration.problem import Problem

log = logging.getLogger(__name__)


def readmit(context: FitContext, problem: Problem, final, inlier: np.ndarray, free: np.ndarray, bounds,
            least_squares_from):
    """The dropped observations (`inlier` (N,) False) that the fit `final` of the others
    predicts within the outlier rule taken back, the best predicted first; with the
    markers' offsets each alone, and kept only where the posterior of all the pixels
    prefers it. Returns the problem, its fit and the inliers."""
    observations, options, marker_sd = context.observations, context.options, context.marker_sd
    over = readmitted(problem, context.problem(observations.select(~inlier), problem.prior_px), final, free, options)
    if not ((over <= 1.0).any() and pixel_rms(final.fun, problem) <= max_rms(options, context.templates)):
        return problem, final, inlier
    before = inlier.copy()
    back = np.flatnonzero(~inlier)[np.argsort(over)][: np.sum(over <= 1.0)]  # the best predicted first
    whole = context.problem()
    # with the offsets, each one taken back alone and kept only where the posterior of all
    # the pixels prefers it: a wild pixel whose marker few cameras see is predicted loosely
    # (its offset free within the prior); taken back, it can draw a weak camera along its
    # valley, and taken back with a good one, the good one's gain hid its cost
    for group in [back] if marker_sd is None else back[:, None]:
        trial = inlier.copy()
        trial[group] = True
        p = context.problem(observations.select(trial), problem.prior_px)
        f = least_squares_from(p, final.x, bounds)
        if marker_sd is not None:
            p, f = weighed_prior(context.select(trial), f, least_squares_from, bounds)
            if posterior(whole, f.x, options) > posterior(whole, final.x, options):
                continue
        problem, final, inlier = p, f, trial
    if not np.array_equal(inlier, before):
        log.info("%d observation(s) named outliers agree with the fit without them: kept",
                 np.sum(inlier & ~before))
    return problem, final, inlier


def readmitted(problem: Problem, dropped: Problem, final, free: np.ndarray, options: CalibrationOptions) -> np.ndarray:
    """(D,) how far the fit `final` of the others predicts each dropped observation (the
    problem `dropped`, at the prior weight of `problem`), over the outlier rule's threshold
    (at most 1: within the rule, to be taken back): each residual over sqrt(1 + its
    leverage) (the variance of a pixel the fit did not see is the noise plus the fit's own
    uncertainty projected), against the threshold that the kept observations' standardised
    residuals give (to first order the statistic by which it was dropped, sqrt(1 - leverage)
    for a fitted residual, without the wild pixels' pull)."""
    n = dropped.n_pixel_rows
    if not n:
        return np.zeros(0)
    kept, _ = noise.standardised_errors(final.fun, final.jac, problem.n_pixel_rows)
    jacobian = dropped.jacobian(final.x)[:n][:, free]
    covariance = identify.inverse_information(final.jac.T @ final.jac)
    leverage = np.einsum("ij,jk,ik->i", jacobian, covariance, jacobian).reshape(-1, 2).mean(axis=1)
    errors = np.linalg.norm(dropped.residuals(final.x)[:n].reshape(-1, 2), axis=1) / np.sqrt(1.0 + leverage)
    threshold = options.outlier_px if options.outlier_px is not None else max(4.0, 5.0 * noise.robust_sigma(kept))
    return errors / threshold


def posterior(problem: Problem, x: np.ndarray, options: CalibrationOptions) -> float:
    """The negative log posterior (up to a constant) of the parameters x (P,) of `problem`
    (its prior rows at any weight), by which fits of the same pixels are told apart: every
    observation's residual under a soft-L1 loss at `f_scale_px` (a wild pixel counts little,
    whichever fit named it an outlier) at the stated pixel noise, and the markers' offsets
    over their prior SDs."""
    fun = problem.residuals(x)
    n = problem.n_pixel_rows
    e = np.linalg.norm(fun[:n].reshape(-1, 2), axis=1) / options.f_scale_px
    scale = (options.f_scale_px / options.noise_px) ** 2 / 2.0  # a small residual r counts r^2 / (2 noise^2)
    prior = 0.5 * float(np.sum((fun[n:] / problem.prior_px) ** 2))
    return scale * float(np.sum(2.0 * (np.sqrt(1.0 + e**2) - 1.0))) + prior
