"""Small synthetic scenes with known truth: cameras placed around a machine, and the
marker pixels they would observe (noise, misses, wrong detections). Seeded through `rng`.
"""

from __future__ import annotations

import numpy as np

from mocap.core.camera import Camera, default_principal_point, intrinsic_matrix
from mocap.core.geometry import Rigid
from mocap.core.machine import Machine
from mocap.core.tracks import Tracks


def look_at_camera(
    name: str,
    size: tuple[int, int],
    focal: float,
    center: np.ndarray,
    target: np.ndarray,
    roll: float = 0.0,
    distortion: np.ndarray | None = None,
) -> Camera:
    """A camera at `center` (world, m) looking at `target`, image up towards world +z,
    turned by `roll` (rad) about its optical axis; principal point at the image centre."""
    center = np.asarray(center, dtype=float)
    forward = np.asarray(target, dtype=float) - center
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-9:
        right = np.array([0.0, -1.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c, s = np.cos(roll), np.sin(roll)
    right, down = c * right + s * down, -s * right + c * down
    cam_from_world_rotation = np.stack([right, down, forward])  # rows: camera axes in world
    pose = Rigid(cam_from_world_rotation, -cam_from_world_rotation @ center)
    matrix = intrinsic_matrix(focal, default_principal_point(size))
    return Camera(name, size, matrix, np.zeros(5) if distortion is None else distortion, pose)


def ring_of_cameras(
    n: int,
    target: np.ndarray,
    distance: tuple[float, float],
    rng: np.random.Generator,
    size: tuple[int, int] = (1920, 1080),
    height: tuple[float, float] = (2.0, 12.0),
    fov_deg: tuple[float, float] = (25.0, 45.0),
    spread_deg: float = 160.0,
) -> list[Camera]:
    """`n` cameras spread over `spread_deg` of azimuth in front of and beside the machine,
    at random distances and heights, each aimed near `target` with a random field of view."""
    target = np.asarray(target, dtype=float)
    azimuths = np.radians(np.linspace(-spread_deg / 2, spread_deg / 2, n) if n > 1 else [20.0])
    azimuths = azimuths + np.radians(rng.uniform(-10, 10, n))
    cameras = []
    for k, azimuth in enumerate(azimuths):
        d = rng.uniform(*distance)
        center = target + np.array([d * np.cos(azimuth), d * np.sin(azimuth), 0.0])
        center[2] = rng.uniform(*height)
        fov = np.radians(rng.uniform(*fov_deg))
        focal = 0.5 * size[0] / np.tan(fov / 2)
        aim = target + rng.normal(0, 0.5, 3)
        cameras.append(
            look_at_camera(f"cam{k + 1}", size, focal, center, aim, roll=rng.normal(0, 0.02))
        )
    return cameras


def random_joints(machine: Machine, n: int, rng: np.random.Generator, margin: float = 0.15) -> np.ndarray:
    """(n, J) joint values drawn uniformly inside the limits, `margin` of the range from each
    end; unbounded joints are drawn in ±1 m, swing in ±60°."""
    limits = machine.joint_limits.copy()
    limits[:, 0] = np.where(np.isfinite(limits[:, 0]), limits[:, 0], -1.0)
    limits[:, 1] = np.where(np.isfinite(limits[:, 1]), limits[:, 1], 1.0)
    full_circle = machine.wraps
    limits[full_circle] = np.radians([-60.0, 60.0])
    span = limits[:, 1] - limits[:, 0]
    low, high = limits[:, 0] + margin * span, limits[:, 1] - margin * span
    return rng.uniform(low, high, size=(n, machine.n_joints))


def observe(
    cameras: list[Camera],
    machine: Machine,
    joints: np.ndarray,
    rng: np.random.Generator,
    noise_px: float = 0.5,
    miss_fraction: float = 0.0,
    outliers: int = 0,
    outlier_px: tuple[float, float] = (15.0, 60.0),
    frames: np.ndarray | None = None,
) -> Tracks:
    """Marker pixels as the cameras would observe them at joint values (F, J).

    Gaussian noise of `noise_px` per axis; each observation missed with probability
    `miss_fraction`; `outliers` observations moved by a random 15-60 px; points outside the
    image or behind the camera are not seen.
    """
    joints = np.atleast_2d(joints)
    frames = np.arange(len(joints)) if frames is None else np.asarray(frames)
    world = machine.markers(joints)  # (F, M, 3)
    rows = []
    for camera in cameras:
        uv = camera.project(world)  # (F, M, 2)
        uv = uv + rng.normal(0.0, noise_px, uv.shape)
        w, h = camera.size
        seen = np.all(np.isfinite(uv), axis=-1) & (uv[..., 0] >= 0) & (uv[..., 0] <= w - 1)
        seen &= (uv[..., 1] >= 0) & (uv[..., 1] <= h - 1)
        seen &= rng.random(seen.shape) >= miss_fraction
        f, m = np.nonzero(seen)
        rows.append((np.full(len(f), camera.name, dtype=object), frames[f], np.asarray(machine.marker_names, dtype=object)[m], uv[f, m]))
    camera = np.concatenate([r[0] for r in rows])
    frame = np.concatenate([r[1] for r in rows])
    marker = np.concatenate([r[2] for r in rows])
    xy = np.concatenate([r[3] for r in rows])
    if outliers:
        pick = rng.choice(len(xy), size=min(outliers, len(xy)), replace=False)
        angle = rng.uniform(0, 2 * np.pi, len(pick))
        radius = rng.uniform(*outlier_px, len(pick))
        xy[pick] += np.c_[np.cos(angle), np.sin(angle)] * radius[:, None]
    return Tracks.from_rows(camera, frame, marker, xy)
