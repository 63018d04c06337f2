"""A session as a structure-from-motion reconstruction: one image per camera and frame, the
triangulated markers as 3-D points, each with its 2-D track (the cameras that saw it).

The 2-D observations are the tracks on the reference camera's clock (the same resampled
pixels that triangulation used), so image ``cam2/000120`` holds camera cam2's marker
pixels at reference frame 120. Shapes: C cameras, F frames, M markers, I = C·F images,
N points, E observations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mocap.core.points import Points
from mocap.errors import InputError


@dataclass(frozen=True)
class Reconstruction:
    """image_names (I,), image_cameras (I,) camera index, image_frames (I,) reference frame,
    keypoints: I arrays (K_i, 2) OpenCV px, keypoint_markers: I arrays (K_i,) marker index,
    points (N, 3) m, point_markers (N,), point_frames (N,), tracks (E, 3) rows of
    (point, image, keypoint) indices."""

    image_names: tuple[str, ...]
    image_cameras: np.ndarray
    image_frames: np.ndarray
    keypoints: tuple[np.ndarray, ...]
    keypoint_markers: tuple[np.ndarray, ...]
    points: np.ndarray
    point_markers: np.ndarray
    point_frames: np.ndarray
    tracks: np.ndarray

    def __post_init__(self) -> None:
        n_images, n_points = len(self.image_names), len(self.points)
        if not (len(self.image_cameras) == len(self.image_frames) == len(self.keypoints) == n_images):
            raise ValueError("Reconstruction needs one camera, frame and keypoint array per image")
        if np.shape(self.points) != (n_points, 3) or np.shape(self.tracks)[1:] != (3,):
            raise ValueError("Reconstruction needs points (N, 3) and tracks (E, 3)")


def reconstruction(
    camera_names: tuple[str, ...],
    marker_names: tuple[str, ...],
    frames: np.ndarray,
    pixels: np.ndarray,
    points: Points,
) -> Reconstruction:
    """The reconstruction of the triangulated `points` from the resampled tracks.

    camera_names (C,), marker_names (M,), frames (F,) the reference frames of `pixels`
    (C, F, M, 2) (NaN: not seen); every point's frame must be among `frames`.
    """
    n_cameras = len(camera_names)
    marker_index = {name: k for k, name in enumerate(marker_names)}
    unknown = sorted({m for m in points.marker if m not in marker_index})
    if unknown:
        raise InputError(f"points name marker(s) {unknown[:5]} that the tracks lack; triangulate again")
    position = np.searchsorted(frames, points.frame)
    if np.any(position >= len(frames)) or np.any(frames[np.minimum(position, len(frames) - 1)] != points.frame):
        raise InputError("points lie at frames the tracks do not cover; triangulate again from these tracks")
    point_markers = np.array([marker_index[m] for m in points.marker], dtype=int)

    export_frames, point_frame_index = np.unique(points.frame, return_inverse=True)
    on_frames = pixels[:, np.searchsorted(frames, export_frames)]  # (C, F', M, 2)
    seen = np.isfinite(on_frames).all(axis=-1)  # (C, F', M)
    keypoint_index = np.cumsum(seen, axis=-1) - 1  # (C, F', M): index of the marker among the image's keypoints

    # images in order camera-major: image i = c * F' + f
    n_frames = len(export_frames)
    image_cameras = np.repeat(np.arange(n_cameras), n_frames)
    image_frames = np.tile(export_frames, n_cameras)
    names = tuple(f"{camera_names[c]}/{f:06d}" for c, f in zip(image_cameras, image_frames))
    keypoints, keypoint_markers = [], []
    for c, f in zip(image_cameras, np.tile(np.arange(n_frames), n_cameras)):
        markers = np.flatnonzero(seen[c, f])
        keypoints.append(on_frames[c, f, markers])
        keypoint_markers.append(markers)

    observed = seen[:, point_frame_index, point_markers]  # (C, N)
    camera, point = np.nonzero(observed)
    image = camera * n_frames + point_frame_index[point]
    keypoint = keypoint_index[camera, point_frame_index[point], point_markers[point]]
    return Reconstruction(
        names, image_cameras, image_frames, tuple(keypoints), tuple(keypoint_markers),
        np.asarray(points.xyz, dtype=float), point_markers, np.asarray(points.frame), np.c_[point, image, keypoint],
    )
