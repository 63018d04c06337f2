"""A rigid chessboard moved by hand through the view of webcams with strong barrel
distortion: the scene for measuring self-calibration on real lenses.

Shapes: C cameras, K frames, M corners. The world is the board's pose in frame 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mocap.core.camera import Camera
from mocap.core.geometry import rotvec_to_matrix
from mocap.core.machine import Machine
from mocap.core.tracks import Tracks
from mocap.io.machine_toml import machine_from_dict
from mocap.synthetic.scenes import look_at_camera


def chessboard(columns: int = 9, rows: int = 6, square: float = 0.04) -> Machine:
    """A chessboard's inner corners as a rigid one-link machine, corner (0, 0) at its origin."""
    corners = [((i % columns) * square, (i // columns) * square, 0.0) for i in range(columns * rows)]
    return machine_from_dict({
        "name": f"chessboard {columns} x {rows}",
        "source": f"{columns} x {rows} inner corners, {square * 1000:g} mm squares",
        "links": [{"name": "board"}],
        "markers": [{"name": f"C{i:02d}", "link": "board", "position": list(p)} for i, p in enumerate(corners)],
    })


@dataclass(frozen=True)
class BoardScene:
    """cameras (C) true; board the rigid model; world_from_board (K, 4, 4) true poses;
    pixels (C, K, M, 2) observed corners, NaN where the corner is out of the image or the
    board faces away from the camera; noise_px the pixel noise SD."""

    cameras: tuple[Camera, ...]
    board: Machine
    world_from_board: np.ndarray
    pixels: np.ndarray
    noise_px: float

    def tracks(self) -> Tracks:
        """The observed corners as tracks: one row per camera, frame and corner seen."""
        c, k, m = np.nonzero(np.isfinite(self.pixels[..., 0]))
        names = np.array([camera.name for camera in self.cameras])
        return Tracks.from_rows(names[c], k, np.array(self.board.marker_names)[m], self.pixels[c, k, m])

    def corners(self) -> np.ndarray:
        """(K, M, 3) the corners in the world."""
        local = self.board.marker_positions
        return local @ np.swapaxes(self.world_from_board[:, :3, :3], 1, 2) + self.world_from_board[:, None, :3, 3]


def board_scene(rng: np.random.Generator, n_frames: int = 60, n_cameras: int = 4, k1: float = -0.35,
                noise_px: float = 0.3, size: tuple[int, int] = (1280, 720), distance: float = 1.2,
                board: Machine | None = None) -> BoardScene:
    """Webcams (radial k1, k2 = 0.1 k1 ** 2 / 0.35, focal about 0.55 width) on an arc of
    70 degrees about 1.2 m in front of the board; the board wanders through +-0.25 m and
    turns +-35 degrees, frame 0 at the world origin."""
    board = board or chessboard()
    centre = board.marker_positions.mean(0)
    cameras = []
    for c, azimuth in enumerate(np.radians(np.linspace(-35, 35, n_cameras) + rng.normal(0, 3, n_cameras))):
        position = centre + distance * rng.uniform(0.9, 1.1) * np.array([np.sin(azimuth), -0.2, -np.cos(azimuth)])
        distortion = np.array([k1 * rng.uniform(0.9, 1.1), 0.1 * k1**2 / 0.35, 0.0, 0.0, 0.0])
        camera = look_at_camera(f"cam{c + 1}", size, size[0] * rng.uniform(0.5, 0.6), position,
                                centre + rng.normal(0, 0.03, 3), distortion=distortion)
        cameras.append(camera)
    poses = np.tile(np.eye(4), (n_frames, 1, 1))
    turn = rng.uniform(-0.6, 0.6, (n_frames, 3))
    turn[0] = 0.0
    shift = rng.uniform(-0.25, 0.25, (n_frames, 3)) * [1.0, 0.7, 0.6]
    shift[0] = 0.0
    poses[:, :3, :3] = rotvec_to_matrix(turn)
    poses[:, :3, 3] = centre - centre @ np.swapaxes(poses[:, :3, :3], 1, 2) + shift  # turned about its centre
    scene = BoardScene(tuple(cameras), board, poses, np.zeros(0), noise_px)
    world = scene.corners()
    normal = poses[:, :3, 2]  # (K, 3) the board's z axis in the world
    pixels = []
    for camera in cameras:
        uv = camera.project(world) + rng.normal(0, noise_px, world.shape[:2] + (2,))
        facing = np.einsum("kd,kd->k", normal, camera.center - poses[:, :3, 3]) < -0.3 * distance  # board faces it
        inside = np.all((uv > 0) & (uv < np.array(size) - 1), -1) & facing[:, None]
        pixels.append(np.where(inside[..., None], uv, np.nan))
    return BoardScene(tuple(cameras), board, poses, np.stack(pixels), noise_px)
