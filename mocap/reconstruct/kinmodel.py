"""The kinematic model seen by cameras, as the fit and the uncertainty propagation use it:
marker positions and their analytic derivatives by the per-frame parameters, projected
residuals and Jacobians, robust weights, and limit-respecting parameter steps.

Parameters of a frame, in this order: joint values (J,) rad / m, then with base motion a
rotation increment (3,) rad applied on the left of ``world_from_base`` and its
translation (3,) m. Shapes: C cameras, F frames, M markers, J joints, P parameters,
N = C * M * 2 residual rows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mocap.core.camera import Camera, project_cam
from mocap.core.geometry import rotvec_to_matrix
from mocap.core.machine import Machine

LOSSES = ("huber", "cauchy", "linear")


def base_matrices(base: np.ndarray) -> np.ndarray:
    """(F, 6) rotation vector and translation -> (F, 4, 4) ``world_from_base``."""
    out = np.tile(np.eye(4), (len(base), 1, 1))
    out[:, :3, :3] = rotvec_to_matrix(base[:, :3])
    out[:, :3, 3] = base[:, 3:]
    return out


@dataclass
class FrameState:
    """Mutable per-frame solver state: joints (F, J), base rotation (F, 3, 3) and
    translation (F, 3) or None, robust cost (F,); after a solve also the weighted normal
    matrix (F, P, P), residuals (F, N) and robust weights (F, N) at the solution."""

    joints: np.ndarray
    rotation: np.ndarray | None
    translation: np.ndarray | None
    cost: np.ndarray
    hessian: np.ndarray | None = None
    residual: np.ndarray | None = None
    weight: np.ndarray | None = None

    _FIELDS = ("joints", "rotation", "translation", "cost", "hessian", "residual", "weight")

    @staticmethod
    def concatenate(parts: list[FrameState]) -> FrameState:
        return FrameState(*(
            None if getattr(parts[0], f) is None else np.concatenate([getattr(p, f) for p in parts])
            for f in FrameState._FIELDS
        ))

    def take(self, index: np.ndarray) -> FrameState:
        return FrameState(*(None if getattr(self, f) is None else getattr(self, f)[index] for f in self._FIELDS))

    def put(self, index: np.ndarray, other: FrameState, mask: np.ndarray) -> None:
        target = index[mask]
        for f in self._FIELDS:
            if getattr(self, f) is not None:
                getattr(self, f)[target] = getattr(other, f)[mask]


class KinematicModel:
    """A machine seen by cameras: residuals and Jacobians of marker pixels for per-frame
    parameters, robust weights, and parameter steps that respect the joint limits."""

    def __init__(self, machine: Machine, cameras: tuple[Camera, ...], base_motion: bool = False,
                 loss: str = "huber", scale_px: float = 2.0, marker_sd: np.ndarray | None = None,
                 noise_px: float = 0.5):
        """`marker_sd` (M,) m: each marker's position uncertainty (the model's tolerance);
        each residual is then divided by sqrt(1 + (t / noise_px)²), t the SD (px) of that
        uncertainty projected into the camera (focal / depth), so that the residuals stay
        in pixels at the noise level and far or uncertain markers weigh less."""
        self.machine = machine
        self.cameras = cameras
        self.loss, self.scale_px = loss, scale_px
        self.marker_sd = None if marker_sd is None else np.asarray(marker_sd, dtype=float)
        self.noise_px = noise_px
        limits = machine.joint_limits.astype(float)
        self.wrap = machine.wraps
        self.lower, self.upper = limits[:, 0], limits[:, 1]
        self.n_params = machine.n_joints + (6 if base_motion else 0)
        self.moves = machine.moves[:, machine.marker_links]  # (J, M)
        self._camera_arrays = (
            np.array([c.cam_from_world.rotation for c in cameras], dtype=float).reshape(-1, 3, 3),
            np.array([c.cam_from_world.translation for c in cameras], dtype=float).reshape(-1, 3),
            np.array([[c.matrix[0, 0], c.matrix[0, 1], c.matrix[0, 2], c.matrix[1, 1], c.matrix[1, 2]]
                      for c in cameras], dtype=float).reshape(-1, 5),
            np.array([np.broadcast_to(c.distortion, 5) for c in cameras], dtype=float).reshape(-1, 5),
        )
        first, second = machine._motion_terms
        revolute, parents, at_zero, axes = machine._chain
        self._chain_arrays = (
            first, second, np.asarray(revolute, dtype=bool), np.asarray(parents, dtype=np.int64), np.ascontiguousarray(at_zero, dtype=float),
            np.asarray(machine.joint_links, dtype=np.int64).reshape(-1), np.ascontiguousarray(axes),
            np.asarray(machine.marker_links, dtype=np.int64).reshape(-1),
            np.ascontiguousarray(machine.marker_positions, dtype=float).reshape(-1, 3),
            np.ascontiguousarray(self.moves, dtype=bool).reshape(machine.n_joints, len(machine.marker_names)), len(machine.links),
        )

    def world_markers(self, state: FrameState):
        """Markers in the world (F, M, 3) and their derivatives by the parameters (F, M, 3, P).

        Revolute joint j moving marker m: d p / d q_j = a_j x (p - o_j) with a_j the joint's
        axis and o_j its origin in the world; prismatic: a_j. Base rotation increment w
        (on the left): d p / d w = -[p - t]x; base translation: the identity.
        """
        from mocap.reconstruct.kinkernel import world_markers

        machine, joints = self.machine, np.ascontiguousarray(state.joints, dtype=float)
        n_frames = len(joints)
        markers = np.empty((n_frames, len(machine.marker_names), 3))
        d_world = np.empty(markers.shape + (self.n_params,))
        if state.rotation is None:
            rotation, translation = np.empty((0, 3, 3)), np.empty((0, 3))
        else:
            rotation = np.ascontiguousarray(state.rotation, dtype=float)
            translation = np.ascontiguousarray(state.translation, dtype=float)
        world_markers(joints.reshape(n_frames, machine.n_joints), rotation, translation, *self._chain_arrays,
                      markers, d_world)
        return markers, d_world

    def evaluate(self, pixels: np.ndarray, state: FrameState):
        """For pixels (F, C, M, 2): residuals (F, N) with N = C * M * 2 (zero where
        unobserved) and Jacobians (F, N, P) of the predicted pixels by the parameters."""
        markers, d_world = self.world_markers(state)
        n_frames, n_markers = markers.shape[:2]
        residual = np.empty((n_frames, len(self.cameras), n_markers, 2))
        jac = np.empty((n_frames, len(self.cameras), n_markers, 2, self.n_params))
        for c, camera in enumerate(self.cameras):
            rot = camera.cam_from_world.rotation
            points_cam = markers @ rot.T + camera.cam_from_world.translation
            uv, d_uv = project_cam(points_cam, camera.matrix, camera.distortion, with_jacobian=True)
            seen = np.isfinite(pixels[:, c, :, 0]) & np.isfinite(uv[..., 0])
            weight = seen.astype(float)  # (F, M)
            if self.marker_sd is not None:
                model_px = self.marker_sd * camera.focal / np.abs(points_cam[..., 2])
                weight = weight / np.sqrt(1.0 + (model_px / self.noise_px) ** 2)
            residual[:, c] = np.where(seen[..., None], (pixels[:, c] - uv) * weight[..., None], 0.0)
            d_uv_world = (d_uv.reshape(-1, 3) @ rot).reshape(d_uv.shape) * weight[..., None, None]
            np.matmul(d_uv_world, d_world, out=jac[:, c])
        return residual.reshape(n_frames, -1), jac.reshape(n_frames, -1, self.n_params)

    def robust(self, residual: np.ndarray):
        """Per-observation weights and per-frame cost for residuals (F, N)."""
        r2 = (residual.reshape(residual.shape[0], -1, 2) ** 2).sum(-1)  # (F, C*M)
        s = self.scale_px
        if self.loss == "huber":
            e = np.sqrt(r2)
            weight = np.where(e <= s, 1.0, s / np.maximum(e, 1e-300))
            rho = np.where(e <= s, r2, 2 * s * e - s * s)
        elif self.loss == "cauchy":
            weight = 1.0 / (1.0 + r2 / (s * s))
            rho = s * s * np.log1p(r2 / (s * s))
        else:
            weight, rho = np.ones_like(r2), r2
        return np.repeat(weight, 2, axis=1), rho.sum(1)

    def step(self, state: FrameState, delta: np.ndarray) -> FrameState:
        n_joints = self.machine.n_joints
        joints = state.joints + delta[:, :n_joints]
        span = self.upper - self.lower
        wrapped = self.lower + np.mod(joints - self.lower, np.where(self.wrap, span, 1.0))
        joints = np.where(self.wrap, wrapped, np.clip(joints, self.lower, self.upper))
        if state.rotation is None:
            return FrameState(joints, None, None, state.cost)
        rotation = rotvec_to_matrix(delta[:, n_joints : n_joints + 3]) @ state.rotation
        return FrameState(joints, rotation, state.translation + delta[:, n_joints + 3 :], state.cost)

