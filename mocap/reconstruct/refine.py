"""Model refinement: a bundle adjustment over many frames of the cameras, the per-frame
joint values and, optionally, the marker positions within a stated tolerance.

The cameras calibrated from one frame and a tape-measured machine (markers ±5 %) leave
errors that one frame cannot reveal; many frames of a moving machine can. The problem is
solved by Levenberg-Marquardt on the normal equations (mocap.reconstruct.sparse_lm; a Huber
loss with its scale in pixels) of an analytic sparse Jacobian: every residual depends on one camera, one frame
and one marker. A marker's offset from its measured position has a Gaussian prior of SD
``Tolerance.sd`` per coordinate (mocap.core.machine), expressed in pixel units through
the pixel noise. The priors also fix the gauge: a rigid motion of the base's markers
together with the cameras, or a turn of a link's markers about its joint together with
that joint's values, leaves the pixels unchanged and is resolved towards the measured
positions (so a link's mean angular marker error is not recoverable). The named points (bucket tip), which no camera sees, stay where the
model puts them relative to their links.

Camera parameters: a rotation increment (3,) on the left of ``cam_from_world``, a
translation increment (3,), with `fit_focal` the log of a focal-length scale, with
`fit_principal_point` the principal point's increment (2,) px and with `distortion` the
increments of the chosen OpenCV coefficients (k1; k1, k2; or all five). Cameras whose
intrinsics are known (`fixed_intrinsics`) keep them: those columns are not solved for.
With `base_motion` the base moves every frame (a hand-held board, a bouncing or walking
machine): a rotation increment (3,) on the left of ``world_from_base`` and a translation
(3,) per frame, started from each frame's pose seen by its best camera; the best-seen
frame's base pose is held to fix the world. With distortion "auto" the lens model is
chosen by the data: none, k1, then k1 k2 while the Bayesian information criterion of the
pixel residuals falls.
Shapes: C cameras, K frames used, M markers, J joints.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
import scipy.linalg
from scipy.sparse import coo_matrix

from mocap.core.camera import DISTORTION_MODELS, Camera, project_cam
from mocap.core.geometry import Rigid, cross, matrix_to_rotvec, rotvec_to_matrix
from mocap.core.machine import Machine, Tolerance
from mocap.errors import ConvergenceError, DegenerateError
from mocap.reconstruct.camera_share import CAMERA_PARAMETERS, CameraCovariance, named_parameters
from mocap.reconstruct.kinfit import FitOptions, fit_joints
from mocap.reconstruct.kinmodel import FrameState, KinematicModel
from mocap.reconstruct.lens_start import board_poses
from mocap.reconstruct.offsets import tape_sd
from mocap.reconstruct.sparse_lm import Solution, levenberg_marquardt

log = logging.getLogger(__name__)

DEFAULT_TOLERANCE = Tolerance(0.05)  # the paper's tape measurement, when nothing is stated
DISTORTION_CHOICES = (*DISTORTION_MODELS, "auto")
PLAIN_EVALUATIONS = 100  # plain least-squares evaluations before the robust loss
AUTO_MODELS = ("none", "k1", "k1k2")  # tried in turn by "auto" while the criterion falls
LABEL_RATIO = 5.0  # a camera's median distance this many times the other cameras' contradicts them
LABEL_FLOOR_PX = 2.0  # ... and beyond this (a worse lens or a blurrier image stays within it)
SYNC_MIN_FRAMES = 0.5  # a camera's clock this many frames off the first's names a wrong sync
NOISE_RATIO = 5.0  # tracks lying this many times their own noise from the refined model contradict it
LIE_FLOOR_PX = 2.0  # ... and beyond this (a lens a little off the model stays within it)
RAYLEIGH_MEDIAN = 1.1774  # median length of a 2-D Gaussian of unit SD per axis


@dataclass(frozen=True)
class RefineOptions:
    """frames: at most this many frames (the best-observed, spread over the session);
    markers: also refine the marker positions (always, when the tolerance is stated here or
    in the model); tolerance: how far they may be off (default: the model's, else 5 %);
    fit_focal: refine each camera's focal length; scale_px: robust loss scale;
    max_evaluations: residual evaluations allowed to the solver; distortion: the lens
    coefficients freed ("none", "k1", "k1k2", "full", or "auto": chosen by the data);
    fit_principal_point: free the principal point; base_motion: a 6-DoF base pose per frame;
    fixed_intrinsics: names of cameras whose focal length, principal point and distortion
    are known and kept; max_median_px: refuse when a camera's tracks lie further than this
    from the refined cameras, median (None: no fixed gate; only a named contradiction, wrong
    labels or a wrong sync, is refused)."""

    frames: int = 120
    markers: bool = False
    tolerance: Tolerance | None = None
    fit_focal: bool = True
    scale_px: float = 2.0
    max_evaluations: int = 100
    max_median_px: float | None = None
    distortion: str = "none"
    fit_principal_point: bool = False
    base_motion: bool = False
    fixed_intrinsics: frozenset[str] = frozenset()

    def __post_init__(self) -> None:
        if self.distortion not in DISTORTION_CHOICES:
            raise ValueError(f"distortion must be one of {', '.join(DISTORTION_CHOICES)}, got {self.distortion!r}")
        if self.frames < 2 or not self.scale_px > 0 or self.max_evaluations < 1:
            raise ValueError("frames >= 2, scale_px > 0 and max_evaluations >= 1 are required")
        if self.max_median_px is not None and not self.max_median_px > 0:
            raise ValueError("max_median_px must be positive")


@dataclass(frozen=True)
class RefineResult:
    """cameras (C) refined; machine with refined marker positions (or the input model);
    frames (K,) indices of the frames used; joints (K, J) their fitted joint values;
    rms_before / rms_after the pixel residual RMS (per coordinate) over those frames; message the solver's;
    base (K, 6) the frames' ``world_from_base`` (rotation vector, translation m) with base
    motion, else None; distortion the lens model used; criterion {model: BIC} of the models
    tried by "auto" (empty otherwise); median_px (C,) each camera's median distance (px)
    from its tracks to the refined cameras; noise_px the tracks' noise estimated from the
    residuals (robust SD per coordinate, px); clock_frames (C,) each camera's clock offset
    from the first's, frames (a fraction of a frame: cameras not genlocked); track_noise_px
    the noise the 2-D tracks show by themselves (`track_noise`, px), against which the
    distances are judged; rms_px (C,) each camera's residual RMS (px, of the distances)
    over its seen points."""

    cameras: tuple[Camera, ...]
    machine: Machine
    frames: np.ndarray
    joints: np.ndarray
    rms_before: float
    rms_after: float
    message: str
    base: np.ndarray | None = None
    distortion: str = "none"
    criterion: dict | None = None
    median_px: tuple[float, ...] = ()
    noise_px: float = float("nan")
    clock_frames: tuple[float, ...] = ()
    track_noise_px: float = float("nan")
    camera_covariance: CameraCovariance | None = None
    rms_px: tuple[float, ...] = ()


def refine(machine: Machine, cameras: list[Camera], pixels: np.ndarray, options: RefineOptions | None = None) -> RefineResult:
    """Bundle-adjust cameras (and markers) to pixels (C, F, M, 2) of many frames."""
    options = options or RefineOptions()
    pixels = np.asarray(pixels, dtype=float)
    n_cams, n_markers, n_joints = len(cameras), len(machine.marker_names), machine.n_joints
    if pixels.ndim != 4 or pixels.shape[0] != n_cams or pixels.shape[2:] != (n_markers, 2):
        raise ValueError(f"pixels must have shape (C={n_cams}, F, M={n_markers}, 2), got {pixels.shape}")
    frames = select_frames(pixels, options.frames, minimum=n_joints + 2)
    if len(frames) < 2:
        raise DegenerateError(
            "fewer than 2 frames show enough markers to refine the cameras; track more frames "
            "or refine with the calibration as it is"
        )
    obs = pixels[:, frames]
    stated = options.tolerance or machine.tolerance
    options = replace(options, markers=options.markers or bool(stated), tolerance=stated or DEFAULT_TOLERANCE)
    fit_options = FitOptions(scale_px=options.scale_px, tolerance=stated, base_motion=options.base_motion)
    base = board_poses(machine, cameras, obs) if options.base_motion else None
    if n_joints:
        fit = fit_joints(machine, cameras, obs, options=fit_options, initial_base=base)
        joints, noise_px = np.nan_to_num(fit.joints), fit.noise_px
        base = None if fit.base is None else np.where(np.isfinite(fit.base), fit.base, np.nan_to_num(base))
    else:  # a rigid model: its pose (calibration's, or each frame's seen by PnP), the loss scale for the noise
        joints, noise_px = np.zeros((len(frames), 0)), options.scale_px
    models = AUTO_MODELS if options.distortion == "auto" else (options.distortion,)
    velocity = image_velocity(pixels)[:, frames]  # (C, K, M, 2): each camera's clock offset is solved for
    criterion: dict[str, float] = {}
    best = None
    start_cameras = tuple(cameras)
    for model in models:
        problem = _Bundle(machine, start_cameras, obs, replace(options, distortion=model), noise_px, base, velocity)
        x0 = np.r_[np.zeros(problem.n_camera_params * n_cams), joints.ravel(), np.zeros(6 * len(frames) * options.base_motion),
                   np.zeros(3 * n_markers * options.markers), np.zeros(n_cams)]
        if best is None:
            before = problem.pixel_rms(x0)
        solution = _solve(problem, x0, options)
        criterion[model] = problem.bic(solution.x)
        if best is not None and criterion[model] >= criterion[best[0]]:
            break
        best = (model, problem, solution, x0)
        if model != models[-1]:  # the next model starts where this one ended
            start_cameras, joints, _, base = problem.unpack(solution.x)
            start_cameras = tuple(start_cameras)
    model, problem, solution, x0 = best
    cams, joints, refined, base = problem.unpack(solution.x)
    after = problem.pixel_rms(solution.x)
    log.info("bundle adjustment over %d frames: %.3f -> %.3f px, distortion %s (%s)", len(frames), before, after,
             model, solution.message)
    residual = problem.pixel_residuals(solution.x)  # (C, K, M, 2), 0 where not seen
    distance = np.linalg.norm(residual, axis=-1)
    medians = tuple(float(np.median(d[seen])) if np.any(seen) else 0.0 for d, seen in zip(distance, problem.seen))
    rms = tuple(float(np.sqrt(np.mean(d[seen] ** 2))) if np.any(seen) else float("nan")
                for d, seen in zip(distance, problem.seen))
    noise = float(1.4826 * np.median(np.abs(residual[problem.seen]))) if problem.seen.any() else float("nan")
    names = [camera.name for camera in cameras]
    clocks = problem.clocks(solution.x)
    own_noise = track_noise(pixels)
    contradiction = contradicting_camera(residual, problem.seen, clocks, names, distance[problem.seen], own_noise)
    if contradiction:
        raise ConvergenceError(f"{contradiction}; the calibration is left as it is")
    for name, median in zip(names, medians):
        if options.max_median_px is not None and median > options.max_median_px:
            raise ConvergenceError(
                f"camera {name}'s tracks lie {median:.1f} px (median) from the refined cameras, more than "
                f"--max-median {options.max_median_px:g} px; the calibration is left as it is"
            )
    return RefineResult(tuple(cams), refined, frames, joints, before, after, str(solution.message), base, model,
                        criterion if len(models) > 1 else {}, medians, noise,
                        tuple(float(c) for c in clocks), own_noise,
                        camera_covariance(problem, solution.x, options.scale_px, noise), rms)


def camera_covariance(problem: "_Bundle", x: np.ndarray, scale_px: float, noise_px: float) -> CameraCovariance | None:
    """The refined cameras' covariance (named as the calibration names them, with the
    markers' offsets when they were refined) from the bundle's normal equations at the
    solution: (Jᵀ W J)⁻¹ over the free parameters, the pixel rows over the tracks' noise
    `noise_px` squared with their Huber weights, the markers' prior rows at their own SDs;
    the camera block carried to the cameras' named parameters by their derivative by the
    bundle's increments."""
    if not noise_px > 0:
        return None
    free = problem.free
    jac = problem.jacobian(x)[:, free]
    residual = problem.residuals(x)
    n_pixel = problem.seen.size * 2
    weight = np.minimum(1.0, scale_px / np.maximum(np.abs(residual), 1e-12)) / noise_px**2
    weight[n_pixel:] = 1.0 / problem.noise_px**2  # a prior row is an offset over its SD times noise_px
    information = np.asarray((jac.T @ jac.multiply(weight[:, None])).toarray() if hasattr(jac, "multiply")
                             else jac.T @ (jac * weight[:, None]))
    if not np.all(np.isfinite(information)):
        return None
    position = np.cumsum(free) - 1  # index among the free parameters
    cameras = problem.unpack(x)[0]
    named = [named_parameters(c) for c in cameras]
    n_named = len(CAMERA_PARAMETERS)
    size = problem.n_camera_params
    columns = [c * size + i for c in range(len(cameras)) for i in range(size) if free[c * size + i]]
    transform = np.zeros((len(cameras) * n_named, len(columns)))
    step = 1e-7
    for k, column in enumerate(columns):
        c = column // size
        moved = x.copy()
        moved[column] += step
        transform[c * n_named : (c + 1) * n_named, k] = (named_parameters(problem.unpack(moved)[0][c]) - named[c]) / step
    names = [f"{c.name}.{p}" for c in cameras for p in CAMERA_PARAMETERS]
    if problem.options.markers:  # the markers' offsets, estimated with the cameras, in their links' frames
        offsets = list(range(problem.marker_start, problem.clock_start))
        transform = np.block([[transform, np.zeros((len(transform), len(offsets)))],
                              [np.zeros((len(offsets), len(columns))), np.eye(len(offsets))]])
        columns = columns + [i for i in offsets if free[i]]
        names += [f"{m}.d{a}" for m in problem.machine.marker_names for a in "xyz"]
    block = _inverse_block(information, position[columns])
    full = transform @ block @ transform.T
    keep = np.nonzero(np.diag(full) > 0)[0]
    return CameraCovariance(tuple(names[i] for i in keep), full[np.ix_(keep, keep)])


def _inverse_block(information: np.ndarray, index: np.ndarray) -> np.ndarray:
    """The rows and columns `index` of the inverse of the symmetric `information` (n, n):
    solved for those columns alone from its Cholesky factor (scaled to a unit diagonal),
    about a tenth of the time of the whole pseudo-inverse over the session's per-frame
    joints; the pseudo-inverse where the factor fails (a direction the data leave free)."""
    scale = 1.0 / np.sqrt(np.maximum(np.diag(information), 1e-300))
    try:
        factor = scipy.linalg.cho_factor(information * np.outer(scale, scale), check_finite=False)
        unit = np.zeros((len(information), len(index)))
        unit[index, np.arange(len(index))] = 1.0
        block = scipy.linalg.cho_solve(factor, unit * scale[:, None], check_finite=False)[index] * scale[index, None]
        if np.all(np.isfinite(block)) and np.all(np.diag(block) > 0):
            return 0.5 * (block + block.T)
    except np.linalg.LinAlgError:
        pass
    return np.linalg.pinv(information, hermitian=True)[np.ix_(index, index)]


def image_velocity(pixels: np.ndarray) -> np.ndarray:
    """(C, F, M, 2) each track's image velocity in px per frame row: the central difference,
    one-sided at a track's ends, NaN where a track has no neighbouring frame."""
    ahead = np.full_like(pixels, np.nan)
    behind = np.full_like(pixels, np.nan)
    ahead[:, :-1] = pixels[:, 1:] - pixels[:, :-1]
    behind[:, 1:] = pixels[:, 1:] - pixels[:, :-1]
    central = 0.5 * (ahead + behind)
    return np.where(np.isfinite(central), central, np.where(np.isfinite(ahead), ahead, behind))


def track_noise(pixels: np.ndarray) -> float:
    """The pixel noise (SD per coordinate, px) the 2-D tracks (C, F, M, 2) show by
    themselves: a robust scale (1.4826 MAD) of their second differences over consecutive
    frame rows, over sqrt(6) (noise alone gives second differences sqrt(6) times its SD).
    A motion adds its acceleration: frames far apart (every k-th frame of a video, stills)
    make the estimate larger, never smaller. NaN where no track has three consecutive points."""
    pixels = np.asarray(pixels, dtype=float)
    if pixels.shape[1] < 3:
        return float("nan")
    second = pixels[:, 2:] - 2 * pixels[:, 1:-1] + pixels[:, :-2]
    second = second[np.isfinite(second)]
    return float(1.4826 * np.median(np.abs(second)) / np.sqrt(6)) if second.size else float("nan")


def contradicting_model(distance: np.ndarray, noise_px: float) -> str:
    """The contradiction of the model as a whole, or "": the tracks' distances (N,) px from
    the refined model (median) beyond NOISE_RATIO times what their own noise `noise_px`
    (`track_noise`) gives and beyond LIE_FLOOR_PX: no camera, clock or lens explains it
    (another machine's model, a calibration of another rig, labels of other markers)."""
    if not distance.size or not np.isfinite(noise_px):
        return ""
    median = float(np.median(distance))
    if median > max(NOISE_RATIO * RAYLEIGH_MEDIAN * noise_px, LIE_FLOOR_PX):
        return (f"the tracks lie {median:.1f} px (median) from the refined model where their own noise is "
                f"{noise_px:.2f} px: a wrong machine model, calibration or labels")
    return ""


def contradicting_camera(residual: np.ndarray, seen: np.ndarray, clocks: np.ndarray, names: list[str],
                         distance: np.ndarray | None = None, noise_px: float = float("nan")) -> str:
    """The contradiction that the refined cameras' residuals (C, K, M, 2) and clock offsets
    (C,) frames name, or "": one camera's wrong labels, then the model as a whole
    (`contradicting_model` of the seen distances (N,) and the tracks' own noise), then a
    wrong sync (a clock far off that left the residuals small).

    A wrong sync: a camera's clock SYNC_MIN_FRAMES or more off the first's (a fraction of a
    frame is cameras not genlocked, solved for and kept). Wrong labels: a camera's median
    distance is LABEL_RATIO times the other cameras' (the median over them) and beyond
    LABEL_FLOOR_PX. Noise and a lens model a little off spread over every camera alike and
    name nothing."""
    lengths = np.linalg.norm(residual, axis=-1)
    medians = np.array([np.median(d[s]) if np.any(s) else 0.0 for d, s in zip(lengths, seen)])
    for c, name in enumerate(names if len(names) >= 2 else ()):
        others = float(np.median(np.delete(medians, c)))
        if medians[c] > max(LABEL_RATIO * others, LABEL_FLOOR_PX):
            return (f"camera {name}'s tracks lie {medians[c]:.1f} px (median) from the refined cameras, the other "
                    f"cameras' {others:.2f} px: its labels contradict theirs (markers swapped, or a tracker on the "
                    "wrong marker)")
    if distance is not None and (model := contradicting_model(distance, noise_px)):
        return model
    if np.any(np.abs(clocks) >= SYNC_MIN_FRAMES):
        listed = ", ".join(f"{name} {clock:+.1f}" for name, clock in zip(names[1:], clocks[1:]))
        return (f"the cameras' clocks disagree by up to {np.abs(clocks).max():.1f} frames ({listed} frames from "
                f"{names[0]}'s, estimated from the tracks' motion): a wrong sync (run `mocap sync`, or check the "
                "frame times)")
    return ""


def _solve(problem: "_Bundle", x0: np.ndarray, options: RefineOptions) -> Solution:
    """Plain least squares first (a robust loss from a start pixels off stalls), then the
    Huber loss at the loss scale; over the free parameters only (Levenberg-Marquardt on the
    sparse normal equations, mocap.reconstruct.sparse_lm)."""
    free = problem.free

    def residuals(z):
        return problem.residuals(_full(x0, free, z))

    def jacobian(z):
        return problem.jacobian(_full(x0, free, z))[:, free]

    start = levenberg_marquardt(residuals, jacobian, x0[free], max_iterations=PLAIN_EVALUATIONS)
    solution = levenberg_marquardt(residuals, jacobian, start.x, scale=options.scale_px,
                                   max_iterations=options.max_evaluations)
    return replace(solution, x=_full(x0, free, solution.x))


def _full(x0: np.ndarray, free: np.ndarray, z: np.ndarray) -> np.ndarray:
    x = x0.copy()
    x[free] = z
    return x


def select_frames(pixels: np.ndarray, count: int, minimum: int) -> np.ndarray:
    """Up to `count` frame indices spread evenly over the frames whose observations (2-D,
    all cameras) number at least `minimum`."""
    n_obs = np.isfinite(pixels[..., 0]).sum((0, 2))
    usable = np.nonzero(n_obs >= minimum)[0]
    if len(usable) <= count:
        return usable
    return usable[np.unique(np.linspace(0, len(usable) - 1, count).round().astype(int))]


class _Bundle:
    """Residuals of the bundle adjustment as a pure function of the parameter vector:
    camera parameters (C, n_camera_params), joints (K, J), with base motion the base
    increments (K, 6), with markers the marker offsets (M, 3). `free` (parameters,) marks
    what is solved for: known intrinsics and the reference frame's base pose are held."""

    def __init__(self, machine: Machine, cameras: tuple[Camera, ...], pixels: np.ndarray, options: RefineOptions,
                 noise_px: float, base: np.ndarray | None = None, velocity: np.ndarray | None = None):
        self.machine, self.cameras, self.pixels, self.options = machine, cameras, pixels, options
        self.seen = np.isfinite(pixels[..., 0])  # (C, K, M)
        self.terms = list(DISTORTION_MODELS[options.distortion])
        self.n_camera_params = 6 + options.fit_focal + 2 * options.fit_principal_point + len(self.terms)
        self.prior_sd = tape_sd(options.tolerance or machine.tolerance or DEFAULT_TOLERANCE, machine.marker_positions)  # (M, 3)
        self.noise_px = noise_px
        n_cams, n_frames, n_markers = self.seen.shape
        self.base0 = None
        if options.base_motion:
            self.base0 = np.zeros((n_frames, 6)) if base is None else np.asarray(base, dtype=float)
        self.joint_start = self.n_camera_params * n_cams
        self.base_start = self.joint_start + n_frames * machine.n_joints
        self.marker_start = self.base_start + 6 * n_frames * options.base_motion
        self.clock_start = self.marker_start + 3 * n_markers * options.markers
        self.velocity = None if velocity is None else np.where(self.seen[..., None], np.nan_to_num(velocity), 0.0)
        self.free = np.ones(self.clock_start + n_cams * (velocity is not None), dtype=bool)
        if velocity is not None:  # the first camera's clock is the reference
            self.free[self.clock_start] = False
        for c, camera in enumerate(cameras):
            if camera.name in options.fixed_intrinsics:
                self.free[c * self.n_camera_params + 6 : (c + 1) * self.n_camera_params] = False
        if options.base_motion:  # the best-seen frame's base fixes the world
            reference = int(np.argmax(self.seen.sum((0, 2))))
            self.free[self.base_start + 6 * reference : self.base_start + 6 * reference + 6] = False

    def _split(self, x: np.ndarray):
        n_cams, n_frames, n_markers = self.seen.shape
        camera_params = x[: self.joint_start].reshape(n_cams, self.n_camera_params)
        joints = x[self.joint_start : self.base_start].reshape(n_frames, self.machine.n_joints)
        increments = x[self.base_start : self.marker_start].reshape(n_frames, 6) if self.options.base_motion else None
        offsets = x[self.marker_start : self.clock_start].reshape(n_markers, 3) if self.options.markers else None
        return camera_params, joints, increments, offsets

    def _base(self, increments: np.ndarray | None):
        """world_from_base rotation (K, 3, 3) and translation (K, 3), or None, None."""
        if increments is None:
            return None, None
        rotation = rotvec_to_matrix(increments[:, :3]) @ rotvec_to_matrix(self.base0[:, :3])
        return rotation, self.base0[:, 3:] + increments[:, 3:]

    def clocks(self, x: np.ndarray) -> np.ndarray:
        """(C,) each camera's clock offset (frames) from the first's: its pixels are seen that
        much later, predicted by its tracks' own image velocities; zeros without them."""
        return x[self.clock_start :] if self.velocity is not None else np.zeros(len(self.cameras))

    def unpack(self, x: np.ndarray):
        """cameras (C), joints (K, J), machine (its markers moved), base (K, 6) or None."""
        camera_params, joints, increments, offsets = self._split(x)
        machine = self.machine
        if offsets is not None:
            machine = replace(machine, marker_positions=machine.marker_positions + offsets)
        cameras = [self._camera(camera, p) for camera, p in zip(self.cameras, camera_params)]
        rotation, translation = self._base(increments)
        base = None if rotation is None else np.c_[matrix_to_rotvec(rotation), translation]
        return cameras, joints, machine, base

    def _camera(self, camera: Camera, params: np.ndarray) -> Camera:
        pose = camera.cam_from_world
        rotation = rotvec_to_matrix(params[:3]) @ pose.rotation
        matrix, distortion = camera.matrix.copy(), camera.distortion.copy()
        k = 6
        if self.options.fit_focal:
            matrix[:2, :2] *= np.exp(params[k])
            k += 1
        if self.options.fit_principal_point:
            matrix[:2, 2] += params[k : k + 2]
            k += 2
        distortion[self.terms] += params[k:]
        return replace(camera, cam_from_world=Rigid(rotation, pose.translation + params[3:6]), matrix=matrix,
                       distortion=distortion)

    def _world(self, x: np.ndarray):
        cameras, joints, machine, _ = self.unpack(x)
        world = machine.markers(joints)  # (K, M, 3) in the base frame
        rotation, translation = self._base(self._split(x)[2])
        if rotation is not None:
            world = world @ np.swapaxes(rotation, 1, 2) + translation[:, None]
        return cameras, world

    def pixel_residuals(self, x: np.ndarray) -> np.ndarray:
        cameras, world = self._world(x)
        out = np.stack([c.project(world) for c in cameras])  # (C, K, M, 2)
        residual = self.pixels - out
        if self.velocity is not None:  # a clock offset: seen later by clock times the image velocity
            residual = residual - self.clocks(x)[:, None, None, None] * self.velocity
        return np.where(self.seen[..., None], np.nan_to_num(residual, nan=1e3), 0.0)

    def residuals(self, x: np.ndarray) -> np.ndarray:
        pixel = self.pixel_residuals(x).ravel()
        if not self.options.markers:
            return pixel
        offsets = self._split(x)[3]
        return np.r_[pixel, (offsets / self.prior_sd * self.noise_px).ravel()]

    def pixel_rms(self, x: np.ndarray) -> float:
        residual = self.pixel_residuals(x)
        return float(np.sqrt((residual**2).sum() / max(2 * self.seen.sum(), 1)))  # per coordinate

    def bic(self, x: np.ndarray) -> float:
        """Bayesian information criterion of the pixel residuals at x: n log(cost / n) +
        p log(n), with the Huber cost at the loss scale (an outlier counts linearly) and p the
        free parameters."""
        n = max(2 * int(self.seen.sum()), 1)
        e = np.abs(self.pixel_residuals(x)[self.seen]).ravel()
        s = self.options.scale_px
        cost = np.where(e <= s, e * e, 2 * s * e - s * s).sum()
        return float(n * np.log(max(cost, 1e-300) / n) + self.free.sum() * np.log(n))

    def jacobian(self, x: np.ndarray):
        """Sparse (rows, parameters) Jacobian of `residuals`, analytic: every pixel row
        depends on its camera's parameters, its frame's joints and base and its marker's offset."""
        n_cams, n_frames, n_markers = self.seen.shape
        n_joints = self.machine.n_joints
        cameras, joints, machine, _ = self.unpack(x)
        camera_params, _, increments, _ = self._split(x)
        rotation, translation = self._base(increments)
        model = KinematicModel(machine, (), base_motion=self.options.base_motion)
        world, d_world_params = model.world_markers(FrameState(joints, rotation, translation, np.zeros(n_frames)))
        d_joints = d_world_params[..., :n_joints]
        link_rotation = machine.link_poses(joints)[:, machine.marker_links, :3, :3]  # (K, M, 3, 3)
        if rotation is not None:
            link_rotation = rotation[:, None] @ link_rotation
            left = np.stack([_left_jacobian(w) for w in increments[:, :3]])  # (K, 3, 3)
            d_base = np.concatenate([d_world_params[..., n_joints : n_joints + 3] @ left[:, None],
                                     d_world_params[..., n_joints + 3 :]], -1)  # (K, M, 3, 6)
        blocks = []
        for camera, params in zip(cameras, camera_params):
            rot = camera.cam_from_world.rotation
            rotated = world @ rot.T
            points_cam = rotated + camera.cam_from_world.translation
            uv, d_uv = project_cam(points_cam, camera.matrix, camera.distortion, True)
            d_rot = np.stack([cross(np.eye(3)[i], rotated) for i in range(3)], -1) @ _left_jacobian(params[:3])
            parts = [d_uv @ d_rot, d_uv]  # rotation increment, translation
            if self.options.fit_focal:
                parts.append((uv - camera.matrix[:2, 2])[..., None])  # d uv / d log(focal scale)
            if self.options.fit_principal_point:
                parts.append(np.broadcast_to(np.eye(2), uv.shape + (2,)))
            if self.terms:
                parts.append(_distortion_jacobian(points_cam, camera.matrix, self.terms))
            d_world = d_uv @ rot  # (K, M, 2, 3)
            parts.append(d_world @ d_joints)
            if rotation is not None:
                parts.append(d_world @ d_base)
            if self.options.markers:
                parts.append(d_world @ link_rotation)
            blocks.append(-np.concatenate(parts, -1))  # residual = observed - projected
        values = np.stack(blocks) * self.seen[..., None, None]  # (C, K, M, 2, columns)
        values = np.nan_to_num(values)
        c, k, m, a = np.meshgrid(np.arange(n_cams), np.arange(n_frames), np.arange(n_markers), np.arange(2), indexing="ij")
        rows = np.arange(values[..., 0].size).reshape(c.shape)
        columns = [c * self.n_camera_params + p for p in range(self.n_camera_params)]
        columns += [self.joint_start + k * n_joints + j for j in range(n_joints)]
        if rotation is not None:
            columns += [self.base_start + 6 * k + p for p in range(6)]
        if self.options.markers:
            columns += [self.marker_start + 3 * m + axis for axis in range(3)]
        column_index = np.stack(columns, -1)
        row_index = np.broadcast_to(rows[..., None], column_index.shape)
        data, row_list, col_list = [values.ravel()], [row_index.ravel()], [column_index.ravel()]
        n_rows = rows.size
        if self.velocity is not None:
            data.append(-self.velocity.ravel())
            row_list.append(rows.ravel())
            col_list.append((self.clock_start + c).ravel())
        if self.options.markers:
            prior = np.arange(3 * n_markers)
            data.append((self.noise_px / self.prior_sd).ravel())
            row_list.append(n_rows + prior)
            col_list.append(self.marker_start + prior)
            n_rows += 3 * n_markers
        return coo_matrix((np.concatenate(data), (np.concatenate(row_list), np.concatenate(col_list))),
                          shape=(n_rows, len(self.free))).tocsr()


def _distortion_jacobian(points_cam: np.ndarray, matrix: np.ndarray, terms: list[int]) -> np.ndarray:
    """d uv / d (distortion coefficients `terms`) (*, 2, len(terms)) of camera-frame points (*, 3)."""
    x = points_cam[..., 0] / points_cam[..., 2]
    y = points_cam[..., 1] / points_cam[..., 2]
    r2 = x * x + y * y
    normalised = {0: (x * r2, y * r2), 1: (x * r2 * r2, y * r2 * r2), 2: (2 * x * y, r2 + 2 * y * y),
                  3: (r2 + 2 * x * x, 2 * x * y), 4: (x * r2**3, y * r2**3)}
    d = np.stack([np.stack(normalised[t], -1) for t in terms], -1)  # (*, 2, T) in normalised coordinates
    return matrix[:2, :2] @ d


def _left_jacobian(rotvec: np.ndarray) -> np.ndarray:
    """SO(3) left Jacobian (3, 3): d exp(w) / d w as a left increment, for R = exp(w) R0."""
    theta = np.linalg.norm(rotvec)
    k = np.array([[0.0, -rotvec[2], rotvec[1]], [rotvec[2], 0.0, -rotvec[0]], [-rotvec[1], rotvec[0], 0.0]])
    if theta < 1e-8:
        return np.eye(3) + 0.5 * k
    return np.eye(3) + (1 - np.cos(theta)) / theta**2 * k + (theta - np.sin(theta)) / theta**3 * (k @ k)
