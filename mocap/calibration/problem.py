"""The calibration least-squares problem: parameters, residuals and their analytic Jacobian.

Unknowns, packed in one vector by `Layout`: per camera its rotation (Rodrigues vector,
world -> camera), translation (m), focal length f = fx = fy (px) and, as options, the
principal point (px) and distortion coefficients; then the machine's joint values (rad / m)
at the calibration frame, shared by all cameras or one set per camera (`per_camera`).
Residuals are projected minus observed pixels, (2N,) for N observations.

`Problem` evaluates the residuals and their Jacobian together in one compiled pass
(`problem_kernel.evaluate`) and keeps the last x's: the solver asks for the Jacobian at
the x whose residuals it has just taken.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from mocap.calibration.problem_kernel import BEHIND_PX, evaluate
from mocap.core.camera import DISTORTION_MODELS, Camera
from mocap.core.geometry import Rigid

__all__ = ["BEHIND_PX", "Layout", "Observations", "Problem"]
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
        if layout.n_markers and (marker_sd is None or np.shape(marker_sd) not in ((layout.n_markers,),
                                                                                   (layout.n_markers, 3))):
            raise ValueError(f"marker offsets need marker_sd of shape ({layout.n_markers},) or ({layout.n_markers}, 3)")
        self.prior_px = prior_px
        self._prior = None if not layout.n_markers else prior_px / np.broadcast_to(
            np.asarray(marker_sd, float).reshape(layout.n_markers, -1), (layout.n_markers, 3)).ravel()
        # the evaluation's fixed inputs as the compiled kernel takes them
        self._camera = _owned(observations.camera, np.int64)
        self._marker = _owned(observations.marker, np.int64)
        self._xy = _owned(observations.xy, float).reshape(-1, 2)
        self._group = self._camera.copy() if layout.per_camera else np.zeros(len(observations), dtype=np.int64)
        revolute, parents, at_zero, axes = machine._chain
        first, second = machine._motion_terms  # motion(q) = I + a(q) A + b(q) B (Machine.link_poses)
        self._parents, self._revolute = _owned(parents, np.int64), _owned(revolute, bool)
        self._at_zero, self._axes = _owned(at_zero, float), _owned(axes, float)
        self._first, self._second = _owned(first, float), _owned(second, float)
        self._joint_links = _owned(machine.joint_links, np.int64)
        self._marker_links = _owned(machine.marker_links, np.int64)
        self._positions = _owned(machine.marker_positions, float).reshape(-1, 3)
        self._moves = _owned(machine.marker_moves, bool)
        groups = range(layout.n_cameras if layout.per_camera else 1)
        self._camera_start = _owned([layout.camera_slice(c).start for c in range(layout.n_cameras)], np.int64)
        self._joint_start = _owned([layout.joint_slice(g).start for g in groups], np.int64)
        self._fitted = _owned([t.name not in layout.fixed_intrinsics for t in templates], bool)
        self._matrices = _owned([t.matrix for t in templates], float).reshape(-1, 3, 3)
        self._distortions = _owned([t.distortion for t in templates], float).reshape(-1, 5)
        self._terms = _owned(layout.distortion_terms, np.int64)
        self._offset_start = int(layout.offset_slice.start) if layout.n_markers else -1
        self._prior_weights = np.zeros(0) if self._prior is None else _owned(self._prior, float)
        self._shape = (2 * len(observations) + 3 * layout.n_markers, layout.size)
        self._last = None  # (x, residuals, Jacobian) of the last evaluation

    @property
    def n_pixel_rows(self) -> int:
        return 2 * len(self.obs)

    def residuals(self, x: np.ndarray) -> np.ndarray:
        return self._evaluate(x)[0].copy()

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        return self._evaluate(x)[1].copy()

    def machine_at(self, x: np.ndarray):
        """The machine with its markers moved by the offsets in `x` (itself without)."""
        if not self.layout.n_markers:
            return self.machine
        offsets = x[self.layout.offset_slice].reshape(-1, 3)
        return replace(self.machine, marker_positions=self.machine.marker_positions + offsets)

    def _evaluate(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residuals (2N + 3M,) and Jacobian (2N + 3M, P) at x, both at once (the solver
        asks for the Jacobian at the x whose residuals it has just taken): the last x's kept."""
        if self._last is not None and np.array_equal(self._last[0], x):
            return self._last[1], self._last[2]
        x = np.array(x, dtype=float)
        residuals, jac = np.empty(self._shape[0]), np.zeros(self._shape)
        evaluate(x, self._camera, self._marker, self._group, self._xy, self._parents, self._joint_links,
                 self._at_zero, self._first, self._second, self._revolute, self._axes, len(self.machine.links),
                 self._marker_links, self._positions, self._moves, self._camera_start, self._joint_start,
                 self._fitted, self._matrices, self._distortions, self._terms, bool(self.layout.fit_principal_point),
                 self._offset_start, self._prior_weights, residuals, jac)
        self._last = (x, residuals, jac)
        return residuals, jac


def _owned(values, dtype) -> np.ndarray:
    """A fresh writeable C-ordered array of `values`: the compiled kernel's one signature
    for every problem (a Fortran-ordered or read-only input would compile another)."""
    return np.array(values, dtype=dtype, order="C")
