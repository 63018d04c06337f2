"""A machine drawn with shapes the tracker does not assume: tapered, kinked links, a cab and a
counterweight sticking out, hoses that cross in front of markers, markers on slanted plates.

The tracker guesses each link's solid as the box around its markers (`mocap.core.shapes.link_boxes`)
and each marker's normal as the nearest face of that box. A world drawn from the same boxes
cannot show what that guess costs. Here every link is one or two convex hexahedra (the box
shrunk, each end's cross-section scaled and shifted: a tapered, bent boom), the upper works
carry a cab and a counterweight beyond the guessed box, some links a hose or a ladder rail
standing off one face, and each marker sits on its own thin plate whose normal is its box
face's turned by 10-40°. Visibility (the truth's) is computed against these solids; the
renderer (`MeshRenderer`) draws them.

A hexahedron is 8 corners in its link's frame ordered as `mocap.core.shapes.box_corners` (faces
`BOX_FACES`), convex; its face normals come from its corners.

Shapes: S solids, F frames, M markers, P points per marker.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from mocap.core.camera import project_cam
from mocap.core.machine import Machine
from mocap.core.shapes import BOX_FACES, box_corners, link_boxes
from mocap.core.visibility import MIN_FACING_COS, marker_normals, plane_axes

TILT_DEG = (10.0, 40.0)  # a marker plate's turn from its box face
LIFT_M = 1e-3  # a marker's point is tested from this far above its plate


@dataclass(frozen=True)
class Solids:
    """Convex hexahedra fixed in the machine's links: `links` (S,) link index, `corners`
    (S, 8, 3) in the link's frame, `plate_of` (S,) the marker a plate carries (-1: none),
    `kind` (S,) 0 link body, 1 plate, 2 hose or rail (drawn dark)."""

    links: np.ndarray
    corners: np.ndarray
    plate_of: np.ndarray
    kind: np.ndarray

    @property
    def face_normals(self) -> np.ndarray:
        """(S, 6, 3) outward unit normals of the faces (`BOX_FACES`), in the link frames."""
        quads = self.corners[:, BOX_FACES]  # (S, 6, 4, 3)
        n = np.cross(quads[:, :, 2] - quads[:, :, 0], quads[:, :, 3] - quads[:, :, 1])
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
        outward = np.einsum("sfi,sfi->sf", n, quads.mean(axis=2) - self.corners.mean(axis=1, keepdims=True))
        return n * np.where(outward < 0, -1.0, 1.0)[..., None]


def machine_solids(machine: Machine, rng: np.random.Generator, square_m: float) -> tuple[Solids, np.ndarray]:
    """Random shapes for `machine`'s links and the markers' plates; returns the solids and
    each marker's normal (M, 3) in its link frame (its plate's). `square_m` is the side of a
    marker's painted square."""
    boxes = link_boxes(machine)
    plate_t = 0.08 * square_m
    links, corners, plate_of, kind = [], [], [], []

    def add(link, c, marker=-1, k=0):
        links.append(link), corners.append(c), plate_of.append(marker), kind.append(k)

    for i, box in enumerate(boxes):
        size = box[1] - box[0]
        inset = np.minimum(plate_t + 0.02 * square_m, 0.2 * size)
        low, high = box[0] + inset, box[1] - inset
        long = int(np.argmax(size))
        for piece in _bent_body(low, high, long, rng):
            add(i, piece)
    # the upper works (the link with the most markers among the first two) get a cab and a counterweight
    upper = int(np.argmax([np.sum(machine.marker_links == i) for i in range(min(2, len(boxes)))]))
    for share in ((0.35, 0.3), (0.5, 0.25)):
        extra = _sticking_out(boxes[upper], share, rng, machine.marker_positions[machine.marker_links == upper])
        if extra is not None:
            add(upper, extra)
    # hoses and rails standing off a face of the longest links
    longest = np.argsort(-np.ptp(boxes, axis=1).max(axis=1))[:2]
    for i in longest:
        add(int(i), _rail(boxes[i], rng, 0.12 * square_m, 0.7 * square_m), k=2)
    normals = marker_normals(machine, boxes)
    normals = np.array([_tilted(n, rng) for n in normals])
    for m, (p, n) in enumerate(zip(machine.marker_positions, normals)):
        add(int(machine.marker_links[m]), _plate(p, n, 0.6 * square_m, plate_t), m, 1)
    solids = Solids(np.array(links), np.array(corners), np.array(plate_of), np.array(kind))
    return solids, normals


def _bent_body(low: np.ndarray, high: np.ndarray, long: int, rng: np.random.Generator) -> list[np.ndarray]:
    """One or two hexahedra inside the box (low, high) along axis `long`: the ends' cross-sections
    scaled by 0.45-0.9 and shifted within the box (a tapered, kinked boom)."""
    mid = 0.5 * (low + high)
    half = 0.5 * (high - low)
    across = [a for a in range(3) if a != long]
    n_pieces = int(rng.integers(1, 3))
    stations = np.linspace(low[long], high[long], n_pieces + 1)
    sections = []  # (centre offset (2,), scale (2,)) per station
    for k in range(n_pieces + 1):
        scale = np.ones(2) if (n_pieces == 2 and k == 1) else rng.uniform(0.45, 0.9, 2)
        shift = rng.uniform(-1, 1, 2) * (1 - scale) * half[across]
        sections.append((shift, scale))
    pieces = []
    for k in range(n_pieces):
        c = box_corners(np.array([low, high]))
        for end, station in ((0, stations[k]), (1, stations[k + 1])):
            shift, scale = sections[k + end]
            at = (c[:, long] > mid[long]) if end else (c[:, long] <= mid[long])
            c[at, long] = station
            for j, a in enumerate(across):
                c[at, a] = mid[a] + shift[j] + (c[at, a] - mid[a]) * scale[j]
        pieces.append(c)
    return pieces


def _sticking_out(box: np.ndarray, share: tuple[float, float], rng: np.random.Generator,
                  markers: np.ndarray) -> np.ndarray | None:
    """A block (cab, counterweight) at an end or side of `box`, reaching `share[1]` of its
    size beyond it; None if every try would bury one of `markers` (K, 3)."""
    size = box[1] - box[0]
    for _ in range(8):
        axis = int(rng.integers(0, 2))
        side = int(rng.integers(0, 2))
        low = box[0] + rng.uniform(0, 1 - share[0], 3) * size
        high = low + share[0] * size
        if side:
            high[axis], low[axis] = box[1, axis] + share[1] * size[axis], box[1, axis] - share[0] * size[axis]
        else:
            low[axis], high[axis] = box[0, axis] - share[1] * size[axis], box[0, axis] + share[0] * size[axis]
        margin = 0.05 * size.max()
        buried = np.all((markers > low - margin) & (markers < high + margin), axis=1)
        if not np.any(buried):
            return box_corners(np.array([low, high]))
    return None


def _rail(box: np.ndarray, rng: np.random.Generator, width: float, stand_off: float) -> np.ndarray:
    """A thin bar along the box's longest axis, `stand_off` above one of its side faces and
    running across it at a slant (a hose or a ladder's rail)."""
    size = box[1] - box[0]
    long = int(np.argmax(size))
    face_axis = [a for a in range(3) if a != long][int(rng.integers(0, 2))]
    other = 3 - long - face_axis
    side = int(rng.integers(0, 2))
    level = box[side, face_axis] + (1 if side else -1) * (stand_off + width / 2)
    a, b = rng.uniform(0.1, 0.9, 2)
    start, end = np.empty(3), np.empty(3)
    start[long], end[long] = box[0, long] + 0.1 * size[long], box[1, long] - 0.1 * size[long]
    start[other], end[other] = box[0, other] + a * size[other], box[0, other] + b * size[other]
    start[face_axis] = end[face_axis] = level
    along = (end - start) / np.linalg.norm(end - start)
    up = np.eye(3)[face_axis]
    side_dir = np.cross(along, up)
    c = box_corners(np.array([[0.0, -0.5, -0.5], [1.0, 0.5, 0.5]]))
    return start + np.outer(c[:, 0], end - start) + width * (np.outer(c[:, 1], side_dir) + np.outer(c[:, 2], up))


def _tilted(normal: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """`normal` turned by TILT_DEG about a random axis across it."""
    axis = np.cross(normal, rng.normal(size=3))
    axis /= np.linalg.norm(axis)
    angle = np.radians(rng.uniform(*TILT_DEG))
    return np.cos(angle) * normal + np.sin(angle) * np.cross(axis, normal)


def _plate(centre: np.ndarray, normal: np.ndarray, half: float, thickness: float) -> np.ndarray:
    """A square plate of half-side `half` whose top face, normal `normal`, is centred on `centre`."""
    first, second = plane_axes(normal[None])
    c = box_corners(np.array([[-half, -half, -thickness], [half, half, 0.0]]))
    return centre + np.outer(c[:, 0], first[0]) + np.outer(c[:, 1], second[0]) + np.outer(c[:, 2], normal)


def marker_test_points(squares: np.ndarray, disks: np.ndarray) -> np.ndarray:
    """(M, 25 + N, 3) the points a marker must show to be wholly in view: a 5 x 5 grid over
    its square (corners (M, 4, 3)) and its disk's outline (M, N, 3), in its link frame (a thin
    hose may cross the square between its corners and edges' midpoints)."""
    grid = np.linspace(0.0, 1.0, 5)
    a, b = np.meshgrid(grid, grid, indexing="ij")
    across = squares[:, 1] - squares[:, 0], squares[:, 3] - squares[:, 0]  # (M, 3) each
    square_grid = (squares[:, None, 0] + a.reshape(1, -1, 1) * across[0][:, None]
                   + b.reshape(1, -1, 1) * across[1][:, None])
    return np.concatenate([square_grid, disks], axis=1)


def solids_in_view(machine: Machine, solids: Solids, normals: np.ndarray, link_poses: np.ndarray,
                   cam_from_world: np.ndarray, matrix: np.ndarray, distortion: np.ndarray, size: tuple[int, int],
                   points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (F, M, P, 2) of points (M, P, 3) on the markers (link frames), and whether each
    is in the image, its marker facing the camera, and not hidden by any solid but the
    marker's own plate (F, M, P) bool. `normals` (M, 3) the markers' in their link frames."""
    links = machine.marker_links
    on_link = link_poses[:, links]  # (F, M, 4, 4)
    lift = points + LIFT_M * normals[:, None]
    # row vectors times the transposed rotations (matmul: einsum is tenfold slower on these shapes)
    world = lift @ np.swapaxes(on_link[..., :3, :3], -1, -2) + on_link[..., None, :3, 3]
    rotation, translation = cam_from_world[:, :3, :3], cam_from_world[:, :3, 3]
    centre = -np.einsum("fji,fj->fi", rotation, translation)
    cam = world @ np.swapaxes(rotation, -1, -2)[:, None] + translation[:, None, None]
    uv = project_cam(cam, matrix, distortion)
    w, h = size
    seen = np.all(np.isfinite(uv), axis=-1)
    seen &= (uv[..., 0] >= 0) & (uv[..., 0] <= w - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= h - 1)
    normal_world = np.einsum("fmij,mj->fmi", on_link[..., :3, :3], normals)
    centre_world = np.einsum("fmij,mj->fmi", on_link[..., :3, :3], machine.marker_positions) + on_link[..., :3, 3]
    to_camera = centre[:, None] - centre_world
    facing = np.einsum("fmi,fmi->fm", normal_world, to_camera) / np.linalg.norm(to_camera, axis=-1)
    seen &= (facing > MIN_FACING_COS)[..., None]
    face_normals = solids.face_normals
    offsets = np.einsum("sfi,sfi->sf", face_normals, solids.corners[:, BOX_FACES[:, 0]])
    rotation_t = np.ascontiguousarray(np.swapaxes(link_poses[..., :3, :3], -1, -2))  # link_from_world (F, L, 3, 3)
    shift = np.ascontiguousarray(link_poses[..., :3, 3])
    seen &= ~_hidden(np.ascontiguousarray(world), np.ascontiguousarray(centre), rotation_t, shift,
                     np.ascontiguousarray(solids.links, dtype=np.int64), np.ascontiguousarray(face_normals),
                     np.ascontiguousarray(offsets), np.ascontiguousarray(solids.plate_of, dtype=np.int64),
                     np.ascontiguousarray(seen))  # one compiled version: C order
    return uv, seen


@njit(cache=True, nogil=True)
def _hidden(world, centre, rotation_t, shift, links, normals, offsets, plate_of, todo):
    """(F, M, P) whether the segment from each point `world` (F, M, P, 3) to the camera centre
    (F, 3) passes through a solid (not marker m's own plate); only where `todo`."""
    n_frames, n_markers, n_points = todo.shape
    hit = np.zeros(todo.shape, dtype=np.bool_)
    start, end = np.empty(3), np.empty(3)
    for f in range(n_frames):
        for m in range(n_markers):
            for p in range(n_points):
                if not todo[f, m, p]:
                    continue
                for s in range(len(links)):
                    if plate_of[s] == m:
                        continue
                    link = links[s]
                    for i in range(3):
                        start[i] = 0.0
                        end[i] = 0.0
                        for j in range(3):
                            start[i] += rotation_t[f, link, i, j] * (world[f, m, p, j] - shift[f, link, j])
                            end[i] += rotation_t[f, link, i, j] * (centre[f, j] - shift[f, link, j])
                    enter, leave = 0.0, 1.0
                    for k in range(6):
                        a = -offsets[s, k]
                        b = 0.0
                        for i in range(3):
                            a += normals[s, k, i] * start[i]
                            b += normals[s, k, i] * (end[i] - start[i])
                        if b == 0.0:
                            if a > 0.0:
                                enter, leave = 1.0, 0.0
                                break
                        elif b < 0.0:
                            enter = max(enter, -a / b)
                        else:
                            leave = min(leave, -a / b)
                        if enter >= leave:
                            break
                    if enter < leave:
                        hit[f, m, p] = True
                        break
    return hit
