"""The calibration least-squares problem: parameters, residuals and their analytic Jacobian.

Unknowns, packed in one vector by `Layout`: per camera its rotation (Rodrigues vector,
world -> camera), translation (m), focal length f = fx = fy (px) and, as options, the
principal point (px) and distortion coefficients; then the machine's joint values (rad / m)
at the calibration frame, shared by all cameras or one set per camera (`per_camera`).
Residuals are projected minus observed pixels, (2N,) for N observations.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from mocap.core.camera import DISTORTION_MODELS, Camera, project_cam
from mocap.core.geometry import Rigid

BEHIND_PX = 1e4  # the residual of a marker behind its camera (finite, so that the solver can start)
_DISTORTION_NAMES = ("k1", "k2", "p1", "p2", "k3")


@dataclass(frozen=True)
class Observations:
    """N marker pixels of one frame: camera (N,) index, marker (N,) index, xy (N, 2) px."""

    camera: np.ndarray
    marker: np.ndarray
    xy: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.camera)
        if len(self.marker) != n or np.shape(self.xy) != (n, 2):
            raise ValueError("Observations: camera (N,), marker (N,) and xy (N, 2) must agree")

    def __len__(self) -> int:
        return len(self.camera)

    def select(self, mask: np.ndarray) -> Observations:
        return Observations(self.camera[mask], self.marker[mask], self.xy[mask])


@dataclass(frozen=True)
class Layout:
    """Where each unknown sits in the parameter vector."""

    n_cameras: int
    n_joints: int
    per_camera: bool = False
    fit_principal_point: bool = False
    distortion: str = "none"
    n_markers: int = 0  # M markers whose offsets from their measured positions are unknowns too
    fixed_intrinsics: frozenset[str] = frozenset()  # cameras whose K and distortion are their templates'

    @property
    def distortion_terms(self) -> tuple[int, ...]:
        return DISTORTION_MODELS[self.distortion]

    @property
    def camera_size(self) -> int:
        return 7 + 2 * self.fit_principal_point + len(self.distortion_terms)

    @property
    def size(self) -> int:
        joints = self.n_joints * (self.n_cameras if self.per_camera else 1)
        return self.n_cameras * self.camera_size + joints + 3 * self.n_markers

    @property
    def offset_slice(self) -> slice:
        """The markers' offsets (M * 3,), m in their links' frames, last in the vector."""
        return slice(self.size - 3 * self.n_markers, self.size)

    def camera_slice(self, c: int) -> slice:
        return slice(c * self.camera_size, (c + 1) * self.camera_size)

    def joint_slice(self, c: int) -> slice:
        start = self.n_cameras * self.camera_size + (c * self.n_joints if self.per_camera else 0)
        return slice(start, start + self.n_joints)

    def names(self, camera_names, joint_names, marker_names=()) -> list[str]:
        out = []
        for name in camera_names:
            out += [f"{name}.r{a}" for a in "xyz"] + [f"{name}.t{a}" for a in "xyz"] + [f"{name}.f"]
            if self.fit_principal_point:
                out += [f"{name}.cx", f"{name}.cy"]
            out += [f"{name}.{_DISTORTION_NAMES[k]}" for k in self.distortion_terms]
        for c in range(self.n_cameras if self.per_camera else 1):
            prefix = f"{camera_names[c]}." if self.per_camera else ""
            out += [prefix + j for j in joint_names]
        out += [f"{m}.d{a}" for m in list(marker_names)[: self.n_markers] for a in "xyz"]
        return out

    def kinds(self, camera_names, joint_names, marker_names=()) -> list[tuple]:
        """Per parameter: ("camera", camera, parameter), ("joint", camera or None, joint) or
        ("marker", None, offset)."""
        first_offset = self.offset_slice.start
        return [
            ("marker", None, name) if i >= first_offset
            else ("joint", name.split(".")[0] if self.per_camera else None, name.rsplit(".", 1)[-1])
            if i >= self.n_cameras * self.camera_size
            else ("camera", camera_names[i // self.camera_size], name.split(".", 1)[1])
            for i, name in enumerate(self.names(camera_names, joint_names, marker_names))
        ]

    def pack(self, cameras: list[Camera], joints: np.ndarray) -> np.ndarray:
        """Cameras and joint values ((J,), or (C, J) per camera) -> parameter vector."""
        x = np.empty(self.size)
        for c, camera in enumerate(cameras):
            block = [camera.cam_from_world.rotvec, camera.cam_from_world.translation, [camera.focal]]
            if self.fit_principal_point:
                block.append(camera.matrix[:2, 2])
            block.append(camera.distortion[list(self.distortion_terms)])
            x[self.camera_slice(c)] = np.concatenate(block)
        joints = np.asarray(joints, dtype=float)
        for c in range(self.n_cameras if self.per_camera else 1):
            x[self.joint_slice(c)] = joints[c] if self.per_camera else joints
        x[self.offset_slice] = 0.0
        return x

    def unpack(self, x: np.ndarray, templates: list[Camera]) -> tuple[list[Camera], np.ndarray]:
        """Parameter vector -> cameras (names, sizes and unfitted intrinsics from `templates`)
        and joint values ((J,), or (C, J) per camera)."""
        cameras = []
        for c, template in enumerate(templates):
            block = x[self.camera_slice(c)]
            matrix, distortion = self.intrinsics(block, template)
            pose = Rigid.from_rotvec(block[:3], block[3:6])
            cameras.append(Camera(template.name, template.size, matrix, distortion, pose))
        if self.per_camera:
            joints = np.stack([x[self.joint_slice(c)] for c in range(self.n_cameras)])
        else:
            joints = x[self.joint_slice(0)].copy()
        return cameras, joints

    def intrinsics(self, block: np.ndarray, template: Camera) -> tuple[np.ndarray, np.ndarray]:
        """K (3, 3) and distortion (5,) of a camera's parameter block; the values not fitted
        come from `template` (all of them for a camera in `fixed_intrinsics`, whose block's
        intrinsics are placeholders held at their start)."""
        if template.name in self.fixed_intrinsics:
            return template.matrix.copy(), template.distortion.copy()
        matrix = template.matrix.copy()
        matrix[0, 0] = matrix[1, 1] = block[6]
        matrix[0, 1] = 0.0
        k = 7
        if self.fit_principal_point:
            matrix[:2, 2] = block[7:9]
            k = 9
        distortion = template.distortion.copy()
        distortion[list(self.distortion_terms)] = block[k:]
        return matrix, distortion


class Problem:
    """Residuals and Jacobian of one frame's marker pixels for a machine and cameras.

    With `layout.n_markers`, the markers' offsets from their measured positions are
    unknowns too, each coordinate with a Gaussian prior of SD `marker_sd` (M,) m: 3M rows
    ``prior_px * offset / sd`` follow the 2N pixel rows (the prior in pixel units at a
    pixel noise of `prior_px`).
    """

    def __init__(self, machine, observations: Observations, layout: Layout, templates: list[Camera],
                 marker_sd: np.ndarray | None = None, prior_px: float = 1.0):
        self.machine = machine
        self.obs = observations
        self.layout = layout
        self.templates = templates
        self._rows = [np.nonzero(observations.camera == c)[0] for c in range(layout.n_cameras)]
        if layout.n_markers and (marker_sd is None or np.shape(marker_sd) not in ((layout.n_markers,),
                                                                                   (layout.n_markers, 3))):
            raise ValueError(f"marker offsets need marker_sd of shape ({layout.n_markers},) or ({layout.n_markers}, 3)")
        self.prior_px = prior_px
        self._prior = None if not layout.n_markers else prior_px / np.broadcast_to(
            np.asarray(marker_sd, float).reshape(layout.n_markers, -1), (layout.n_markers, 3)).ravel()

    @property
    def n_pixel_rows(self) -> int:
        return 2 * len(self.obs)

    def residuals(self, x: np.ndarray) -> np.ndarray:
        out = self._evaluate(x, jacobian=False)
        return out if self._prior is None else np.r_[out, self._prior * x[self.layout.offset_slice]]

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        out = self._evaluate(x, jacobian=True)
        if self._prior is None:
            return out
        prior = np.zeros((len(self._prior), self.layout.size))
        prior[:, self.layout.offset_slice] = np.diag(self._prior)
        return np.r_[out, prior]

    def machine_at(self, x: np.ndarray):
        """The machine with its markers moved by the offsets in `x` (itself without)."""
        if not self.layout.n_markers:
            return self.machine
        offsets = x[self.layout.offset_slice].reshape(-1, 3)
        return replace(self.machine, marker_positions=self.machine.marker_positions + offsets)

    def _evaluate(self, x: np.ndarray, jacobian: bool) -> np.ndarray:
        layout, obs = self.layout, self.obs
        machine = self.machine_at(x)
        n = len(obs)
        residuals = np.empty((n, 2))
        jac = np.zeros((n, 2, layout.size)) if jacobian else None
        groups = range(layout.n_cameras) if layout.per_camera else [None]
        for g in groups:
            q = x[layout.joint_slice(0 if g is None else g)]
            if jacobian:
                world, d_world_d_q = machine.markers_with_jacobian(q[None])
                world, d_world_d_q = world[0], d_world_d_q[0]
                if layout.n_markers:  # d world / d offset: the marker's link's rotation
                    world_from_link = machine.link_poses(q[None])[0, :, :3, :3][machine.marker_links]
            else:
                world = machine.markers(q[None])[0]
            for c, template in enumerate(self.templates):
                if g is not None and c != g:
                    continue
                rows = self._rows[c]
                if not len(rows):
                    continue
                start = layout.camera_slice(c).start
                block = x[start : start + layout.camera_size]
                matrix, distortion = layout.intrinsics(block, template)
                rotation, d_rotation = cv2.Rodrigues(block[:3])  # d_rotation (3, 9): d R.flat / d rvec
                points = world[obs.marker[rows]]
                points_cam = points @ rotation.T + block[3:6]
                projected = project_cam(points_cam, matrix, distortion, jacobian)
                uv, d_uv_d_cam = projected if jacobian else (projected, None)
                behind = ~np.isfinite(uv[:, 0])  # a start with markers behind the camera: a flat penalty
                residuals[rows] = np.where(behind[:, None], BEHIND_PX, uv - obs.xy[rows])
                if jacobian:
                    uv, d_uv_d_cam = np.nan_to_num(uv), np.nan_to_num(d_uv_d_cam)
                    self._camera_jacobian(jac, rows, start, matrix, d_rotation, points, points_cam, uv, d_uv_d_cam)
                    jac[rows[behind]] = 0.0
                    d_uv_d_world = d_uv_d_cam @ rotation
                    cols = layout.joint_slice(c if layout.per_camera else 0)
                    jac[rows, :, cols] = d_uv_d_world @ d_world_d_q[obs.marker[rows]]
                    if layout.n_markers:
                        first = layout.offset_slice.start + 3 * obs.marker[rows]
                        d_offset = d_uv_d_world @ world_from_link[obs.marker[rows]]  # (n, 2, 3)
                        for a in range(3):
                            jac[rows, :, first + a] = d_offset[:, :, a]
        return jac.reshape(2 * n, layout.size) if jacobian else residuals.reshape(-1)

    def _camera_jacobian(self, jac, rows, start, matrix, d_rotation, points, points_cam, uv, d_uv_d_cam):
        layout = self.layout
        d_rotation = d_rotation.reshape(3, 3, 3)  # [k, i, j] = d R_ij / d rvec_k
        d_cam_d_rvec = np.einsum("kij,nj->nik", d_rotation, points)  # (n, 3, 3)
        jac[rows, :, start : start + 3] = d_uv_d_cam @ d_cam_d_rvec
        jac[rows, :, start + 3 : start + 6] = d_uv_d_cam
        focal = matrix[0, 0]
        jac[rows, :, start + 6] = (uv - matrix[:2, 2]) / focal
        k = start + 7
        if layout.fit_principal_point:
            jac[rows, 0, k] = 1.0
            jac[rows, 1, k + 1] = 1.0
            k += 2
        if layout.distortion_terms:
            x = points_cam[:, 0] / points_cam[:, 2]
            y = points_cam[:, 1] / points_cam[:, 2]
            r2 = x * x + y * y
            d_normalised = {
                0: (x * r2, y * r2),
                1: (x * r2 * r2, y * r2 * r2),
                2: (2 * x * y, r2 + 2 * y * y),
                3: (r2 + 2 * x * x, 2 * x * y),
                4: (x * r2**3, y * r2**3),
            }
            for term in layout.distortion_terms:
                dx, dy = d_normalised[term]
                jac[rows, 0, k] = focal * dx
                jac[rows, 1, k] = focal * dy
                k += 1
