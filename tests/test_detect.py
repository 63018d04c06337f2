"""Disk and tag detection on drawn images: anti-aliased (supersampled) disks on white
squares, with blur, noise and clutter; sub-pixel centres against the drawn truth.

The drawing helpers here are shared with the tracking tests."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mocap.tracking.detect import (
    DetectOptions,
    Detections,
    detect_disks,
    detect_tags,
    disk_centre_from_ellipse,
    refine,
    as_gray,
)
from mocap.core.tags import tag_dictionary
from mocap.synthetic.scenes import look_at_camera

SUPERSAMPLE = 8


def fill_polygon(image: np.ndarray, polygon: np.ndarray, level: float) -> None:
    """Paint `polygon` (K, 2) px into the float image with exact-area anti-aliasing (by
    supersampling): a pixel is covered by the fraction of its area inside the polygon."""
    h, w = image.shape
    x0 = int(max(np.floor(polygon[:, 0].min()) - 1, 0))
    y0 = int(max(np.floor(polygon[:, 1].min()) - 1, 0))
    x1 = int(min(np.ceil(polygon[:, 0].max()) + 2, w))
    y1 = int(min(np.ceil(polygon[:, 1].max()) + 2, h))
    if x1 <= x0 or y1 <= y0:
        return
    s = SUPERSAMPLE
    mask = np.zeros(((y1 - y0) * s, (x1 - x0) * s), np.uint8)
    # low-res pixel u spans [u - 0.5, u + 0.5]; high-res pixel centre I sits at (I + 0.5) / s - 0.5
    hi = ((polygon - [x0, y0]) + 0.5) * s - 0.5
    cv2.fillPoly(mask, [np.round(hi * 256).astype(np.int32)], 255, lineType=cv2.LINE_8, shift=8)
    cover = cv2.resize(mask.astype(np.float32) / 255.0, (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA)
    region = image[y0:y1, x0:x1]
    region[...] = region * (1 - cover) + level * cover


def ellipse_polygon(centre, axes, angle, n: int = 180) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    c, s = np.cos(angle), np.sin(angle)
    x = axes[0] * np.cos(t)
    y = axes[1] * np.sin(t)
    return np.c_[centre[0] + c * x - s * y, centre[1] + s * x + c * y]


def finish(image: np.ndarray, rng: np.random.Generator, blur: float = 0.8, noise: float = 3.0) -> np.ndarray:
    if blur > 0:
        image = cv2.GaussianBlur(image, (0, 0), blur)
    image = image + rng.normal(0, noise, image.shape)
    return np.clip(np.round(image), 0, 255).astype(np.uint8)


def background(size, rng: np.random.Generator, level: float = 110.0) -> np.ndarray:
    """A textured grey background (H, W) float."""
    w, h = size
    low = cv2.resize(rng.normal(0, 25, (h // 40 + 2, w // 40 + 2)), (w, h), interpolation=cv2.INTER_CUBIC)
    return level + low


def disk_frame(camera, centre, normal, radius, n: int = 180) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane of a disk with `normal` (3,) in the world."""
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    helper = np.array([0.0, 0.0, 1.0]) if abs(normal[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(normal, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(normal, e1)


def draw_markers(image, camera, centres, normals, radius: float, square: float = 2.4, dark: float = 20.0, white: float = 235.0):
    """Project disk markers (black disk of `radius` m on a white square of side
    `square` * diameter) at `centres` (N, 3) with `normals` (N, 3) (world) into `image`.
    Returns the true projected centres (N, 2)."""
    t = np.linspace(0, 2 * np.pi, 180, endpoint=False)
    half = square * radius
    for centre, normal in zip(centres, normals):
        e1, e2 = disk_frame(camera, centre, normal, radius)
        corners = centre + half * np.array([e1 + e2, e1 - e2, -e1 - e2, -e1 + e2])
        fill_polygon(image, camera.project(corners), white)
        circle = centre + radius * (np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2)
        fill_polygon(image, camera.project(circle), dark)
    return camera.project(np.asarray(centres, float))


def draw_clutter(image, rng: np.random.Generator, n: int, radius=(2.0, 12.0)) -> None:
    """Dark blobs without a white surround, bright specks (dust), dark lines."""
    h, w = image.shape
    for _ in range(n):
        c = rng.uniform([0, 0], [w, h])
        r = rng.uniform(*radius)
        kind = rng.integers(3)
        if kind == 0:
            fill_polygon(image, ellipse_polygon(c, (r, r * rng.uniform(0.5, 1)), rng.uniform(0, np.pi)), 30.0)
        elif kind == 1:
            fill_polygon(image, ellipse_polygon(c, (r / 3, r / 3), 0.0), 250.0)
        else:
            d = rng.normal(0, 1, 2)
            d = d / np.linalg.norm(d) * r * 3
            n_ = np.array([-d[1], d[0]]) / np.linalg.norm(d) * 1.5
            fill_polygon(image, np.array([c - d - n_, c + d - n_, c + d + n_, c - d + n_]), 40.0)


def draw_ellipse_markers(rng, size=(640, 480), n=30, radius=(3.0, 12.0), clutter=40, blur=1.0, noise=3.0):
    """Random ellipse markers (black on a white ellipse 2.4 times larger) on a textured
    background, with clutter; returns the image and the true centres (N, 2)."""
    image = background(size, rng)
    draw_clutter(image, rng, clutter)  # behind the markers; dust on them is tested apart
    centres = []
    while len(centres) < n:
        c = rng.uniform([30, 30], [size[0] - 30, size[1] - 30])
        a = rng.uniform(*radius)
        if centres and np.min(np.linalg.norm(np.array(centres) - c, axis=1)) < 2.6 * (a + radius[1]):
            continue
        b, angle = a * rng.uniform(0.6, 1.0), rng.uniform(0, np.pi)
        fill_polygon(image, ellipse_polygon(c, (2.4 * a, 2.4 * b), angle), 235.0)
        fill_polygon(image, ellipse_polygon(c, (a, b), angle), 20.0)
        centres.append(c)
    return finish(image, rng, blur, noise), np.array(centres)


def match(found: np.ndarray, truth: np.ndarray, tolerance: float = 1.0):
    """For each true centre the distance to the nearest detection (T,), and the number of
    detections farther than `tolerance` from every true centre."""
    if len(found) == 0:
        return np.full(len(truth), np.inf), 0
    dist = np.linalg.norm(found[:, None] - truth[None], axis=-1)
    return dist.min(axis=0), int(np.sum(dist.min(axis=1) > tolerance))


def test_disk_centres_are_sub_pixel_among_clutter():
    rng = np.random.default_rng(0)
    image, truth = draw_ellipse_markers(rng)
    found = detect_disks(image)
    error, _ = match(found.xy, truth)
    # noise 3 grey levels against a contrast of ~215 over >= 20 edge pixels: the centroid's
    # standard error is a few hundredths of a pixel
    assert np.all(error < 0.15)
    assert np.median(error) < 0.04


def test_clutter_without_a_white_surround_is_rejected():
    rng = np.random.default_rng(1)
    image = background((640, 480), rng, level=130.0)
    draw_clutter(image, rng, 80)  # dark blobs (grey 30) on a textured grey, lines, specks
    marker = ellipse_polygon((320.0, 240.0), (6.0, 5.0), 0.3)
    fill_polygon(image, marker * 2.4 - np.array([320.0, 240.0]) * 1.4, 235.0)
    fill_polygon(image, marker, 20.0)
    found = detect_disks(finish(image, rng), DetectOptions(min_contrast=170))
    assert len(found) == 1 and np.linalg.norm(found.xy[0] - [320.0, 240.0]) < 0.15


def test_detections_follow_blur_and_noise_bounds():
    rng = np.random.default_rng(2)
    image, truth = draw_ellipse_markers(rng, n=20, radius=(4.0, 10.0), clutter=0, blur=2.0, noise=6.0)
    # the background's texture holds faint wide blobs of 50-70 grey levels of contrast, which
    # the default least contrast (40, for worn markers in haze) lets through to the tracker's
    # model gates; above them, nothing but the markers
    found = detect_disks(image, DetectOptions(min_contrast=80))
    error, false = match(found.xy, truth)
    assert false == 0
    assert np.all(error < 0.3) and np.median(error) < 0.1
    # blur 2 px lowers the small disks' contrast and widens their moments ellipse
    assert np.all(found.fill > 0.7) and np.all(found.contrast > 80)


def test_refine_converges_from_a_few_pixels_off():
    rng = np.random.default_rng(3)
    image, truth = draw_ellipse_markers(rng, n=10, radius=(6.0, 10.0), clutter=0)
    start = truth + rng.uniform(-3, 3, truth.shape)
    found, spread = refine(image, start, np.full(len(truth), 8.0), iterations=6)
    assert np.max(np.linalg.norm(found.xy - truth, axis=1)) < 0.15
    assert np.all(spread < 0.2)


def _fit_conic(points: np.ndarray):
    """Least-squares ellipse (centre, axes, angle) through boundary points (K, 2)."""
    x, y = points[:, 0], points[:, 1]
    design = np.c_[x * x, x * y, y * y, x, y, np.ones_like(x)]
    a, b, c, d, e, f = np.linalg.svd(design)[2][-1]
    quad = np.array([[a, b / 2], [b / 2, c]])
    centre = np.linalg.solve(2 * quad, [-d, -e])
    scale = centre @ quad @ centre - f
    evals, evecs = np.linalg.eigh(quad / scale)
    axes = 1 / np.sqrt(evals)  # ascending eigenvalues: the major axis first
    return centre, axes, np.arctan2(evecs[1, 0], evecs[0, 0])


def _tilted_disk():
    camera = look_at_camera("near", (640, 480), 400.0, [0.0, -0.7, 0.0], [0.0, 0.0, 0.0])
    centre = np.array([0.2, 0.0, 0.08])
    normal = np.array([np.sin(np.radians(45)), -np.cos(np.radians(45)), 0.0])
    return camera, centre, normal, 0.05


def test_perspective_centre_from_the_disk_plane_is_exact():
    camera, centre, normal, radius = _tilted_disk()
    e1, e2 = disk_frame(camera, centre, normal, radius)
    t = np.linspace(0, 2 * np.pi, 50, endpoint=False)
    outline = camera.project(centre + radius * (np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2))
    ellipse_centre, axes, angle = _fit_conic(outline)
    truth = camera.project(centre)
    assert np.linalg.norm(ellipse_centre - truth) > 0.3  # the bias being corrected
    normal_cam = camera.cam_from_world.rotation @ normal
    fixed = disk_centre_from_ellipse(ellipse_centre, axes, angle, normal_cam, camera.matrix)
    assert np.linalg.norm(fixed[0] - truth) < 1e-6


def test_perspective_correction_of_a_drawn_disk():
    camera, centre, normal, radius = _tilted_disk()
    rng = np.random.default_rng(4)
    image = background(camera.size, rng)
    truth = draw_markers(image, camera, centre[None], normal[None], radius)[0]
    found = detect_disks(finish(image, rng, blur=0.7, noise=2.0), DetectOptions(block=151, max_radius=60))
    found = found.select(np.argsort(-found.score)[:1])  # the marker, not a dark patch of the backdrop
    before = np.linalg.norm(found.xy[0] - truth)
    normal_cam = camera.cam_from_world.rotation @ normal
    fixed = disk_centre_from_ellipse(found.xy, found.axes, found.angle, normal_cam, camera.matrix)[0]
    assert before > 0.3
    assert np.linalg.norm(fixed - truth) < 0.15


def test_tags_identify_themselves_with_exact_centres():
    dictionary = tag_dictionary("DICT_4X4_50")
    side = 120
    tags = [(7, (80.0, 90.0)), (23, (330.0, 200.0))]
    image = np.full((360, 480), 255, np.uint8)
    truth = {}
    for tag_id, (x, y) in tags:
        tile = cv2.aruco.generateImageMarker(dictionary, tag_id, side)
        square = np.array([[0, 0], [side, 0], [side, side], [0, side]], np.float32) - 0.5
        target = np.array([[x, y], [x + 100, y + 15], [x + 95, y + 110], [x - 8, y + 90]], np.float32)
        homography = cv2.getPerspectiveTransform(square, target)
        warped = cv2.warpPerspective(tile, homography, (480, 360), flags=cv2.INTER_AREA, borderValue=255)
        mask = cv2.warpPerspective(np.full_like(tile, 255), homography, (480, 360)) > 0
        image[mask] = warped[mask]
        centre = cv2.perspectiveTransform(np.array([[[side / 2 - 0.5, side / 2 - 0.5]]], np.float32), homography)
        truth[tag_id] = centre[0, 0]
    found = detect_tags(image, "DICT_4X4_50")
    assert sorted(found.ids.tolist()) == [7, 23]
    for tag_id, xy in zip(found.ids, found.xy):
        assert np.linalg.norm(xy - truth[tag_id]) < 0.5


def test_guards():
    with pytest.raises(ValueError, match="odd"):
        DetectOptions(block=4)
    with pytest.raises(ValueError, match="min_radius"):
        DetectOptions(min_radius=5, max_radius=4)
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        Detections(np.zeros((3, 2)), np.zeros((2, 2)), *(np.zeros(3) for _ in range(4)))
    with pytest.raises(ValueError, match="unknown tag dictionary"):
        tag_dictionary("DICT_NOPE")
    with pytest.raises(ValueError, match="expected an image"):
        as_gray(np.zeros((2, 3, 4, 5)))


def test_empty_image_has_no_detections():
    assert len(detect_disks(np.full((100, 120), 200, np.uint8))) == 0
    assert len(detect_tags(np.full((100, 120), 200, np.uint8)).ids) == 0
