"""The machine model seen by one calibrated camera: predicted marker pixels, which markers
the machine's own links hide, and a small robust Gauss-Newton fit of the joint values to
labelled pixels (batched over frames; the tracker calls it with one frame at a time).

Shapes: F frames, M markers, J joints, L links.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mocap.camera import Camera, project_cam
from mocap.machine import Machine
from mocap.shapes import link_boxes


@dataclass(frozen=True)
class CameraModel:
    """A machine model and one calibrated camera; `boxes` (L, 2, 3) link solids in link frames."""

    machine: Machine
    camera: Camera
    boxes: np.ndarray = field(default=None)

    def __post_init__(self) -> None:
        if self.boxes is None:
            object.__setattr__(self, "boxes", link_boxes(self.machine))
        if np.shape(self.boxes) != (len(self.machine.links), 2, 3):
            raise ValueError(f"boxes must be (L={len(self.machine.links)}, 2, 3), got {np.shape(self.boxes)}")

    def pixels(self, joints: np.ndarray) -> np.ndarray:
        """Marker pixels (F, M, 2) for joint values (F, J); NaN behind the camera."""
        return self.camera.project(self.machine.markers(joints))

    def visible(self, joints: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """(F, M) bool: in the image (`margin_px` inside its border), in front of the camera
        and not hidden by a link's box (its own included: a marker on a box's far side)."""
        joints = np.atleast_2d(joints)
        uv = self.pixels(joints)
        w, h = self.camera.size
        inside = np.all(np.isfinite(uv), axis=-1)
        inside &= (uv[..., 0] >= margin_px) & (uv[..., 0] <= w - 1 - margin_px)
        inside &= (uv[..., 1] >= margin_px) & (uv[..., 1] <= h - 1 - margin_px)
        return inside & ~self.hidden(joints)

    def hidden(self, joints: np.ndarray) -> np.ndarray:
        """(F, M) bool: the segment from the camera to the marker passes through a link box
        before reaching it (slab test in each link's frame)."""
        joints = np.atleast_2d(joints)
        poses = self.machine.link_poses(joints)  # (F, L, 4, 4) world_from_link
        markers = self.machine.markers(joints)  # (F, M, 3)
        link_from_world_rot = np.swapaxes(poses[:, :, :3, :3], -1, -2)  # (F, L, 3, 3)
        origin = np.einsum("flij,flj->fli", link_from_world_rot, self.camera.center - poses[:, :, :3, 3])
        target = np.einsum("flij,flmj->flmi", link_from_world_rot, markers[:, None] - poses[:, :, None, :3, 3])
        direction = target - origin[:, :, None]  # (F, L, M, 3), t in [0, 1] along it
        with np.errstate(divide="ignore", invalid="ignore"):
            t0 = (self.boxes[None, :, None, 0] - origin[:, :, None]) / direction
            t1 = (self.boxes[None, :, None, 1] - origin[:, :, None]) / direction
        t_enter = np.nanmax(np.minimum(t0, t1), axis=-1)
        t_exit = np.nanmin(np.maximum(t0, t1), axis=-1)
        # entering a box clearly before the marker (1 cm before it) hides it
        size = np.linalg.norm(direction, axis=-1)
        return np.any((t_enter < t_exit) & (t_exit > 0) & (t_enter < 1.0 - 0.01 / size), axis=1)

    def fit(
        self,
        pixels: np.ndarray,
        start: np.ndarray,
        iterations: int = 6,
        scale_px: float = 2.0,
        prior_weight: float = 1e-2,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Joint values that best explain labelled pixels, by robust Gauss-Newton.

        Parameters
        ----------
        pixels : (F, M, 2) observed marker pixels, NaN where a marker was not found.
        start : (F, J) or (J,) starting joint values (rad / m).
        iterations : Gauss-Newton steps.
        scale_px : Huber scale of the pixel residuals.
        prior_weight : weight (px² per unit²) pulling unobserved joints to `start`.

        Returns
        -------
        joints (F, J), clipped to the limits, and residuals (F, M) px (NaN where not observed).
        """
        pixels = np.asarray(pixels, dtype=float)
        start = np.broadcast_to(np.asarray(start, dtype=float), (len(pixels), self.machine.n_joints))
        observed = np.all(np.isfinite(pixels), axis=-1)  # (F, M)
        target = np.where(observed[..., None], pixels, 0.0)
        rotation = self.camera.cam_from_world.rotation
        n_joints = self.machine.n_joints
        joints = start.copy()
        for _ in range(iterations):
            residual, jac = self._residuals(joints, target, rotation)
            norm = np.linalg.norm(residual, axis=-1)
            weight = np.where(observed & np.isfinite(norm), np.minimum(1.0, scale_px / np.maximum(norm, 1e-12)), 0.0)
            residual = np.where(weight[..., None] > 0, residual, 0.0)
            jac = np.where(weight[..., None, None] > 0, jac, 0.0)
            normal = np.einsum("fm,fmaj,fmak->fjk", weight, jac, jac) + prior_weight * np.eye(n_joints)
            gradient = np.einsum("fm,fmaj,fma->fj", weight, jac, residual)
            gradient += prior_weight * (joints - start)
            joints = self.machine.clip_to_limits(joints - np.linalg.solve(normal, gradient[..., None])[..., 0])
        residual, _ = self._residuals(joints, target, rotation)
        return joints, np.where(observed, np.linalg.norm(residual, axis=-1), np.nan)

    def _residuals(self, joints, target, rotation):
        markers, dmarkers = self.machine.markers_with_jacobian(joints)  # (F, M, 3), (F, M, 3, J)
        points_cam = self.camera.cam_from_world.apply(markers)
        uv, duv = project_cam(points_cam, self.camera.matrix, self.camera.distortion, with_jacobian=True)
        jac = np.einsum("fmac,cd,fmdj->fmaj", duv, rotation, dmarkers)  # (F, M, 2, J)
        return uv - target, jac
