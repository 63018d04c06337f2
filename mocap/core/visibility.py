"""Which painted markers a camera sees: facing it, inside the image, not behind a link.

Markers are painted on the faces of the links' boxes (mocap.core.shapes.link_boxes): each
marker's surface normal is the outward normal of the nearest face of its own link's box.
A marker is hidden when the segment from it to the camera centre passes through another
link's box (its own box never hides it: the paint is on the surface). How much of a
marker is in view (`marker_cover`) asks the same of the corners and edges of its square.
A link whose cylinders or meshes the model states (`Machine.link_solids`) hides by those
instead of its box, and a marker on it takes the normal of the solid's nearest facet
(a marker's stated `normal` still comes first).

Shapes: F frames, L links, M markers.
"""

from __future__ import annotations

import numpy as np

from mocap.core.camera import project_cam
from mocap.core.machine import Machine
from mocap.core.shapes import GRAZE, hidden_by_boxes, hidden_by_solids, solid_arrays, solid_normals

MIN_FACING_COS = 0.2  # a disk seen more obliquely than ~78° is not a usable marker


def marker_normals(machine: Machine, boxes: np.ndarray) -> np.ndarray:
    """Outward normals (M, 3) in each marker's link frame: the model's where it states them
    (`Machine.marker_normals`), else the nearest face of the marker's box."""
    box = boxes[machine.marker_links]  # (M, 2, 3)
    p = machine.marker_positions
    gaps = np.concatenate([p - box[:, 0], box[:, 1] - p], axis=1)  # (M, 6): -x -y -z +x +y +z
    face = np.argmin(np.abs(gaps), axis=1)
    normals = np.zeros((len(p), 3))
    normals[np.arange(len(p)), face % 3] = np.where(face < 3, -1.0, 1.0)
    if machine.link_solids:
        on_solid = solid_normals(machine, p, machine.marker_links)
        normals = np.where(np.isfinite(on_solid), on_solid, normals)
    if machine.marker_normals is not None:
        stated = np.all(np.isfinite(machine.marker_normals), axis=1)
        normals[stated] = machine.marker_normals[stated]
    return normals


def segment_hits_box(start: np.ndarray, end: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Whether segments from `start` to `end` (*, 3) pass through the box (2, 3), or boxes
    (*, 2, 3) broadcast with them (both in the box's frame); a start point inside the box
    counts as a hit, one on its surface only when the segment goes into it (`GRAZE`)."""
    low_corner, high_corner = box[..., 0, :], box[..., 1, :]
    d = end - start
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (low_corner - start) / d
        t2 = (high_corner - start) / d
    parallel = d == 0
    inside_slab = (start >= low_corner) & (start <= high_corner)
    low = np.where(parallel, np.where(inside_slab, -np.inf, np.inf), np.minimum(t1, t2))
    high = np.where(parallel, np.where(inside_slab, np.inf, -np.inf), np.maximum(t1, t2))
    enter, leave = low.max(axis=-1), high.min(axis=-1)
    return (leave - np.maximum(enter, 0.0) > GRAZE) & (enter <= 1.0)


def visible_markers(
    machine: Machine,
    boxes: np.ndarray,
    normals: np.ndarray,
    link_poses: np.ndarray,
    cam_from_world: np.ndarray,
    matrix: np.ndarray,
    distortion: np.ndarray,
    size: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray]:
    """Marker pixels (F, M, 2) and visibility (F, M) bool in one camera: the centre is in
    the image and unhidden, the marker facing the camera.

    boxes (L, 2, 3) and normals (M, 3) in link frames; link_poses (F, L, 4, 4)
    world_from_link; cam_from_world (F, 4, 4) the camera's pose per frame.
    """
    centres = machine.marker_positions[:, None]
    uv, in_view = _in_view(machine, boxes, link_poses, cam_from_world, matrix, distortion, size, centres)
    seen = in_view[..., 0] & _facing(machine, normals, link_poses, cam_from_world)
    return uv[:, :, 0], seen


def marker_cover(
    machine: Machine,
    boxes: np.ndarray,
    normals: np.ndarray,
    link_poses: np.ndarray,
    cam_from_world: np.ndarray,
    matrix: np.ndarray,
    distortion: np.ndarray,
    size: tuple[int, int],
    outline: np.ndarray,
) -> np.ndarray:
    """(F, M) how much of each marker is in view, 0 to 1: the share of the points of its
    `outline` (M, K, 3), in its link frame (e.g. `square_outline`), that are in the image
    and unhidden; 0 for a marker facing away. 1 means the whole marker can be measured."""
    _, in_view = _in_view(machine, boxes, link_poses, cam_from_world, matrix, distortion, size, outline)
    return np.mean(in_view, axis=-1) * _facing(machine, normals, link_poses, cam_from_world)


def _facing(machine: Machine, normals: np.ndarray, link_poses: np.ndarray, cam_from_world: np.ndarray) -> np.ndarray:
    """(F, M) bool: each marker's face turns towards the camera by more than MIN_FACING_COS."""
    on_link = link_poses[:, machine.marker_links]  # (F, M, 4, 4)
    world = np.einsum("fmij,mj->fmi", on_link[..., :3, :3], machine.marker_positions) + on_link[..., :3, 3]
    rotation, translation = cam_from_world[:, :3, :3], cam_from_world[:, :3, 3]
    centre = -np.einsum("fji,fj->fi", rotation, translation)  # camera centre in the world (F, 3)
    normal_world = np.einsum("fmij,mj->fmi", on_link[..., :3, :3], normals)
    to_camera = centre[:, None] - world
    facing = np.einsum("fmi,fmi->fm", normal_world, to_camera) / np.linalg.norm(to_camera, axis=-1)
    return facing > MIN_FACING_COS


def _in_view(machine, boxes, link_poses, cam_from_world, matrix, distortion, size, points):
    """Pixels (F, M, P, 2) of points (M, P, 3) fixed in the markers' links, and whether
    each is in the image and not hidden behind another link's box (F, M, P) bool."""
    links = machine.marker_links
    on_link = link_poses[:, links]  # (F, M, 4, 4)
    # row vectors times the transposed rotations (matmul: einsum is tenfold slower on these shapes)
    world = points @ np.swapaxes(on_link[..., :3, :3], -1, -2) + on_link[..., None, :3, 3]
    rotation, translation = cam_from_world[:, :3, :3], cam_from_world[:, :3, 3]
    centre = -np.einsum("fji,fj->fi", rotation, translation)  # camera centre in the world (F, 3)
    points_cam = world @ np.swapaxes(rotation, -1, -2)[:, None] + translation[:, None, None]
    uv = project_cam(points_cam, matrix, distortion)
    w, h = size
    seen = np.all(np.isfinite(uv), axis=-1)
    seen &= (uv[..., 0] >= 0) & (uv[..., 0] <= w - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= h - 1)
    n_frames, n_markers, n_points = world.shape[:3]
    flat = np.ascontiguousarray(world.reshape(n_frames, n_markers * n_points, 3))
    point_links = np.repeat(links, n_points).astype(np.int64)
    poses = np.ascontiguousarray(link_poses, dtype=float)
    centre = np.ascontiguousarray(centre)
    hides = ~box_replaced(machine)  # a link's stated cylinders or meshes hide instead of its box
    if hides.any():
        seen &= ~hidden_by_boxes(flat, centre, poses, point_links, np.ascontiguousarray(boxes, dtype=float),
                                 hides).reshape(seen.shape)
    if machine.link_solids:
        seen &= ~hidden_by_solids(flat, centre, poses, point_links, *solid_arrays(machine)).reshape(seen.shape)
    return uv, seen


def box_replaced(machine: Machine) -> np.ndarray:
    """(L,) bool: the links whose stated cylinders or meshes hide markers instead of a box
    (one whose box the model states hides by that box too)."""
    replaced = np.zeros(len(machine.links), dtype=bool)
    replaced[[s.link for s in machine.link_solids]] = True
    if machine.link_boxes is not None:
        replaced &= ~np.all(np.isfinite(machine.link_boxes), axis=(1, 2))
    return replaced


def marker_outlines(
    machine: Machine, normals: np.ndarray, disk: float, square: float, n_points: int = 48
) -> tuple[np.ndarray, np.ndarray]:
    """Square corners (M, 4, 3) and disk outlines (M, n_points, 3) of the painted markers
    in their link frames, in the plane of each marker's face (normals (M, 3)), centred on
    the marker; `disk` and `square` are the disk's diameter and the square's side (m)."""
    first, second = plane_axes(normals)
    centre = machine.marker_positions[:, None]
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=float) * 0.5 * square
    squares = centre + corners[None, :, :1] * first[:, None] + corners[None, :, 1:] * second[:, None]
    angles = np.linspace(0, 2 * np.pi, n_points, endpoint=False)
    c, s = 0.5 * disk * np.cos(angles), 0.5 * disk * np.sin(angles)
    disks = centre + c[None, :, None] * first[:, None] + s[None, :, None] * second[:, None]
    return squares, disks


def plane_axes(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit axes (M, 3) in the plane of each of `normals` (M, 3), right-handed with it:
    the next coordinate axis after the normal's largest component, made square to it."""
    axis = np.argmax(np.abs(normals), axis=1)
    first = np.eye(3)[(axis + 1) % 3]
    first = first - np.einsum("mi,mi->m", first, normals)[:, None] * normals
    first /= np.linalg.norm(first, axis=1, keepdims=True)
    return first, np.cross(normals, first)


def square_outline(squares: np.ndarray) -> np.ndarray:
    """The corners and edge midpoints (M, 8, 3) of squares given by their corners (M, 4, 3)."""
    return np.concatenate([squares, 0.5 * (squares + np.roll(squares, -1, axis=1))], axis=1)
