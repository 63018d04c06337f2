"""Field cameras around a working machine: placement, clocks and shake.

A crew sets 2-4 cameras on tripods or benches 20-80 m from an EX3500 (distances scale
with the machine's reach), away from the pile and the truck, each aimed and zoomed so the
whole working envelope fits in its frame. Each camera runs its own clock: camera k's
frame f shows time f / fps_k + offset_k (DESIGN.md); the first is the reference (offset 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mocap.core.camera import Camera
from mocap.core.geometry import Rigid, rot_x, rot_y, rpy_to_matrix
from mocap.synthetic.paths import SmoothNoise
from mocap.synthetic.scenes import look_at_camera

FRAME_RATES = (29.97, 30.0)


@dataclass(frozen=True)
class FieldCamera:
    """A camera with its clock: `fps`, `time_offset` s, `frames` in its video, and an
    optional `shake` (roll, pitch, yaw noise in rad applied in the camera frame)."""

    camera: Camera
    fps: float
    time_offset: float
    frames: int
    shake: SmoothNoise | None = None

    def __post_init__(self) -> None:
        if not self.fps > 0 or self.frames < 1:
            raise ValueError(
                f"camera {self.camera.name!r}: needs fps > 0 and frames >= 1, got {self.fps}, {self.frames}"
            )

    @property
    def name(self) -> str:
        return self.camera.name

    def times(self, frames: np.ndarray | None = None) -> np.ndarray:
        """Reference-clock times (F,) s of this camera's frames (all frames by default)."""
        frames = np.arange(self.frames) if frames is None else np.asarray(frames)
        return frames / self.fps + self.time_offset

    def cam_from_world(self, times: np.ndarray) -> np.ndarray:
        """(F, 4, 4) camera poses at `times`: the nominal pose, shaken if it shakes."""
        nominal = self.camera.cam_from_world.matrix
        out = np.tile(nominal, (len(times), 1, 1))
        if self.shake is not None:
            out[:, :3, :] = rpy_to_matrix(self.shake(times)) @ nominal[:3, :]
        return out


def place_cameras(
    n: int,
    working_points: np.ndarray,
    reach: float,
    avoid_azimuths: tuple[float, ...],
    duration: float,
    rng: np.random.Generator,
    *,
    size: tuple[int, int] = (1920, 1080),
    distortion: bool = False,
    shake_deg: float = 0.0,
    fps: float = 30.0,
) -> list[FieldCamera]:
    """`n` cameras around the machine.

    working_points (N, 3) world points the cameras must see (the links over the session);
    `avoid_azimuths` (rad) directions of the pile and the truck, kept clear by 55°, the
    first (the pile) also behind the machine by 50°: a crew films the digging from the front
    and the sides, where the bucket shows; the recordings cover the session's `duration` s
    on the reference clock.
    """
    scale = reach / 15.5
    free = np.radians(np.arange(-180, 180, 2.0))
    keep_clear = [(a, 55.0) for a in avoid_azimuths] + [(avoid_azimuths[0] + np.pi, 50.0)]
    for azimuth, clearance in keep_clear:
        gap = np.abs((free - azimuth + np.pi) % (2 * np.pi) - np.pi)
        free = free[gap > np.radians(clearance)]
    start = rng.integers(len(free))
    picks = free[(start + np.round(np.arange(n) * len(free) / n).astype(int)) % len(free)]
    centre = 0.5 * (working_points.min(axis=0) + working_points.max(axis=0))
    cameras = []
    for k, azimuth in enumerate(picks + np.radians(rng.uniform(-6, 6, n))):
        distance = rng.uniform(20.0, 80.0) * scale
        height = rng.uniform(1.5, 10.0) * scale
        position = np.array([distance * np.cos(azimuth), distance * np.sin(azimuth), height])
        name = f"cam{k + 1}"
        aim = look_at_camera(name, size, 1.0, position, centre)
        aim = _centred(_centred(aim, working_points), working_points)
        focal = _fitting_focal(aim, working_points, size)
        dist = np.zeros(5)
        if distortion:
            dist = np.array([rng.uniform(-0.12, 0.02), rng.uniform(-0.02, 0.05), 0.0, 0.0, 0.0])
        camera = Camera(name, size, np.array([[focal, 0, (size[0] - 1) / 2], [0, focal, (size[1] - 1) / 2], [0, 0, 1]]),
                        dist, aim.cam_from_world)
        rate = float(fps) if k == 0 else float(rng.choice(FRAME_RATES)) * (fps / 30.0)  # 29.97: NTSC 30, exactly at 30
        offset = 0.0 if k == 0 else float(rng.uniform(-1.0, 1.0))
        frames = int(np.floor((duration - offset) * rate)) + 1
        shake = None
        if shake_deg > 0:
            shake = SmoothNoise.random(rng, np.radians(shake_deg) * np.ones(3), (0.5, 6.0))
        cameras.append(FieldCamera(camera, rate, offset, frames, shake))
    return cameras


def _centred(camera: Camera, points: np.ndarray) -> Camera:
    """Turn `camera` so that the middle of the points' angular extent is on its axis."""
    p = camera.cam_from_world.apply(points)
    ax = np.arctan2(p[:, 0], p[:, 2])
    ay = np.arctan2(p[:, 1], p[:, 2])
    yaw, pitch = 0.5 * (ax.min() + ax.max()), 0.5 * (ay.min() + ay.max())
    new_from_old = rot_x(pitch) @ rot_y(-yaw)  # turn right by yaw, then down by pitch
    rotation = new_from_old @ camera.cam_from_world.rotation
    center = camera.center
    return camera.with_pose(Rigid(rotation, -rotation @ center))


def _fitting_focal(camera: Camera, points: np.ndarray, size: tuple[int, int]) -> float:
    """The focal length (px) that fits the points in 85 % of the frame, within the range
    of zoom lenses (horizontal field of view 12°-70°)."""
    p = camera.cam_from_world.apply(points)
    x, y = np.abs(p[:, 0] / p[:, 2]).max(), np.abs(p[:, 1] / p[:, 2]).max()
    focal = min(0.425 * size[0] / x, 0.425 * size[1] / y)
    widest = 0.5 * size[0] / np.tan(np.radians(35.0))
    narrowest = 0.5 * size[0] / np.tan(np.radians(6.0))
    return float(np.clip(focal, widest, narrowest))
