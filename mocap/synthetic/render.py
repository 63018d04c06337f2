"""Rendering a synthetic session's videos: the machine as flat-shaded boxes over the
camera's still backdrop, the painted markers as black disks on white squares seen in
perspective, then the camera's effects.

Links are drawn far to near (painter's order by box centre), each link's faces that face
the camera and then its markers. A marker is drawn only where the truth calls it visible
(facing the camera, in the image, not behind another link's box), so the truth tracks
and the pictures agree. Marker squares and disks are filled on an 8x finer grid over a
small region and area-averaged back, so their centres are exact to a few hundredths of a
pixel. Motion blur is the shutter's: a frame whose markers move is the average of the
machine drawn at instants spread over the exposure. A rolling shutter (the session's
`readout`) reads the rows one after another: a moving frame is composed by rows from the
machine drawn at instants spread over all the rows' exposures (`mocap.synthetic.shutter`),
so that each marker lies where the truth has it, at the instant its own row is read.

Shapes: F frames, L links, M markers, N outline points.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from mocap.core.camera import project_cam
from mocap.core.shapes import BOX_FACES, box_corners
from mocap.synthetic.backdrop import BOX_NORMALS, render_backdrop
from mocap.synthetic.effects import CameraEffects, EffectOptions, Weather
from mocap.synthetic.encode import CODECS
from mocap.synthetic.looks import Look
from mocap.synthetic.session import SyntheticSession, marker_sizes
from mocap.synthetic.shutter import instants, row_weights

SMEAR_STEP_PX = 1.5  # the most a marker moves between two instants of an exposure
MAX_SMEAR_SAMPLES = 6
MAX_ROLLING_SAMPLES = 12  # instants a rolling shutter's frame is composed of, at most
STILL_PX = 0.02  # a frame whose markers move less than this over its rows' exposures is drawn once
BEND_PX = 0.01  # the most a marker's path leaves the straight line between two instants composed by rows

WHITE, BLACK = (235, 235, 235), (18, 18, 18)
EDGES = np.array([(a, a | bit) for bit in (1, 2, 4) for a in range(8) if not a & bit])  # of `box_corners`


@dataclass(frozen=True)
class RenderOptions:
    """`codec` one of CODECS, the camera `effects`, the scene's `look` (paint, light,
    markers, haze, defocus, compression: `mocap.synthetic.looks`), the fine grid's
    `supersample` factor, frames per batch `chunk`, encoder `threads` (0: automatic). The
    markers' squares are the session's (`mocap.synthetic.session.marker_sizes`), their
    disks the look's share of them."""

    codec: str = "h264"
    effects: EffectOptions = field(default_factory=EffectOptions)
    look: Look = field(default_factory=Look)
    supersample: int = 8
    chunk: int = 32
    threads: int = 0

    def __post_init__(self) -> None:
        if self.codec not in CODECS:
            raise ValueError(f"codec must be one of {CODECS}, got {self.codec!r}")
        if not 1 <= self.supersample <= 8:
            raise ValueError(f"supersample must be 1..8, got {self.supersample}")


class CameraRenderer:
    """Renders one camera's frames of a session (clean pictures and the camera's own)."""

    def __init__(self, session: SyntheticSession, index: int, options: RenderOptions, rng: np.random.Generator):
        self.session, self.options = session, options
        self.field = session.cameras[index]
        camera = self.field.camera
        reach = session.reach
        self.look = look = options.look
        elevation, azimuth = np.radians(rng.uniform(35, 60)), rng.uniform(0, 2 * np.pi)
        self.sun = np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                             np.sin(elevation)]) if look.sun() is None else look.sun()
        self.backdrop = render_backdrop(camera, session.plan.pile, session.plan.truck, reach, self.sun, rng,
                                        look.people, look.trucks, look.other_machine)
        self.corners = np.array([box_corners(b) for b in session.boxes])  # (L, 8, 3)
        self.colours = look.palette[np.arange(len(session.boxes)) % len(look.palette)]
        self.squares, self.disks = session.marker_outlines()
        centres = session.machine.marker_positions[:, None]
        disk_m, square_m = marker_sizes(reach)
        self.disks = centres + (self.disks - centres) * (look.disk_ratio * square_m / disk_m)
        if look.square_grey is not None:
            self.square_grey = np.full(len(centres), look.square_grey)
        else:  # no squares; but a disk on a dark link (undercarriage, bucket) would not show: those keep theirs
            grey = self.colours[session.machine.marker_links] @ np.array([0.114, 0.587, 0.299])  # BGR luma
            self.square_grey = np.where(grey < 110, WHITE[0], np.nan)
        self.effects = CameraEffects(camera.size, options.effects, rng)
        self.weather = Weather(camera.size, look.rain, look.glare, rng.spawn(1)[0])  # leaves `rng` as it is
        self.dust_radius = 0.2 * reach
        self.readout = session.options.readout
        self._weights: dict[tuple[float, int], np.ndarray] = {}

    def _project(self, cams: np.ndarray, points: np.ndarray) -> np.ndarray:
        """World points (F, ..., 3) into pixels (F, ..., 2) with per-frame poses (F, 4, 4)."""
        flat = points.reshape(len(points), -1, 3)
        p = flat @ np.swapaxes(cams[:, :3, :3], -1, -2) + cams[:, None, :3, 3]
        uv = project_cam(p, self.field.camera.matrix, self.field.camera.distortion)
        return uv.reshape(points.shape[:-1] + (2,))

    def frames(self, frames: np.ndarray | None = None, clean: bool = False):
        """Yield (frame, image (H, W, 3) uint8 BGR) for the camera's `frames` (all by default);
        `clean` skips the camera's effects. With motion blur, the shutter stays open `blur`
        of a frame interval, centred on the frame's time: the machine is drawn at instants
        spread over the exposure (enough that no marker moves more than SMEAR_STEP_PX
        between them) and the pictures averaged, so that a moving marker smears as a camera
        shows it and its darkness centroid stays where the truth has it at the frame's time.
        With a rolling shutter, each row's exposure is centred on the instant it is read
        (`mocap.synthetic.shutter.row_delay`) and the frame composed by rows (`_draw_rows`);
        the backdrop stays as at the frame's time."""
        frames = np.arange(self.field.frames) if frames is None else np.asarray(frames)
        session = self.session
        exposure = 0.0 if clean else self.options.effects.blur
        for start in range(0, len(frames), self.options.chunk):
            chunk = frames[start : start + self.options.chunk]
            times = self.field.times(chunk)
            cams = self.field.cam_from_world(times)
            view = self._view(chunk)
            samples = self._exposure_samples(chunk, exposure)
            tip = session.plan_tips(times)
            uv_tip = self._project(cams, tip[:, None])[:, 0]
            depth = np.einsum("fi,fi->f", cams[:, 2, :3], tip) + cams[:, 2, 3]
            density = session.dust_density(times)
            for k, frame in enumerate(chunk):
                image = self._backdrop(cams[k])
                if samples[k] == 1:
                    self._draw_machine(image, *(v[k] for v in view))
                elif self.readout > 0:  # instants over all the rows' exposures, composed by rows
                    views = self._view(frame + instants(self.readout, exposure, samples[k]))
                    self._draw_rows(image, [[v[i] for v in views] for i in range(samples[k])],
                                    self._row_weights(exposure, int(samples[k])))
                else:  # the instants of the exposure, spread evenly over it
                    offsets = exposure * ((np.arange(samples[k]) + 0.5) / samples[k] - 0.5)
                    views = self._view(frame + offsets)
                    self._draw_smear(image, [[v[i] for v in views] for i in range(samples[k])])
                if not clean:
                    image = self.weather.apply(self.look.finish(image), int(frame))
                    radius = self.field.camera.focal * self.dust_radius / max(depth[k], 1e-3)
                    image = self.effects.apply(image, float(times[k]), uv_tip[k], radius, float(density[k]))
                yield int(frame), image

    def _exposure_samples(self, chunk: np.ndarray, exposure: float) -> np.ndarray:
        """(F,) instants to draw each frame at: as many as its fastest marker needs to move
        no more than SMEAR_STEP_PX between them over the exposure (1: no smear). With a
        rolling shutter, over all the rows' exposures: also as many as keep the straight
        line between two instants within BEND_PX of a marker's path (a shaking camera's
        markers turn within a frame interval), at least two (the first and the last row's)
        unless no marker moves by more than STILL_PX over them."""
        span = exposure + self.readout
        if span <= 0:
            return np.ones(len(chunk), dtype=int)
        if self.readout <= 0:
            early = self.session.observe(self.field, chunk - span / 2)[0]
            late = self.session.observe(self.field, chunk + span / 2)[0]
            travel = np.nanmax(np.nan_to_num(np.linalg.norm(late - early, axis=-1)), axis=1, initial=0.0)
            return np.clip(np.ceil(travel / SMEAR_STEP_PX), 1, MAX_SMEAR_SAMPLES).astype(int)
        offsets = np.linspace(-span / 2, span / 2, 5)
        at = np.broadcast_to((chunk[:, None] + offsets).reshape(-1, 1), (len(chunk) * 5, len(self.disks)))
        uv = self.session.pixels_at(self.field, at).reshape(len(chunk), 5, -1, 2)  # (F, 5, M, 2)
        path = np.nan_to_num(np.linalg.norm(np.diff(uv, axis=1), axis=-1)).sum(axis=1).max(axis=1)
        step = offsets[1] - offsets[0]
        bend = np.nan_to_num(np.linalg.norm(uv[:, 2:] - 2 * uv[:, 1:-1] + uv[:, :-2], axis=-1)).max(axis=(1, 2))
        reach = np.nan_to_num(np.linalg.norm(uv - uv[:, 2:3], axis=-1)).max(axis=(1, 2))
        # linear interpolation over h frame intervals misses a path of acceleration a by a h^2 / 8
        curving = span * np.sqrt(bend / step**2 / (8 * BEND_PX))
        samples = np.ceil(np.maximum(path / SMEAR_STEP_PX, curving)) + 1
        return np.where(reach <= STILL_PX, 1, np.clip(samples, 2, MAX_ROLLING_SAMPLES)).astype(int)

    def _row_weights(self, exposure: float, count: int) -> np.ndarray:
        key = (exposure, count)
        if key not in self._weights:
            self._weights[key] = row_weights(self.field.camera.size[1], self.readout, exposure, count)
        return self._weights[key]

    def _view(self, at: np.ndarray):
        """What `_draw_machine` needs at (fractional) frames `at` (F,): camera centres, box
        corners and face normals, their pixels, the markers' squares and disks in pixels and
        which markers are seen, each with the frame first."""
        machine = self.session.machine
        cams = self.field.cam_from_world(self.field.times(at))
        _, seen, poses = self.session.observe(self.field, at)
        centres = -np.einsum("fji,fj->fi", cams[:, :3, :3], cams[:, :3, 3])
        turn = np.swapaxes(poses[..., :3, :3], -1, -2)  # (F, L, 3, 3): row vectors times it (matmul, not einsum: tenfold faster)
        corners = self.corners @ turn + poses[:, :, None, :3, 3]
        normals = BOX_NORMALS @ turn  # (F, L, 6, 3)
        on_link = poses[:, machine.marker_links]
        squares = self.squares @ turn[:, machine.marker_links] + on_link[..., None, :3, 3]
        disks = self.disks @ turn[:, machine.marker_links] + on_link[..., None, :3, 3]
        uv_corners = self._project(cams, corners)
        return (centres, corners, normals, uv_corners, self._project(cams, squares), self._project(cams, disks), seen,
                cams)

    def _draw_smear(self, image: np.ndarray, views: list) -> None:
        """The machine drawn at each instant of the exposure and the pictures averaged, over
        the region the machine covers at any of them."""
        box = self._bounds(np.concatenate([view[3].reshape(-1, 2) for view in views]))
        if box is None:
            return
        x0, y0, x1, y1 = box
        total = np.zeros((y1 - y0, x1 - x0, 3), np.float32)
        for view in views:
            picture = image.copy()
            self._draw_machine(picture, *view)
            total += picture[y0:y1, x0:x1]
        image[y0:y1, x0:x1] = np.round(total / len(views)).astype(np.uint8)

    def _draw_rows(self, image: np.ndarray, views: list, weights: np.ndarray) -> None:
        """The machine drawn at each of the instants (`mocap.synthetic.shutter.instants`)
        and the pictures composed by rows with `weights` (K, H), over the region the machine
        covers at any of them; at each instant only the links that reach the rows it makes."""
        box = self._bounds(np.concatenate([view[3].reshape(-1, 2) for view in views]))
        if box is None:
            return
        x0, y0, x1, y1 = box
        total = np.zeros((y1 - y0, x1 - x0, 3), np.float32)
        behind = image[y0:y1, x0:x1].copy()  # the machine is drawn inside the box: put back after each instant
        for view, weight in zip(views, weights):
            rows = np.flatnonzero(weight[y0:y1] > 0)
            if not len(rows):
                continue
            a, b = y0 + rows[0], y0 + rows[-1] + 1
            self._draw_machine(image, *view, rows=(a, b))
            total[a - y0 : b - y0] += weight[a:b, None, None] * image[a:b, x0:x1]
            image[y0:y1, x0:x1] = behind
        image[y0:y1, x0:x1] = np.round(total).astype(np.uint8)

    def _bounds(self, uv: np.ndarray) -> tuple[int, int, int, int] | None:
        """Pixel bounds (x0, y0, x1, y1) of the machine's projected boxes, clipped to the image."""
        w, h = self.field.camera.size
        uv = uv.reshape(-1, 2)
        uv = uv[np.all(np.isfinite(uv), axis=1)]
        if not len(uv):
            return None
        x0, y0 = np.clip(np.floor(uv.min(axis=0)).astype(int) - 2, 0, [w, h])
        x1, y1 = np.clip(np.ceil(uv.max(axis=0)).astype(int) + 3, 0, [w, h])
        return (int(x0), int(y0), int(x1), int(y1)) if x1 > x0 and y1 > y0 else None

    def _backdrop(self, cam_from_world: np.ndarray) -> np.ndarray:
        nominal = self.field.camera.cam_from_world.rotation
        turn = cam_from_world[:3, :3] @ nominal.T
        if np.allclose(turn, np.eye(3), atol=1e-12):
            return self.backdrop.copy()
        k = self.field.camera.matrix
        homography = k @ turn @ np.linalg.inv(k)
        w, h = self.field.camera.size
        return cv2.warpPerspective(self.backdrop, homography, (w, h), borderMode=cv2.BORDER_REPLICATE)

    def _draw_machine(self, image, centre, corners, normals, uv_corners, uv_squares, uv_disks, seen, cam,
                      rows: tuple[int, int] | None = None) -> None:
        """The machine's links far to near, each its faces, markers and the shadows on it;
        with `rows` (first, end), only the links whose pictures reach those rows."""
        links = self.session.machine.marker_links
        order = np.argsort(-np.linalg.norm(corners.mean(axis=1) - centre, axis=-1))
        if rows is not None:
            v = uv_corners[..., 1]
            low = np.where(np.isfinite(v), v, np.inf).min(axis=1)  # (L,)
            high = np.where(np.isfinite(v), v, -np.inf).max(axis=1)
            order = [l for l in order if not (high[l] < rows[0] - 3 or low[l] > rows[1] + 2)]
            v = uv_squares[..., 1]
            seen = seen & (v.max(axis=1) >= rows[0] - 3) & (v.min(axis=1) <= rows[1] + 2)
        middles = corners[:, BOX_FACES].mean(axis=2)  # (L, 6, 3) the faces' centres
        for l in order:
            for f, quad in enumerate(BOX_FACES):
                if normals[l, f] @ (centre - middles[l, f]) <= 0:
                    continue
                pts = uv_corners[l, quad]
                if not np.all(np.isfinite(pts)) or np.abs(pts).max() > 1e5:
                    continue
                shade = self.look.shade(float(normals[l, f] @ self.sun))
                cv2.fillPoly(image, [np.round(pts * 16).astype(np.int32)], (self.colours[l] * shade).tolist(),
                             lineType=cv2.LINE_AA, shift=4)
            for m in np.flatnonzero(seen & (links == l)):
                white = None if np.isnan(self.square_grey[m]) else float(self.square_grey[m])
                draw_marker(image, uv_squares[m], uv_disks[m], self.options.supersample, white, self.look.disk_grey)
            if self.look.shadows:
                self._cast_shadows(image, l, centre, corners, normals, cam)

    def _cast_shadows(self, image, l, centre, corners, normals, cam) -> None:
        """Darken, on link `l`'s sunlit faces that face the camera (paint and markers alike),
        the shadows of the other links' boxes: each box, clipped to the face's sunny side,
        projected along the sun onto the face's plane, its hull cut to the face in the picture
        and the pixels there scaled down to the shaded level."""
        camera = self.field.camera
        shadows = []  # (polygons, factor) per face
        for f, quad in enumerate(BOX_FACES):
            n, origin = normals[l, f], corners[l, quad[0]]
            facing_sun = float(n @ self.sun)
            if facing_sun <= 0.05 or n @ (centre - corners[l, quad].mean(axis=0)) <= 0:
                continue
            factor = self.look.shade(-1.0) / self.look.shade(facing_sun)
            if factor > 0.99:
                continue
            face_uv = project_cam(corners[l, quad] @ cam[:3, :3].T + cam[:3, 3], camera.matrix, camera.distortion)
            if not np.all(np.isfinite(face_uv)) or np.abs(face_uv).max() > 1e5:
                continue
            pieces = []
            for b in range(len(corners)):
                if b == l:
                    continue
                height = (corners[b] - origin) @ n  # (8,) above the face's plane
                if height.max() <= 1e-6:
                    continue
                a, c = corners[b][EDGES[:, 0]], corners[b][EDGES[:, 1]]
                ha, hc = height[EDGES[:, 0]], height[EDGES[:, 1]]
                cross = (ha > 0) != (hc > 0)
                cut = a[cross] + (c[cross] - a[cross]) * (ha[cross] / (ha[cross] - hc[cross]))[:, None]
                above = corners[b][height > 0]
                shadow = np.concatenate([above - np.outer(height[height > 0] / facing_sun, self.sun), cut])
                uv = project_cam(shadow @ cam[:3, :3].T + cam[:3, 3], camera.matrix, camera.distortion)
                if len(uv) < 3 or not np.all(np.isfinite(uv)) or np.abs(uv).max() > 1e5:
                    continue
                hull = cv2.convexHull(uv.astype(np.float32))
                area, piece = cv2.intersectConvexConvex(hull, cv2.convexHull(face_uv.astype(np.float32)))
                if area > 0.5 and piece is not None:
                    pieces.append(piece.reshape(-1, 2))
            if pieces:
                shadows.append((pieces, factor))
        if shadows:
            darken(image, shadows)


def darken(image: np.ndarray, shadows: list[tuple[list[np.ndarray], float]]) -> None:
    """Scale the pixels inside each union of polygons (each (N, 2) px) by its factor, edges
    anti-aliased; where shadows overlap (or their edges do), the darkest one only."""
    h, w = image.shape[:2]
    points = np.concatenate([polygon for polygons, _ in shadows for polygon in polygons])
    x0, y0 = np.clip(np.floor(points.min(axis=0)).astype(int) - 1, 0, [w, h])
    x1, y1 = np.clip(np.ceil(points.max(axis=0)).astype(int) + 2, 0, [w, h])
    if x1 <= x0 or y1 <= y0:
        return
    scale = np.ones((y1 - y0, x1 - x0), np.float32)
    for polygons, factor in shadows:
        mask = np.zeros_like(scale)
        for polygon in polygons:  # one at a time: fillPoly of several would cancel where they overlap
            cv2.fillPoly(mask, [np.round((polygon - [x0, y0]) * 16).astype(np.int32)], 1.0, lineType=cv2.LINE_AA,
                         shift=4)
        scale = np.minimum(scale, 1.0 - (1.0 - factor) * mask)
    scale = scale[..., None]
    image[y0:y1, x0:x1] = np.clip(image[y0:y1, x0:x1] * scale + 0.5, 0, 255).astype(np.uint8)


def draw_marker(image: np.ndarray, square: np.ndarray, disk: np.ndarray, factor: int,
                white: float | None = WHITE[0], black: float = BLACK[0]) -> None:
    """A black disk (outline (N, 2) px) on a white square (4, 2) px, filled on a grid
    `factor` times finer and area-averaged back into `image`; greys `white` (None: no
    square, the disk straight on the paint) and `black`."""
    h, w = image.shape[:2]
    x0, y0 = np.floor(square.min(axis=0)).astype(int) - 1
    x1, y1 = np.ceil(square.max(axis=0)).astype(int) + 2
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
    if x1 - x0 < 1 or y1 - y0 < 1:
        return
    roi = image[y0:y1, x0:x1]
    fine = cv2.resize(roi, None, fx=factor, fy=factor, interpolation=cv2.INTER_NEAREST)
    origin = np.array([x0, y0], dtype=float)
    paints = ((square, (white,) * 3), (disk, (black,) * 3)) if white is not None else ((disk, (black,) * 3),)
    for outline, colour in paints:
        pts = ((outline - origin + 0.5) * factor - 0.5) * 256  # fine-grid pixels, 8 fraction bits
        cv2.fillPoly(fine, [np.round(pts).astype(np.int32)], colour, lineType=cv2.LINE_8, shift=8)
    image[y0:y1, x0:x1] = cv2.resize(fine, (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA)
