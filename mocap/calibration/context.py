"""What one calibration's fits share: the options, the result, and the fit context (the
machine, the observations, the parameter layout, the camera templates, the options, the
guess and the markers' prior) that the start, the fit, the outlier rule and the
readmission all work from; with the measures by which fits are compared."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from mocap.calibration import noise
from mocap.calibration.problem import DISTORTION_MODELS, Layout, Observations, Problem
from mocap.core.camera import Camera
from mocap.core.guess import Guess
from mocap.core.machine import Machine, Tolerance
from mocap.errors import InputError


@dataclass(frozen=True)
class CalibrationOptions:
    """How to calibrate.

    per_camera: each camera with its own joint values instead of one shared pose.
    fit_principal_point, distortion ("none", "k1", "k1k2", "full"): extra intrinsics.
    f_scale_px: scale of the robust (soft L1) loss. outlier_px: residual beyond which an
    observation is named an outlier and dropped (default: max(4 px, 5 sigma)).
    max_rms_px: residual RMS beyond which the fit is reported as not converged (default: 1 %
    of the largest image diagonal, 22 px at 1920x1080; a model error of a few per cent
    stays below it, a wrong solution or wrong labels do not). tolerance: how far the
    model's marker positions may be off (None: the model's own statement, if any); each
    residual is then weighted by the pixel noise plus the tolerance projected into the
    image, so that model error is not taken for outliers and far markers count less.
    fixed_intrinsics: names of cameras whose intrinsics (focal length, principal point,
    distortion) are known: their templates' values are used and kept, not fitted.
    noise_px: the pixel noise (per axis) assumed where the residuals cannot tell it (a
    tolerance's offsets absorb nearly all of one camera's residuals); the residuals' own
    estimate takes over as their redundancy grows.
    """

    per_camera: bool = False
    fit_principal_point: bool = False
    distortion: str = "none"
    f_scale_px: float = 2.0
    outlier_px: float | None = None
    max_rms_px: float | None = None
    tolerance: Tolerance | None = None
    fixed_intrinsics: frozenset[str] = frozenset()
    noise_px: float = 1.0

    def __post_init__(self) -> None:
        if self.distortion not in DISTORTION_MODELS:
            raise InputError(
                f"distortion model {self.distortion!r} unknown; use one of {', '.join(DISTORTION_MODELS)}"
            )
        if not self.noise_px > 0:
            raise InputError(f"noise_px must be positive, got {self.noise_px}")
        if not self.f_scale_px > 0:
            raise InputError(f"f_scale_px must be positive, got {self.f_scale_px}")


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
    marker_offsets: np.ndarray | None = None  # (M, 3) m, link frames: fitted within the tolerance
    marker_offsets_sd: np.ndarray | None = None  # (M, 3)
    warnings: tuple[str, ...] = ()  # what the data leave doubtful, one sentence each
    estimated_tolerance: float | None = None  # the markers' tolerance estimated from the residuals (none stated)

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


@dataclass(frozen=True)
class FitContext:
    """What every fit of one calibration works from: the machine, the observations (N rows),
    the parameter layout, one template camera per camera, the options, the user's guess
    (None: the start is found from the pixels) and the markers' prior SDs (M, 3) m (None:
    the model taken as exact, no offsets fitted)."""

    machine: Machine
    observations: Observations
    layout: Layout
    templates: list[Camera]
    options: CalibrationOptions
    guess: Guess | None = None
    marker_sd: np.ndarray | None = None

    @property
    def names(self) -> list[str]:
        return [t.name for t in self.templates]

    def select(self, mask: np.ndarray) -> FitContext:
        """The same context over the observations `mask` (N,) bool selects."""
        return replace(self, observations=self.observations.select(mask))

    def problem(self, observations: Observations | None = None, prior_px: float = 1.0) -> Problem:
        """The least-squares problem of `observations` (default: the context's) with the
        markers' prior weighed at `prior_px`."""
        observations = self.observations if observations is None else observations
        return Problem(self.machine, observations, self.layout, self.templates, self.marker_sd, prior_px)


def vector(result: CalibrationResult) -> np.ndarray:
    """The fit's whole parameter vector (P,): cameras and joints, then the markers' offsets."""
    return np.r_[result.parameters, () if result.marker_offsets is None else result.marker_offsets.ravel()]


def robust_cost(result: CalibrationResult, options: CalibrationOptions, cap_px: float = np.inf) -> float:
    """Soft-L1 cost of every observation's residual (outliers too) at the robust loss' scale;
    a residual beyond `cap_px` counts as one at `cap_px` (an outlier costs the same however
    wild: with every residual so capped, a fit that leaves one observation beyond the cap is
    preferred exactly where the others' gain outweighs it, the outlier rule's own test)."""
    e = np.minimum([np.linalg.norm(r.residual) for r in result.residuals], cap_px) / options.f_scale_px
    return float(np.sum(2.0 * (np.sqrt(1.0 + e**2) - 1.0)))


def pixel_errors(fun: np.ndarray, problem: Problem) -> np.ndarray:
    """(N,) residual lengths (px) of the observations (the prior rows left out)."""
    return np.linalg.norm(fun[: problem.n_pixel_rows].reshape(-1, 2), axis=1)


def pixel_rms(fun: np.ndarray, problem: Problem) -> float:
    """RMS length (px) of the observations' residuals (the prior rows left out)."""
    return float(np.sqrt(np.mean(fun[: problem.n_pixel_rows] ** 2) * 2))


def max_rms(options: CalibrationOptions, templates) -> float:
    """The residual RMS (px) beyond which a fit has not converged: `max_rms_px`, else 1 % of
    the largest image diagonal."""
    return options.max_rms_px or 0.01 * max(np.hypot(*t.size) for t in templates)


def weighed_prior(context: FitContext, final, least_squares_from, bounds, rounds: int = 2):
    """The offsets' prior weighed at the pixel noise that the fit `final`'s residuals show
    (leverage-corrected, `noise.pixel_noise`), the fit of the context's observations
    repeated; `rounds` times, as the noise and the prior's weight depend on each other.
    Returns the problem and its fit."""
    n_pixel_rows = 2 * len(context.observations)
    for _ in range(rounds):
        sigma = noise.pixel_noise(final.fun, final.jac, n_pixel_rows, context.options.noise_px)
        problem = context.problem(prior_px=float(np.clip(sigma, 0.05, 20.0)))
        final = least_squares_from(problem, final.x, bounds)
    return problem, final


def robust_loss(problem: Problem, options: CalibrationOptions) -> dict:
    """The robust loss of a fit with the markers' offsets (soft L1 on the pixel rows, the
    prior's rows plain) at the options' scale: `least_squares`' keywords."""
    return dict(loss=noise.pixel_robust_loss(problem.n_pixel_rows), f_scale=options.f_scale_px)
