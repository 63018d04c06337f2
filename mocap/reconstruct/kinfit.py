"""The batched kinematic fit: per frame, the joint values that best explain every camera's
marker pixels (the paper's multi-frame fit).

All frames are solved in one compiled call (mocap.reconstruct.kinkernel): each frame's
Levenberg-Marquardt iterations build its small normal equations from the model's pixels
and derivatives and solve them until the frame converges. Residuals are robustified by
iteratively reweighted least squares (Huber or Cauchy, scale in pixels). Without starting
values, every few frames (key frames) start from the best of a coarse grid of joint values
inside the limits (evaluated for all key frames by one matrix product) and the frames
between from the interpolated key solutions; a frame that ends far worse than is typical
is fitted again from the grid, and one that ends far worse than a neighbour is restarted
from that neighbour's solution. Joint limits are kept by clipping (full-circle joints
wrap). Optionally the base (undercarriage) moves too, by a 6-DoF
``world_from_base`` per frame (bouncing, or a machine that moved since calibration).

Parameters of a frame (mocap.reconstruct.kinmodel): joint values (J,) rad / m, then with
base motion a rotation increment (3,) and a translation (3,) of ``world_from_base``.
Shapes: C cameras, F frames, M markers, J joints, P parameters.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from mocap.core.camera import Camera
from mocap.core.geometry import matrix_to_rotvec, rotvec_to_matrix
from mocap.core.machine import Machine, Tolerance
from mocap.progress import progress
from mocap.reconstruct.chi2 import upper_quantile
from mocap.reconstruct.kinmodel import LOSSES, FrameState, KinematicModel, base_matrices

log = logging.getLogger(__name__)

_BEHIND_PX = 1e5  # stand-in pixel for a grid candidate behind a camera
_EPS_INFO = 1e-6  # px^2 per unit^2 added to the normal equations: unobserved stays finite
_CONVERGED = 1e-7  # relative change of a frame's cost below which it has converged
NEIGHBOUR_RATIO = 1.5  # a frame whose cost per observation is this much above a neighbour's is fitted from it
PREFERRED_CHI2 = 4.0  # a chi-square this much lower: the pixels prefer that solution (95 %, 1 dof)
FAR_SDS = 5.0  # a solution this many SDs (Mahalanobis) from another is a different one
DETOUR_FRAMES = 32  # the longest stretch of frames on another solution that `mend_detours` mends
_SAME_JOINT = 0.01  # rad or m: joints a frame does not see are the same solution only this close
_SAME_PX2 = 0.1  # a restart this close (px^2, by the normal matrix) to a known solution has found it


@dataclass(frozen=True)
class FitOptions:
    """Options of `fit_joints`.

    iterations: LM iterations; loss: "huber", "cauchy" or "linear"; scale_px: the robust
    loss's scale (px); noise_px: pixel noise SD for the covariance, None to estimate it from
    the residuals of all frames; base_motion: also fit a 6-DoF base pose per frame; grid:
    number of coarse-grid candidates for frames without a starting value; chunk: frames
    solved together (memory); repair_passes: restarts from neighbours' solutions;
    key_stride: without a start, every key_stride-th frame is fitted from the grid and the
    frames between start from the interpolated key solutions (a frame that then ends badly
    is fitted again from the grid); tolerance: how far the model's markers may be off (None:
    the model's own statement): residuals are weighted by the noise plus that tolerance
    projected into each camera (the pixel noise taken as noise_px, or 0.5 px, for that).
    """

    iterations: int = 30
    loss: str = "huber"
    scale_px: float = 2.0
    noise_px: float | None = None
    base_motion: bool = False
    grid: int = 400
    chunk: int = 2048
    repair_passes: int = 3
    key_stride: int = 8
    tolerance: Tolerance | None = None

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise ValueError(f"loss must be one of {LOSSES}, got {self.loss!r}")
        if not self.scale_px > 0:
            raise ValueError(f"scale_px must be positive, got {self.scale_px}")
        if self.noise_px is not None and not self.noise_px > 0:
            raise ValueError(f"noise_px must be positive or None, got {self.noise_px}")
        if min(self.iterations, self.grid, self.chunk, self.key_stride) < 1 or self.repair_passes < 0:
            raise ValueError("iterations, grid, chunk and key_stride must be >= 1, repair_passes >= 0")

    def tolerance_of(self, machine: Machine) -> Tolerance | None:
        """The markers' tolerance the fit uses: the options', else the model's (falsy: exact)."""
        return machine.tolerance if self.tolerance is None else self.tolerance


@dataclass(frozen=True)
class JointFit:
    """The result of `fit_joints` for F frames.

    joints (F, J) rad / m; base (F, 6) ``world_from_base`` as rotation vector and
    translation, or None without base motion; covariance (F, P, P) of the parameters from
    the pixel noise; information (F, P, P) its inverse without regularisation (singular
    where a joint is unobserved); residuals (C, F, M, 2) observed minus predicted px, NaN
    where not observed (divided by the tolerance's weight, if any); weights (C, F, M) final
    robust weights (both float32: a two-hour session's are large); rms_px (F,) RMS residual
    of the inlier-weighted observations; n_observations (F,) 2-D observations used; noise_px
    the pixel SD behind the covariance (given, or estimated robustly from the residuals);
    valid (F,) frames with enough observations; explained (F,) False for a valid frame
    whose residuals are far beyond the noise after every restart (the model, the labels
    or the calibration is wrong there, not the noise).
    """

    joints: np.ndarray
    base: np.ndarray | None
    covariance: np.ndarray
    information: np.ndarray
    residuals: np.ndarray
    weights: np.ndarray
    rms_px: np.ndarray
    n_observations: np.ndarray
    noise_px: float
    valid: np.ndarray
    explained: np.ndarray

    def __post_init__(self) -> None:
        n, j = np.shape(self.joints)
        p = j + (6 if self.base is not None else 0)
        if np.shape(self.covariance) != (n, p, p) or np.shape(self.information) != (n, p, p):
            raise ValueError(f"JointFit covariance and information must be ({n}, {p}, {p})")
        if self.base is not None and np.shape(self.base) != (n, 6):
            raise ValueError(f"JointFit.base must be ({n}, 6), got {np.shape(self.base)}")
        for name in ("rms_px", "n_observations", "valid", "explained"):
            if np.shape(getattr(self, name)) != (n,):
                raise ValueError(f"JointFit.{name} must be ({n},)")

    @property
    def world_from_base(self) -> np.ndarray | None:
        """(F, 4, 4) base poses, or None without base motion."""
        return None if self.base is None else base_matrices(self.base)

    @property
    def joints_sd(self) -> np.ndarray:
        """(F, J) standard deviations of the joint values."""
        j = self.joints.shape[1]
        return np.sqrt(np.diagonal(self.covariance, axis1=1, axis2=2)[:, :j])


def fit_joints(
    machine: Machine,
    cameras: list[Camera],
    pixels: np.ndarray,
    initial: np.ndarray | None = None,
    options: FitOptions | None = None,
    initial_base: np.ndarray | None = None,
) -> JointFit:
    """Fit the machine's joint values to marker pixels of every frame at once.

    Parameters
    ----------
    machine : the model, M markers and J joints.
    cameras : C calibrated cameras (one is enough).
    pixels : (C, F, M, 2) observed marker pixels, NaN where a camera did not see a marker.
    initial : (F, J) or (J,) starting joint values, or None for key frames from the
        coarse grid (frames in time order fit faster then; any order works).
    options : FitOptions.
    initial_base : (F, 6) or (6,) starting base pose with ``options.base_motion``.

    Returns
    -------
    JointFit; frames with fewer than P / 2 observations have NaN joints and valid False.
    """
    options = options or FitOptions()
    pixels = np.asarray(pixels, dtype=float)
    n_cams, n_markers, n_joints = len(cameras), len(machine.marker_names), machine.n_joints
    if pixels.ndim != 4 or pixels.shape[0] != n_cams or pixels.shape[2:] != (n_markers, 2):
        raise ValueError(
            f"pixels must have shape (C={n_cams}, F, M={n_markers}, 2), got {pixels.shape}"
        )
    n_frames = pixels.shape[1]
    start = None if initial is None else _broadcast(initial, n_frames, n_joints, "initial")
    if n_joints == 0:  # a rigid model: no joints to start from the grid
        start = np.zeros((n_frames, 0))
    start_base = None
    if options.base_motion:
        start_base = np.zeros((n_frames, 6)) if initial_base is None else _broadcast(
            initial_base, n_frames, 6, "initial_base"
        )
    problem = _Problem(machine, tuple(cameras), options)
    if start is None and n_frames > 2 * options.key_stride:
        start = problem.key_frame_start(pixels, start_base)
        state = problem.solve_all(pixels, start, start_base)
        problem.restart_from_grid(pixels, state, start_base)
    else:
        state = problem.solve_all(pixels, start, start_base)
    problem.repair(pixels, state, options.repair_passes)
    for sweep in (False, True):  # neighbours' solutions first; the grid and joint sweeps for what is left
        noise = options.noise_px or problem.noise(pixels, state)
        suspect = problem.misfit(pixels, state, noise, 1e-4, 0.2) if not sweep else problem.misfit(pixels, state, noise)
        if not suspect.any():
            break
        if sweep:
            problem.multistart(pixels, state, np.nonzero(suspect)[0])
        else:
            problem.propagate(pixels, state, np.nonzero(suspect)[0])
        problem.repair(pixels, state, n_frames)  # mended frames hand their solution on along a wrong stretch
    noise = options.noise_px or problem.noise(pixels, state)
    if problem.marker_sd is not None:  # residuals weighed by the tolerance are pixels at the nominal noise, or more
        noise = max(noise, problem.noise_px)
    # a wrong minimum whose residual is not far enough above the noise to be suspect (a few
    # markers off, taken for wild pixels by the robust loss), or a stretch of them, mended from
    # its neighbours' solutions where the pixels prefer theirs (not where they cannot tell)
    problem.propagate(pixels, state, problem.above_a_neighbour(pixels, state), margin=PREFERRED_CHI2 * noise**2)
    problem.mend_detours(pixels, state, noise)
    unexplained = problem.misfit(pixels, state, noise, floor=noise_floor(pixels))
    if unexplained.any():
        log.info("%d frame(s) that no solution explains (residuals far beyond the %.2f px noise)",
                 unexplained.sum(), noise)
    return problem.result(pixels, state, noise, unexplained)


FLOOR_WINDOW = 3  # frames either side over which a track's bend is read (a wrong frame or three do not move it)


def noise_floor(pixels: np.ndarray) -> np.ndarray:
    """(C, F, M) each observation's error that pixel noise leaves out, px SD per axis: the
    pixel quantisation (1 / sqrt(12) px where a camera's coordinates are whole pixels) and
    the error of interpolating between frames (a camera whose clock is a fraction of a frame
    off the reference is resampled linearly: at most an eighth of the track's second
    difference, read as its median over the frames within FLOOR_WINDOW, so that a wrong
    frame does not excuse itself)."""
    import warnings

    pixels = np.asarray(pixels, dtype=float)
    n_cams, n_frames, n_markers = pixels.shape[:3]
    bend = np.zeros((n_cams, n_frames, n_markers))
    if n_frames >= 3:
        second = np.full((n_cams, n_frames + 2 * FLOOR_WINDOW, n_markers), np.nan)
        second[:, FLOOR_WINDOW + 1 : FLOOR_WINDOW + n_frames - 1] = np.linalg.norm(
            pixels[:, :-2] - 2 * pixels[:, 1:-1] + pixels[:, 2:], axis=-1)
        windows = np.lib.stride_tricks.sliding_window_view(second, 2 * FLOOR_WINDOW + 1, axis=1)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a window with no bend known: no floor
            bend = np.nan_to_num(np.nanmedian(windows, axis=-1))
    seen = np.isfinite(pixels[..., 0])
    whole = np.array([bool(s.any()) and bool(np.all(p[s] == np.round(p[s]))) for p, s in zip(pixels, seen)])
    quantisation = np.where(whole, 1 / np.sqrt(12), 0.0)[:, None, None]
    return np.sqrt(quantisation**2 + (bend / 8) ** 2)


def refit(machine: Machine, cameras: list[Camera], pixels: np.ndarray, starts: np.ndarray, options: FitOptions,
          known: FrameState | None = None) -> FrameState:
    """Levenberg-Marquardt alone (no restarts) of every frame of pixels (C, F, M, 2) from
    starts (F, J) (a fixed base); with `known` (joints (F, J) and normal matrix (F, J, J) in
    px²) a frame that comes back within `_SAME_PX2` of it stops there with cost +inf."""
    problem = _Problem(machine, tuple(cameras), options)
    start = FrameState(machine.clip_to_limits(np.asarray(starts, dtype=float)), None, None, np.zeros(len(starts)))
    return problem.levenberg_marquardt(np.moveaxis(pixels, 1, 0), start, known)


class FrameFitter:
    """Frames fitted as they come (`mocap live`): Levenberg-Marquardt alone of each batch of
    frames from given starts (the frame before's solution), by the same compiled kernel as
    `fit_joints`, the model and cameras prepared once."""

    def __init__(self, machine: Machine, cameras: list[Camera], options: FitOptions | None = None):
        self._problem = _Problem(machine, tuple(cameras), options or FitOptions())

    @property
    def n_params(self) -> int:
        return self._problem.n_params

    def fit(self, pixels: np.ndarray, starts: np.ndarray, base: np.ndarray | None = None) -> FrameState:
        """pixels (C, F, M, 2) from starts (F, J) and, with base motion, base poses (F, 6)
        (rotation vector, translation): joints, base, cost, normal matrix (px²), residuals."""
        machine = self._problem.machine
        rotation = translation = None
        if self._problem.options.base_motion:
            base = np.zeros((len(starts), 6)) if base is None else np.asarray(base, dtype=float)
            rotation, translation = rotvec_to_matrix(base[:, :3]), base[:, 3:].copy()
        start = FrameState(machine.clip_to_limits(np.asarray(starts, dtype=float)), rotation, translation,
                           np.zeros(len(starts)))
        return self._problem.levenberg_marquardt(np.moveaxis(np.asarray(pixels, dtype=float), 1, 0), start)


def _broadcast(values, n_frames: int, width: int, name: str) -> np.ndarray:
    values = np.asarray(values, dtype=float)
    if values.shape == (width,):
        return np.tile(values, (n_frames, 1))
    if values.shape != (n_frames, width):
        raise ValueError(f"{name} must have shape ({n_frames}, {width}) or ({width},), got {values.shape}")
    return values.copy()


class _Problem(KinematicModel):
    """The model, cameras and options of one fit, and the batched solver."""

    def __init__(self, machine: Machine, cameras: tuple[Camera, ...], options: FitOptions):
        tolerance = options.tolerance_of(machine)
        marker_sd = tolerance.sd(machine.marker_positions) if tolerance else None
        super().__init__(machine, cameras, options.base_motion, options.loss, options.scale_px,
                         marker_sd, options.noise_px or 0.5)
        self.options = options

    def solve_all(self, pixels: np.ndarray, start: np.ndarray | None, start_base: np.ndarray | None) -> FrameState:
        """Fit every frame of pixels (C, F, M, 2) in chunks."""
        chunk = self.options.chunk
        starts = range(0, pixels.shape[1], chunk)
        return FrameState.concatenate([
            self.solve(
                pixels[:, s : s + chunk],
                None if start is None else start[s : s + chunk],
                None if start_base is None else start_base[s : s + chunk],
            )
            for s in (progress(starts, desc="fit", unit="chunk") if len(starts) > 2 else starts)
        ])

    def key_frame_start(self, pixels: np.ndarray, start_base: np.ndarray | None) -> np.ndarray:
        """Starting joints (F, J): every `key_stride`-th frame fitted from the grid (and up to
        64 of them from many starts), the frames between interpolated linearly (angles of
        full-circle joints unwrapped first)."""
        n_frames = pixels.shape[1]
        keys = np.unique(np.r_[np.arange(0, n_frames, self.options.key_stride), n_frames - 1])
        key_pixels = pixels[:, keys]
        state = self.solve_all(key_pixels, None, None if start_base is None else start_base[keys])
        # up to 64 key frames are fitted again from many starts, whatever their residuals (a
        # wrong start everywhere looks like large noise), and what they find is handed on
        probes = np.unique(np.linspace(0, len(keys) - 1, min(64, len(keys))).round().astype(int))
        self.multistart(key_pixels, state, probes)
        self.repair(key_pixels, state, len(keys))
        n_obs = np.isfinite(key_pixels[..., 0]).sum((0, 2))
        good = 2 * n_obs >= self.n_params
        if good.sum() < 2:
            return np.tile(self.machine.clip_to_limits(np.zeros(self.machine.n_joints)), (n_frames, 1))
        joints = state.joints[good]
        joints[:, self.wrap] = np.unwrap(joints[:, self.wrap], axis=0)
        frames = np.arange(n_frames)
        return np.stack([np.interp(frames, keys[good], joints[:, j]) for j in range(joints.shape[1])], 1)

    def restart_from_grid(self, pixels: np.ndarray, state: FrameState, start_base: np.ndarray | None) -> None:
        """Frames that ended far worse than is typical are fitted again from the grid; the
        better solution is kept."""
        n_obs = np.isfinite(pixels[..., 0]).sum((0, 2))
        per_obs = state.cost / np.maximum(n_obs, 1)
        typical = np.median(per_obs[n_obs > 0]) if (n_obs > 0).any() else 0.0
        bad = np.nonzero((per_obs > 4.0 * typical + self.options.scale_px**2) & (n_obs > 0))[0]
        if not len(bad):
            return
        fitted = self.solve_all(pixels[:, bad], None, None if start_base is None else start_base[bad])
        state.put(bad, fitted, fitted.cost < state.cost[bad])

    def solve(self, pixels: np.ndarray, start: np.ndarray | None, start_base: np.ndarray | None) -> FrameState:
        """Fit one chunk of frames; pixels (C, F, M, 2)."""
        pixels = np.moveaxis(pixels, 1, 0)  # (F, C, M, 2)
        joints = self.grid_start(pixels) if start is None else self.machine.clip_to_limits(start)
        rotation = translation = None
        if start_base is not None:
            rotation = rotvec_to_matrix(start_base[:, :3])
            translation = start_base[:, 3:].copy()
        return self.levenberg_marquardt(pixels, FrameState(joints, rotation, translation, np.zeros(len(joints))))

    def levenberg_marquardt(self, pixels: np.ndarray, state: FrameState, known: FrameState | None = None) -> FrameState:
        """LM from `state` for pixels (F, C, M, 2), every frame on its own until it converges
        (compiled: mocap.reconstruct.kinkernel.levenberg_marquardt).

        `known` (a solved FrameState over the same frames): a frame also leaves once it is
        within `_SAME_PX2` (its model pixels moved by less than that, squared and summed, by
        the known solution's normal matrix) of the known solution, with cost +inf: it would
        only converge to it (a restart that finds the frame's own minimum again stops early
        and is never preferred to it)."""
        from mocap.reconstruct.kinkernel import LOSS_CODES, levenberg_marquardt

        n_frames, n_rows = len(state.joints), 2 * len(self.cameras) * len(self.machine.marker_names)
        base = state.rotation is not None
        joints = np.array(state.joints, dtype=float, order="C").reshape(n_frames, self.machine.n_joints)
        rotation = np.array(state.rotation, dtype=float, order="C") if base else np.empty((0, 3, 3))
        translation = np.array(state.translation, dtype=float, order="C") if base else np.empty((0, 3))
        if known is None:
            known_arrays = (np.empty((0, joints.shape[1])), np.empty((0, 3, 3)), np.empty((0, 3)),
                            np.empty((0, self.n_params, self.n_params)))
        else:
            known_arrays = (np.ascontiguousarray(known.joints, dtype=float),
                            np.ascontiguousarray(known.rotation, dtype=float) if base else np.empty((0, 3, 3)),
                            np.ascontiguousarray(known.translation, dtype=float) if base else np.empty((0, 3)),
                            np.ascontiguousarray(known.hessian, dtype=float))
        cost, hessian = np.empty(n_frames), np.empty((n_frames, self.n_params, self.n_params))
        residual, weight = np.empty((n_frames, n_rows), np.float32), np.empty((n_frames, n_rows), np.float32)
        sd = np.empty(0) if self.marker_sd is None else self.marker_sd
        levenberg_marquardt(joints, rotation, translation, np.ascontiguousarray(pixels, dtype=float),
                            *self._chain_arrays, *self._camera_arrays, sd, float(self.noise_px),
                            LOSS_CODES[self.loss], float(self.scale_px), np.ascontiguousarray(self.lower),
                            np.ascontiguousarray(self.upper),
                            np.asarray(self.wrap, dtype=bool), self.options.iterations, _EPS_INFO, _CONVERGED,
                            *known_arrays, _SAME_PX2, cost, hessian, residual, weight)
        return FrameState(joints, rotation if base else None, translation if base else None, cost, hessian,
                          residual, weight)

    def grid_start(self, pixels: np.ndarray) -> np.ndarray:
        """The best of a coarse grid of joint values for every frame (F, J), by the sum of
        squared pixel residuals, computed as matrix products over frames and candidates."""
        candidates = self.grid()
        return candidates[np.argmin(self.grid_costs(pixels, candidates), axis=1)]

    def grid_costs(self, pixels: np.ndarray, candidates: np.ndarray) -> np.ndarray:
        """(F, K) sum of squared pixel residuals (up to a per-frame constant) of every frame
        of pixels (F, C, M, 2) at every candidate (K, J), as matrix products."""
        predicted = np.stack([c.project(self.machine.markers(candidates)) for c in self.cameras], 1)
        predicted = np.where(np.isfinite(predicted), predicted, _BEHIND_PX).reshape(len(candidates), -1)
        observed = pixels.reshape(len(pixels), -1)
        seen = np.isfinite(observed)
        obs = np.where(seen, observed, 0.0)
        return -2.0 * obs @ predicted.T + seen.astype(float) @ (predicted**2).T

    def grid(self) -> np.ndarray:
        """(K, J) candidates: a regular grid inside the limits (unbounded joints ±1 m)."""
        n_joints = self.machine.n_joints
        if n_joints == 0:  # a rigid model: one candidate, the empty joint vector
            return np.zeros((1, 0))
        lower = np.where(np.isfinite(self.lower), self.lower, -1.0)
        upper = np.where(np.isfinite(self.upper), self.upper, 1.0)
        span = upper - lower
        weights = np.where(self.wrap, 2.0, 1.0)
        levels = np.maximum(2, np.round(self.options.grid ** (weights / weights.sum()))).astype(int)
        axes = []
        for j in range(n_joints):
            if self.wrap[j]:
                axes.append(lower[j] + span[j] * np.arange(levels[j]) / levels[j])
            else:
                axes.append(lower[j] + span[j] * (np.arange(levels[j]) + 0.5) / levels[j])
        return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, n_joints)

    def repair(self, pixels: np.ndarray, state: FrameState, passes: int) -> bool:
        """Restart frames whose cost is far above a neighbour's from that neighbour's
        solution and keep the better, up to `passes` times; after the first pass only the
        frames next to one that improved are looked at again. Returns whether any frame
        improved."""
        n_frames = pixels.shape[1]
        frames, improved = np.arange(n_frames), False
        n_obs = (np.isfinite(pixels[..., 0]) & np.isfinite(pixels[..., 1])).sum((0, 2))
        for _ in range(passes):
            mended = self._repair_pass(pixels, state, frames, n_obs)
            if not len(mended):
                break
            improved = True
            frames = np.unique(np.clip(np.r_[mended - 1, mended, mended + 1], 0, n_frames - 1))
        return improved

    def above_a_neighbour(self, pixels: np.ndarray, state: FrameState) -> np.ndarray:
        """The frames whose cost per observation is above `NEIGHBOUR_RATIO` times a
        neighbour's: where a wrong minimum ends, and one frame in ten of a right fit."""
        n_obs = np.maximum(np.isfinite(pixels[..., 0]).sum((0, 2)), 1)
        per_obs = state.cost / n_obs
        above = np.zeros(len(per_obs), dtype=bool)
        above[1:] |= per_obs[1:] > NEIGHBOUR_RATIO * per_obs[:-1]
        above[:-1] |= per_obs[:-1] > NEIGHBOUR_RATIO * per_obs[1:]
        return np.nonzero(above)[0]

    def mend_detours(self, pixels: np.ndarray, state: FrameState, noise: float) -> None:
        """A stretch of at most `DETOUR_FRAMES` frames whose solution jumps away from the frame
        before's and comes back, where the solution carried on from the frame before explains
        every frame as well (a chi-square within `PREFERRED_CHI2`: the pixels cannot tell them
        apart), takes the carried one: a mirror solution that a machine moving smoothly cannot
        have reached and left. The frame it comes back to must lead back to the carried path
        (fitted from its solution, the stretch's last frame comes to the carried one: a path
        carried from a lone wrong frame comes back only by a jump of its own). A stretch
        carried to the session's first or last frame has no frame to come back to
        (`_edge_detours`). Forward, then backward in time; the shortest stretch first; a stretch whose frame before was mended
        is not one."""
        n_frames = pixels.shape[1]
        if n_frames < 3 or state.rotation is not None or self.machine.n_joints == 0:
            return
        tie, by_frame, mended = PREFERRED_CHI2 * noise**2, np.moveaxis(pixels, 1, 0), 0
        for step in (1, -1):
            later = np.arange(1, n_frames) if step == 1 else np.arange(n_frames - 1)
            jumped = later[self._far(state.joints[later - step], state.joints[later], state.hessian[later], noise)]
            if not len(jumped):
                continue
            carried = self.levenberg_marquardt(by_frame[jumped], state.take(jumped - step))
            opened = (self._far(carried.joints, state.joints[jumped], state.hessian[jumped], noise)
                      & (carried.cost < state.cost[jumped] + tie))
            starts = jumped[opened]
            path = [carried.take(np.nonzero(opened)[0])]  # path[k]: every detour's k-th frame carried on
            alive, found, edge = np.ones(len(starts), bool), [], []
            for k in range(1, DETOUR_FRAMES + 1):
                frames = starts + k * step
                inside = (frames >= 0) & (frames < n_frames)
                edge += [(k, d) for d in np.nonzero(alive & ~inside)[0]]  # carried to the session's end
                alive &= inside
                if not alive.any():
                    break
                index = np.nonzero(alive)[0]
                fitted = self.levenberg_marquardt(by_frame[frames[index]], path[-1].take(index))
                ahead = path[-1].take(np.arange(len(starts)))
                ahead.put(index, fitted, np.ones(len(index), bool))
                path.append(ahead)
                at = frames[index]
                back = ~self._far(fitted.joints, state.joints[at], state.hessian[at], noise)
                found += [(k, d) for d in index[back]]
                alive[index[back | (fitted.cost >= state.cost[at] + tie)]] = False
            if found:  # the frame it comes back to must lead back to the carried path's last frame
                k, d = np.array(found).T
                ends, last = starts[d] + k * step, FrameState.concatenate([path[k - 1].take([d]) for k, d in found])
                led = self.levenberg_marquardt(by_frame[ends - step], state.take(ends))
                found = [f for f, near in zip(found, ~self._far(led.joints, last.joints, last.hessian, noise)) if near]
            found = sorted(found + self._edge_detours(state, starts, edge, step, noise))
            changed = np.zeros(n_frames, bool)
            for k, d in found:  # shortest first
                if changed[starts[d] - step]:
                    continue
                rows = starts[d] + step * np.arange(k)
                state.put(rows, FrameState.concatenate([p.take([d]) for p in path[:k]]), np.ones(k, bool))
                changed[rows] = True
            mended += int(changed.sum())
        if mended:
            log.info("%d frame(s) on a solution the frames around them do not have, which their pixels cannot "
                     "tell from the continuous one, take the continuous one", mended)

    def _edge_detours(self, state: FrameState, starts: np.ndarray, edge: list, step: int,
                      noise: float) -> list:
        """The stretches (k, d) of `mend_detours` that the carried path explains up to the
        session's first or last frame, where there is no frame to come back to: mended
        where the frames before the stretch outnumber it and the two frames before it agree
        (the carried path comes from a continuous stretch, not from a lone wrong frame)."""
        n_frames, kept = len(state.joints), []
        for k, d in edge:
            before, earlier = starts[d] - step, starts[d] - 2 * step
            outnumbered = (before + 1 if step == 1 else n_frames - before) > k
            if outnumbered and 0 <= earlier < n_frames and not self._far(
                    state.joints[[earlier]], state.joints[[before]], state.hessian[[before]], noise)[0]:
                kept.append((k, d))
        return kept

    def _far(self, joints: np.ndarray, own: np.ndarray, hessian: np.ndarray, noise: float) -> np.ndarray:
        """(N,) joints (N, J) further than `FAR_SDS` from the solutions `own` (N, J) by their
        normal matrices (N, P, P) in px² (and `_SAME_JOINT` for joints they do not see)."""
        gap = joints - own
        gap = np.where(self.wrap, np.mod(gap + np.pi, 2 * np.pi) - np.pi, gap)
        n_joints = gap.shape[1]
        information = hessian[:, :n_joints, :n_joints] / noise**2 + np.eye(n_joints) / _SAME_JOINT**2
        return np.einsum("ni,nij,nj->n", gap, information, gap) > FAR_SDS**2

    def _repair_pass(self, pixels: np.ndarray, state: FrameState, frames: np.ndarray, n_obs: np.ndarray) -> np.ndarray:
        """One pass of `repair` over `frames` (sorted), n_obs (F,) observations per frame;
        the frames that improved."""
        n_frames, improved = pixels.shape[1], []
        per_obs = state.cost / np.maximum(n_obs, 1)
        for shift in (1, -1):
            neighbour = np.clip(frames - shift, 0, n_frames - 1)
            bad = (per_obs[frames] > 4.0 * per_obs[neighbour] + self.options.scale_px**2) & (n_obs[frames] > 0)
            if not bad.any():
                continue
            index = frames[bad]
            fitted = self.levenberg_marquardt(np.moveaxis(pixels[:, index], 1, 0), state.take(neighbour[bad]))
            better = fitted.cost < state.cost[index]
            state.put(index, fitted, better)
            per_obs[index[better]] = fitted.cost[better] / np.maximum(n_obs[index[better]], 1)
            improved.append(index[better])
        return np.unique(np.concatenate(improved)) if improved else np.zeros(0, int)

    # --- frames nothing explains -------------------------------------------------------
    def noise(self, pixels: np.ndarray, state: FrameState) -> float:
        """Pixel noise SD per axis from the median residual length of all frames (Rayleigh:
        median = 1.1774 sigma), corrected for the parameters fitted: a few wild pixels or
        wrong frames do not move it."""
        seen = np.isfinite(pixels[..., 0]).transpose(1, 0, 2).reshape(pixels.shape[1], -1)  # (F, C*M)
        length = np.hypot(*np.moveaxis(state.residual.reshape(len(seen), -1, 2), -1, 0))
        n_obs = seen.sum(1)
        valid = 2 * n_obs > self.n_params
        if not valid.any():
            return 1.0
        sigma = np.median(length[seen & valid[:, None]]) / np.sqrt(2 * np.log(2))
        dof_share = 1.0 - self.n_params * valid.sum() / (2.0 * n_obs[valid].sum())
        return float(max(sigma / np.sqrt(max(dof_share, 0.1)), 1e-6))

    def misfit(self, pixels: np.ndarray, state: FrameState, noise: float, tail: float | None = None,
               far_share: float = 0.5, floor: np.ndarray | None = None) -> np.ndarray:
        """(F,) frames whose residuals the pixel noise does not explain: more than
        `far_share` of their observations beyond 4 sigma (a chance of 3e-4 each), or, with a
        `tail`, the others' chi-square beyond that quantile. With the defaults (most pixels
        far: no pose explains the frame) wild pixels, a little model error or the clock's
        interpolation during fast motion leave a frame explained; the stricter setting
        picks the frames worth fitting again. `floor` (C, F, M) px: each observation's error
        beyond the noise (`noise_floor`: interpolation between frames, quantisation), added
        to the noise in quadrature."""
        seen = np.isfinite(pixels[..., 0]).transpose(1, 0, 2).reshape(pixels.shape[1], -1)
        variance = noise**2 if floor is None else noise**2 + floor.transpose(1, 0, 2).reshape(len(seen), -1) ** 2
        e2 = (state.residual.reshape(len(seen), -1, 2) ** 2).sum(-1) / variance
        far = seen & (e2 > 16.0)
        n_obs, n_far = seen.sum(1), far.sum(1)
        dof = 2 * (n_obs - n_far) - self.n_params
        inlier_chi2 = np.where(seen & ~far, e2, 0.0).sum(1)
        misfit = n_far > far_share * n_obs
        if tail is not None:
            limit = upper_quantile(np.maximum(dof, 1), tail)
            misfit |= (dof > 0) & (inlier_chi2 > limit)
        return (2 * n_obs > self.n_params) & misfit

    def multistart(self, pixels: np.ndarray, state: FrameState, frames: np.ndarray, sweep: bool = True) -> None:
        """Fit `frames` again from many starts and keep each frame's best: the solutions of
        frames 1 to 32 away (a wrong stretch is left from both ends) and, with `sweep`, the
        best grid candidates and each joint swept over its range with the others kept (a
        joint's mirror solutions)."""
        n_frames, n_joints = pixels.shape[1], self.machine.n_joints
        sources = [np.clip(frames + shift, 0, n_frames - 1) for step in (1, 2, 4, 8, 16, 32) for shift in (step, -step)]
        starts = [state.take(s) for s in sources]
        own = state.take(frames)
        if not sweep:
            self._keep_best(pixels, state, frames, starts)
            return
        grid = self.grid()
        predicted = self.grid_costs(np.moveaxis(pixels[:, frames], 1, 0), grid)
        for k in np.argsort(predicted, axis=1)[:, :8].T:
            starts.append(FrameState(grid[k], own.rotation, own.translation, own.cost))
        lower = np.where(np.isfinite(self.lower), self.lower, -1.0)
        upper = np.where(np.isfinite(self.upper), self.upper, 1.0)
        for j in range(n_joints):
            for level in (np.arange(6) + 0.5) / 6:
                joints = own.joints.copy()
                joints[:, j] = lower[j] + level * (upper[j] - lower[j])
                starts.append(FrameState(joints, own.rotation, own.translation, own.cost))
        self._keep_best(pixels, state, frames, starts)

    def propagate(self, pixels: np.ndarray, state: FrameState, frames: np.ndarray, margin: float = 0.0) -> None:
        """Fit `frames` again from each neighbour's solution (the frames before and after)
        and keep any improvement of the cost by more than `margin` (px²); the neighbours of a
        frame that improved are fitted again from it in turn, until nothing improves: a wrong
        stretch is mended from its ends inward, however long, at two restarts per frame and
        pass."""
        n_frames = pixels.shape[1]
        todo = np.unique(frames)
        for _ in range(n_frames):
            if not len(todo):
                break
            improved = []
            for shift in (1, -1):
                source = np.clip(todo + shift, 0, n_frames - 1)
                own = state.take(todo)
                fitted = self.levenberg_marquardt(np.moveaxis(pixels[:, todo], 1, 0), state.take(source), own)
                better = fitted.cost < own.cost - margin
                state.put(todo, fitted, better)
                improved.append(todo[better])
            improved = np.concatenate(improved)
            todo = np.unique(np.clip(np.r_[improved - 1, improved + 1], 0, n_frames - 1))

    def _keep_best(self, pixels: np.ndarray, state: FrameState, frames: np.ndarray, starts: list[FrameState]) -> None:
        """LM on `frames` from every start (each a FrameState over the frames); the best kept
        where it beats the frame's own solution."""
        tries = FrameState.concatenate([
            FrameState(s.joints, s.rotation, s.translation, s.cost) for s in starts
        ])
        repeated = np.tile(frames, len(starts))
        own = state.take(repeated)
        fitted = self.levenberg_marquardt(np.moveaxis(pixels[:, repeated], 1, 0), tries, own)
        best = np.argmin(fitted.cost.reshape(len(starts), len(frames)), axis=0)
        chosen = fitted.take(best * len(frames) + np.arange(len(frames)))
        state.put(frames, chosen, chosen.cost < state.cost[frames])

    # --- result --------------------------------------------------------------------------
    def result(self, pixels: np.ndarray, state: FrameState, noise: float, unexplained: np.ndarray) -> JointFit:
        n_cams, n_frames, n_markers, _ = pixels.shape
        hessian, residual, weight = state.hessian, state.residual, state.weight
        seen = np.isfinite(pixels).all(-1)  # (C, F, M)
        seen_rows = np.repeat(np.moveaxis(seen, 1, 0).reshape(n_frames, -1), 2, axis=1)
        n_obs = seen.sum((0, 2))
        valid = 2 * n_obs >= self.n_params
        weighted = (weight * residual**2).sum(1, dtype=float)
        inlier_weight = (weight * seen_rows).sum(1, dtype=float)
        rms = np.sqrt(weighted / np.maximum(inlier_weight, 1e-12))
        log.info("pixel noise: %.3f px", noise)
        eye = np.eye(self.n_params)
        covariance = noise**2 * np.linalg.inv(hessian + _EPS_INFO * eye)
        information = hessian / noise**2
        joints = np.where(valid[:, None], state.joints, np.nan)
        base = None
        if state.rotation is not None:
            finite = np.isfinite(state.rotation).all((1, 2)) & np.isfinite(state.translation).all(1)
            rotation = np.where(finite[:, None, None], state.rotation, np.eye(3))  # a diverged frame is no rotation
            base = np.where((valid & finite)[:, None], np.c_[matrix_to_rotvec(rotation), state.translation], np.nan)
        residual_out = np.where(seen[..., None], np.moveaxis(residual.reshape(n_frames, n_cams, n_markers, 2), 0, 1), np.nan)
        weight_out = np.moveaxis(weight[:, ::2].reshape(n_frames, n_cams, n_markers), 0, 1)
        return JointFit(
            joints=joints,
            base=base,
            covariance=covariance,
            information=np.where(valid[:, None, None], information, 0.0),
            residuals=residual_out,
            weights=np.where(seen, weight_out, np.nan),
            rms_px=np.where(valid, rms, np.nan),
            n_observations=n_obs,
            noise_px=noise,
            valid=valid,
            explained=~unexplained,
        )
