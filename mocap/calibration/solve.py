"""Model-based calibration: cameras and the machine's joint values fitted together.

`calibrate` takes one frame's marker pixels from one or several cameras, finds a starting
point by itself (or takes the user's guess in the paper's parameters), fits all unknowns
with a robust loss, names the outliers, refits without them, checks identifiability and
returns the parameters with their standard deviations.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy.optimize import least_squares

from mocap.calibration import doubts, identify, initial, noise
from mocap.core.guess import Guess
from mocap.calibration.problem import DISTORTION_MODELS, Layout, Observations, Problem
from mocap.camera import Camera, PaperCamera, default_principal_point, intrinsic_matrix
from mocap.errors import ConvergenceError, DegenerateError, InputError
from mocap.machine import Machine, Tolerance
from mocap.reconstruct.offsets import tape_sd

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
    fraction = _shown_tolerance(machine, result, options.noise_px)
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


def _shown_tolerance(machine: Machine, result: CalibrationResult, noise_px: float) -> float | None:
    """The tolerance the residuals of an exact model's calibration show (`noise.model_error_fraction`)."""
    if result.per_camera:
        return None
    index = {c.name: k for k, c in enumerate(result.cameras)}
    camera = np.array([index[r.camera] for r in result.residuals])
    marker = machine.marker_index([r.marker for r in result.residuals])
    squared = np.array([np.sum(r.residual**2) for r in result.residuals])
    spread = np.linalg.norm(tape_sd(Tolerance(0.5), machine.marker_positions), axis=1) / 0.5 / np.sqrt(3.0)  # (M,) m per axis, a fraction of 1
    depth = np.array([(c.cam_from_world.rotation @ result.markers_world[m] + c.cam_from_world.translation)[2]
                      for c, m in zip((result.cameras[k] for k in camera), marker)])
    focal = np.array([result.cameras[k].focal for k in camera])
    scale = focal * spread[marker] / np.maximum(np.abs(depth), 1e-6)
    return noise.model_error_fraction(squared, scale, marker, noise_px, result.sigma_px)


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
    x0 = _starting_point(machine, observations, templates, options, guess, layout)
    wild = _wild_base_pixels(machine, observations, templates, options.fixed_intrinsics) if guess is None else []
    try:
        result = _from_start(machine, observations, layout, templates, x0, options, guess, marker_sd)
    except InputError as failure:
        if not wild:
            raise
        result, first_failure = None, failure
    if wild:
        # a wild pixel among a camera's base markers bends its placement, and the start with
        # it: the start is found again without those pixels (the fit still sees them all)
        kept = np.ones(len(observations), dtype=bool)
        kept[wild] = False
        again = _starting_point(machine, observations.select(kept), templates, options, guess, layout)
        try:
            other = _from_start(machine, observations, layout, templates, again, options, guess, marker_sd)
        except InputError:
            if result is None:
                raise first_failure from None
            return result
        if result is None or _robust_cost(other, options) < _robust_cost(result, options):
            log.info("the start without the wild base pixel(s) explains the pixels better: kept")
            result = other
    return result


def _from_start(machine, observations, layout, templates, x0, options, guess, marker_sd) -> CalibrationResult:
    """The calibration from the start x0 (P,), and if it fails, from the joints searched
    again with every camera placed (`_chained_start`)."""
    try:
        return _calibrated(machine, observations, layout, templates, x0, options, guess, marker_sd)
    except InputError as failure:
        # a camera that sees too few base markers is placed at the joint values the others
        # found alone, which can be far off: the joints are searched again with every camera
        # placed, and those cameras placed again
        again = None if guess is not None or options.per_camera else _chained_start(machine, observations, templates,
                                                                                   options, layout, x0)
        if again is None:
            raise
        log.info("the fit from the first start failed (%s); the joints searched again with every camera", failure)
        try:
            return _calibrated(machine, observations, layout, templates, again, options, guess, marker_sd)
        except InputError:
            raise failure from None


def _wild_base_pixels(machine: Machine, observations: Observations, templates, known=frozenset()) -> list[int]:
    """The observations (indices) that look wild among each camera's five or more base
    markers (`initial.wild_point`, on the pixels undistorted for a known lens)."""
    base = machine.marker_links[observations.marker] == 0
    wild = []
    for c, template in enumerate(templates):
        rows = np.flatnonzero((observations.camera == c) & base)
        if len(rows) < 5:
            continue
        pixels, focal = observations.xy[rows], None
        if template.name in known:
            pixels, focal = _undistorted(pixels, template), template.focal
        k = initial.wild_point(machine.marker_positions[observations.marker[rows]], pixels, template, focal)
        if k is not None:
            wild.append(int(rows[k]))
    return wild


def _calibrated(machine, observations, layout, templates, x0, options, guess, marker_sd) -> CalibrationResult:
    """The calibration from the start x0 (P,): the first fit, new starts where it named
    outliers or left residuals above the stated noise; refused (DegenerateError) when a
    camera stays unfixed."""
    result = _first_fit(machine, observations, layout, templates, x0, options, marker_sd)
    starts, swept = [], np.zeros(0, int)
    if result.outliers:
        # pixels named outliers may be a wrong minimum's doing: the start is found again
        # without them, and the cameras that lost many are placed again on all their markers
        # at the fitted pose; the fit from each is kept if it explains the pixels better
        kept = np.array([not r.outlier for r in result.residuals])
        starts.append(lambda: _starting_point(machine, observations.select(kept), templates, options, guess, layout))
        doubtful = doubts.doubtful_cameras(result)
        if doubtful:
            starts.append(lambda: layout.pack(_replaced_cameras(result, observations, templates, doubtful,
                                                                options.fixed_intrinsics), result.joints))
        swept = observations.marker[~kept]
    if result.sigma_px > options.noise_px:
        # residuals above the pixels' stated noise: a joint may sit in a mirror minimum (the
        # cameras' focal lengths and places bent to suit it); that of the link whose markers
        # the fit explains worst is searched across its range
        log.info("residual noise %.2f px above the stated %.2f px: the worst-fitted link's joint searched",
                 result.sigma_px, options.noise_px)
        swept = np.union1d(swept, _worst_links_markers(machine, observations, result))
    if not result.per_camera:
        starts += _swept_joints(machine, layout, result, swept)
    for start in starts:
        try:
            again = _fit(machine, observations, layout, templates, start(), options, marker_sd)
        except (InputError, np.linalg.LinAlgError) as exc:  # a start the solver cannot leave
            log.info("a new start did not converge: %s", exc)
            continue
        if _robust_cost(again, options) < _robust_cost(result, options):
            log.info("a new start explains the pixels better: kept")
            result = again
    if result.sigma_px > options.noise_px:
        result = _without_worst(machine, observations, layout, templates, result, options, marker_sd)
    if marker_sd is not None:  # the offsets can absorb perspective: a weak camera may slide to the orthographic limit
        doubts.refuse_unfixed(result)
    return replace(result, warnings=doubts.warnings(result))


def _without_worst(machine, observations, layout, templates, result, options, marker_sd,
                   tries: int = 3) -> CalibrationResult:
    """Residuals still above the stated noise after every start: a wrong answer or a wild
    pixel the outlier rule let through (judged against a noise that the wild pixel itself,
    drawing its neighbours off, had raised). The fit without each of the `tries` worst-fitted
    observations in turn; one that this fit predicts beyond the outlier rule (`outlier_px`,
    else 5 sigma and 4 px) is named an outlier where the fit explains all the pixels better
    (robust cost)."""
    error = np.array([-1.0 if r.outlier else np.linalg.norm(r.residual) for r in result.residuals])
    for k in np.argsort(-error)[:tries]:
        if error[k] <= 4.0:
            break
        kept = np.ones(len(observations), dtype=bool)
        kept[k] = False
        try:
            again = _fit(machine, observations.select(kept), layout, templates, _vector(result), options, marker_sd)
        except (InputError, np.linalg.LinAlgError):  # the others alone do not fix the cameras
            continue
        left_out = Problem(machine, observations.select(~kept), layout, templates, marker_sd, again.sigma_px)
        residual = left_out.residuals(_vector(again))[:2]
        rule = options.outlier_px if options.outlier_px is not None else max(4.0, 5.0 * again.sigma_px)
        if np.linalg.norm(residual) <= rule:
            continue
        residuals = np.empty(len(observations), dtype=object)
        residuals[kept] = again.residuals
        residuals[k] = replace(result.residuals[k], residual=residual, outlier=True)
        merged = replace(again, residuals=tuple(residuals))
        if _robust_cost(merged, options, rule) < _robust_cost(result, options, rule):
            log.info("camera %s, marker %s: %.1f px from the fit of the others, whose residuals fall to %.2f px "
                     "(from %.2f): an outlier", residuals[k].camera, residuals[k].marker, np.linalg.norm(residual),
                     again.sigma_px, result.sigma_px)
            result = merged
    return result


def _vector(result: CalibrationResult) -> np.ndarray:
    """The fit's whole parameter vector (P,): cameras and joints, then the markers' offsets."""
    return np.r_[result.parameters, () if result.marker_offsets is None else result.marker_offsets.ravel()]


def _chained_start(machine, observations, templates, options, layout, x0) -> np.ndarray | None:
    """The start x0 (P,) again where some camera saw fewer than four base markers (placed
    at joint values the others fixed alone): the joints searched along the chain with every
    camera as placed, then those cameras placed again on all their markers at these joint
    values. None when every camera was placed from the base link."""
    cameras, joints = layout.unpack(x0, templates)
    base = machine.marker_links[observations.marker] == 0
    late = [c for c in range(len(templates)) if np.sum((observations.camera == c) & base) < 4]
    if not late:
        return None
    joints = initial.joints_along_chain(machine, cameras, observations.camera, observations.marker, observations.xy,
                                        joints)
    world = machine.markers(joints[None])[0]
    for c in late:
        rows = observations.camera == c
        placed, rms = _placed(world[observations.marker[rows]], observations.xy[rows], templates[c],
                              options.fixed_intrinsics)
        if np.isfinite(rms):
            cameras[c] = placed
    return layout.pack(cameras, joints)


def _first_fit(machine, observations, layout, templates, x0, options, marker_sd) -> CalibrationResult:
    """The fit from the automatic start. With a tolerance it begins robust (a wild pixel can
    draw a far camera to the orthographic limit, a plateau no later fit leaves); should it
    fail or leave a camera there, the fit that begins with plain least squares (which a poor
    start's large residuals mislead less) is tried too, the better kept."""
    try:
        result = _fit(machine, observations, layout, templates, x0, options, marker_sd)
    except InputError as exc:
        if marker_sd is None:
            raise
        failure, result = exc, None
    if marker_sd is None or (result is not None and not doubts.far_cameras(result)):
        return result
    try:
        plain = _fit(machine, observations, layout, templates, x0, options, marker_sd, robust_start=False)
    except InputError:
        if result is None:
            raise failure from None
        return result
    if result is None or _robust_cost(plain, options) < _robust_cost(result, options):
        return plain
    return result


def _posterior(problem: Problem, x: np.ndarray, options: CalibrationOptions) -> float:
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


def _worst_links_markers(machine: Machine, observations: Observations, result: CalibrationResult,
                         links: int = 1) -> np.ndarray:
    """The markers (indices) of the `links` moving links whose observations' residuals have
    the largest RMS (outliers left out)."""
    error = np.array([np.linalg.norm(r.residual) if not r.outlier else np.nan for r in result.residuals])
    link = machine.marker_links[observations.marker]
    moving = [k for k in np.unique(link) if k != 0 and np.isfinite(error[link == k]).any()]
    rms = [np.sqrt(np.nanmean(error[link == k] ** 2)) for k in moving]
    worst = [moving[i] for i in np.argsort(rms)[::-1][:links]]
    return np.flatnonzero(np.isin(machine.marker_links, worst))


def _swept_joints(machine: Machine, layout: Layout, result: CalibrationResult, dropped: np.ndarray) -> list:
    """Starts (callables of no argument) with the joint of each dropped marker's link set
    across its range, the rest as fitted: that joint's mirror solutions."""
    cameras = list(result.cameras)
    limits = machine.joint_limits
    lower = np.where(np.isfinite(limits[:, 0]), limits[:, 0], -1.0)
    upper = np.where(np.isfinite(limits[:, 1]), limits[:, 1], 1.0)
    out = []
    own_joint = {int(link): j for j, link in enumerate(machine.joint_links)}  # the joint that moves each link
    for j in sorted({own_joint[int(link)] for link in machine.marker_links[dropped] if int(link) in own_joint}):
        for level in (np.arange(6) + 0.5) / 6:
            joints = np.array(result.joints, dtype=float)
            joints[j] = lower[j] + level * (upper[j] - lower[j])
            out.append(lambda joints=joints: layout.pack(cameras, joints))
    return out


def _starting_point(machine, observations, templates, options: CalibrationOptions, guess, layout: Layout):
    """The parameter vector (P,) to start the fit from, found from `observations` alone."""
    groups = [[c] for c in range(len(templates))] if options.per_camera else [list(range(len(templates)))]
    cameras: list[Camera | None] = [None] * len(templates)
    joints = np.zeros((len(templates), machine.n_joints)) if options.per_camera else None
    for group in groups:
        mask = np.isin(observations.camera, group)
        placed, q = _start(machine, observations.select(mask), templates, group, guess, options.fixed_intrinsics)
        for c in group:
            cameras[c] = placed[c]
            if templates[c].name in options.fixed_intrinsics:  # a guess's focal length gives way to the known one
                cameras[c] = replace(templates[c], cam_from_world=placed[c].cam_from_world)
        if options.per_camera:
            joints[group[0]] = q
        else:
            joints = q
    return layout.pack(cameras, joints)


def _start(machine, obs: Observations, templates, group, guess: Guess | None, known=frozenset()):
    """Starting cameras (a list by camera index, None outside `group`) and joint values for
    the cameras in `group`; the cameras named in `known` keep their templates' intrinsics."""
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
                cameras[c], rms = _placed(machine.marker_positions[obs.marker[rows]], obs.xy[rows], templates[c],
                                          known)
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
            cameras[c], rms = _placed(world, obs.xy[rows], templates[c], known)
            log.info("camera %s placed from all its markers, rms %.2f px", templates[c].name, rms)
    return cameras, joints


def _replaced_cameras(result: CalibrationResult, observations: Observations, templates, doubtful,
                      known=frozenset()) -> list[Camera]:
    """The result's cameras, those in `doubtful` placed again by PnP of all their markers at
    the fitted joint values."""
    cameras = list(result.cameras)
    for c in doubtful:
        joints = result.joints[c] if result.per_camera else result.joints
        rows = observations.camera == c
        world = result.machine.markers(np.asarray(joints)[None])[0][observations.marker[rows]]
        placed, rms = _placed(world, observations.xy[rows], templates[c], known)
        if np.isfinite(rms):
            cameras[c] = placed
    return cameras


def _robust_cost(result: CalibrationResult, options: CalibrationOptions, cap_px: float = np.inf) -> float:
    """Soft-L1 cost of every observation's residual (outliers too) at the robust loss' scale;
    a residual beyond `cap_px` counts as one at `cap_px` (an outlier costs the same however
    wild: with every residual so capped, a fit that leaves one observation beyond the cap is
    preferred exactly where the others' gain outweighs it, the outlier rule's own test)."""
    e = np.minimum([np.linalg.norm(r.residual) for r in result.residuals], cap_px) / options.f_scale_px
    return float(np.sum(2.0 * (np.sqrt(1.0 + e**2) - 1.0)))


def _placed(points: np.ndarray, pixels: np.ndarray, template: Camera, known=frozenset()) -> tuple[Camera, float]:
    """A camera placed by PnP on known points; one with known intrinsics (named in `known`)
    keeps its template's focal length and distortion (the pixels undistorted for the PnP)."""
    if template.name not in known:
        return initial.place_camera(points, pixels, template)
    placed, rms = initial.place_camera(points, _undistorted(pixels, template), template, focal=template.focal)
    return Camera(template.name, template.size, template.matrix, template.distortion, placed.cam_from_world), rms


def _undistorted(pixels: np.ndarray, template: Camera) -> np.ndarray:
    """(N, 2) pixels through the template's lens undistorted, in its pinhole's pixels."""
    return cv2.undistortPoints(np.ascontiguousarray(pixels, dtype=np.float64).reshape(-1, 1, 2),
                               template.matrix, template.distortion, P=template.matrix).reshape(-1, 2)


def _free(layout: Layout, templates) -> np.ndarray:
    """(P,) bool: the parameters solved for; a known camera's intrinsics are held."""
    free = np.ones(layout.size, dtype=bool)
    for c, template in enumerate(templates):
        if template.name in layout.fixed_intrinsics:
            free[layout.camera_slice(c).start + 6 : layout.camera_slice(c).stop] = False
    return free


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


def _fit(machine, observations, layout, templates, x0, options, marker_sd=None, robust_start=True) -> CalibrationResult:
    """Least squares from x0; if some residuals are implausible, a robust fit names the
    outliers and the least-squares fit is repeated without them. With `marker_sd` the
    markers' offsets are fitted too, within their prior (the model's tolerance): the prior
    is weighed at the pixel noise estimated from a first fit."""
    names = [t.name for t in templates]
    bounds, x0 = _bounds(layout, machine, x0)
    free = _free(layout, templates)

    def _least_squares(problem, x_start, bounds, **robust):
        return _solve(problem, x_start, bounds, free, **robust)

    def problem_of(obs, prior_px=1.0):
        return Problem(machine, obs, layout, templates, marker_sd, prior_px)

    problem = problem_of(observations)
    if marker_sd is None:
        final = _least_squares(problem, x0, bounds)
    else:  # robust from the start: a wild pixel drawn at by plain least squares can push a far
        # camera towards the orthographic limit, a plateau that no later fit leaves
        def robust_loss(problem):
            return dict(loss=noise.pixel_robust_loss(problem.n_pixel_rows), f_scale=options.f_scale_px)

        start_loss = robust_loss if robust_start else lambda p: {}
        final = _least_squares(problem, x0, bounds, **start_loss(problem))
        problem, final = _weighed_prior(problem_of, observations, final, options,
                                        lambda p, x, b: _least_squares(p, x, b, **start_loss(p)), bounds)
    inlier = np.ones(len(observations), dtype=bool)
    if marker_sd is not None or options.outlier_px is not None or _suspects(_pixel_errors(final.fun, problem),
                                                                             options).any():
        if marker_sd is None:
            robust = _least_squares(problem, x0, bounds, loss="soft_l1", f_scale=options.f_scale_px)
            errors = _pixel_errors(robust.fun, problem)
            suspect = _suspects(errors, options)
        else:
            # outliers judged against the noise with the markers' offsets marginalised: each
            # residual of the robust fit over sqrt(1 - its leverage), the share of its variance
            # the fit leaves; a wild pixel on a marker that only one camera sees is mostly
            # absorbed by that marker's offset, but its residual's variance is then small too
            robust = _least_squares(problem, final.x, bounds, **robust_loss(problem))
            errors, _ = noise.standardised_errors(robust.fun, robust.jac, problem.n_pixel_rows)
            suspect = _suspects(errors, options)
        inlier = _drop_while_identifiable(machine, names, observations, layout, suspect, errors)
        if np.all(inlier):
            final = _least_squares(problem, robust.x, bounds)
        else:
            log.info("%d outlier(s) dropped", np.sum(~inlier))
            problem = problem_of(observations.select(inlier), problem.prior_px)
            final = _least_squares(problem, robust.x, bounds)
        if marker_sd is not None:  # the noise again, without the outliers
            problem, final = _weighed_prior(problem_of, observations.select(inlier), final, options, _least_squares,
                                            bounds)
        over = _readmitted(problem, problem_of(observations.select(~inlier), problem.prior_px), final, free, options)
        # a wild pixel's pull on the robust fit can make its neighbours look wild too
        if (over <= 1.0).any() and _pixel_rms(final.fun, problem) <= _max_rms(options, templates):
            before = inlier.copy()
            back = np.flatnonzero(~inlier)[np.argsort(over)][: np.sum(over <= 1.0)]  # the best predicted first
            whole = problem_of(observations)
            # with the offsets, each one taken back alone and kept only where the posterior of all
            # the pixels prefers it: a wild pixel whose marker few cameras see is predicted loosely
            # (its offset free within the prior); taken back, it can draw a weak camera along its
            # valley, and taken back with a good one, the good one's gain hid its cost
            for group in [back] if marker_sd is None else back[:, None]:
                trial = inlier.copy()
                trial[group] = True
                p = problem_of(observations.select(trial), problem.prior_px)
                f = _least_squares(p, final.x, bounds)
                if marker_sd is not None:
                    p, f = _weighed_prior(problem_of, observations.select(trial), f, options, _least_squares, bounds)
                    if _posterior(whole, f.x, options) > _posterior(whole, final.x, options):
                        continue
                problem, final, inlier = p, f, trial
            if not np.array_equal(inlier, before):
                log.info("%d observation(s) named outliers agree with the fit without them: kept",
                         np.sum(inlier & ~before))
    rms = _pixel_rms(final.fun, problem)
    if rms > _max_rms(options, templates):
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
    all_residuals = problem_of(observations).residuals(final.x)[: 2 * len(observations)].reshape(-1, 2)
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


def _weighed_prior(problem_of, observations, final, options, least_squares_from, bounds, rounds: int = 2):
    """The offsets' prior weighed at the pixel noise that the fit `final`'s residuals show
    (leverage-corrected, `noise.pixel_noise`), the fit repeated; `rounds` times, as the
    noise and the prior's weight depend on each other. Returns the problem and its fit."""
    n_pixel_rows = 2 * len(observations)
    for _ in range(rounds):
        sigma = noise.pixel_noise(final.fun, final.jac, n_pixel_rows, options.noise_px)
        problem = problem_of(observations, float(np.clip(sigma, 0.05, 20.0)))
        final = least_squares_from(problem, final.x, bounds)
    return problem, final


def _solve(problem: Problem, x0, bounds, free: np.ndarray, loss="linear", f_scale: float = 1.0):
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


def _pixel_errors(fun: np.ndarray, problem: Problem) -> np.ndarray:
    """(N,) residual lengths (px) of the observations (the prior rows left out)."""
    return np.linalg.norm(fun[: problem.n_pixel_rows].reshape(-1, 2), axis=1)


def _suspects(errors: np.ndarray, options: CalibrationOptions) -> np.ndarray:
    """(N,) observations whose residual (px) is implausible: beyond `outlier_px` if given,
    else beyond 5 sigma of the noise the residuals show and beyond 4 px."""
    if options.outlier_px is not None:
        return errors > options.outlier_px
    return errors > max(4.0, 5.0 * noise.robust_sigma(errors))


def _pixel_rms(fun: np.ndarray, problem: Problem) -> float:
    """RMS length (px) of the observations' residuals (the prior rows left out)."""
    return float(np.sqrt(np.mean(fun[: problem.n_pixel_rows] ** 2) * 2))


def _max_rms(options: CalibrationOptions, templates) -> float:
    """The residual RMS (px) beyond which a fit has not converged: `max_rms_px`, else 1 % of
    the largest image diagonal."""
    return options.max_rms_px or 0.01 * max(np.hypot(*t.size) for t in templates)


def _readmitted(problem: Problem, dropped: Problem, final, free: np.ndarray, options: CalibrationOptions) -> np.ndarray:
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


def _drop_while_identifiable(machine, names, observations, layout, suspect, errors) -> np.ndarray:
    """(N,) inliers: the suspects dropped worst first (by `errors` (N,)), each only while
    the rest still satisfy the counts (a camera's fourth base marker stays, its residual
    reported)."""
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
