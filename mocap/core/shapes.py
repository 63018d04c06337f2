"""Solid shapes of a machine's links, stated in the model or derived from it, for rendering and replay.

Each link is drawn as the box in its own frame that holds its joint origin, its markers and
points and its children's joint origins, so that markers at the extremes lie on its faces;
boxes thinner than a minimum are thickened about their middle. A plain stand-in for the
manufacturer's geometry, enough to hide markers behind links and to see the machine move.

A model may state a link's solid instead: a box (`Machine.link_boxes`), or cylinders and
meshes (`Machine.link_solids`, triangles in the link's frame). Those hide markers by their
triangles (`hidden_by_solids`), give the normals of the markers on them (`solid_normals`)
and, for what takes a box (the viewer), their bounding box.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from mocap.core.machine import Machine

CYLINDER_SIDES = 48  # a stated cylinder's facets (a facet's normal is within 3.75 deg of the surface's)


def link_boxes(machine: Machine, thickness: float | None = None) -> np.ndarray:
    """Axis-aligned boxes in each link's frame: (L, 2, 3) = (min corner, max corner), metres.

    `thickness`, the least size of a box along any axis, defaults to 3 % of the machine's
    extent (at least 5 cm). A link whose box the model states (`Machine.link_boxes`, the
    machine file's `box`) has that one instead.
    """
    extent = np.ptp(machine.markers(np.zeros((1, machine.n_joints)))[0], axis=0).max()
    thickness = max(0.05, 0.03 * extent) if thickness is None else thickness
    boxes = np.empty((len(machine.links), 2, 3))
    for i, link in enumerate(machine.links):
        pts = [np.zeros((1, 3)) if i else np.empty((0, 3))]
        pts.append(machine.marker_positions[machine.marker_links == i])
        pts.append(machine.point_positions[machine.point_links == i])
        for child in machine.links:
            if child.parent == i:
                pts.append(child.joint.origin[None])
        pts = np.concatenate(pts)
        if i == 0:
            pts = np.concatenate([pts, [[pts[:, 0].mean(), pts[:, 1].mean(), 0.0]]])
        low, high = pts.min(axis=0), pts.max(axis=0)
        grow = np.maximum(thickness - (high - low), 0.0) / 2
        boxes[i, 0], boxes[i, 1] = low - grow, high + grow
    for i in {solid.link for solid in machine.link_solids}:
        corners = np.concatenate([solid.triangles.reshape(-1, 3) for solid in machine.link_solids if solid.link == i])
        boxes[i] = corners.min(axis=0), corners.max(axis=0)
    if machine.link_boxes is not None:
        stated = np.all(np.isfinite(machine.link_boxes), axis=(1, 2))
        boxes[stated] = machine.link_boxes[stated]
    return boxes


def cylinder_triangles(a: np.ndarray, b: np.ndarray, radius: float, sides: int = CYLINDER_SIDES) -> np.ndarray:
    """(4 * sides, 3, 3) the surface of the cylinder from `a` to `b` (3,) of `radius`, its
    side and both caps, wound outward."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    axis = (b - a) / np.linalg.norm(b - a)
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
    first = np.cross(axis, helper)
    first /= np.linalg.norm(first)
    second = np.cross(axis, first)
    angle = np.linspace(0.0, 2 * np.pi, sides, endpoint=False)
    ring = radius * (np.cos(angle)[:, None] * first + np.sin(angle)[:, None] * second)  # (S, 3)
    here, next_ = ring, np.roll(ring, -1, axis=0)
    side_one = np.stack([a + here, a + next_, b + next_], axis=1)
    side_two = np.stack([a + here, b + next_, b + here], axis=1)
    cap_a = np.stack([np.broadcast_to(a, here.shape), a + next_, a + here], axis=1)
    cap_b = np.stack([np.broadcast_to(b, here.shape), b + here, b + next_], axis=1)
    return np.concatenate([side_one, side_two, cap_a, cap_b])


def solid_arrays(machine: Machine) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The stated solids packed for `hidden_by_solids`: triangles (T, 3, 3) in link frames,
    each solid's first triangle (S + 1,) (the last the count), its link (S,) and its bounding
    box (S, 2, 3) in its link's frame."""
    solids = machine.link_solids
    if not solids:
        return np.zeros((0, 3, 3)), np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros((0, 2, 3))
    triangles = np.ascontiguousarray(np.concatenate([s.triangles for s in solids]), dtype=float)
    first = np.concatenate([[0], np.cumsum([len(s.triangles) for s in solids])]).astype(np.int64)
    links = np.array([s.link for s in solids], dtype=np.int64)
    bounds = np.array([[s.triangles.reshape(-1, 3).min(axis=0), s.triangles.reshape(-1, 3).max(axis=0)]
                       for s in solids])
    return triangles, first, links, bounds


def solid_normals(machine: Machine, positions: np.ndarray, links: np.ndarray) -> np.ndarray:
    """(M, 3) the outward normal of the stated solid's triangle nearest each point
    `positions` (M, 3) in the frame of its link `links` (M,); NaN where its link states no
    cylinder or mesh."""
    normals = np.full((len(positions), 3), np.nan)
    for i in np.unique(links):
        mine = [s for s in machine.link_solids if s.link == i]
        if not mine:
            continue
        triangles = np.concatenate([s.triangles for s in mine])
        facet = np.concatenate([s.normals for s in mine])
        rows = np.flatnonzero(links == i)
        distance = point_triangle_distance(positions[rows], triangles)  # (K, T)
        normals[rows] = facet[np.argmin(distance, axis=1)]
    return normals


def point_triangle_distance(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(K, T) the distance from each of `points` (K, 3) to each triangle (T, 3, 3): to its
    plane where the foot falls inside it, else to the nearest of its edges."""
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    normal = np.cross(b - a, c - a)
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-300)
    p = points[:, None]  # (K, 1, 3)
    height = np.einsum("kti,ti->kt", p - a, normal)
    foot = p - height[..., None] * normal
    inside = np.ones(height.shape, dtype=bool)
    for start, end in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("kti,ti->kt", np.cross(end - start, foot - start), normal) >= 0
    edges = []
    for start, end in ((a, b), (b, c), (c, a)):
        d = end - start
        t = np.clip(np.einsum("kti,ti->kt", p - start, d) / np.maximum(np.einsum("ti,ti->t", d, d), 1e-300), 0, 1)
        edges.append(np.linalg.norm(p - (start + t[..., None] * d), axis=-1))
    return np.where(inside, np.abs(height), np.minimum.reduce(edges))


# a segment that runs inside a box for no more than this share of its length only touches it: a
# marker painted where another link's box meets its own (random machines put markers there) is
# hidden when the line of sight goes into that box, not when rounding puts the marker a hair inside
GRAZE = 1e-9


@njit(cache=True, nogil=True)
def hidden_by_solids(world, centre, poses, point_links, triangles, first, solid_links, bounds):
    """(F, N) bool: whether the segment from each point `world` (F, N, 3) to the camera
    centre `centre` (F, 3) passes through a stated solid of another link than the point's own
    (`point_links` (N,)); `poses` (F, L, 4, 4) world_from_link; the solids as `solid_arrays`
    packs them. Each segment is tested against a solid's bounding box first, then against
    its triangles (Moller-Trumbore)."""
    n_frames, n_points = world.shape[0], world.shape[1]
    hidden = np.zeros((n_frames, n_points), dtype=np.bool_)
    start = np.empty(3)
    end = np.empty(3)
    for f in range(n_frames):
        for m in range(n_points):
            for s in range(solid_links.shape[0]):
                link = solid_links[s]
                if link == point_links[m]:
                    continue
                _in_link(world[f, m], centre[f], poses[f, link], start, end)
                if not segment_crosses_box(start, end, bounds[s, 0], bounds[s, 1]):
                    continue
                for t in range(first[s], first[s + 1]):
                    if _segment_hits_triangle(start, end, triangles[t]):
                        hidden[f, m] = True
                        break
                if hidden[f, m]:
                    break
    return hidden


@njit(cache=True, nogil=True)
def hidden_by_boxes(world, centre, poses, point_links, boxes, box_hides):
    """(F, N) bool: whether the segment from each point `world` (F, N, 3) to the camera
    centre `centre` (F, 3) passes through the box (L, 2, 3) of another link than the point's
    own (`point_links` (N,)), of the links `box_hides` (L,) marks; `poses` (F, L, 4, 4)
    world_from_link (`visibility.segment_hits_box` over every link, compiled: a point stops
    at the first box that hides it)."""
    n_frames, n_points = world.shape[0], world.shape[1]
    hidden = np.zeros((n_frames, n_points), dtype=np.bool_)
    start = np.empty(3)
    end = np.empty(3)
    for f in range(n_frames):
        for m in range(n_points):
            hidden[f, m] = behind_a_box(world[f, m], centre[f], poses[f], point_links[m], boxes, box_hides, start, end)
    return hidden


@njit(cache=True, nogil=True)
def behind_a_box(point, centre, poses, own, boxes, box_hides, start, end):
    """Whether the segment from `point` to `centre` (3,) in the world passes through the box
    of a link other than `own` among those `box_hides` marks (poses (L, 4, 4)
    world_from_link; start and end (3,) scratch)."""
    for link in range(boxes.shape[0]):
        if link == own or not box_hides[link]:  # its own box never hides it
            continue
        _in_link(point, centre, poses[link], start, end)
        if segment_crosses_box(start, end, boxes[link, 0], boxes[link, 1]):
            return True
    return False


@njit(cache=True, nogil=True)
def _in_link(point, centre, pose, start, end):
    """Fill start and end (3,) with `point` and `centre` (3,) in the frame of the link whose
    world_from_link is `pose` (4, 4): R^T (p - t)."""
    for a in range(3):
        start[a] = ((pose[0, a] * (point[0] - pose[0, 3]) + pose[1, a] * (point[1] - pose[1, 3]))
                    + pose[2, a] * (point[2] - pose[2, 3]))
        end[a] = ((pose[0, a] * (centre[0] - pose[0, 3]) + pose[1, a] * (centre[1] - pose[1, 3]))
                  + pose[2, a] * (centre[2] - pose[2, 3]))


@njit(cache=True, nogil=True)
def segment_crosses_box(start, end, low_corner, high_corner):
    """Whether the segment from `start` to `end` (3,) passes through the box between its
    corners (3,) (slabs; the compiled, one-segment form of `visibility.segment_hits_box`)."""
    enter, leave = -math.inf, math.inf
    for a in range(3):
        d = end[a] - start[a]
        if d == 0:
            if not (low_corner[a] <= start[a] <= high_corner[a]):
                return False
            continue
        t1 = (low_corner[a] - start[a]) / d
        t2 = (high_corner[a] - start[a]) / d
        enter = max(enter, min(t1, t2))
        leave = min(leave, max(t1, t2))
    return leave - max(enter, 0.0) > GRAZE and enter <= 1.0


@njit(cache=True, nogil=True)
def _segment_hits_triangle(start, end, triangle):
    """Whether the segment from `start` to `end` (3,) crosses the triangle (3, 3) (Moller-Trumbore)."""
    dx, dy, dz = end[0] - start[0], end[1] - start[1], end[2] - start[2]
    e1x, e1y, e1z = triangle[1, 0] - triangle[0, 0], triangle[1, 1] - triangle[0, 1], triangle[1, 2] - triangle[0, 2]
    e2x, e2y, e2z = triangle[2, 0] - triangle[0, 0], triangle[2, 1] - triangle[0, 1], triangle[2, 2] - triangle[0, 2]
    px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz
    if abs(det) < 1e-15:
        return False
    inv = 1.0 / det
    tx, ty, tz = start[0] - triangle[0, 0], start[1] - triangle[0, 1], start[2] - triangle[0, 2]
    u = (tx * px + ty * py + tz * pz) * inv
    if u < 0.0 or u > 1.0:
        return False
    qx, qy, qz = ty * e1z - tz * e1y, tz * e1x - tx * e1z, tx * e1y - ty * e1x
    v = (dx * qx + dy * qy + dz * qz) * inv
    if v < 0.0 or u + v > 1.0:
        return False
    t = (e2x * qx + e2y * qy + e2z * qz) * inv
    return 0.0 < t <= 1.0


def box_corners(box: np.ndarray) -> np.ndarray:
    """Corners of a box (2, 3) -> (8, 3), index bits (x, y, z) = (k & 1, k & 2, k & 4)."""
    k = np.arange(8)
    return np.stack([box[(k >> 0) & 1, 0], box[(k >> 1) & 1, 1], box[(k >> 2) & 1, 2]], axis=-1)


# faces of `box_corners` as quads, outward normals by the right-hand rule
BOX_FACES = np.array(
    [[0, 4, 6, 2], [1, 3, 7, 5], [0, 1, 5, 4], [2, 6, 7, 3], [0, 2, 3, 1], [4, 5, 7, 6]]
)
