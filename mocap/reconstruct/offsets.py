"""The markers' offsets from their measured positions, estimated over a whole session
together with the per-frame fit.

A tape-measured model puts every marker a little off (the paper's ±5 %), by an offset that
is the same in every frame. Weighting the residuals by the tolerance (the per-frame fit's
way, mocap.reconstruct.kinfit) keeps that error from being taken for noise or outliers;
many frames of a moving machine show the offsets themselves. Each marker's offset, in its
link's frame, is a parameter shared by all frames, with a Gaussian prior centred on the
measured position: the tolerance read as a tape measure's, each coordinate off by up to
the fraction of itself (of at least `TAPE_FLOOR_M`) plus the metres (`tape_sd`).

The estimate is the maximum a posteriori of joints and offsets together, reached by
rounds. The first per-frame fit weighs the residuals by the tolerance, so that outliers are
judged against what the model can explain. Each round then takes one Gauss-Newton step of
the offsets with every frame's parameters eliminated (the Schur complement, as in a bundle
adjustment's reduced camera system: each frame's small normal equations folded into one
3M x 3M system), moves the markers and fits every frame again with the pixels weighed as
they are, from its last solution and afresh (as the first fit: grid, key frames, restarts),
keeping the better of the two (a frame left on a mirror solution finds its own again once
the markers are better placed). Rounds end when no offset moves by more than `SETTLED_SD`
of its SD. No offset goes beyond the tolerance (a step is cut there): the markers are
stated to be within it. Only inliers feed the offsets: observations in frames the fit
explains, within `FAR_SDS` of their prediction counting the noise and the offset's
uncertainty projected. An offset the data do not fix (a marker seen by one camera along
its line of sight, a link that never turns, a turn of a link's markers about its joint,
which the joint's values absorb) stays at the prior: its estimate near zero, its SD the
prior's.

Shapes: C cameras, F frames, M markers, J joints, P parameters of a frame.
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass, replace

import numpy as np

from mocap.core.camera import Camera, project_cam
from mocap.core.geometry import rotvec_to_matrix
from mocap.core.machine import Machine, Tolerance
from mocap.reconstruct.kinfit import FitOptions, JointFit, fit_joints
from mocap.reconstruct.kinmodel import FrameState, KinematicModel, base_matrices

log = logging.getLogger(__name__)

ROUNDS = 8  # most offsets steps
SETTLED_SD = 0.1  # the offsets have settled when no marker's step exceeds this many of its SDs
FAR_SDS = 4.0  # an observation this many SDs from its prediction is an outlier
TAPE_FLOOR_M = 0.1  # a coordinate's tolerance is at least the fraction of this
_CHUNK = 2048  # frames whose Jacobians are held at once


SHOWN_CHI2 = 13.8  # a marker's median residual over the frames this far (chi-square, 2 dof) is off: 1e-3 by chance
SHOWN_MARKERS = 3  # markers that must be off before the model is (a wild track or two is not)
SHOWN_FRAMES = 5  # frames a camera must see a marker in before its median residual counts
SHOWN_PX = 0.1  # ... and beyond this: a steadier bias is the tracker's own (a disk's centroid under
# perspective, a few hundredths of a pixel), which long, quiet tracks make significant, not the tape's
ASSUMED_TOLERANCE = Tolerance(0.05)  # the paper's tape measure, where the residuals show one and nothing states it


def markers_off(fit: JointFit) -> np.ndarray:
    """(M,) the markers that an exact model's fit (over many frames) leaves off in some
    camera: the median of their residuals over the explained frames further from zero than
    the pixel noise explains (its variance pi/2 sigma^2 / n per axis, a chi-square beyond
    `SHOWN_CHI2`) and than `SHOWN_PX`, over at least `SHOWN_FRAMES` frames. A marker the tape
    put off sits off in every frame; pixel noise averages out, and wild pixels do not move a
    median."""
    residuals = np.where((fit.valid & fit.explained)[None, :, None, None], fit.residuals, np.nan)
    n = np.isfinite(residuals[..., 0]).sum(1)  # (C, M)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a marker a camera never sees: its median NaN
        median = np.nanmedian(residuals, axis=1)
    chi2 = n * np.nansum(median**2, -1) / (np.pi / 2 * max(fit.noise_px, 1e-6) ** 2)
    material = np.hypot(*np.moveaxis(median, -1, 0)) > SHOWN_PX
    return ((n >= SHOWN_FRAMES) & (chi2 > SHOWN_CHI2) & material).any(0)


def tape_sd(tolerance: Tolerance, positions: np.ndarray) -> np.ndarray:
    """(M, 3) m, the SD of each coordinate of markers at positions (M, 3) in their link
    frames, measured by tape within `tolerance`: each coordinate off by up to the fraction of
    itself (at least of `TAPE_FLOOR_M`) plus the metres, uniformly (the bound over sqrt(3))."""
    reach = np.maximum(np.abs(np.asarray(positions, dtype=float)), TAPE_FLOOR_M)
    return np.hypot(tolerance.fraction * reach, tolerance.metres) / np.sqrt(3.0)


def tape_bound(tolerance: Tolerance, positions: np.ndarray) -> np.ndarray:
    """(M, 3) m, how far each coordinate of markers at positions (M, 3) may be from the
    truth: the fraction of the true coordinate (the measured one over 1 - fraction, a
    measurement can be short by that much) plus the metres."""
    reach = np.maximum(np.abs(np.asarray(positions, dtype=float)), TAPE_FLOOR_M)
    return tolerance.fraction * reach / (1.0 - tolerance.fraction) + tolerance.metres


@dataclass(frozen=True)
class MarkerOffsets:
    """Each marker's estimated position minus its measured one, in its link's frame.

    names (M,); offsets (M, 3) m; covariance (M, 3, 3) m² of each estimate (the prior's
    where the data add nothing); prior_sd (M, 3) m the prior's SD per coordinate;
    observations (M,) the inlier observations that fed each marker; rounds the offsets
    steps taken; settled whether the last moved the offsets by less than `SETTLED_SD`.
    """

    names: tuple[str, ...]
    offsets: np.ndarray
    covariance: np.ndarray
    prior_sd: np.ndarray
    observations: np.ndarray
    rounds: int
    settled: bool

    def __post_init__(self) -> None:
        m = len(self.names)
        for name, shape in (("offsets", (m, 3)), ("covariance", (m, 3, 3)), ("prior_sd", (m, 3)),
                            ("observations", (m,))):
            if np.shape(getattr(self, name)) != shape:
                raise ValueError(f"MarkerOffsets.{name} must be {shape}, got {np.shape(getattr(self, name))}")

    @property
    def sd(self) -> np.ndarray:
        """(M, 3) m, the SD of each offset coordinate."""
        return np.sqrt(np.diagonal(self.covariance, axis1=1, axis2=2))

    @property
    def fixed(self) -> np.ndarray:
        """(M,) markers whose offset the data fix in every direction: no direction keeps
        more than a quarter of the prior's variance."""
        whitened = self.covariance / (self.prior_sd[:, :, None] * self.prior_sd[:, None, :])
        return np.linalg.eigvalsh(whitened)[:, -1] < 0.25

    def apply(self, machine: Machine) -> Machine:
        """The model with its markers moved to their estimated positions."""
        return replace(machine, marker_positions=machine.marker_positions + self.offsets)


@dataclass(frozen=True)
class OffsetFit:
    """The result of `fit_with_offsets`: fit the per-frame JointFit of the model with its
    markers at the estimated positions (its covariance from the pixel noise alone); offsets
    the MarkerOffsets; shared (F, P, P) what the offsets' uncertainty adds to each frame's
    covariance (an error common to all frames, which smoothing does not lessen)."""

    fit: JointFit
    offsets: MarkerOffsets
    shared: np.ndarray


def fit_with_offsets(
    machine: Machine,
    cameras: list[Camera],
    pixels: np.ndarray,
    initial: np.ndarray | None = None,
    options: FitOptions | None = None,
    initial_base: np.ndarray | None = None,
) -> OffsetFit:
    """The per-frame fit of `fit_joints` with the markers' offsets estimated over all frames.

    machine: the measured model; its tolerance is ``options.tolerance`` or, if None, the
    model's own, and one of them must be stated. pixels (C, F, M, 2), NaN where not seen;
    initial, initial_base as for `fit_joints`.
    """
    options = options or FitOptions()
    tolerance = options.tolerance_of(machine)
    if not tolerance:
        raise ValueError("estimating the markers' offsets needs a stated tolerance (options.tolerance or the model's)")
    prior_sd = tape_sd(tolerance, machine.marker_positions)
    bound = tape_bound(tolerance, machine.marker_positions)
    offsets = np.zeros(prior_sd.shape)
    covariance = np.eye(3) * prior_sd[:, None, :] ** 2
    fit = fit_joints(machine, cameras, pixels, initial, options, initial_base)
    exact = replace(options, tolerance=Tolerance())  # with the offsets estimated, the pixels weighed as they are
    for rounds in range(1, ROUNDS + 1):
        moved = replace(machine, marker_positions=machine.marker_positions + offsets)
        # the first fit's noise is the nominal at least (its residuals are divided by the tolerance)
        reduced, rhs, used = offsets_system(moved, cameras, pixels, fit, offsets, prior_sd, covariance, fit.noise_px)
        full = np.linalg.inv(reduced)
        step = bounded_step(reduced, rhs, offsets.ravel(), bound.ravel()).reshape(offsets.shape)
        covariance = _marginals(full)
        distance = np.einsum("mi,mij,mj->m", step, np.linalg.inv(covariance), step)
        log.debug("offsets round %d: largest step %.2f SD", rounds, np.sqrt(distance.max(initial=0.0)))
        settled = bool((distance < SETTLED_SD**2).all())
        if settled or rounds == ROUNDS:
            break
        offsets = offsets + step
        moved = replace(machine, marker_positions=machine.marker_positions + offsets)
        start = np.where(np.isfinite(fit.joints), fit.joints, np.nan_to_num(np.nanmedian(fit.joints, axis=0)))
        base = None if fit.base is None else np.nan_to_num(fit.base)
        fit = _better(moved, cameras, exact, fit_joints(moved, cameras, pixels, start, exact, base),
                      fit_joints(moved, cameras, pixels, initial, exact, initial_base))
    if not settled:
        log.warning("the markers' offsets still moved by %.1f SD after %d rounds", np.sqrt(distance.max()), rounds)
    result = MarkerOffsets(machine.marker_names, offsets, covariance, prior_sd, used, rounds, settled)
    _log(result)
    return OffsetFit(fit, result, shared_covariance(moved, cameras, pixels, fit, full))


def _better(machine: Machine, cameras: list[Camera], options: FitOptions, one: JointFit, other: JointFit) -> JointFit:
    """Per frame, the fit of the two (of the same model, pixels and options) whose robust
    cost is lower: a frame the last round left on a mirror solution finds its own again
    from a fresh start, and one that a fresh start would put there keeps its own."""
    model = KinematicModel(machine, tuple(cameras), loss=options.loss, scale_px=options.scale_px)
    with np.errstate(divide="ignore", over="ignore"):  # the weights of unseen observations, unused
        costs = [model.robust(np.nan_to_num(np.moveaxis(f.residuals, 1, 0)).reshape(len(f.valid), -1))[1]
                 for f in (one, other)]
    take = costs[1] < costs[0]

    def pick(a, b, axis=0):
        if a is None:
            return None
        shape = [1] * np.ndim(a)
        shape[axis] = len(take)
        return np.where(take.reshape(shape), b, a)

    return JointFit(
        joints=pick(one.joints, other.joints), base=pick(one.base, other.base),
        covariance=pick(one.covariance, other.covariance), information=pick(one.information, other.information),
        residuals=pick(one.residuals, other.residuals, 1), weights=pick(one.weights, other.weights, 1),
        rms_px=pick(one.rms_px, other.rms_px), n_observations=one.n_observations, noise_px=one.noise_px,
        valid=one.valid, explained=pick(one.explained, other.explained),
    )


def offsets_system(machine: Machine, cameras: list[Camera], pixels: np.ndarray, fit: JointFit, offsets: np.ndarray,
                   prior_sd: np.ndarray, covariance: np.ndarray, noise_px: float):
    """The Gauss-Newton equations of the offsets with every frame's parameters eliminated,
    at the fit's parameters and the offsets (M, 3) already applied to `machine`; covariance
    (M, 3, 3) the offsets' present uncertainty (for the outlier test), prior_sd (M, 3),
    noise_px the pixel noise SD.

    Returns the reduced system (3M, 3M) m⁻² (its inverse the offsets' covariance), its
    right-hand side (3M,) (the step solves one with the other) and the inlier observations
    of each marker (M,).
    """
    n_markers = len(machine.marker_names)
    reduced = np.zeros((3 * n_markers, 3 * n_markers))
    rhs = -(offsets / prior_sd**2).ravel()
    used = np.zeros(n_markers, int)
    for _, cross, solved, hdd, gd, n in _eliminated(machine, cameras, pixels, fit, covariance, noise_px):
        reduced -= np.einsum("fpi,fpj->ij", cross, solved[..., :-1])
        rhs += gd.ravel() - np.einsum("fpi,fp->i", cross, solved[..., -1])
        index = np.arange(n_markers)
        reduced.reshape(n_markers, 3, n_markers, 3)[index, :, index, :] += hdd
        used += n
    reduced += np.diag(1.0 / prior_sd.ravel() ** 2)
    return 0.5 * (reduced + reduced.T), rhs, used


def bounded_step(reduced: np.ndarray, rhs: np.ndarray, offsets: np.ndarray, bound: np.ndarray) -> np.ndarray:
    """The Gauss-Newton step (N,) of offsets (N,) that stay within ±bound (N,): the
    quadratic model's minimum over the box (½ sᵀ A s − bᵀ s, A = reduced, b = rhs, as
    ½‖Lᵀs − L⁻¹b‖² with A = LLᵀ, by bounded-variable least squares). Clipping each
    coordinate of the free step instead would leave a correlated marker's step off its
    valley, and the next round would undo it."""
    from scipy.linalg import solve_triangular
    from scipy.optimize import lsq_linear

    lower = np.linalg.cholesky(reduced)
    whitened = solve_triangular(lower, rhs, lower=True)
    step = solve_triangular(lower.T, whitened, lower=False)
    if np.all(np.abs(offsets + step) <= bound):
        return step
    low, high = np.minimum(-bound - offsets, 0.0), np.maximum(bound - offsets, 0.0)  # a step of 0 is allowed
    return lsq_linear(lower.T, whitened, bounds=(low, high), method="bvls").x


def shared_covariance(machine: Machine, cameras: list[Camera], pixels: np.ndarray, fit: JointFit,
                      full: np.ndarray) -> np.ndarray:
    """(F, P, P) what the offsets' uncertainty (full (3M, 3M)) adds to each frame's
    parameter covariance: X Σ Xᵀ, X = H_qq⁻¹ H_qd the frame's response to the offsets."""
    out = np.zeros(fit.covariance.shape)
    for part, _, solved, _, _, _ in _eliminated(machine, cameras, pixels, fit, _marginals(full), fit.noise_px):
        response = solved[..., :-1]
        out[part] = response @ full @ np.swapaxes(response, 1, 2)
    return out


def _marginals(full: np.ndarray) -> np.ndarray:
    """(M, 3, 3) each marker's block of a (3M, 3M) covariance."""
    n_markers = len(full) // 3
    index = np.arange(n_markers)
    return full.reshape(n_markers, 3, n_markers, 3)[index, :, index, :]


def _eliminated(machine: Machine, cameras: list[Camera], pixels: np.ndarray, fit: JointFit, covariance: np.ndarray,
                noise_px: float):
    """Per chunk of frames: the chunk (slice), H_qd (F, P, 3M), H_qq⁻¹ [H_qd | g_q]
    (F, P, 3M + 1), the chunk's H_dd (M, 3, 3), g_d (M, 3) and inliers per marker (M,)."""
    n_params = fit.covariance.shape[1]
    for s in range(0, pixels.shape[1], _CHUNK):
        part = slice(s, s + _CHUNK)
        hqq, hqd, hdd, gq, gd, used = _normal_blocks(machine, cameras, pixels[:, part], fit, part, covariance, noise_px)
        hqq = hqq + 1e-9 * np.eye(n_params)  # a frame's joint that nothing shows stays finite
        cross = hqd.reshape(len(hqq), n_params, -1)
        solved = np.linalg.solve(hqq, np.concatenate([cross, gq[..., None]], axis=2))
        yield part, cross, solved, hdd, gd, used


def _normal_blocks(machine: Machine, cameras: list[Camera], pixels: np.ndarray, fit: JointFit, part: slice,
                   covariance: np.ndarray, noise_px: float):
    """The normal equations of frames `part` (pixels (C, F, M, 2)) over the pixel noise
    squared: per frame H_qq (F, P, P), H_qd (F, P, M, 3), g_q (F, P); summed over the
    frames H_dd (M, 3, 3) (each residual moves with one marker's offset), g_d (M, 3) and
    the inliers per marker (M,). Only the fit's valid, explained frames count, and in them
    the observations within `FAR_SDS` of their prediction, counting the noise and the
    offset's uncertainty (covariance (M, 3, 3)) projected."""
    counted = (fit.valid & fit.explained)[part]
    joints = np.nan_to_num(fit.joints[part])
    rotation = translation = world_from_base = None
    if fit.base is not None:
        base = np.nan_to_num(fit.base[part])
        rotation, translation, world_from_base = rotvec_to_matrix(base[:, :3]), base[:, 3:], base_matrices(base)
    model = KinematicModel(machine, tuple(cameras), base_motion=fit.base is not None)
    world, d_world = model.world_markers(FrameState(joints, rotation, translation, np.zeros(len(joints))))
    link_rotation = machine.link_poses(joints, world_from_base)[:, machine.marker_links, :3, :3]  # (F, M, 3, 3)
    n_frames, n_markers, n_params = len(joints), world.shape[1], d_world.shape[-1]
    hqq, gq = np.zeros((n_frames, n_params, n_params)), np.zeros((n_frames, n_params))
    hqd = np.zeros((n_frames, n_params, n_markers, 3))
    hdd, gd = np.zeros((n_markers, 3, 3)), np.zeros((n_markers, 3))
    used = np.zeros(n_markers, int)
    noise2 = noise_px**2
    for camera, observed in zip(cameras, pixels):
        rot = camera.cam_from_world.rotation
        points_cam = world @ rot.T + camera.cam_from_world.translation
        uv, d_uv = project_cam(points_cam, camera.matrix, camera.distortion, True)
        d_pixel = np.nan_to_num(d_uv @ rot)  # d pixel / d world point (F, M, 2, 3)
        jq = d_pixel @ d_world  # (F, M, 2, P)
        jd = d_pixel @ link_rotation  # (F, M, 2, 3)
        residual = observed - uv
        model2 = np.einsum("fmak,mkl,fmal->fm", jd, covariance, jd) / 2  # the offset's variance, px² per axis
        inlier = (residual**2).sum(-1) <= FAR_SDS**2 * (noise2 + model2)  # False where not seen
        inlier &= counted[:, None]
        used += inlier.sum(0)
        w = inlier / noise2
        residual = np.where(inlier[..., None], residual, 0.0) * w[..., None]
        wjq = jq * w[..., None, None]
        hqq += np.einsum("fmap,fmaq->fpq", wjq, jq)
        hqd += np.einsum("fmap,fmak->fpmk", wjq, jd)
        hdd += np.einsum("fmak,fmal,fm->mkl", jd, jd, w)
        gq += np.einsum("fmap,fma->fp", jq, residual)
        gd += np.einsum("fmak,fma->mk", jd, residual)
    return hqq, hqd, hdd, gq, gd, used


def _log(result: MarkerOffsets) -> None:
    log.info("marker offsets estimated in %d round(s); the data fix %d of %d markers", result.rounds,
             int(result.fixed.sum()), len(result.names))
    for name, offset, sd, n in zip(result.names, result.offsets, result.sd, result.observations):
        log.info("  %s: offset [%+.4f %+.4f %+.4f] m, SD [%.4f %.4f %.4f] m, %d observations", name, *offset, *sd, n)
