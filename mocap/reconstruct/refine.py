"""Model refinement: a bundle adjustment over many frames of the cameras, the per-frame
joint values and, optionally, the marker positions within a stated tolerance.

The cameras calibrated from one frame and a tape-measured machine (markers ±5 %) leave
errors that one frame cannot reveal; many frames of a moving machine can. The problem is
solved with scipy.optimize.least_squares (trust region, robust loss with its scale in
pixels) and an analytic sparse Jacobian: every residual depends on one camera, one frame
and one marker. A marker's offset from its measured position has a Gaussian prior of SD
``Tolerance.sd`` per coordinate (mocap.machine), expressed in pixel units through
the pixel noise. The priors also fix the gauge: a rigid motion of the base's markers
together with the cameras, or a turn of a link's markers about its joint together with
that joint's values, leaves the pixels unchanged and is resolved towards the measured
positions (so a link's mean angular marker error is not recoverable). The named points (bucket tip), which no camera sees, stay where the
model puts them relative to their links.

Camera parameters: a rotation increment (3,) on the left of ``cam_from_world``, a
translation increment (3,) and, with `fit_focal`, the log of a focal-length scale.
Shapes: C cameras, K frames used, M markers, J joints.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix

from mocap.camera import Camera, project_cam
from mocap.errors import ConvergenceError, DegenerateError
from mocap.geometry import Rigid, cross, rotvec_to_matrix
from mocap.machine import Machine, Tolerance
from mocap.reconstruct.kinfit import FitOptions, fit_joints
from mocap.reconstruct.kinmodel import FrameState, KinematicModel

log = logging.getLogger(__name__)

DEFAULT_TOLERANCE = Tolerance(0.05)  # the paper's tape measurement, when nothing is stated


@dataclass(frozen=True)
class RefineOptions:
    """frames: at most this many frames (the best-observed, spread over the session);
    markers: also refine the marker positions (always, when the tolerance is stated here or
    in the model); tolerance: how far they may be off (default: the model's, else 5 %);
    fit_focal: refine each camera's focal length; scale_px: robust loss scale;
    max_evaluations: residual evaluations allowed to the solver."""

    frames: int = 120
    markers: bool = False
    tolerance: Tolerance | None = None
    fit_focal: bool = True
    scale_px: float = 2.0
    max_evaluations: int = 100
    max_median_px: float = 1.0

    def __post_init__(self) -> None:
        if self.frames < 2 or not self.scale_px > 0 or self.max_evaluations < 1:
            raise ValueError("frames >= 2, scale_px > 0 and max_evaluations >= 1 are required")
        if not self.max_median_px > 0:
            raise ValueError("max_median_px must be positive")


@dataclass(frozen=True)
class RefineResult:
    """cameras (C) refined; machine with refined marker positions (or the input model);
    frames (K,) indices of the frames used; joints (K, J) their fitted joint values;
    rms_before / rms_after the pixel residual RMS (per coordinate) over those frames; message the solver's."""

    cameras: tuple[Camera, ...]
    machine: Machine
    frames: np.ndarray
    joints: np.ndarray
    rms_before: float
    rms_after: float
    message: str


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
    if n_joints:
        fit = fit_joints(machine, cameras, obs, options=FitOptions(scale_px=options.scale_px, tolerance=stated))
        joints, noise_px = np.nan_to_num(fit.joints), fit.noise_px
    else:  # a rigid model holds its calibration pose: no joints to start, the loss scale for the noise
        joints, noise_px = np.zeros((len(frames), 0)), options.scale_px
    problem = _Bundle(machine, tuple(cameras), obs, options, noise_px)
    x0 = np.r_[np.zeros(problem.n_camera_params * n_cams), joints.ravel(), np.zeros(3 * n_markers * options.markers)]
    before = problem.pixel_rms(x0)
    # plain least squares first: a robust loss from a start pixels off stalls the trust region
    start = least_squares(problem.residuals, x0, jac=problem.jacobian, method="trf", x_scale="jac", max_nfev=10)
    solution = least_squares(
        problem.residuals, start.x, jac=problem.jacobian, method="trf", loss="huber",
        f_scale=options.scale_px, x_scale="jac", max_nfev=options.max_evaluations,
    )
    cams, joints, refined = problem.unpack(solution.x)
    after = problem.pixel_rms(solution.x)
    log.info("bundle adjustment over %d frames: %.3f -> %.3f px (%s)", len(frames), before, after, solution.message)
    distance = np.linalg.norm(problem.pixel_residuals(solution.x), axis=-1)  # (C, K, M), 0 where not seen
    for camera, d, seen in zip(cameras, distance, problem.seen):
        median = float(np.median(d[seen])) if np.any(seen) else 0.0
        if median > options.max_median_px:
            raise ConvergenceError(
                f"camera {camera.name}'s tracks lie {median:.1f} px (median) from the refined cameras, more than "
                f"{options.max_median_px:g} px: the tracks disagree with each other (wrong labels or a bad sync?); "
                "the calibration is left as it is (check the tracks, or raise --max-median)"
            )
    return RefineResult(tuple(cams), refined, frames, joints, before, after, str(solution.message))


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
    camera parameters (C, n_camera_params), joints (K, J), marker offsets (M, 3)."""

    def __init__(self, machine: Machine, cameras: tuple[Camera, ...], pixels: np.ndarray, options: RefineOptions, noise_px: float):
        self.machine, self.cameras, self.pixels, self.options = machine, cameras, pixels, options
        self.seen = np.isfinite(pixels[..., 0])  # (C, K, M)
        self.n_camera_params = 7 if options.fit_focal else 6
        self.prior_sd = (options.tolerance or machine.tolerance or DEFAULT_TOLERANCE).sd(machine.marker_positions)
        self.noise_px = noise_px

    def unpack(self, x: np.ndarray):
        n_cams, n_frames, n_markers = self.seen.shape
        n_joints = self.machine.n_joints
        k = self.n_camera_params * n_cams
        camera_params = x[:k].reshape(n_cams, self.n_camera_params)
        joints = x[k : k + n_frames * n_joints].reshape(n_frames, n_joints)
        machine = self.machine
        if self.options.markers:
            offsets = x[k + n_frames * n_joints :].reshape(n_markers, 3)
            machine = replace(machine, marker_positions=machine.marker_positions + offsets)
        cameras = [self._camera(camera, p) for camera, p in zip(self.cameras, camera_params)]
        return cameras, joints, machine

    def _camera(self, camera: Camera, params: np.ndarray) -> Camera:
        pose = camera.cam_from_world
        rotation = rotvec_to_matrix(params[:3]) @ pose.rotation
        moved = replace(camera, cam_from_world=Rigid(rotation, pose.translation + params[3:6]))
        if self.options.fit_focal:
            matrix = camera.matrix.copy()
            matrix[:2, :2] *= np.exp(params[6])
            moved = replace(moved, matrix=matrix)
        return moved

    def pixel_residuals(self, x: np.ndarray) -> np.ndarray:
        cameras, joints, machine = self.unpack(x)
        world = machine.markers(joints)  # (K, M, 3)
        out = np.stack([c.project(world) for c in cameras])  # (C, K, M, 2)
        residual = self.pixels - out
        return np.where(self.seen[..., None], np.nan_to_num(residual, nan=1e3), 0.0)

    def residuals(self, x: np.ndarray) -> np.ndarray:
        pixel = self.pixel_residuals(x).ravel()
        if not self.options.markers:
            return pixel
        n_cams, n_frames, n_markers = self.seen.shape
        start = self.n_camera_params * n_cams + n_frames * self.machine.n_joints
        offsets = x[start:].reshape(n_markers, 3)
        return np.r_[pixel, (offsets / self.prior_sd[:, None] * self.noise_px).ravel()]

    def pixel_rms(self, x: np.ndarray) -> float:
        residual = self.pixel_residuals(x)
        return float(np.sqrt((residual**2).sum() / max(2 * self.seen.sum(), 1)))  # per coordinate

    def jacobian(self, x: np.ndarray):
        """Sparse (rows, parameters) Jacobian of `residuals`, analytic: every pixel row
        depends on its camera's parameters, its frame's joints and its marker's offset."""
        n_cams, n_frames, n_markers = self.seen.shape
        n_joints = self.machine.n_joints
        cameras, joints, machine = self.unpack(x)
        model = KinematicModel(machine, ())
        state = FrameState(joints, None, None, np.zeros(n_frames))
        world, d_joints = model.world_markers(state)  # (K, M, 3), (K, M, 3, J)
        link_rotation = machine.link_poses(joints)[:, machine.marker_links, :3, :3]  # (K, M, 3, 3)
        blocks = []
        camera_params = x[: self.n_camera_params * n_cams].reshape(n_cams, self.n_camera_params)
        for camera, params in zip(cameras, camera_params):
            rot = camera.cam_from_world.rotation
            rotated = world @ rot.T
            uv, d_uv = project_cam(rotated + camera.cam_from_world.translation, camera.matrix, camera.distortion, True)
            d_rot = np.stack([cross(np.eye(3)[i], rotated) for i in range(3)], -1) @ _left_jacobian(params[:3])
            parts = [d_uv @ d_rot, d_uv]  # rotation increment, translation
            if self.options.fit_focal:
                parts.append((uv - camera.matrix[:2, 2])[..., None])  # d uv / d log(focal scale)
            d_world = d_uv @ rot  # (K, M, 2, 3)
            parts.append(d_world @ d_joints)
            if self.options.markers:
                parts.append(d_world @ link_rotation)
            blocks.append(-np.concatenate(parts, -1))  # residual = observed - projected
        values = np.stack(blocks) * self.seen[..., None, None]  # (C, K, M, 2, columns)
        values = np.nan_to_num(values)
        c, k, m, a = np.meshgrid(np.arange(n_cams), np.arange(n_frames), np.arange(n_markers), np.arange(2), indexing="ij")
        rows = np.arange(values[..., 0].size).reshape(c.shape)
        columns = [c * self.n_camera_params + p for p in range(self.n_camera_params)]
        joint_start = self.n_camera_params * n_cams
        columns += [joint_start + k * n_joints + j for j in range(n_joints)]
        marker_start = joint_start + n_frames * n_joints
        if self.options.markers:
            columns += [marker_start + 3 * m + axis for axis in range(3)]
        column_index = np.stack(columns, -1)
        row_index = np.broadcast_to(rows[..., None], column_index.shape)
        data, row_list, col_list = [values.ravel()], [row_index.ravel()], [column_index.ravel()]
        n_rows = rows.size
        if self.options.markers:
            prior = np.arange(3 * n_markers)
            data.append(np.repeat(self.noise_px / self.prior_sd, 3))
            row_list.append(n_rows + prior)
            col_list.append(marker_start + prior)
            n_rows += 3 * n_markers
        n_params = marker_start + 3 * n_markers * self.options.markers
        return coo_matrix((np.concatenate(data), (np.concatenate(row_list), np.concatenate(col_list))), shape=(n_rows, n_params)).tocsr()


def _left_jacobian(rotvec: np.ndarray) -> np.ndarray:
    """SO(3) left Jacobian (3, 3): d exp(w) / d w as a left increment, for R = exp(w) R0."""
    theta = np.linalg.norm(rotvec)
    k = np.array([[0.0, -rotvec[2], rotvec[1]], [rotvec[2], 0.0, -rotvec[0]], [-rotvec[1], rotvec[0], 0.0]])
    if theta < 1e-8:
        return np.eye(3) + 0.5 * k
    return np.eye(3) + (1 - np.cos(theta)) / theta**2 * k + (theta - np.sin(theta)) / theta**3 * (k @ k)
