"""Model-based calibration: cameras and the machine's joint values fitted together.

`calibrate` takes one frame's marker pixels from one or several cameras, finds a starting
point by itself (or takes the user's guess in the paper's parameters), fits all unknowns
with a robust loss, names the outliers, refits without them, checks identifiability and
returns the parameters with their standard deviations.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from mocap.calibration import identify, initial
from mocap.calibration.problem import DISTORTION_MODELS, Layout, Observations, Problem
from mocap.camera import Camera, PaperCamera, default_principal_point, intrinsic_matrix
from mocap.errors import ConvergenceError, DegenerateError, InputError
from mocap.machine import Machine

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CalibrationOptions:
    """How to calibrate.

    per_camera: each camera with its own joint values instead of one shared pose.
    fit_principal_point, distortion ("none", "k1", "k1k2", "full"): extra intrinsics.
    f_scale_px: scale of the robust (soft L1) loss. outlier_px: residual beyond which an
    observation is named an outlier and dropped (default: max(4 px, 5 sigma)).
    max_rms_px: residual RMS beyond which the fit is reported as not converged (default: 1 %
    of the largest image diagonal, 22 px at 1920x1080; a model error of a few per cent
    stays below it, a wrong solution or wrong labels do not).
    """

    per_camera: bool = False
    fit_principal_point: bool = False
    distortion: str = "none"
    f_scale_px: float = 2.0
    outlier_px: float | None = None
    max_rms_px: float | None = None

    def __post_init__(self) -> None:
        if self.distortion not in DISTORTION_MODELS:
            raise InputError(
                f"distortion model {self.distortion!r} unknown; use one of {', '.join(DISTORTION_MODELS)}"
            )
        if not self.f_scale_px > 0:
            raise InputError(f"f_scale_px must be positive, got {self.f_scale_px}")


@dataclass(frozen=True)
class Guess:
    """A user's initial guess: per camera name the paper's parameters; joints (J,) rad / m."""

    cameras: dict = field(default_factory=dict)
    joints: np.ndarray | None = None


@dataclass(frozen=True)
class Residual:
    camera: str
    marker: str
    observed: np.ndarray  # (2,) px
    residual: np.ndarray  # (2,) projected minus observed, px
    outlier: bool


@dataclass(frozen=True)
class CalibrationResult:
    """The fitted cameras and joint values with what they rest on.

    joints: (J,) rad / m shared, or (C, J) with `per_camera`. parameters, covariance: the
    fitted vector and its covariance (sigma^2 (J^T J)^-1 over the inliers) in the order of
    `parameter_names`. paper_sd: per camera the paper parameters' standard deviations
    (rad, m, px). markers_world: (M, 3) every marker at the fitted joint values (the first
    camera's with `per_camera`): the reference points for a DLT or a survey check.
    """

    machine: Machine
    cameras: tuple[Camera, ...]
    joints: np.ndarray
    per_camera: bool
    parameter_names: tuple[str, ...]
    parameters: np.ndarray
    covariance: np.ndarray
    paper_sd: tuple[np.ndarray, ...]
    residuals: tuple[Residual, ...]
    rms_px: float
    sigma_px: float
    rank: int
    condition: float
    markers_world: np.ndarray
    marker_views: np.ndarray  # (M,) number of cameras that saw each marker (inliers)

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance))

    @property
    def outliers(self) -> tuple[Residual, ...]:
        return tuple(r for r in self.residuals if r.outlier)

    def camera_rms(self, name: str) -> float:
        errs = [np.sum(r.residual**2) for r in self.residuals if r.camera == name and not r.outlier]
        return float(np.sqrt(np.mean(errs))) if errs else float("nan")

    @property
    def joints_sd(self) -> np.ndarray:
        """Standard deviations of the joint values, shaped like `joints` (joints come last)."""
        return self.std[len(self.parameters) - self.joints.size :].reshape(self.joints.shape)


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
    """
    names = [t.name for t in templates]
    layout = Layout(
        len(templates), machine.n_joints, options.per_camera, options.fit_principal_point, options.distortion
    )
    identify.check_counts(
        machine, names, observations.camera, observations.marker, options.per_camera, layout.camera_size
    )
    if guess is not None and guess.cameras:
        missing = [n for n in names if n not in guess.cameras]
        if missing:
            raise InputError(f"the initial guess lacks camera(s) {', '.join(missing)}")
    groups = [[c] for c in range(len(templates))] if options.per_camera else [list(range(len(templates)))]
    cameras: list[Camera | None] = [None] * len(templates)
    joints = np.zeros((len(templates), machine.n_joints)) if options.per_camera else None
    for group in groups:
        mask = np.isin(observations.camera, group)
        placed, q = _start(machine, observations.select(mask), templates, group, guess)
        for c in group:
            cameras[c] = placed[c]
        if options.per_camera:
            joints[group[0]] = q
        else:
            joints = q
    x0 = layout.pack(cameras, joints)
    return _fit(machine, observations, layout, templates, x0, options)


def _start(machine, obs: Observations, templates, group, guess: Guess | None):
    """Starting cameras (a list by camera index, None outside `group`) and joint values for
    the cameras in `group`."""
    cameras: list[Camera | None] = [None] * len(templates)
    base = machine.marker_links[obs.marker] == 0
    if guess is not None and guess.cameras:
        for c in group:
            paper: PaperCamera = guess.cameras[templates[c].name]
            cameras[c] = Camera.from_paper(
                templates[c].name, templates[c].size, paper, tuple(templates[c].matrix[:2, 2])
            )
            rows = (obs.camera == c) & base
            if guess.joints is None and np.sum(rows) >= 4:
                cameras[c] = initial.refine_camera(
                    machine.marker_positions[obs.marker[rows]], obs.xy[rows], cameras[c]
                )
    else:
        for c in group:
            rows = (obs.camera == c) & base
            if np.sum(rows) >= 4:
                cameras[c], rms = initial.place_camera(
                    machine.marker_positions[obs.marker[rows]], obs.xy[rows], templates[c]
                )
                log.info("camera %s placed from the base link, rms %.2f px", templates[c].name, rms)
    start = _neutral_joints(machine)
    if guess is not None and guess.joints is not None:
        joints = machine.clip_to_limits(np.asarray(guess.joints, dtype=float))
    else:
        joints = initial.joints_along_chain(machine, cameras, obs.camera, obs.marker, obs.xy, start)
    for c in group:
        if cameras[c] is None:
            rows = obs.camera == c
            world = machine.markers(joints[None])[0][obs.marker[rows]]
            cameras[c], rms = initial.place_camera(world, obs.xy[rows], templates[c])
            log.info("camera %s placed from all its markers, rms %.2f px", templates[c].name, rms)
    return cameras, joints


def _neutral_joints(machine: Machine) -> np.ndarray:
    """Zero where the limits allow it, else the middle of the limits."""
    limits = machine.joint_limits
    middle = np.where(np.isfinite(limits).all(axis=1), limits.mean(axis=1), 0.0)
    return np.where((limits[:, 0] <= 0) & (limits[:, 1] >= 0), 0.0, middle)


def _bounds(layout: Layout, machine: Machine, x0: np.ndarray):
    lower = np.full(layout.size, -np.inf)
    upper = np.full(layout.size, np.inf)
    for c in range(layout.n_cameras):
        lower[layout.camera_slice(c).start + 6] = 1.0  # focal length stays positive
    limits = machine.joint_limits
    for c in range(layout.n_cameras if layout.per_camera else 1):
        s = layout.joint_slice(c)
        lower[s], upper[s] = limits[:, 0], limits[:, 1]
    x0 = np.clip(x0, lower + 1e-9 * np.isfinite(lower), upper - 1e-9 * np.isfinite(upper))
    return (lower, upper), x0


def _fit(machine, observations, layout, templates, x0, options) -> CalibrationResult:
    """Least squares from x0; if some residuals are implausible, a robust fit names the
    outliers and the least-squares fit is repeated without them."""
    names = [t.name for t in templates]
    bounds, x0 = _bounds(layout, machine, x0)
    problem = Problem(machine, observations, layout, templates)
    final = _least_squares(problem, x0, bounds)
    inlier = np.ones(len(observations), dtype=bool)
    err = np.linalg.norm(final.fun.reshape(-1, 2), axis=1)
    if options.outlier_px is not None or np.max(err) > max(4.0, 5.0 * _robust_sigma(err)):
        robust = _least_squares(problem, x0, bounds, loss="soft_l1", f_scale=options.f_scale_px)
        err = np.linalg.norm(robust.fun.reshape(-1, 2), axis=1)
        threshold = options.outlier_px or max(4.0, 5.0 * _robust_sigma(err))
        inlier = err <= threshold
        if np.all(inlier):
            final = _least_squares(problem, robust.x, bounds)
        else:
            log.info("%d outlier(s) beyond %.1f px", np.sum(~inlier), threshold)
            kept = observations.select(inlier)
            try:
                identify.check_counts(
                    machine, names, kept.camera, kept.marker, layout.per_camera, layout.camera_size
                )
            except DegenerateError as exc:
                raise DegenerateError(
                    f"after dropping {np.sum(~inlier)} outlier(s): {exc.detail}"
                ) from None
            problem = Problem(machine, kept, layout, templates)
            final = _least_squares(problem, robust.x, bounds)
    rms = float(np.sqrt(np.mean(final.fun**2) * 2))
    diagonal = max(np.hypot(*t.size) for t in templates)
    if rms > (options.max_rms_px or 0.01 * diagonal):
        raise ConvergenceError(
            f"the fit did not converge: {rms:.1f} px rms over {len(final.fun) // 2} observations "
            "(expected about the pixel noise); check the marker labels, or give a --guess "
            "(or a larger --max-rms)"
        )
    jacobian = final.jac
    parameter_names = layout.names(names, machine.joint_names)
    rank, condition = identify.check_jacobian(jacobian, parameter_names, layout.kinds(names, machine.joint_names))
    dof = max(jacobian.shape[0] - jacobian.shape[1], 1)
    sigma2 = float(final.fun @ final.fun) / dof
    covariance = sigma2 * np.linalg.pinv(jacobian.T @ jacobian)

    cameras, joints = layout.unpack(final.x, templates)
    all_residuals = Problem(machine, observations, layout, templates).residuals(final.x).reshape(-1, 2)
    residuals = tuple(
        Residual(names[c], machine.marker_names[m], observations.xy[k], all_residuals[k], not inlier[k])
        for k, (c, m) in enumerate(zip(observations.camera, observations.marker))
    )
    inlier_err = all_residuals[inlier]
    rms = float(np.sqrt(np.mean(np.sum(inlier_err**2, axis=1))))
    first_joints = joints[0] if layout.per_camera else joints
    markers_world = machine.markers(first_joints[None])[0]
    views = np.zeros(len(machine.marker_names), dtype=int)
    for m in range(len(views)):
        views[m] = len(np.unique(observations.camera[inlier & (observations.marker == m)]))
    return CalibrationResult(
        machine=machine,
        cameras=tuple(cameras),
        joints=joints,
        per_camera=layout.per_camera,
        parameter_names=tuple(parameter_names),
        parameters=final.x,
        covariance=covariance,
        paper_sd=tuple(_paper_sd(layout, final.x, covariance, templates, c) for c in range(len(templates))),
        residuals=residuals,
        rms_px=rms,
        sigma_px=float(np.sqrt(sigma2)),
        rank=rank,
        condition=condition,
        markers_world=markers_world,
        marker_views=views,
    )


def _least_squares(problem: Problem, x0, bounds, loss: str = "linear", f_scale: float = 1.0):
    return least_squares(
        problem.residuals,
        x0,
        jac=problem.jacobian,
        bounds=bounds,
        loss=loss,
        f_scale=f_scale,
        x_scale="jac",
        method="trf",
    )


def _robust_sigma(err: np.ndarray) -> float:
    """Per-axis pixel noise from the median residual length (Rayleigh: median = 1.1774 sigma)."""
    return float(np.median(err) / np.sqrt(2 * np.log(2)))


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


def template_camera(name: str, size: tuple[int, int]) -> Camera:
    """A camera with only name and size known: principal point at the centre, no distortion."""
    return Camera(name, size, intrinsic_matrix(float(size[0]), default_principal_point(size)))
