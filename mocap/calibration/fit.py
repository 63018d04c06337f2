"""One calibration fit from a start: least squares over the free parameters, the outlier
rule and the readmission, the markers' prior weighed at the noise the residuals show, and
the result with its covariance and identifiability."""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from mocap.calibration import doubts, identify
from mocap.calibration.bias import bias_corrected
from mocap.calibration.context import (
    CalibrationResult,
    FitContext,
    Residual,
    max_rms,
    pixel_errors,
    pixel_rms,
    robust_cost,
    robust_loss,
    weighed_prior,
)
from mocap.calibration.outliers import suspects, without_outliers
from mocap.calibration.problem import Layout, Problem
from mocap.calibration.readmission import readmit
from mocap.calibration.start import bounds_and_start
from mocap.errors import ConvergenceError, InputError


def first_fit(context: FitContext, x0: np.ndarray) -> CalibrationResult:
    """The fit from the automatic start. With a tolerance it begins robust (a wild pixel can
    draw a far camera to the orthographic limit, a plateau no later fit leaves); should it
    fail or leave a camera there, the fit that begins with plain least squares (which a poor
    start's large residuals mislead less) is tried too, the better kept."""
    marker_sd, options = context.marker_sd, context.options
    try:
        result = fit(context, x0)
    except InputError as exc:
        if marker_sd is None:
            raise
        failure, result = exc, None
    if marker_sd is None or (result is not None and not doubts.far_cameras(result)):
        return result
    try:
        plain = fit(context, x0, robust_start=False)
    except InputError:
        if result is None:
            raise failure from None
        return result
    if result is None or robust_cost(plain, options) < robust_cost(result, options):
        return plain
    return result


def fit(context: FitContext, x0: np.ndarray, robust_start: bool = True) -> CalibrationResult:
    """Least squares from x0; if some residuals are implausible, a robust fit names the
    outliers and the least-squares fit is repeated without them. With the markers' prior
    (`context.marker_sd`) the markers' offsets are fitted too, within it (the model's
    tolerance): the prior is weighed at the pixel noise estimated from a first fit."""
    machine, observations, layout, templates = context.machine, context.observations, context.layout, context.templates
    options, marker_sd, names = context.options, context.marker_sd, context.names
    bounds, x0 = bounds_and_start(layout, machine, x0)
    free = free_parameters(layout, templates)

    def _least_squares(problem, x_start, bounds, **robust):
        return solve_least_squares(problem, x_start, bounds, free, **robust)

    problem = context.problem()
    if marker_sd is None:
        final = _least_squares(problem, x0, bounds)
    else:  # robust from the start: a wild pixel drawn at by plain least squares can push a far
        # camera towards the orthographic limit, a plateau that no later fit leaves
        def start_loss(p):
            return robust_loss(p, options) if robust_start else {}

        final = _least_squares(problem, x0, bounds, **start_loss(problem))
        problem, final = weighed_prior(context, final, lambda p, x, b: _least_squares(p, x, b, **start_loss(p)),
                                       bounds)
    inlier = np.ones(len(observations), dtype=bool)
    if marker_sd is not None or options.outlier_px is not None or suspects(pixel_errors(final.fun, problem),
                                                                            options).any():
        problem, final, inlier = without_outliers(context, problem, final, x0, bounds, _least_squares)
        problem, final, inlier = readmit(context, problem, final, inlier, free, bounds, _least_squares)
    if marker_sd is not None:  # a far camera's distance, skewed by the perspective's fall with it: its bias removed
        final.x = bias_corrected(problem, final.x, free, problem.prior_px)
    rms = pixel_rms(final.fun, problem)
    if rms > max_rms(options, templates):
        raise ConvergenceError(
            f"the fit did not converge: {rms:.1f} px rms over {problem.n_pixel_rows // 2} observations "
            "(expected about the pixel noise); check the marker labels, or give a --guess "
            "(or a larger --max-rms)"
        )
    jacobian = final.jac  # of the free parameters
    all_names = layout.names(names, machine.joint_names, machine.marker_names)
    kinds = layout.kinds(names, machine.joint_names, machine.marker_names)
    rank, condition = identify.check_jacobian(
        jacobian, [n for n, f in zip(all_names, free) if f], [k for k, f in zip(kinds, free) if f]
    )
    rank += int(np.sum(~free))  # the held parameters are known
    dof = max(jacobian.shape[0] - jacobian.shape[1], 1)
    # with the offsets fitted the rows are whitened at the noise the residuals show (their
    # leverage counted); else the noise from the residuals over their degrees of freedom
    sigma2 = problem.prior_px**2 if marker_sd is not None else float(final.fun @ final.fun) / dof
    covariance = np.zeros((layout.size, layout.size))  # the held parameters' variance is zero
    covariance[np.ix_(free, free)] = sigma2 * identify.inverse_information(jacobian.T @ jacobian)
    fitted = problem.machine_at(final.x)
    offsets, offsets_sd = None, None
    core = slice(0, layout.size - 3 * layout.n_markers)  # cameras and joints
    if layout.n_markers:
        offsets = final.x[layout.offset_slice].reshape(-1, 3)
        offsets_sd = np.sqrt(np.diag(covariance)[layout.offset_slice]).reshape(-1, 3)

    cameras, joints = layout.unpack(final.x, templates)
    all_residuals = context.problem().residuals(final.x)[: 2 * len(observations)].reshape(-1, 2)
    residuals = tuple(
        Residual(names[c], machine.marker_names[m], observations.xy[k], all_residuals[k], not inlier[k])
        for k, (c, m) in enumerate(zip(observations.camera, observations.marker))
    )
    inlier_err = all_residuals[inlier]
    rms = float(np.sqrt(np.mean(np.sum(inlier_err**2, axis=1))))
    first_joints = joints[0] if layout.per_camera else joints
    markers_world = fitted.markers(first_joints[None])[0]
    views = np.zeros(len(machine.marker_names), dtype=int)
    for m in range(len(views)):
        views[m] = len(np.unique(observations.camera[inlier & (observations.marker == m)]))
    return CalibrationResult(
        machine=machine,
        cameras=tuple(cameras),
        joints=joints,
        per_camera=layout.per_camera,
        parameter_names=tuple(all_names[core]),
        parameters=final.x[core],
        covariance=covariance[core, core],
        paper_sd=tuple(_paper_sd(layout, final.x, covariance, templates, c) for c in range(len(templates))),
        residuals=residuals,
        rms_px=rms,
        sigma_px=float(np.sqrt(sigma2)),
        rank=rank - 3 * layout.n_markers,  # of the cameras and joints: the offsets' priors fix them
        condition=condition,
        markers_world=markers_world,
        marker_views=views,
        marker_offsets=offsets,
        marker_offsets_sd=offsets_sd,
    )


def solve_least_squares(problem: Problem, x0, bounds, free: np.ndarray, loss="linear", f_scale: float = 1.0):
    """Least squares over the parameters `free` (P,) bool, the others held at x0's values;
    the solution's x is the whole vector, its jac the free parameters' columns."""

    def whole(z):
        x = x0.copy()
        x[free] = z
        return x

    solution = least_squares(
        lambda z: problem.residuals(whole(z)),
        x0[free],
        jac=lambda z: problem.jacobian(whole(z))[:, free],
        bounds=(bounds[0][free], bounds[1][free]),
        loss=loss,
        f_scale=f_scale,
        x_scale="jac",
        method="trf",
    )
    solution.x = whole(solution.x)
    return solution


def free_parameters(layout: Layout, templates) -> np.ndarray:
    """(P,) bool: the parameters solved for; a known camera's intrinsics are held."""
    free = np.ones(layout.size, dtype=bool)
    for c, template in enumerate(templates):
        if template.name in layout.fixed_intrinsics:
            free[layout.camera_slice(c).start + 6 : layout.camera_slice(c).stop] = False
    return free


def _paper_sd(layout: Layout, x: np.ndarray, covariance: np.ndarray, templates, c: int) -> np.ndarray:
    """Standard deviations (7,) of camera c's paper parameters, by first-order propagation."""
    s = layout.camera_slice(c)

    def paper(block):
        y = x.copy()
        y[s] = block
        return layout.unpack(y, templates)[0][c].to_paper().as_vector()

    block = x[s]
    base = paper(block)
    jac = np.empty((7, len(block)))
    for i in range(len(block)):
        step = 1e-6 * max(1.0, abs(block[i]))
        shifted = block.copy()
        shifted[i] += step
        diff = paper(shifted) - base
        diff[:3] = (diff[:3] + np.pi) % (2 * np.pi) - np.pi
        jac[:, i] = diff / step
    return np.sqrt(np.diag(jac @ covariance[s, s] @ jac.T))
