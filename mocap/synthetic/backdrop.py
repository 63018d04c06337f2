"""The still part of a camera's view: sky, textured ground and pile, the truck, clutter.

Rendered once per camera: rays through a quarter-resolution pixel grid (lens distortion
ignored: the backdrop carries no measurement) hit the ground plane or the pile's height
field, are shaded by the sun and hazed by distance, and the image is scaled up with a
fine grain added. The truck's boxes and the clutter (dark rocks, marker-like signs that
are not markers) are drawn on top at full resolution.
"""

from __future__ import annotations

import cv2
import numpy as np

from mocap.core.camera import Camera, project_cam
from mocap.core.shapes import BOX_FACES, box_corners
from mocap.synthetic.motion import Pile, Truck

SKY = np.array([235.0, 200.0, 150.0])  # BGR, zenith
HAZE = np.array([225.0, 222.0, 215.0])  # BGR, horizon
GROUND = np.array([105.0, 135.0, 160.0])
ROCK = np.array([100.0, 112.0, 125.0])
BOX_NORMALS = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], dtype=float)


def pile_height(a: np.ndarray, b: np.ndarray, pile: Pile) -> np.ndarray:
    """Height (m) of the pile at distance `a` along its azimuth and `b` across it: a face at
    the pile's slope from the toe, flat at the top, falling off at 35° at the sides."""
    face = np.clip((a - pile.toe) * np.tan(pile.slope), 0.0, pile.height)
    side = np.clip((0.5 * pile.width - np.abs(b)) * np.tan(np.radians(35.0)), 0.0, pile.height)
    return np.minimum(face, side)


def value_noise(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """A tileable multi-scale noise texture (size, size) float32 in about [-1, 1]."""
    out = np.zeros((size, size), np.float32)
    for cells, weight in ((4, 0.5), (16, 0.3), (64, 0.2)):
        grid = rng.uniform(-1, 1, (cells, cells)).astype(np.float32)
        tiled = np.tile(grid, (3, 3))
        big = cv2.resize(tiled, (3 * size, 3 * size), interpolation=cv2.INTER_CUBIC)
        out += weight * big[size : 2 * size, size : 2 * size]
    return out


def _sample(texture: np.ndarray, x: np.ndarray, y: np.ndarray, period: float) -> np.ndarray:
    n = texture.shape[0]
    mx = ((x / period) % 1.0 * n).astype(np.float32)
    my = ((y / period) % 1.0 * n).astype(np.float32)
    return cv2.remap(texture, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)


def render_backdrop(camera: Camera, pile: Pile, truck: Truck, reach: float, sun: np.ndarray,
                    rng: np.random.Generator, people: int = 0, trucks: int = 0,
                    other_machine: bool = False) -> np.ndarray:
    """The camera's still view (H, W, 3) uint8 BGR; `people`, `trucks` (beyond the plan's
    `truck`) and `other_machine`: clutter standing behind the machine (`_draw_behind`)."""
    w, h = camera.size
    step = 4
    u, v = np.meshgrid(np.arange(0.5 * step - 0.5, w, step), np.arange(0.5 * step - 0.5, h, step))
    rays_cam = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(camera.matrix).T
    rays = rays_cam @ camera.cam_from_world.rotation  # world directions (h', w', 3)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    origin = camera.center
    far = 60.0 * reach
    down = rays[..., 2] < -1e-6
    t_ground = np.where(down, -origin[2] / np.where(down, rays[..., 2], -1.0), far)
    t_hit = np.minimum(t_ground, far)
    along = np.array([np.cos(pile.azimuth), np.sin(pile.azimuth), 0.0])
    across = np.array([-along[1], along[0], 0.0])

    # march the pile's height field inside its bounding box (and before the ground hit),
    # then bisect the crossing
    enter, leave = _slabs(origin, rays, along, across, pile, reach)
    leave = np.minimum(leave, t_hit)
    crossing = leave > enter  # only the rays through the pile's box are marched
    hit, t_pile = _march_pile(origin, rays[crossing], enter[crossing], leave[crossing], along, across, pile)
    hit_pile = np.zeros(t_hit.shape, dtype=bool)
    hit_pile[crossing] = hit
    t_final = t_hit.copy()
    t_final[crossing] = np.where(hit, t_pile, t_hit[crossing])
    point = origin + rays * t_final[..., None]
    texture = value_noise(rng)

    # pile shading: the face's normal where it rises, the bench's top elsewhere
    a, b = point @ along, point @ across
    on_face = (point[..., 2] < pile.height - 0.05) & hit_pile
    normal = np.where(on_face[..., None], np.sin(pile.slope) * -along + np.cos(pile.slope) * np.array([0, 0, 1.0]),
                      np.array([0, 0, 1.0]))
    light = 0.55 + 0.45 * np.clip(normal @ sun, 0, 1)
    grain_ground = 1.0 + 0.25 * _sample(texture, point[..., 0], point[..., 1], 0.9 * reach)
    grain_pile = 1.0 + 0.35 * _sample(texture, b, point[..., 2] + 0.3 * a, 0.4 * reach)
    colour = np.where(hit_pile[..., None], ROCK * (light * grain_pile)[..., None],
                      GROUND * ((0.55 + 0.45 * sun[2]) * grain_ground)[..., None])
    haze = 1.0 - np.exp(-t_final / (25.0 * reach))
    colour = colour * (1 - haze[..., None]) + HAZE * haze[..., None]
    sky = ~down & ~hit_pile
    elevation = np.clip(rays[..., 2], 0, 1)[..., None]
    colour = np.where(sky[..., None], HAZE + (SKY - HAZE) * np.sqrt(elevation), colour)
    small = np.clip(colour, 0, 255).astype(np.uint8)
    image = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
    fine = rng.normal(0.0, 5.0, (h, w, 1)).astype(np.float32)
    image = np.clip(image + np.where(cv2.resize(sky.astype(np.uint8), (w, h))[..., None] > 0, 0, fine), 0, 255)
    image = image.astype(np.uint8)
    _draw_truck(image, camera, truck, reach, sun)
    _draw_clutter(image, camera, reach, rng)
    if people or trucks or other_machine:
        # from a child stream: the camera's other draws stay as they are without the clutter
        _draw_behind(image, camera, reach, sun, rng.spawn(1)[0], people, trucks, other_machine)
    return image


def _march_pile(origin, rays, enter, leave, along, across, pile: Pile) -> tuple[np.ndarray, np.ndarray]:
    """Whether rays (N, 3) from `origin`, between `enter` and `leave` (N,), meet the pile's
    height field, and where first (N,): 160 steps, then the crossing bisected."""
    hit = np.zeros(len(rays), dtype=bool)
    t_pile = leave.copy()
    prev = enter.copy()
    for s in np.linspace(0.0, 1.0, 160):
        t = enter + (leave - enter) * s
        p = origin + rays * t[..., None]
        above = p[..., 2] > pile_height(p @ along, p @ across, pile)
        new = ~above & ~hit
        t_pile[new] = t[new]
        hit |= new
        prev = np.where(hit, prev, t)
    lo, hi = prev, t_pile
    for _ in range(8):
        mid = 0.5 * (lo + hi)
        p = origin + rays * mid[..., None]
        above = p[..., 2] > pile_height(p @ along, p @ across, pile)
        lo, hi = np.where(above, mid, lo), np.where(above, hi, mid)
    return hit, hi


def _slabs(origin, rays, along, across, pile: Pile, reach: float):
    """Where rays (h, w, 3) from `origin` enter and leave the pile's bounding box (h, w)."""
    low = np.array([pile.toe, -0.5 * pile.width, -1.0])
    high = np.array([pile.toe + 40.0 * reach, 0.5 * pile.width, pile.height + 0.01])
    o = np.array([origin @ along, origin @ across, origin[2]])
    d = np.stack([rays @ along, rays @ across, rays[..., 2]], axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (low - o) / d, (high - o) / d
    inside = (o >= low) & (o <= high)
    flat = d == 0
    t_low = np.where(flat, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2)).max(axis=-1)
    t_high = np.where(flat, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2)).min(axis=-1)
    enter = np.maximum(t_low, 0.0)
    return enter, np.maximum(t_high, enter)


def draw_boxes(image: np.ndarray, camera_matrix: np.ndarray, distortion: np.ndarray, cam_from_world: np.ndarray,
               centre: np.ndarray, corners: np.ndarray, normals: np.ndarray, colours: np.ndarray,
               sun: np.ndarray) -> None:
    """Flat-shaded boxes, far to near: corners (B, 8, 3) and face normals (B, 6, 3) in the
    world, colours (B, 3) BGR; faces turned away from the camera are skipped."""
    cam = corners @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    uv = project_cam(cam, camera_matrix, distortion)
    order = np.argsort(-np.linalg.norm(corners.mean(axis=1) - centre, axis=-1))
    for k in order:
        for f, quad in enumerate(BOX_FACES):
            face_centre = corners[k, quad].mean(axis=0)
            if normals[k, f] @ (centre - face_centre) <= 0:
                continue
            pts = uv[k, quad]
            if not np.all(np.isfinite(pts)) or np.abs(pts).max() > 1e5:
                continue
            shade = 0.45 + 0.55 * max(0.0, float(normals[k, f] @ sun))
            cv2.fillPoly(image, [np.round(pts * 16).astype(np.int32)], (colours[k] * shade).tolist(),
                         lineType=cv2.LINE_AA, shift=4)


def _draw_truck(image: np.ndarray, camera: Camera, truck: Truck, reach: float, sun: np.ndarray) -> None:
    radial = np.array([np.cos(truck.azimuth), np.sin(truck.azimuth), 0.0])
    tangent = np.array([-radial[1], radial[0], 0.0])
    up = np.array([0.0, 0.0, 1.0])
    length, width = 0.8 * reach, 0.45 * reach
    centre = radial * truck.distance
    boxes = [  # (centre offset along tangent, half sizes along tangent, radial, up; z range)
        (0.0, 0.5 * length, 0.5 * width, 0.12 * reach, truck.height),
        (0.5 * length + 0.1 * reach, 0.1 * reach, 0.5 * width, 0.12 * reach, 0.75 * truck.height),
        (0.0, 0.55 * length, 0.45 * width, 0.0, 0.12 * reach),
    ]
    corners, normals = [], []
    rotation = np.stack([tangent, radial, up], axis=1)  # world_from_truck
    for offset, half_t, half_r, z0, z1 in boxes:
        box = np.array([[-half_t + offset, -half_r, z0], [half_t + offset, half_r, z1]])
        corners.append(box_corners(box) @ rotation.T + centre)
        normals.append(BOX_NORMALS @ rotation.T)
    colours = np.array([[40.0, 170.0, 230.0], [50.0, 180.0, 235.0], [35.0, 35.0, 35.0]])
    pose = camera.cam_from_world.matrix
    draw_boxes(image, camera.matrix, camera.distortion, pose, camera.center, np.array(corners), np.array(normals),
               colours, sun)


def _draw_clutter(image: np.ndarray, camera: Camera, reach: float, rng: np.random.Generator) -> None:
    """Dark rocks on the ground and marker-like signs (black disks on white) near the machine."""
    angles = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    circle = np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)], axis=-1)
    pose = camera.cam_from_world.matrix
    for k in range(40):
        distance, azimuth = rng.uniform(0.4, 2.0) * reach, rng.uniform(0, 2 * np.pi)
        centre = np.array([distance * np.cos(azimuth), distance * np.sin(azimuth), 0.0])
        radius = rng.uniform(0.01, 0.04) * reach
        outline = centre + radius * circle * [1.0, rng.uniform(0.5, 1.0), 0.0] + [0, 0, 0.02 * radius]
        if k < 3:  # a sign: a board standing up, facing the camera
            facing = camera.center - centre
            facing[2] = 0.0
            facing /= np.linalg.norm(facing)
            side = np.array([-facing[1], facing[0], 0.0])
            middle = centre + [0, 0, 0.06 * reach]
            corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=float)
            square = middle + 0.016 * reach * corners @ np.stack([side, [0, 0, 1.0]])
            disk = middle + 0.0095 * reach * (np.cos(angles)[:, None] * side + np.sin(angles)[:, None] * [0, 0, 1.0])
            for outline, colour in ((square, (230, 230, 230)), (disk, (25, 25, 25))):
                _fill(image, camera, pose, outline, colour)
        else:
            grey = rng.uniform(25, 60)
            _fill(image, camera, pose, outline, tuple(float(grey * t) for t in rng.uniform(0.9, 1.1, 3)))


def _fill(image, camera, pose, outline, colour) -> None:
    uv = project_cam(outline @ pose[:3, :3].T + pose[:3, 3], camera.matrix, camera.distortion)
    if np.all(np.isfinite(uv)) and np.abs(uv).max() < 1e5:
        cv2.fillPoly(image, [np.round(uv * 16).astype(np.int32)], colour, lineType=cv2.LINE_AA, shift=4)


def _draw_behind(image: np.ndarray, camera: Camera, reach: float, sun: np.ndarray, rng: np.random.Generator,
                 people: int, trucks: int, other_machine: bool) -> None:
    """Haul trucks (yellow body, black tyres with grey hubs: dark round blobs), another
    machine (white house with a black disk on a white sign, like a marker) and people
    (1.8 m, high-visibility vests with white stripes, dark heads), all standing on the far
    side of the machine from the camera, so that the machine is drawn over them."""
    away = -camera.center[:2] / np.linalg.norm(camera.center[:2])
    side = np.array([-away[1], away[0]])
    up = np.array([0.0, 0.0, 1.0])
    corners, normals, colours, disks = [], [], [], []  # disks: (centre, radius m, grey)

    def place(distance: float, offset: float) -> np.ndarray:
        xy = away * distance + side * offset
        return np.array([xy[0], xy[1], 0.0])

    def boxes(centre: np.ndarray, heading: float, parts) -> np.ndarray:
        along = np.array([np.cos(heading), np.sin(heading), 0.0])
        rotation = np.stack([along, np.cross(up, along), up], axis=1)  # world_from_object
        for low, high, colour in parts:
            corners.append(box_corners(np.array([low, high], dtype=float)) @ rotation.T + centre)
            normals.append(BOX_NORMALS @ rotation.T)
            colours.append(colour)
        return rotation

    for _ in range(trucks):
        centre = place(rng.uniform(1.3, 2.5) * reach, rng.uniform(-1.2, 1.2) * reach)
        heading = rng.uniform(0, 2 * np.pi)
        length, width, tyre = 0.7 * reach, 0.4 * reach, 0.09 * reach
        size = np.array([length, width, 1.0])
        rotation = boxes(centre, heading, [  # bed, cab, chassis (x, y as shares of length, width; z in m)
            (size * (-0.5, -0.5, 1.6 * tyre), size * (0.3, 0.5, 0.35 * reach), (40.0, 170.0, 230.0)),
            (size * (0.32, -0.5, 1.6 * tyre), size * (0.5, 0.5, 0.3 * reach), (50.0, 180.0, 235.0)),
            (size * (-0.45, -0.4, tyre), size * (0.45, 0.4, 1.6 * tyre), (35.0, 35.0, 35.0))])
        for a in (-0.33, 0.33):
            for b in (-0.5, 0.5):
                hub = centre + rotation @ np.array([a * length, b * width, tyre])
                out = rotation[:, 1] * np.sign(b)
                disks += [(hub, out, tyre, 28.0), (hub, out, 0.35 * tyre, 150.0)]  # tyre, hub
    if other_machine:
        centre = place(rng.uniform(1.5, 2.5) * reach, rng.uniform(-1.0, 1.0) * reach)
        heading = rng.uniform(0, 2 * np.pi)
        r = 0.6 * reach
        rotation = boxes(centre, heading, [
            ((-0.3 * r, -0.22 * r, 0.0), (0.3 * r, 0.22 * r, 0.1 * r), (60.0, 62.0, 66.0)),
            ((-0.22 * r, -0.15 * r, 0.1 * r), (0.2 * r, 0.15 * r, 0.26 * r), (210.0, 212.0, 215.0)),
            ((0.2 * r, -0.04 * r, 0.15 * r), (0.9 * r, 0.04 * r, 0.22 * r), (30.0, 180.0, 230.0))])
        for facing in (rotation[:, 1], -rotation[:, 1]):
            sign = centre + rotation @ np.array([0.0, 0.0, 0.18 * r]) + facing * 0.151 * r
            disks += [(sign, facing, 0.05 * r, 235.0, "square"), (sign + 0.001 * facing, facing, 0.028 * r, 20.0)]
    for _ in range(people):
        centre = place(rng.uniform(0.9, 2.0) * reach, rng.uniform(-1.0, 1.0) * reach)
        vest = (20.0, 120.0, 250.0) if rng.random() < 0.5 else (40.0, 230.0, 200.0)
        boxes(centre, rng.uniform(0, 2 * np.pi), [
            ((-0.12, -0.2, 0.0), (0.12, 0.2, 0.85), (60.0, 50.0, 45.0)),
            ((-0.13, -0.23, 0.85), (0.13, 0.23, 1.5), vest),
            ((-0.135, -0.235, 1.1), (0.135, 0.235, 1.16), (245.0, 245.0, 245.0))])
        disks.append((centre + 1.65 * up, None, 0.13, float(rng.choice([30.0, 235.0]))))
    if corners:
        draw_boxes(image, camera.matrix, camera.distortion, camera.cam_from_world.matrix, camera.center,
                   np.array(corners), np.array(normals), np.array(colours), sun)
    pose = camera.cam_from_world.matrix
    angles = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    for centre, facing, radius, grey, *shape in disks:
        if facing is None:  # a head: a disk facing the camera
            facing = camera.center - centre
            facing /= np.linalg.norm(facing)
        elif facing @ (camera.center - centre) <= 0:
            continue
        u = np.cross(facing, up)
        u = u / np.linalg.norm(u) if np.linalg.norm(u) > 1e-9 else np.array([1.0, 0.0, 0.0])
        v = np.cross(facing, u)
        if shape:
            outline = centre + radius * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=float) @ np.stack([u, v])
        else:
            outline = centre + radius * (np.cos(angles)[:, None] * u + np.sin(angles)[:, None] * v)
        _fill(image, camera, pose, outline, (grey,) * 3)
