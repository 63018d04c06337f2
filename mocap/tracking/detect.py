"""Marker detection in grey images: painted disks (a black disk on a white square) and
ArUco / AprilTag markers.

Disks are found in two steps. Candidates are the connected dark regions of an adaptive
threshold (darker than their neighbourhood's mean), kept when their area and shape are in
range, each with the ellipse of its region's moments. Each candidate is then refined on
its own window (compiled: `mocap.tracking.disk_kernel`): the centre is the centroid of the
darkness ``w = clip((white - I) / (white - black), 0, 1)`` inside an elliptical window a
little larger than the disk, "white" being the bright end (85th percentile) of an
elliptical ring around it on the white square and "black" the mean of the disk's
middle; the ellipse (semi-axes, angle) comes from the weighted second moments (a uniform
ellipse of semi-axes a, b has moments a²/4, b²/4), and window and ring follow it. Under
motion blur the darkness centroid is the disk's mean place over the exposure. The tests:
contrast, a filled ellipse (dark area / ellipse area), a white ring that nothing darker
cuts (a partly covered marker is refused) and that is one white (a disk painted without a
square at the edge of a link's face, half its ring on the sky, would lean), size and
elongation in range.

A disk's projected centre is not the centre of its image ellipse under perspective; where
the disk's plane is known, `disk_centre_from_ellipse` gives the exact image of the centre
(the pole of the plane's vanishing line with respect to the ellipse).

Pixels are in the OpenCV convention (centre of the top-left pixel at 0, 0). Shapes: N
detections.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import lru_cache

import cv2
import numpy as np

from mocap.core.tags import tag_dictionary
from mocap.tracking.disk_kernel import refine_disks, refine_disks_converged


FULL_FRAME_BLOCKS = (9, 15, 25)  # px, the smaller adaptive-threshold neighbourhoods of a full-frame search


@dataclass(frozen=True)
class DetectOptions:
    """Disk detection settings (pixels, grey levels 0-255)."""

    min_radius: float = 1.5
    max_radius: float = 40.0
    min_contrast: float = 40.0
    block: int = 51  # adaptive threshold neighbourhood, odd, larger than a marker's square
    threshold_offset: float = 15.0  # grey levels below the neighbourhood mean
    min_fill: float = 0.6  # dark area / ellipse area (blur lowers it for small disks)
    max_fill: float = 1.25
    max_ring_spread: float = 0.9  # (ring white - its 15th percentile) / contrast
    max_elongation: float = 6.0  # major / minor semi-axis

    def __post_init__(self) -> None:
        if self.block < 3 or self.block % 2 == 0:
            raise ValueError(f"DetectOptions.block must be odd and >= 3, got {self.block}")
        if not 0 < self.min_radius < self.max_radius:
            raise ValueError("DetectOptions needs 0 < min_radius < max_radius")


@dataclass(frozen=True)
class Detections:
    """N disk detections: `xy` (N, 2) sub-pixel centres, `axes` (N, 2) semi-axes a >= b px,
    `angle` (N,) rad of the major axis from +x towards +y, `contrast` (N,) grey levels,
    `fill` (N,), `score` (N,) in [0, 1]."""

    xy: np.ndarray
    axes: np.ndarray
    angle: np.ndarray
    contrast: np.ndarray
    fill: np.ndarray
    score: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.xy)
        if np.shape(self.xy) != (n, 2) or np.shape(self.axes) != (n, 2):
            raise ValueError(f"Detections: xy and axes must be (N, 2), got {np.shape(self.xy)}, {np.shape(self.axes)}")
        for name in ("angle", "contrast", "fill", "score"):
            if np.shape(getattr(self, name)) != (n,):
                raise ValueError(f"Detections.{name} must be ({n},), got {np.shape(getattr(self, name))}")

    def __len__(self) -> int:
        return len(self.xy)

    @property
    def radius(self) -> np.ndarray:
        """(N,) geometric mean of the semi-axes."""
        return np.sqrt(self.axes[:, 0] * self.axes[:, 1])

    @property
    def shape(self) -> np.ndarray:
        """(N, 2, 2) semi-axis matrices ``R diag(a², b²) R^T`` (``x^T S^-1 x = 1`` on the edge)."""
        c, s = np.cos(self.angle), np.sin(self.angle)
        rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
        return rot @ (self.axes[:, :, None] ** 2 * np.swapaxes(rot, -1, -2))

    def select(self, mask: np.ndarray) -> Detections:
        return Detections._trusted(self.xy[mask], self.axes[mask], self.angle[mask], self.contrast[mask],
                                   self.fill[mask], self.score[mask])

    @classmethod
    def _trusted(cls, xy, axes, angle, contrast, fill, score) -> Detections:
        """Detections from fields whose shapes agree by construction (a selection, a
        concatenation, the refinement's output): without `__post_init__`'s checks, which cost
        more than the selection itself in a frame's many small ones."""
        new = object.__new__(cls)
        new.__dict__.update(xy=xy, axes=axes, angle=angle, contrast=contrast, fill=fill, score=score)
        return new

    @classmethod
    def empty(cls) -> Detections:
        return cls(np.zeros((0, 2)), np.zeros((0, 2)), *(np.zeros(0) for _ in range(4)))


_FIELDS = ("xy", "axes", "angle", "contrast", "fill", "score")


def concatenate(parts: list[Detections]) -> Detections:
    if not parts:
        return Detections.empty()
    return Detections._trusted(*(np.concatenate([getattr(p, f) for p in parts]) for f in _FIELDS))


def as_gray(image: np.ndarray) -> np.ndarray:
    """A grey uint8 image (H, W) from grey or BGR input."""
    image = np.asarray(image)
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim != 2:
        raise ValueError(f"expected an image (H, W) or (H, W, 3), got shape {image.shape}")
    return image if image.dtype == np.uint8 else np.clip(image, 0, 255).astype(np.uint8)


def find_candidates(
    gray: np.ndarray, options: DetectOptions, origin: tuple[int, int] = (0, 0)
) -> tuple[np.ndarray, np.ndarray]:
    """Dark connected regions of an adaptive threshold: centroids (N, 2) in the coordinates
    of the full image (`origin` = the top-left pixel of `gray` in it) and their ellipses as
    semi-axis matrices (N, 2, 2) (``x^T S^-1 x = 1`` on the edge) from the regions' moments."""
    block = min(options.block, 2 * (min(gray.shape) // 2) - 1)
    if block < 3:
        return np.zeros((0, 2)), np.zeros((0, 2, 2))
    binary = cv2.adaptiveThreshold(
        gray, 255, cv2.ADAPTIVE_THRESH_MEAN_C, cv2.THRESH_BINARY_INV, block, options.threshold_offset
    )
    count, labels, stats, centroids = cv2.connectedComponentsWithStats(binary, connectivity=8)
    area = stats[1:, cv2.CC_STAT_AREA].astype(float)
    width = stats[1:, cv2.CC_STAT_WIDTH].astype(float)
    height = stats[1:, cv2.CC_STAT_HEIGHT].astype(float)
    radius = np.sqrt(area / np.pi)
    keep = (radius >= 0.8 * options.min_radius) & (radius <= options.max_radius)
    keep &= area >= 0.4 * width * height  # compact, not a line or a frame
    keep &= np.maximum(width, height) <= options.max_elongation * np.minimum(width, height) + 2
    if not keep.any():
        return np.zeros((0, 2)), np.zeros((0, 2, 2))
    # second moments of the kept regions, all at once
    index = np.zeros(count, dtype=int)
    index[1:][keep] = np.arange(1, keep.sum() + 1)
    flat = index[labels.ravel()]
    inside = flat > 0
    flat = flat[inside]
    ys, xs = np.divmod(np.nonzero(inside)[0], gray.shape[1])
    n = keep.sum() + 1
    mean = centroids[1:][keep]
    dx, dy = xs - mean[flat - 1, 0], ys - mean[flat - 1, 1]
    sums = [np.bincount(flat, weights=w, minlength=n)[1:] for w in (dx * dx, dx * dy, dy * dy)]
    moments = np.stack([np.stack([sums[0], sums[1]], -1), np.stack([sums[1], sums[2]], -1)], -2)
    shape = 4.0 * (moments / area[keep, None, None] + np.eye(2) / 12.0)
    return mean + np.asarray(origin, dtype=float), shape


def _starts(xy, shape) -> tuple[np.ndarray, np.ndarray]:
    """Starting centres (N, 2) and semi-axis matrices (N, 2, 2), contiguous, from centres
    and matrices or radii (N,)."""
    xy = np.ascontiguousarray(xy, dtype=float).reshape(-1, 2)
    shape = np.asarray(shape, dtype=float)
    if shape.ndim == 1:
        shape = shape[:, None, None] ** 2 * np.eye(2)
    return xy, np.ascontiguousarray(shape.reshape(len(xy), 2, 2))


def refine(gray: np.ndarray, xy: np.ndarray, shape: np.ndarray, iterations: int = 3) -> tuple[Detections, np.ndarray]:
    """Sub-pixel centres and ellipses of dark disks near `xy` (N, 2), of about `shape`:
    semi-axis matrices (N, 2, 2) or radii (N,).

    Each candidate is refined on its own window, which follows the ellipse as it moves and
    grows (to twice its starting size and 4 px). Returns the Detections without any test
    applied (see `accept`) and its surrounding ring (N, 2), relative to its contrast: how far
    the ring's 15th percentile falls short of its white (something darker cuts it), and how
    far its median does (the ring is not one white: half of it on something brighter, as a
    disk painted without a square at the edge of a link's face, whose centroid would lean).
    """
    xy, shape = _starts(xy, shape)
    if len(xy) == 0:
        return Detections.empty(), np.zeros((0, 2))
    major = np.sqrt(np.clip(np.linalg.eigvalsh(shape)[:, 1], 0.25, None))
    centre, axes, angle, contrast, fill, spread, uneven = refine_disks(
        np.ascontiguousarray(gray, dtype=np.uint8), np.ascontiguousarray(xy), shape, 2.0 * major + 4.0, iterations
    )
    return Detections._trusted(centre, axes, angle, contrast, fill, _score(contrast, fill, spread)), np.stack([spread, uneven], axis=-1)


def _score(contrast: np.ndarray, fill: np.ndarray, spread: np.ndarray) -> np.ndarray:
    """(N,) in [0, 1]: high for a dark, filled disk in a clean white ring."""
    return np.clip(contrast / 255.0, 0, 1) * np.exp(-2.0 * np.abs(1.0 - fill)) * np.exp(-2.0 * spread)


def accept(detections: Detections, ring: np.ndarray, options: DetectOptions) -> np.ndarray:
    """(N,) bool: the detections that pass the shape and contrast tests."""
    a, b = detections.axes[:, 0], detections.axes[:, 1]
    ok = detections.contrast >= options.min_contrast
    ok &= (detections.fill >= options.min_fill) & (detections.fill <= options.max_fill)
    ok &= ring[:, 0] <= options.max_ring_spread
    ok &= (np.sqrt(a * b) >= options.min_radius) & (a <= options.max_radius)
    ok &= a <= options.max_elongation * b
    return ok & np.isfinite(detections.xy).all(axis=1)


def detect_disks(
    image: np.ndarray, options: DetectOptions | None = None, roi: tuple[int, int, int, int] | None = None
) -> Detections:
    """Disk markers in an image, or in its region `roi` = (x0, y0, x1, y1) (end exclusive).

    Candidates come from adaptive thresholds of several neighbourhoods, from `options.block`
    down to 9 px (`FULL_FRAME_BLOCKS`): a small disk on a small square beside a dark link
    is darker than a small neighbourhood's mean but not than a large one's, and a disk on
    a link darker than the sky around it stands apart only in a small one. Returns the
    accepted Detections, duplicates (one disk found twice) merged.
    """
    options = options or DetectOptions()
    gray = as_gray(image)
    x0, y0, x1, y1 = roi if roi is not None else (0, 0, gray.shape[1], gray.shape[0])
    xys, shapes = [], []
    for block in sorted({b for b in FULL_FRAME_BLOCKS if b < options.block} | {options.block}):
        xy, shape = find_candidates(gray[y0:y1, x0:x1], replace(options, block=block), (x0, y0))
        xys.append(xy)
        shapes.append(shape)
    xy, shape = np.concatenate(xys), np.concatenate(shapes)
    _, first = np.unique(np.round(xy * 2), axis=0, return_index=True)  # the same region from two blocks
    return refine_and_accept(gray, xy[first], shape[first], options)


def refine_and_accept(gray: np.ndarray, xy: np.ndarray, shape: np.ndarray, options: DetectOptions) -> Detections:
    """`refine` then `accept`, duplicates merged (centres closer than half a radius). A
    candidate that moved more than a quarter of its radius from where it started (a far or
    ill-sized start) is refined once more from where it arrived, so that it converges."""
    return accepted(*refine_converged(gray, xy, shape), options)


def refine_converged(gray: np.ndarray, xy: np.ndarray, shape: np.ndarray) -> tuple[Detections, np.ndarray]:
    """`refine`, and a candidate that moved more than a quarter of its radius from where it
    started refined once more from where it arrived (`disk_kernel.refine_disks_converged`):
    the Detections (those that stayed first) and their rings, no test applied."""
    refined = refine_sourced(gray, xy, shape)
    return refined.detections, refined.ring


@dataclass(frozen=True)
class Refined:
    """`refine_converged`'s output with `source` (N,), the candidate each row came from: the
    rows of a subset of the candidates (`of`) are what refining that subset alone gives."""

    detections: Detections
    ring: np.ndarray
    source: np.ndarray

    def of(self, chosen: np.ndarray) -> tuple[Detections, np.ndarray]:
        """The Detections and rings of the candidates `chosen` (bool over the candidates)."""
        keep = np.asarray(chosen, dtype=bool)[self.source]
        return self.detections.select(keep), self.ring[keep]


def refine_sourced(gray: np.ndarray, xy: np.ndarray, shape: np.ndarray) -> Refined:
    """`refine_converged`, each row with the index of its candidate."""
    xy, shape = _starts(xy, shape)
    if len(xy) == 0:
        return Refined(Detections.empty(), np.zeros((0, 2)), np.zeros(0, dtype=int))
    centre, axes, angle, contrast, fill, spread, uneven, source = refine_disks_converged(
        np.ascontiguousarray(gray, dtype=np.uint8), xy, shape, 3)
    return Refined(Detections._trusted(centre, axes, angle, contrast, fill, _score(contrast, fill, spread)),
                   np.stack([spread, uneven], axis=-1), source)


def accepted(found: Detections, ring: np.ndarray, options: DetectOptions) -> Detections:
    """The refined detections that pass `accept`, duplicates merged (`unique`)."""
    return unique(found.select(accept(found, ring, options)))


def length(d: np.ndarray) -> np.ndarray:
    """(...) the Euclidean lengths of `d` (..., 2) along its last axis: `np.linalg.norm`'s sum,
    without its dispatch (a frame makes dozens of these small ones)."""
    return np.sqrt(np.add.reduce(d * d, axis=-1))


def unique(detections: Detections) -> Detections:
    """Drop detections within half a radius of a better-scored one."""
    if len(detections) < 2:
        return detections
    order = np.argsort(-detections.score)
    xy, radius = detections.xy[order], detections.radius[order]
    dist = length(xy[:, None] - xy[None])
    close = dist < 0.5 * np.minimum(radius[:, None], radius[None])
    keep = ~np.triu(close, 1).any(axis=0)
    return detections.select(order[keep])


# --- perspective: the image of a disk's centre -------------------------------------------


def ellipse_conic(centre: np.ndarray, axes: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Conic matrices (N, 3, 3) of ellipses (x^T C x = 0 in homogeneous pixels)."""
    centre = np.asarray(centre, dtype=float).reshape(-1, 2)
    axes = np.asarray(axes, dtype=float).reshape(-1, 2)
    angle = np.asarray(angle, dtype=float).reshape(-1)
    c, s = np.cos(angle), np.sin(angle)
    rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)  # columns: axes
    inv_shape = rot @ (np.eye(2)[None] / axes[:, None, :] ** 2) @ np.swapaxes(rot, -1, -2)
    conic = np.zeros((len(centre), 3, 3))
    conic[:, :2, :2] = inv_shape
    shift = -np.einsum("nij,nj->ni", inv_shape, centre)
    conic[:, :2, 2] = shift
    conic[:, 2, :2] = shift
    conic[:, 2, 2] = np.einsum("ni,nij,nj->n", centre, inv_shape, centre) - 1.0
    return conic


def disk_centre_from_ellipse(
    centre: np.ndarray, axes: np.ndarray, angle: np.ndarray, normal_cam: np.ndarray, matrix: np.ndarray
) -> np.ndarray:
    """The image (N, 2) of the centre of disks whose image ellipses are given and whose
    planes have normals `normal_cam` (N, 3) in the (undistorted) camera frame, K `matrix`.

    The plane's vanishing line in pixels is ``l = K^-T n``; the image of the circle's centre
    is its pole with respect to the image conic: ``x = C^-1 l``.
    """
    conic = ellipse_conic(centre, axes, angle)
    normal = np.asarray(normal_cam, dtype=float).reshape(-1, 3)
    line = normal @ np.linalg.inv(matrix)  # rows: (K^-T n)^T
    pole = np.linalg.solve(conic, line[..., None])[..., 0]
    return pole[:, :2] / pole[:, 2:]


# --- ArUco / AprilTag ---------------------------------------------------------------------


@dataclass(frozen=True)
class TagDetections:
    """N self-identifying tags: `ids` (N,) int, `corners` (N, 4, 2) px, `xy` (N, 2) centre
    (the intersection of the diagonals, exact under perspective)."""

    ids: np.ndarray
    corners: np.ndarray
    xy: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        corners = np.asarray(self.corners, dtype=float).reshape(-1, 4, 2)
        if len(self.ids) != len(corners):
            raise ValueError(f"TagDetections: {len(self.ids)} ids for {len(corners)} corner sets")
        object.__setattr__(self, "corners", corners)
        object.__setattr__(self, "ids", np.asarray(self.ids, dtype=int).reshape(-1))
        object.__setattr__(self, "xy", diagonal_intersection(corners))


def diagonal_intersection(corners: np.ndarray) -> np.ndarray:
    """(N, 4, 2) quadrilaterals in order -> (N, 2) intersections of their diagonals."""
    h = np.concatenate([corners, np.ones(corners.shape[:-1] + (1,))], axis=-1)
    d1 = np.cross(h[:, 0], h[:, 2])
    d2 = np.cross(h[:, 1], h[:, 3])
    x = np.cross(d1, d2)
    return x[:, :2] / x[:, 2:]


_TAG_PASSES = ((False, 1), (True, 1), (False, 2), (True, 2))  # (inverted, enlargement)


def detect_tags(image: np.ndarray, dictionary: str = "DICT_4X4_50") -> TagDetections:
    """ArUco / AprilTag markers, black on white or printed inverted (white on black): every
    pass of `TagFinder` on one image."""
    return TagFinder(dictionary)(image)


class TagFinder:
    """ArUco / AprilTag markers in the frames of one video, black on white or printed
    inverted (white on black), down to about 12 px across.

    The first pass is OpenCV's own `cv2.aruco.ArucoDetector` on the image with its default
    settings but for the corners, refined on the tag's outer contour
    (`CORNER_REFINE_CONTOUR`, OpenCV's most accurate method on small and slanted tags): a
    tag OpenCV finds is found, with OpenCV's corners. Up to three more passes find what it
    misses: on the image inverted (white-on-black prints; OpenCV's `detectInvertedMarker`
    loses some blurred ones) and on both enlarged twice (bicubic), where small tags, whose
    cells are 2-3 px, are found more often. A tag keeps the corners of the first pass that
    finds it. The first pass runs on every frame, the others on every `recheck`-th frame,
    and on the frames between only while they have found a tag the earlier passes missed
    within the last `recheck` frames (a video of large black-on-white tags costs one pass a
    frame). An id found twice in one pass names no tag and is dropped. The centre is the
    diagonals' crossing (`TagDetections.xy`).
    """

    def __init__(self, dictionary: str = "DICT_4X4_50", recheck: int = 30):
        self.detectors = {1: _tag_detector(dictionary, False), 2: _tag_detector(dictionary, True)}
        self.recheck = recheck
        self.frames = 0
        self.last_useful = {p: -recheck - 1 for p in _TAG_PASSES[1:]}

    def __call__(self, image: np.ndarray) -> TagDetections:
        gray = as_gray(image)
        everything = self.frames % self.recheck == 0 if self.recheck > 0 else True
        found = self._pass(gray, *_TAG_PASSES[0])
        for key in _TAG_PASSES[1:]:
            if not (everything or self.frames - self.last_useful[key] <= self.recheck):
                continue
            more = self._pass(gray, *key)
            if set(more) - set(found):
                self.last_useful[key] = self.frames
            found = more | found  # a tag keeps the earliest pass's corners
        self.frames += 1
        if not found:
            return TagDetections(np.zeros(0, dtype=int), np.zeros((0, 4, 2)))
        return TagDetections(np.array(list(found)), np.array(list(found.values())))

    def _pass(self, gray: np.ndarray, inverted: bool, scale: int) -> dict[int, np.ndarray]:
        picture = 255 - gray if inverted else gray
        if scale > 1:
            picture = cv2.resize(picture, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
        corners, ids, _ = self.detectors[scale].detectMarkers(picture)
        if ids is None or len(ids) == 0:
            return {}
        ids = ids.reshape(-1)
        corners = (np.concatenate(corners).reshape(-1, 4, 2) + 0.5) / scale - 0.5  # pixel centres at integers
        values, counts = np.unique(ids, return_counts=True)
        once = np.isin(ids, values[counts == 1])
        return dict(zip(ids[once].tolist(), corners[once]))


@lru_cache(maxsize=8)
def _tag_detector(dictionary: str, small: bool):
    """OpenCV's defaults, corners refined on the contour; `small`: tags down to 1 % of the
    image's larger side in perimeter (OpenCV's default: 3 %)."""
    parameters = cv2.aruco.DetectorParameters()
    parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_CONTOUR
    if small:
        parameters.minMarkerPerimeterRate = min(parameters.minMarkerPerimeterRate, 0.01)
    return cv2.aruco.ArucoDetector(tag_dictionary(dictionary), parameters)
