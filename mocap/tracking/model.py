"""The machine model seen by one calibrated camera: predicted marker pixels, which markers
it sees (facing it, not hidden by another link), and a small robust Gauss-Newton fit of the joint values to
labelled pixels (batched over frames; the tracker calls it with one frame at a time).

Shapes: F frames, M markers, J joints, L links.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import NamedTuple

import numpy as np

from mocap.core.camera import Camera
from mocap.core.machine import Machine
from mocap.core.shapes import hidden_by_solids, link_boxes, solid_arrays
from mocap.core.visibility import MIN_FACING_COS, box_replaced, marker_normals
from mocap.tracking.fit_kernel import fit_joints, marker_pixels, marker_view


class Fit(NamedTuple):
    """A fit of the joint values: `joints` (F, J), `residual` (F, M) px (NaN where not
    observed) and the fitted marker pixels `uv` (F, M, 2)."""

    joints: np.ndarray
    residual: np.ndarray
    uv: np.ndarray


@dataclass(frozen=True)
class View:
    """The machine seen by a camera at some joint values: marker pixels `uv` (F, M, 2),
    `visible` (F, M) bool, and `scale` (F, M) px per metre: a disk of radius R m on the
    marker's face shows as an ellipse of geometric-mean radius about ``scale * R`` px
    (f / depth, times the square root of the cosine of the viewing angle)."""

    uv: np.ndarray
    visible: np.ndarray
    scale: np.ndarray


@dataclass(frozen=True)
class CameraModel:
    """A machine model and one calibrated camera; `boxes` (L, 2, 3) link solids in link
    frames (default: `mocap.core.shapes.link_boxes`), `normals` (M, 3) each marker's disk normal
    in its link frame (the nearest face of its box). `solid` False: the boxes are not the
    machine's shape (a rigid object's one box is the hull of its markers), so every marker
    in front of the camera and inside the image counts as seen."""

    machine: Machine
    camera: Camera
    boxes: np.ndarray = field(default=None)
    normals: np.ndarray = field(init=False)
    solid: bool = True

    def __post_init__(self) -> None:
        if self.boxes is None:
            object.__setattr__(self, "boxes", link_boxes(self.machine))
        if np.shape(self.boxes) != (len(self.machine.links), 2, 3):
            raise ValueError(f"boxes must be (L={len(self.machine.links)}, 2, 3), got {np.shape(self.boxes)}")
        object.__setattr__(self, "normals", marker_normals(self.machine, self.boxes))

    def with_normals(self, normals: np.ndarray) -> CameraModel:
        """The same model with the markers' normals (M, 3) in their link frames replaced
        where finite (e.g. learned, `mocap.tracking.normals`); the rest as they were."""
        normals = np.where(np.isfinite(normals).all(axis=1)[:, None], normals, self.normals)
        machine = replace(self.machine, marker_normals=normals)
        return CameraModel(machine, self.camera, self.boxes, self.solid)

    def pixels(self, joints: np.ndarray) -> np.ndarray:
        """Marker pixels (F, M, 2) for joint values (F, J); NaN behind the camera."""
        joints = np.ascontiguousarray(np.atleast_2d(joints), dtype=float)
        if joints.shape[1:] != (self.machine.n_joints,):
            raise ValueError(f"joint values must have shape (F, {self.machine.n_joints}), got {joints.shape}")
        return marker_pixels(joints, *self._kernel_arguments)

    @cached_property
    def _kernel_arguments(self) -> tuple:
        """The machine's chain and the camera, as `mocap.tracking.fit_kernel` takes them."""
        machine, camera = self.machine, self.camera
        revolute, parents, at_zero, axes = machine._chain
        first, second = machine._motion_terms
        chain = (np.ascontiguousarray(revolute), np.ascontiguousarray(parents, dtype=np.int64),
                 np.array(machine.joint_links, dtype=np.int64).reshape(-1), np.ascontiguousarray(at_zero, dtype=float),
                 np.ascontiguousarray(first), np.ascontiguousarray(second), np.ascontiguousarray(axes, dtype=float),
                 len(machine.links))
        rotation, translation = camera.cam_from_world.rotation, camera.cam_from_world.translation
        return (chain, np.ascontiguousarray(machine.marker_links, dtype=np.int64),
                np.ascontiguousarray(machine.marker_positions, dtype=float), np.ascontiguousarray(rotation, dtype=float),
                np.ascontiguousarray(translation, dtype=float), np.ascontiguousarray(camera.matrix, dtype=float),
                np.ascontiguousarray(camera.distortion, dtype=float).reshape(5),
                np.require(machine.marker_moves, bool, "CW"))  # one compiled version: C order, writable

    def visible(self, joints: np.ndarray) -> np.ndarray:
        """(F, M) bool: in the image, facing the camera and not hidden behind another link's
        box (the painting convention of `mocap.core.visibility`: markers on the faces
        of the links' boxes)."""
        return self.view(joints).visible

    def view(self, joints: np.ndarray) -> View:
        """What the camera sees of the machine at joint values (F, J), from one pass of
        the forward kinematics."""
        joints = np.ascontiguousarray(np.atleast_2d(joints), dtype=float)
        chain, links, positions, rotation, translation, matrix, distortion, _ = self._kernel_arguments
        width, height = self.camera.size
        uv, seen, scale = marker_view(joints, chain, links, positions, rotation, translation, matrix, distortion,
                                      np.ascontiguousarray(self.boxes, dtype=float), np.ascontiguousarray(self.normals),
                                      float(width), float(height), self.solid, MIN_FACING_COS, self._box_hides)
        if self.solid and self.machine.link_solids and seen.any():  # the stated cylinders and meshes hide too
            machine = self.machine
            poses = np.ascontiguousarray(machine.link_poses(joints), dtype=float)
            world = np.ascontiguousarray(machine.markers(joints))
            centre = np.broadcast_to(-rotation.T @ translation, (len(joints), 3))
            seen &= ~hidden_by_solids(world, np.ascontiguousarray(centre), poses, links, *solid_arrays(machine))
        return View(uv, seen, scale)

    @cached_property
    def _box_hides(self) -> np.ndarray:
        """(L,) bool: the links whose box hides markers (not those whose stated cylinders or
        meshes do instead)."""
        return np.ascontiguousarray(~box_replaced(self.machine))

    def centre_offsets(self, joints: np.ndarray, radius_m: float) -> np.ndarray:
        """(F, M, 2) px from the centre of each disk's image ellipse to the image of the
        disk's centre, for disks of `radius_m` on the markers' faces: under perspective the
        two differ (the near side looks larger), and a detector finds the ellipse's.

        The disk's image is the conic of the homography H = K [e1 e2 c] from its plane;
        the ellipse's centre, the pole of the line at infinity, is the image of
        ``c - r² / c_z (z - n n_z)`` (c the disk's centre and n its normal in the camera
        frame, z the optical axis). Distortion is left out: it bends the offset negligibly."""
        joints = np.atleast_2d(joints)
        poses = self.machine.link_poses(joints)[:, self.machine.marker_links]  # (F, M, 4, 4)
        rotation, translation = self.camera.cam_from_world.rotation, self.camera.cam_from_world.translation
        on_link = rotation @ poses[..., :3, :3]  # camera_from_link rotations (F, M, 3, 3)
        centre = np.einsum("fmij,mj->fmi", on_link, self.machine.marker_positions)
        centre += poses[..., :3, 3] @ rotation.T + translation
        normal = np.einsum("fmij,mj->fmi", on_link, self.normals)
        in_plane = np.array([0.0, 0.0, 1.0]) - normal * normal[..., 2:]  # the optical axis, in the disk's plane
        with np.errstate(divide="ignore", invalid="ignore"):
            ellipse = centre - (radius_m**2 / centre[..., 2:]) * in_plane
            offset = self._pinhole(centre) - self._pinhole(ellipse)
        return np.where(centre[..., 2:] > 0, offset, np.nan)

    def _pinhole(self, points_cam: np.ndarray) -> np.ndarray:
        image = points_cam @ self.camera.matrix.T
        return image[..., :2] / image[..., 2:]

    def observed_joints(self, markers: np.ndarray) -> np.ndarray:
        """(J,) bool: the joints that move at least one of `markers` (indices)."""
        return self.machine.marker_moves[:, np.asarray(markers, dtype=int)].any(axis=1)

    def determined(self, markers: np.ndarray, enough: int) -> bool:
        """Whether the labelled `markers` (indices) are enough for a frame's fit: `enough` of
        them, or fewer whose coordinates (two each) fix the joints they show with two to spare
        on the moving links' markers alone, and those joints and the image's shift (two) with
        two to spare with all of them, a base marker among them, so that a wrong label shows in
        the residuals. The count is the prior of a machine with many markers; one with two a
        link, filmed where a camera sees four, is fitted from a base marker and three that show
        its four joints. (Four markers on moving links alone once let a random digger's camera
        label its arm and bucket markers each on the disk of the marker a link before it, for
        seconds: nothing held the image's shift apart from the swing.)"""
        markers = np.asarray(markers, dtype=int)
        if len(markers) >= enough:
            return True
        moves = self.machine.marker_moves[:, markers]  # (J, K)
        shown = int(moves.any(axis=1).sum())
        moving = int(moves.any(axis=0).sum())
        return 2 * moving >= shown + 2 and moving < len(markers) and 2 * len(markers) >= shown + 4

    def known_markers(self, held: np.ndarray) -> np.ndarray:
        """(M,) bool: the markers whose every moving joint some `held` marker (indices) shows."""
        seen = self.observed_joints(held)
        return ~(self.machine.marker_moves & ~seen[:, None]).any(axis=0)

    def supported(self, new: np.ndarray, held: np.ndarray) -> np.ndarray:
        """(K,) bool over marker indices `new`: the new markers that depend on joints no
        `held` marker shows are kept only if, together, they over-determine those joints by
        two or more coordinates (2 per marker >= unknown joints + 2): a marker alone fits
        any blob along its arc, and two markers at the end of three unseen joints fit
        almost any two blobs."""
        new = np.asarray(new, dtype=int)
        known = self.observed_joints(held)
        unknown = self.machine.marker_moves[:, new] & ~known[:, None]  # (J, K)
        needs = unknown.any(axis=0)
        n_unknown = int(unknown[:, needs].any(axis=1).sum())
        return ~needs | (2 * int(needs.sum()) >= n_unknown + 2)

    def fit(
        self,
        pixels: np.ndarray,
        start: np.ndarray,
        iterations: int = 6,
        scale_px: float = 2.0,
        prior_weight: float = 1e-2,
    ) -> Fit:
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
        Fit: joints (F, J), clipped to the limits, residuals (F, M) px (NaN where not
        observed) and the fitted pixels (F, M, 2).
        """
        pixels = np.require(pixels, float, "CW")  # writable too: one compiled version
        starts = np.empty((len(pixels), self.machine.n_joints))
        starts[:] = start
        limits = np.ascontiguousarray(self.machine.joint_limits)
        return Fit(*fit_joints(pixels, starts, int(iterations), float(scale_px), float(prior_weight), limits,
                               *self._kernel_arguments))
