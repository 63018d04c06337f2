"""The camera calibration TOML format (DESIGN.md), readable by aniposelib and Pose2Sim.

One table per camera, keyed ``cam_00``, ``cam_01``, … so that a reader that sorts the keys
(aniposelib does) keeps the file's order; the first camera is the reference clock. Each has
`name`, `size`, `matrix`, `distortions`, `rotation` (Rodrigues, world -> camera),
`translation` (world -> camera, m), and optional extra keys (`time_offset` s, `fps`, the
paper's parameters, standard deviations, per-camera `joints`). Everything else lives
under ``[metadata]``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mocap.core.calibration import Calibration, finite_number
from mocap.core.camera import Camera
from mocap.core.geometry import Rigid, matrix_to_rotvec, rotvec_to_matrix
from mocap.errors import InputError
from mocap.io import toml_writer
from mocap.io.atomic import write_text
from mocap.io.text import read_toml

_CAMERA_KEYS = {"name", "size", "matrix", "distortions", "rotation", "translation"}


def load_calibration(path: str | Path) -> Calibration:
    path = Path(path)
    data = read_toml(path, "check the calibration path")
    cameras, extras = [], []
    for key, table in data.items():
        if key == "metadata":
            continue
        if not isinstance(table, dict):
            raise InputError(f"{key!r} is not a camera table", path=path)
        camera, extra = _camera_from_table(table, path, f"[{key}]")
        cameras.append(camera)
        extras.append(extra)
    if not cameras:
        raise InputError("no camera tables; is this a calibration file?", path=path)
    names = [c.name for c in cameras]
    if len(set(names)) != len(names):
        raise InputError(f"camera names repeat: {names}", path=path)
    metadata = data.get("metadata", {})
    if not isinstance(metadata, dict):
        raise InputError("[metadata] must be a table", path=path)
    if "joints" in metadata and not isinstance(metadata["joints"], dict):
        raise InputError("[metadata.joints] must be a table of joint values by name", path=path)
    return Calibration(tuple(cameras), tuple(extras), metadata)


def _camera_from_table(table: dict, path, where) -> tuple[Camera, dict]:
    missing = sorted(_CAMERA_KEYS - set(table))
    if missing:
        raise InputError(f"missing {', '.join(missing)}", path=path, where=where)
    if not isinstance(table["name"], str) or not table["name"].strip():
        raise InputError("'name' must be a non-empty string", path=path, where=where)

    def array(key, shape):
        return numbers(table[key], shape, path, where, key)

    size = array("size", (2,))
    if np.any(size != np.round(size)) or np.any(size < 1) or np.any(size > MAX_IMAGE_SIDE):
        raise InputError(f"'size' must be two whole numbers of pixels [width, height] from 1 to "
                         f"{MAX_IMAGE_SIDE}, got {table['size']!r}", path=path, where=where)
    matrix = array("matrix", (3, 3))
    check_matrix(matrix, path, where)
    distortions = _distortions(table["distortions"], path, where)
    rotation = array("rotation", (3,))
    if np.linalg.norm(rotation) > MAX_ROTATION_RAD:
        raise InputError(f"'rotation' {table['rotation']!r} turns by more than {MAX_ROTATION_RAD:g} rad (a Rodrigues "
                         "vector's length is its angle): give it in radians",
                         path=path, where=where)
    translation = array("translation", (3,))
    if np.linalg.norm(translation) > MAX_DISTANCE_M:
        raise InputError(f"'translation' {table['translation']!r} puts the world's origin "
                         f"beyond {MAX_DISTANCE_M:g} m of the camera: give it in metres", path=path, where=where)
    extra = {k: v for k, v in table.items() if k not in _CAMERA_KEYS}
    _check_extras(extra, path, where)
    camera = Camera(
        table["name"],
        (int(size[0]), int(size[1])),
        matrix,
        distortions,
        Rigid(rotvec_to_matrix(rotation), translation),
    )
    return camera, extra


MAX_IMAGE_SIDE = 65536  # pixels
MAX_ROTATION_RAD = 100.0  # a Rodrigues vector's length is its angle: 2 pi (or a few turns) at most, not 1e300
MAX_DISTANCE_M = 1e6  # the world's origin (on the machine) within 1000 km of a camera
MAX_TIME_OFFSET_S = 86400.0  # cameras started within a day of each other
MAX_FPS = 10000.0
_OPENCV_DISTORTION_COUNTS = (0, 4, 5, 8, 12, 14)  # what OpenCV's distortion models take


def numbers(value, shape, path, where, key) -> np.ndarray:
    """`value` as finite floats of `shape`; a string, a boolean or a wrong shape is an InputError."""
    flat = value
    try:
        array = np.asarray(value, dtype=object)
        flat = array.reshape(-1).tolist()
    except ValueError:  # ragged lists
        array = None
    if (array is None or array.shape != shape
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in flat)):
        raise InputError(f"{key!r} must be {_what(shape)}, got {value!r}", path=path, where=where)
    out = np.asarray(flat, dtype=float).reshape(shape)
    if not np.all(np.isfinite(out)):
        raise InputError(f"{key!r} must be {_what(shape)}, got {value!r}", path=path, where=where)
    return out


def _what(shape) -> str:
    return "a finite number" if shape == () else f"finite numbers of shape {shape}"


def check_matrix(matrix: np.ndarray, path, where) -> None:
    """A camera matrix K: [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with positive focal lengths."""
    if not np.array_equal(matrix[2], [0.0, 0.0, 1.0]) or matrix[1, 0] != 0.0:
        raise InputError(
            f"'matrix' must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (OpenCV's K), got last rows "
            f"{matrix[1:].tolist()}", path=path, where=where)
    if not (matrix[0, 0] > 0 and matrix[1, 1] > 0):
        raise InputError(
            f"'matrix' focal lengths fx = {matrix[0, 0]:g}, fy = {matrix[1, 1]:g} must be positive "
            "pixels (a mirrored camera is not a camera matrix)", path=path, where=where)


def _distortions(value, path, where) -> np.ndarray:
    if not isinstance(value, list):
        raise InputError(f"'distortions' must be a list of numbers, got {value!r}", path=path, where=where)
    coefficients = numbers(value, (len(value),), path, where, "distortions")
    if len(coefficients) not in _OPENCV_DISTORTION_COUNTS:
        raise InputError(
            f"'distortions' has {len(coefficients)} coefficients; OpenCV takes 0, 4, 5, 8, 12 or 14 "
            "(k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, tx, ty]]]])", path=path, where=where)
    if np.any(coefficients[5:] != 0):
        raise InputError(
            "'distortions' beyond k1, k2, p1, p2, k3 (rational, thin-prism, tilt) are not supported: "
            "recalibrate with the 5-coefficient model", path=path, where=where)
    return coefficients[:5]


def _check_extras(extra: dict, path, where) -> None:
    if "fps" in extra:
        fps = extra["fps"]
        if not finite_number(fps) or not 0 < fps <= MAX_FPS:
            raise InputError(f"'fps' must be a positive number of frames per second (at most "
                             f"{MAX_FPS:g}), got {fps!r}", path=path, where=where)
    if "time_offset" in extra:
        offset = extra["time_offset"]
        if not finite_number(offset) or not abs(offset) <= MAX_TIME_OFFSET_S:
            raise InputError(f"'time_offset' must be a number of seconds within ±{MAX_TIME_OFFSET_S:g}, "
                             f"got {offset!r}", path=path, where=where)
    if "joints" in extra and not isinstance(extra["joints"], dict):
        raise InputError("'joints' must be a table of joint values by name", path=path, where=where)


def calibration_to_dict(calibration: Calibration) -> dict:
    width = max(2, len(str(len(calibration.cameras) - 1)))
    data = {}
    for k, (camera, extra) in enumerate(zip(calibration.cameras, calibration.extras)):
        table = {
            "name": camera.name,
            "size": [int(camera.size[0]), int(camera.size[1])],
            "matrix": camera.matrix.tolist(),
            "distortions": camera.distortion.tolist(),
            "rotation": matrix_to_rotvec(camera.cam_from_world.rotation).tolist(),
            "translation": camera.cam_from_world.translation.tolist(),
        }
        table.update(_plain(extra))
        data[f"cam_{k:0{width}d}"] = table
    if calibration.metadata:
        data["metadata"] = _plain(calibration.metadata)
    return data


def save_calibration(calibration: Calibration, path: str | Path) -> None:
    write_text(path, toml_writer.dumps(calibration_to_dict(calibration)))


def _plain(value):
    """numpy values -> TOML-writable Python values (None dropped)."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items() if v is not None}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_plain(v) for v in np.asarray(value).tolist()] if isinstance(value, np.ndarray) else [
            _plain(v) for v in value
        ]
    if isinstance(value, np.generic):
        return value.item()
    return value
