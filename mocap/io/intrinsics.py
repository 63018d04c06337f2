"""Known camera intrinsics from the files other tools write, by camera name.

- a calibration TOML: ours or anipose's (`mocap.io.cameras_toml`), every camera table;
- OpenCV YAML / XML (cv2.FileStorage), as OpenCV's calibration samples save it:
  `image_width`, `image_height`, `camera_matrix`, `distortion_coefficients`; the camera is
  named after the file (``cam1.yaml`` -> ``cam1``);
- COLMAP: a ``cameras.txt`` (cameras named by their id) or a model folder (cameras named by
  their images' folder, ``cam1/000001.png`` -> ``cam1``, else by id), through
  `mocap.io.colmap`, with COLMAP's pixel origin moved to OpenCV's (- 0.5 px).

All come back in OpenCV pixels (the centre of the top-left pixel at 0, 0) with the five
OpenCV coefficients k1, k2, p1, p2, k3.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from mocap.core.camera import Camera
from mocap.errors import InputError

_OPENCV_SUFFIXES = (".yaml", ".yml", ".xml")


@dataclass(frozen=True)
class Intrinsics:
    """size (width, height) px, matrix K (3, 3), distortion (5,) k1, k2, p1, p2, k3."""

    size: tuple[int, int]
    matrix: np.ndarray
    distortion: np.ndarray

    def __post_init__(self) -> None:
        matrix = np.asarray(self.matrix, dtype=float)
        distortion = np.asarray(self.distortion, dtype=float).reshape(-1)
        if matrix.shape != (3, 3):
            raise ValueError(f"Intrinsics.matrix must have shape (3, 3), got {matrix.shape}")
        if distortion.shape != (5,):
            raise ValueError(f"Intrinsics.distortion must have shape (5,), got {distortion.shape}")
        if len(self.size) != 2 or min(self.size) <= 0:
            raise ValueError(f"Intrinsics.size must be (width, height) > 0, got {self.size}")
        object.__setattr__(self, "size", (int(self.size[0]), int(self.size[1])))
        object.__setattr__(self, "matrix", matrix)
        object.__setattr__(self, "distortion", distortion)


def load_intrinsics(path: str | Path) -> dict[str, Intrinsics]:
    """Every camera's intrinsics in the file or COLMAP model folder `path`, by name."""
    path = Path(path)
    if path.is_dir():
        from mocap.io.colmap import read_model_cameras

        cameras = read_model_cameras(path)
        return {name: Intrinsics(c.size, c.matrix, c.distortion) for name, c in cameras.items()}
    if not path.exists():
        raise InputError("file not found; check the intrinsics path", path=path)
    suffix = path.suffix.lower()
    if suffix == ".toml":
        return _from_calibration(path)
    if suffix in _OPENCV_SUFFIXES:
        return {path.stem: _from_opencv(path)}
    if suffix == ".txt":
        from mocap.io.colmap import read_cameras_text

        return {str(c.camera_id): Intrinsics(c.size, c.matrix, c.distortion) for c in read_cameras_text(path)}
    raise InputError(
        "unknown intrinsics file: give a calibration .toml, an OpenCV .yaml/.yml/.xml, "
        "a COLMAP cameras.txt or a COLMAP model folder",
        path=path,
    )


def _from_calibration(path: Path) -> dict[str, Intrinsics]:
    from mocap.io.cameras_toml import load_calibration

    return {c.name: Intrinsics(c.size, c.matrix, c.distortion) for c in load_calibration(path).cameras}


def _from_opencv(path: Path) -> Intrinsics:
    import cv2

    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise InputError(f"not a readable OpenCV file ({exc.err})", path=path) from None
    try:
        if not storage.isOpened():
            raise InputError("not a readable OpenCV YAML/XML file", path=path)

        def node(key: str) -> np.ndarray | float:
            item = storage.getNode(key)
            if item.empty():
                raise InputError(
                    f"no {key!r}; expected image_width, image_height, camera_matrix and "
                    "distortion_coefficients (OpenCV's calibration sample layout)",
                    path=path,
                )
            return item.mat() if item.isMap() or item.isSeq() else item.real()

        width, height = node("image_width"), node("image_height")
        matrix, coefficients = node("camera_matrix"), node("distortion_coefficients")
    finally:
        storage.release()
    if not isinstance(matrix, np.ndarray) or matrix.shape != (3, 3):
        raise InputError("camera_matrix must be a 3x3 matrix", path=path)
    if not isinstance(coefficients, np.ndarray) or coefficients.size < 4:
        raise InputError("distortion_coefficients must be a matrix of 4, 5 or more numbers", path=path)
    coefficients = coefficients.reshape(-1).astype(float)
    if np.any(coefficients[5:] != 0):
        raise InputError(
            f"{coefficients.size} distortion coefficients with k4.. non-zero; only k1, k2, p1, p2, k3 are supported",
            path=path,
        )
    distortion = np.r_[coefficients[:5], np.zeros(5 - min(5, coefficients.size))]
    if not (np.all(np.isfinite(matrix)) and np.all(np.isfinite(distortion)) and width > 0 and height > 0):
        raise InputError("image size, camera_matrix and distortion_coefficients must be finite, size > 0", path=path)
    return Intrinsics((int(width), int(height)), matrix.astype(float), distortion)


def with_known_intrinsics(cameras: list[Camera], known: dict, path) -> list[Camera]:
    """The cameras with the intrinsics (matrix, distortion) that `known` names, which must
    match their image size."""
    out = []
    for camera in cameras:
        given = known.get(camera.name)
        if given is None:
            out.append(camera)
            continue
        if tuple(given.size) != tuple(camera.size):
            raise InputError(f"camera {camera.name}'s known intrinsics are for {given.size[0]}x{given.size[1]} images, "
                             f"the calibration's for {camera.size[0]}x{camera.size[1]}; give the intrinsics of "
                             "the same video size", path=path)
        out.append(replace(camera, matrix=given.matrix, distortion=given.distortion))
    if not any(c.name in known for c in cameras):
        raise InputError(f"the intrinsics file names camera(s) {sorted(known)[:5]}, none of the calibration's "
                         f"{[c.name for c in cameras]}; name them alike", path=path)
    return out
