"""The machine model: an articulated chain of rigid links, its markers and named points.

A link's frame at joint value 0 is its parent's frame moved by `origin` and turned by
`rpy` (R = Rz(yaw) Ry(pitch) Rx(roll)); the joint then rotates about (revolute) or slides
along (prismatic) `axis`, given in the link's own frame. The first link is the base; its
frame is the world frame at the calibration frame. Joint values are radians (revolute) or
metres (prismatic), in the order of the links that carry them.

Shapes: F frames, J joints, L links, M markers, P named points.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from mocap.core.geometry import cross, rpy_to_matrix

REVOLUTE = "revolute"
PRISMATIC = "prismatic"


@dataclass(frozen=True)
class Joint:
    """The joint that moves a link relative to its parent.

    `origin` (3,) m and `rpy` (3,) rad place the link frame at joint value 0 in the
    parent's frame; `axis` (3,) is a unit vector in the link frame; `limits` (2,) in rad or m.
    """

    name: str
    type: str
    axis: np.ndarray
    origin: np.ndarray
    rpy: np.ndarray
    limits: np.ndarray

    @cached_property
    def parent_from_zero(self) -> np.ndarray:
        """Homogeneous (4, 4) transform of the link frame at joint value 0 into its parent."""
        out = np.eye(4)
        out[:3, :3] = rpy_to_matrix(self.rpy)
        out[:3, 3] = self.origin
        return out


@dataclass(frozen=True)
class Link:
    name: str
    parent: int | None  # index of the parent link; None for the base
    joint: Joint | None  # None for the base only


@dataclass(frozen=True)
class BucketAngle:
    """The bucket angle: the angle of a link-fixed direction to the horizontal."""

    link: int
    direction: np.ndarray  # (3,) unit vector in the link frame


@dataclass(frozen=True)
class Tolerance:
    """How far the measured marker positions may be off: each marker by up to `fraction`
    of its distance from its link's origin (at least 0.5 m) plus `metres`, in any
    direction (a tape measure's error, the paper's ±5 %)."""

    fraction: float = 0.0
    metres: float = 0.0

    def __post_init__(self) -> None:
        if not (0 <= self.fraction < 1 and 0 <= self.metres < 100):
            raise ValueError(f"tolerance must be a fraction in [0, 1) or metres in [0, 100), got {self}")

    def __bool__(self) -> bool:
        return self.fraction > 0 or self.metres > 0

    def sd(self, positions: np.ndarray) -> np.ndarray:
        """(M,) the SD (m) of each coordinate of markers at positions (M, 3) in their link
        frames: the bound over sqrt(3), as for an error uniform within it."""
        reach = np.maximum(np.linalg.norm(positions, axis=-1), 0.5)
        return np.hypot(self.fraction * reach, self.metres) / np.sqrt(3.0)

    @classmethod
    def parse(cls, text: str | float) -> Tolerance:
        """"5%" or 0.05 (a fraction), "0.03m", "3cm" or "30mm" (metres); ValueError otherwise."""
        if isinstance(text, (int, float)) and not isinstance(text, bool):
            return cls(fraction=float(text))
        value = str(text).strip().lower().replace(" ", "")
        for unit, factor in (("%", 0.01), ("mm", 0.001), ("cm", 0.01), ("m", 1.0)):
            if value.endswith(unit):
                number = float(value[: -len(unit)])
                if not np.isfinite(number):
                    raise ValueError(f"tolerance {text!r} is not finite")
                return cls(fraction=number * factor) if unit == "%" else cls(metres=number * factor)
        return cls(fraction=float(value))

    def __str__(self) -> str:
        parts = ([f"{100 * self.fraction:g}%"] if self.fraction else []) + ([f"{self.metres:g}m"] if self.metres else [])
        return " + ".join(parts) or "0"


@dataclass(frozen=True)
class LinkSolid:
    """A solid the model states for a link, other than a box: a cylinder or a mesh file's
    surface, as `triangles` (T, 3, 3) in the link's frame (metres) wound outward (their
    right-hand normals point out of the solid). `kind` "cylinder" or "mesh"; `source` the
    entry as the model file states it (written back as it was read, a mesh's file made absolute)."""

    link: int
    kind: str
    triangles: np.ndarray
    source: dict = field(default_factory=dict)

    @property
    def normals(self) -> np.ndarray:
        """(T, 3) the triangles' outward unit normals."""
        n = np.cross(self.triangles[:, 1] - self.triangles[:, 0], self.triangles[:, 2] - self.triangles[:, 0])
        return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)


@dataclass(frozen=True)
class Machine:
    """An articulated machine model. Links are in topological order (parents first)."""

    name: str
    source: str
    links: tuple[Link, ...]
    marker_names: tuple[str, ...]
    marker_links: np.ndarray  # (M,) link index
    marker_positions: np.ndarray  # (M, 3) in the link frame
    point_names: tuple[str, ...] = ()
    point_links: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    point_positions: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    bucket_angle: BucketAngle | None = None
    marker_tags: np.ndarray | None = None  # (M,) ArUco / AprilTag id of each marker, -1 for a painted disk
    tag_dictionary: str | None = None  # the tags' OpenCV dictionary, e.g. "DICT_4X4_50"
    tolerance: Tolerance | None = None  # how far the measured marker positions may be off, if stated
    marker_normals: np.ndarray | None = None  # (M, 3) unit disk normals in the link frames where stated, NaN rows not
    link_boxes: np.ndarray | None = None  # (L, 2, 3) stated solids (min, max corners) in the link frames, NaN rows not
    link_solids: tuple[LinkSolid, ...] = ()  # stated cylinders and meshes (a link may have several)

    # --- structure -------------------------------------------------------------------
    @cached_property
    def tags(self) -> np.ndarray:
        """(M,) the tag id each marker carries, -1 for a painted disk (read-only)."""
        if self.marker_tags is None:
            tags = np.full(len(self.marker_names), -1, dtype=int)
        else:
            tags = np.array(self.marker_tags, dtype=int)
        tags.flags.writeable = False
        return tags

    @property
    def link_names(self) -> tuple[str, ...]:
        return tuple(link.name for link in self.links)

    @cached_property
    def joint_links(self) -> tuple[int, ...]:
        """Index of the link each joint moves, in joint order (J,)."""
        return tuple(i for i, link in enumerate(self.links) if link.joint is not None)

    @cached_property
    def joints(self) -> tuple[Joint, ...]:
        return tuple(self.links[i].joint for i in self.joint_links)

    @property
    def joint_names(self) -> tuple[str, ...]:
        return tuple(joint.name for joint in self.joints)

    @property
    def n_joints(self) -> int:
        return len(self.joint_links)

    @cached_property
    def joint_limits(self) -> np.ndarray:
        """(J, 2) lower and upper limits in rad or m (read-only)."""
        limits = np.array([joint.limits for joint in self.joints], dtype=float).reshape(-1, 2)
        limits.flags.writeable = False
        return limits

    @cached_property
    def wraps(self) -> np.ndarray:
        """(J,) bool: revolute joints whose limits span a full turn (angles modulo 2 pi)."""
        limits = self.joint_limits
        revolute = np.array([joint.type == REVOLUTE for joint in self.joints], dtype=bool)
        wraps = revolute & ((limits[:, 1] - limits[:, 0]) >= 2 * np.pi - 1e-9)
        wraps.flags.writeable = False
        return wraps

    @property
    def house_link(self) -> int:
        """The link whose forward axis defines the bucket angle's vertical plane: the base's
        first child (the house of a shovel or excavator), or the base itself."""
        for i, link in enumerate(self.links):
            if link.parent == 0:
                return i
        return 0

    def ancestors(self, link: int) -> list[int]:
        """Links from `link` up to the base, `link` included."""
        chain = []
        while link is not None:
            chain.append(link)
            link = self.links[link].parent
        return chain

    @cached_property
    def moves(self) -> np.ndarray:
        """(J, L) bool: joint j moves link l (l is the joint's link or one of its descendants)."""
        moves = np.zeros((self.n_joints, len(self.links)), dtype=bool)
        for l in range(len(self.links)):
            for a in self.ancestors(l)[:-1]:  # every ancestor but the base carries a joint
                moves[a - 1, l] = True
        return moves

    @cached_property
    def marker_moves(self) -> np.ndarray:
        """(J, M) bool: joint j moves marker m (read-only)."""
        moves = self.moves[:, self.marker_links]
        moves.flags.writeable = False
        return moves

    def marker_index(self, names) -> np.ndarray:
        lookup = {name: i for i, name in enumerate(self.marker_names)}
        return np.array([lookup[name] for name in names], dtype=int)

    def clip_to_limits(self, joints: np.ndarray) -> np.ndarray:
        limits = self.joint_limits
        return np.clip(joints, limits[:, 0], limits[:, 1])

    # --- kinematics --------------------------------------------------------------------
    @cached_property
    def _motion_terms(self) -> tuple[np.ndarray, np.ndarray]:
        """Per joint (J, 4, 4) matrices A, B with motion(q) = I + a(q) A + b(q) B:
        revolute a = sin q, b = 1 - cos q, A = [axis]x, B = [axis]x^2 (Rodrigues);
        prismatic a = q, A = axis in the translation column, B = 0."""
        first = np.zeros((self.n_joints, 4, 4))
        second = np.zeros((self.n_joints, 4, 4))
        for j, joint in enumerate(self.joints):
            x, y, z = joint.axis
            if joint.type == REVOLUTE:
                k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
                first[j, :3, :3] = k
                second[j, :3, :3] = k @ k
            else:
                first[j, :3, 3] = joint.axis
        return first, second

    @cached_property
    def _chain(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per joint: revolute (J,) bool, the parent link (J,), the joint's link-at-zero in
        its parent (J, 4, 4), its axis in its link frame (J, 3)."""
        revolute = np.array([j.type == REVOLUTE for j in self.joints], dtype=bool)
        parents = np.array([self.links[i].parent for i in self.joint_links], dtype=int)
        at_zero = np.array([j.parent_from_zero for j in self.joints]).reshape(-1, 4, 4)
        axes = np.array([j.axis for j in self.joints], dtype=float).reshape(-1, 3)
        return revolute, parents, at_zero, axes

    def link_poses(self, joints: np.ndarray, world_from_base: np.ndarray | None = None) -> np.ndarray:
        """World-from-link transforms for joint values (F, J) -> (F, L, 4, 4).

        `world_from_base` (F, 4, 4) or (4, 4) places a base that has moved; identity by default.
        """
        joints = _frames(joints, self.n_joints)
        n_frames = joints.shape[0]
        poses = np.empty((n_frames, len(self.links), 4, 4))
        poses[:, 0] = np.eye(4) if world_from_base is None else world_from_base
        first, second = self._motion_terms
        revolute, parents, at_zero, _ = self._chain
        a = np.where(revolute, np.sin(joints), joints)
        b = np.where(revolute, 1.0 - np.cos(joints), 0.0)
        motion = np.eye(4) + a[..., None, None] * first + b[..., None, None] * second  # (F, J, 4, 4)
        parent_from_link = at_zero @ motion
        for j, i in enumerate(self.joint_links):
            poses[:, i] = poses[:, parents[j]] @ parent_from_link[:, j]
        return poses

    def markers(
        self, joints: np.ndarray, world_from_base: np.ndarray | None = None, index: np.ndarray | None = None
    ) -> np.ndarray:
        """Marker positions in the world for joint values (F, J) -> (F, M, 3); with `index`
        (N,) only those markers, (F, N, 3)."""
        poses = self.link_poses(joints, world_from_base)
        if index is None:
            return _points_on_links(poses, self.marker_links, self.marker_positions)
        return _points_on_links(poses, self.marker_links[index], self.marker_positions[index])

    def points(self, joints: np.ndarray, world_from_base: np.ndarray | None = None) -> np.ndarray:
        """Named point positions in the world for joint values (F, J) -> (F, P, 3)."""
        poses = self.link_poses(joints, world_from_base)
        return _points_on_links(poses, self.point_links, self.point_positions)

    def markers_with_jacobian(self, joints: np.ndarray):
        """Markers (F, M, 3) and their derivatives by the joint values (F, M, 3, J).

        Revolute joint j moving marker m: d p / d q_j = a_j x (p - o_j) with a_j the joint's
        axis and o_j its origin in the world; prismatic: d p / d q_j = a_j.
        """
        poses = self.link_poses(joints)
        markers = _points_on_links(poses, self.marker_links, self.marker_positions)
        revolute, _, _, axes = self._chain
        on_joints = poses[:, list(self.joint_links)]  # (F, J, 4, 4)
        axis_world = np.einsum("fjab,jb->fja", on_joints[..., :3, :3], axes)[:, :, None]  # (F, J, 1, 3)
        lever = markers[:, None] - on_joints[:, :, None, :3, 3]  # (F, J, M, 3)
        d = np.where(revolute[:, None, None], cross(axis_world, lever), axis_world)
        d *= self.marker_moves[None, :, :, None]
        return markers, np.moveaxis(d, 1, -1)

    def bucket_angles(self, joints: np.ndarray, world_from_base: np.ndarray | None = None) -> np.ndarray:
        """Bucket angle (rad) for joint values (F, J) -> (F,): the angle of the bucket
        link's direction to the horizontal, positive upward, in the vertical plane of the
        house's forward (x) axis. NaN if the model defines no bucket angle."""
        joints = _frames(joints, self.n_joints)
        if self.bucket_angle is None:
            return np.full(joints.shape[0], np.nan)
        poses = self.link_poses(joints, world_from_base)
        direction = poses[:, self.bucket_angle.link, :3, :3] @ self.bucket_angle.direction
        forward = poses[:, self.house_link, :3, 0].copy()
        forward[:, 2] = 0.0
        forward /= np.linalg.norm(forward, axis=-1, keepdims=True)
        return np.arctan2(direction[:, 2], np.einsum("fi,fi->f", direction, forward))


def _frames(joints: np.ndarray, n_joints: int) -> np.ndarray:
    joints = np.asarray(joints, dtype=float)
    if joints.ndim == 1:
        joints = joints[None]
    if joints.ndim != 2 or joints.shape[1] != n_joints:
        raise ValueError(f"joint values must have shape (F, {n_joints}), got {joints.shape}")
    return joints


_CHUNK = 4096  # frames at a time, so that long sessions make no (F, N, 4, 4) array


def _points_on_links(poses: np.ndarray, links: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Points fixed in links: poses (F, L, 4, 4), links (N,), positions (N, 3) -> (F, N, 3)."""
    if poses.shape[0] > _CHUNK:
        return np.concatenate(
            [_points_on_links(poses[k : k + _CHUNK], links, positions) for k in range(0, poses.shape[0], _CHUNK)]
        )
    on_links = poses[:, links]  # (F, N, 4, 4)
    # row vectors times the transposed rotations (matmul: einsum is fourfold slower on these shapes)
    return (positions[:, None, :] @ np.swapaxes(on_links[..., :3, :3], -1, -2))[..., 0, :] + on_links[..., :3, 3]
