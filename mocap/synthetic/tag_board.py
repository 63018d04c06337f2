"""Video of a moving board of ArUco / AprilTag markers as a webcam films it, with the exact
centres of the tags: perspective, lens distortion, motion blur, rolling shutter, defocus,
noise, and prints either way round (black tags on white, or inverted: white on black).

Each frame is drawn at `supersample` times the size and reduced by area (anti-aliasing):
every image pixel is taken back through the lens (the distortion inverted once per camera)
onto the board's plane by the homography of the board's pose at that pixel's row's instant
(rolling shutter: the rows are read one after another over `readout` of the frame
interval, `mocap.synthetic.shutter`), and the board's picture sampled there. Motion blur averages `exposure_steps`
such pictures over the shutter's opening. The true centre of a tag is its board centre
projected with the pose at the instant its row was read, the middle of the exposure.

Shapes: F frames, N tags. Pixels in the OpenCV convention (centre of the top-left pixel at
0, 0).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from mocap.core.tags import tag_dictionary
from mocap.synthetic.shutter import rolling_pixels, row_delay

_CELL_PX = 8  # texture pixels per tag cell


@dataclass(frozen=True)
class BoardLook:
    """How a board is filmed: `tag_px` the tags' side in the image (about, at the board's
    middle), `inverted` white tags on a black board, `speed` px per frame the board drifts
    (at its middle), `shutter` the share of the frame interval the shutter is open (motion
    blur of speed x shutter px; 0: sharp), `rolling_shutter` the share of the frame
    interval over which the rows are read (0: global shutter), `defocus` Gaussian SD px,
    `noise` SD grey levels, `k1` radial distortion, `size` the image (width, height),
    `tilt_deg` the board's slant to the camera."""

    tag_px: float = 24.0
    inverted: bool = False
    speed: float = 2.0
    shutter: float = 0.0
    rolling_shutter: float = 0.0
    defocus: float = 0.0
    noise: float = 2.0
    k1: float = -0.35
    size: tuple[int, int] = (640, 480)
    tilt_deg: float = 30.0
    dictionary: str = "DICT_4X4_50"


@dataclass(frozen=True)
class BoardVideo:
    """Frames (F, H, W) uint8 grey, the tags' `ids` (N,), their true centres `xy` (F, N, 2)
    (NaN where a tag is not wholly inside the picture), and the camera matrix and
    distortion used."""

    frames: np.ndarray
    ids: np.ndarray
    xy: np.ndarray
    matrix: np.ndarray
    distortion: np.ndarray


def render_board(look: BoardLook, n_frames: int, rng: np.random.Generator, supersample: int = 3,
                 exposure_steps: int = 7, grid: tuple[int, int] = (7, 5)) -> BoardVideo:
    """A board of `grid` (columns, rows) tags moving across a camera's view; see `BoardLook`."""
    width, height = look.size
    focal = 1.0 * width
    matrix = np.array([[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]])
    distortion = np.array([look.k1, 0.0, 0.0, 0.0, 0.0])
    cols, rows = grid
    n_tags = cols * rows
    dictionary = tag_dictionary(look.dictionary)
    ids = rng.choice(dictionary.bytesList.shape[0], n_tags, replace=False)
    side = 0.1  # m, the tag's black square (border included)
    pitch = 2.0 * side
    texture, texture_from_board = _board_texture(dictionary, ids, grid, side, pitch, look.inverted, rng)
    distance = focal * side / look.tag_px
    centres_board = np.stack(np.meshgrid((np.arange(cols) - (cols - 1) / 2) * pitch,
                                         (np.arange(rows) - (rows - 1) / 2) * pitch), -1).reshape(-1, 2)
    # the board's pose over time (t in frame intervals): a slow turn and a drift
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    base = Rotation.from_euler("xy", [look.tilt_deg * rng.choice([-1, 1]), rng.uniform(-15, 15)], degrees=True)
    direction = rng.normal(size=2)
    direction /= np.linalg.norm(direction)
    speed = look.speed * distance / focal  # m per frame interval at the board's distance
    start = (rng.uniform(-0.2, 0.2, 2) * np.array([width, height]) * distance / focal
             - 0.5 * speed * (n_frames - 1) * direction)

    def pose(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        turn = Rotation.from_rotvec(np.outer(np.radians(0.4) * t, axis))
        rotation = (turn * base).as_matrix()
        shift = start[None] + np.outer(t, speed * direction)
        return rotation, np.c_[shift, np.full(len(t), distance)]

    s = supersample
    rays = _undistorted_rays(matrix.tobytes(), distortion.tobytes(), width, height, s)  # 2 x (sH, sW)
    texture_from_board3 = np.vstack([texture_from_board, [0.0, 0.0, 1.0]])
    rows = (np.arange(height * s) + 0.5) / s - 0.5  # the supersampled rows' centres, image pixels
    row_time = row_delay(rows, height, look.rolling_shutter, centred=False)  # in frame intervals
    offsets = np.zeros(1)  # instants of the exposure, in frame intervals from the frame's time
    if look.shutter > 0:
        offsets = look.shutter * ((np.arange(exposure_steps) + 0.5) / exposure_steps - 0.5)
    frames = np.empty((n_frames, height, width), np.uint8)
    truth = np.full((n_frames, n_tags, 2), np.nan)
    for f in range(n_frames):
        picture = np.zeros((height * s, width * s), np.float32)
        for dt in offsets:
            rotation, translation = pose(f + dt + row_time)
            # normalised image -> texture pixels, one homography per row: the board's
            # plane (columns r1, r2, t) inverted, then board metres -> texture pixels
            plane = np.concatenate([rotation[:, :, :2], translation[:, :, None]], axis=2)
            texture_from_ray = texture_from_board3 @ np.linalg.inv(plane)  # (sH, 3, 3)
            m = texture_from_ray.astype(np.float32)[:, :, :, None]  # broadcast over columns
            x, y = rays
            w = m[:, 2, 0] * x + m[:, 2, 1] * y + m[:, 2, 2]
            tex_x = (m[:, 0, 0] * x + m[:, 0, 1] * y + m[:, 0, 2]) / w
            tex_y = (m[:, 1, 0] * x + m[:, 1, 1] * y + m[:, 1, 2]) / w
            picture += cv2.remap(texture, np.nan_to_num(tex_x, nan=-1.0), np.nan_to_num(tex_y, nan=-1.0),
                                 cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=110.0)
        picture /= len(offsets)
        image = cv2.resize(picture, (width, height), interpolation=cv2.INTER_AREA)
        if look.defocus > 0:
            image = cv2.GaussianBlur(image, (0, 0), look.defocus)
        image += rng.normal(0.0, look.noise, image.shape).astype(np.float32)
        frames[f] = np.clip(np.round(image), 0, 255).astype(np.uint8)
        truth[f] = _true_centres(centres_board, pose, f, look.rolling_shutter, height, matrix, distortion)
    half = 0.5 * side
    corners = centres_board[:, None] + half * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
    inside = _inside(corners, pose, n_frames, matrix, distortion, look.size)
    truth[~inside] = np.nan
    return BoardVideo(frames, ids, truth, matrix, distortion)


def _board_texture(dictionary, ids, grid, side, pitch, inverted, rng):
    """The board's picture (float32) with the tags on a white ground inside a textured grey
    surround, and the affine map (2, 3) from board metres to its pixels."""
    cols, rows = grid
    bits = dictionary.markerSize + 2
    tag_px = bits * _CELL_PX
    per_m = tag_px / side
    board_w, board_h = cols * pitch + pitch, rows * pitch + pitch
    margin = 3.0  # m of surround around the board
    w, h = int((board_w + 2 * margin) * per_m), int((board_h + 2 * margin) * per_m)
    surround = cv2.GaussianBlur(rng.uniform(60, 160, (h // 8 + 1, w // 8 + 1)).astype(np.float32), (0, 0), 1.5)
    texture = cv2.resize(surround, (w, h), interpolation=cv2.INTER_CUBIC)
    x0, y0 = int(margin * per_m), int(margin * per_m)
    bw, bh = int(board_w * per_m), int(board_h * per_m)
    white, black = 225.0, 25.0
    board = np.full((bh, bw), white, np.float32)
    for k, tag_id in enumerate(ids):
        c, r = k % cols, k // cols
        cx, cy = (c + 1) * pitch * per_m, (r + 1) * pitch * per_m
        tile = cv2.aruco.generateImageMarker(dictionary, int(tag_id), tag_px, borderBits=1).astype(np.float32)
        tile = black + (white - black) * tile / 255.0
        top, left = int(round(cy - tag_px / 2)), int(round(cx - tag_px / 2))
        board[top:top + tag_px, left:left + tag_px] = tile
    if inverted:
        board = white + black - board
    texture[y0:y0 + bh, x0:x0 + bw] = board
    # board (x right, y down, origin at its middle) -> texture pixels (pixel centres at integers)
    centre_x, centre_y = x0 + board_w * per_m / 2, y0 + board_h * per_m / 2
    texture_from_board = np.array([[per_m, 0.0, centre_x - 0.5], [0.0, per_m, centre_y - 0.5]])
    return texture, texture_from_board


@lru_cache(maxsize=4)
def _undistorted_rays(matrix_bytes: bytes, distortion_bytes: bytes, width: int, height: int, s: int) -> np.ndarray:
    """2 x (sH, sW) float32 undistorted normalised coordinates of the supersampled pixels
    (radial distortion k1, k2, k3 only; tangential terms must be 0)."""
    matrix = np.frombuffer(matrix_bytes).reshape(3, 3)
    distortion = np.frombuffer(distortion_bytes)
    u = (np.arange(width * s) + 0.5) / s - 0.5
    v = (np.arange(height * s) + 0.5) / s - 0.5
    uu, vv = np.meshgrid(u, v)
    xd = (uu - matrix[0, 2]) / matrix[0, 0]
    yd = (vv - matrix[1, 2]) / matrix[1, 1]
    radius_d = np.hypot(xd, yd)
    k1, k2, _, _, k3 = distortion
    radius = radius_d.copy()
    for _ in range(8):  # Newton on r (1 + k1 r^2 + k2 r^4 + k3 r^6) = r_d (radial distortion only)
        r2 = radius**2
        value = radius * (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) - radius_d
        slope = 1 + 3 * k1 * r2 + 5 * k2 * r2**2 + 7 * k3 * r2**3
        radius = radius - value / slope
    r2 = radius**2
    solved = np.abs(radius * (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) - radius_d) < 1e-6
    scale = np.where(radius_d > 0, radius / np.maximum(radius_d, 1e-12), 1.0)
    scale[~solved] = np.nan  # beyond the lens's fold: no ray
    return (xd * scale).astype(np.float32), (yd * scale).astype(np.float32)


def _project(points_board: np.ndarray, rotation: np.ndarray, translation: np.ndarray, matrix, distortion) -> np.ndarray:
    """(N, 2) board points (metres) -> distorted pixels under one pose."""
    points = np.c_[points_board, np.zeros(len(points_board))]
    rvec = cv2.Rodrigues(rotation)[0]
    uv, _ = cv2.projectPoints(points, rvec, translation.astype(float), matrix, distortion)
    return uv.reshape(-1, 2)


def _true_centres(centres, pose, frame, readout, height, matrix, distortion) -> np.ndarray:
    """(N, 2) each tag's centre at the middle of its row's exposure (rolling shutter: the
    row depends on where the tag is; `mocap.synthetic.shutter.rolling_pixels`)."""

    def pixels_at(at: np.ndarray) -> np.ndarray:
        rotation, translation = pose(at)
        return np.array([_project(c[None], rotation[k], translation[k], matrix, distortion)[0]
                         for k, c in enumerate(centres)])

    return rolling_pixels(pixels_at, np.full(len(centres), float(frame)), height, readout, centred=False)[0]


def _inside(corners, pose, n_frames, matrix, distortion, size) -> np.ndarray:
    """(F, N) bool: every corner of the tag (with a margin of one cell) inside the picture."""
    width, height = size
    out = np.zeros((n_frames, len(corners)), bool)
    for f in range(n_frames):
        rotation, translation = pose(np.array([float(f)]))
        uv = _project(corners.reshape(-1, 2) * 1.3 - 0.3 * np.repeat(corners.mean(axis=1), 4, axis=0),
                      rotation[0], translation[0], matrix, distortion).reshape(len(corners), 4, 2)
        inside = (uv[..., 0] > 2) & (uv[..., 0] < width - 3) & (uv[..., 1] > 2) & (uv[..., 1] < height - 3)
        out[f] = np.all(inside, axis=1)
    return out
