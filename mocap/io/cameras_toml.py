"""The camera calibration TOML format (DESIGN.md), readable by aniposelib and Pose2Sim.

One table per camera, keyed ``cam_00``, ``cam_01``, … so that a reader that sorts the keys
(aniposelib does) keeps the file's order; the first camera is the reference clock. Each has
`name`, `size`, `matrix`, `distortions`, `rotation` (Rodrigues, world -> camera),
`translation` (world -> camera, m), and optional extra keys (`time_offset` s, `fps`, the
paper's parameters, standard deviations, per-camera `joints`). Everything else lives
under ``[metadata]``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from mocap.camera import Camera
from mocap.errors import InputError
from mocap.geometry import Rigid, matrix_to_rotvec, rotvec_to_matrix
from mocap.io import toml_writer
from mocap.io.atomic import write_text
from mocap.io.text import read_toml
from mocap.machine import REVOLUTE, Machine

_CAMERA_KEYS = {"name", "size", "matrix", "distortions", "rotation", "translation"}


@dataclass(frozen=True)
class Calibration:
    """Cameras in file order, their extra keys and the file's metadata.

    `extras[k]` holds camera k's extra keys as written (file units: degrees, metres);
    `metadata` the ``[metadata]`` table (joints in degrees / metres by joint name).
    """

    cameras: tuple[Camera, ...]
    extras: tuple[dict, ...] = ()
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        extras = tuple(self.extras) or tuple({} for _ in self.cameras)
        if len(extras) != len(self.cameras):
            raise ValueError("one extras table per camera")
        object.__setattr__(self, "cameras", tuple(self.cameras))
        object.__setattr__(self, "extras", extras)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(camera.name for camera in self.cameras)

    @property
    def time_offsets(self) -> np.ndarray:
        """(C,) seconds: camera k's frame f shows time f / fps_k + offset_k."""
        return np.array([float(e.get("time_offset", 0.0)) for e in self.extras])

    def fps(self, default: float = 30.0) -> np.ndarray:
        return np.array([float(e.get("fps", default)) for e in self.extras])

    def camera(self, name: str) -> Camera:
        for camera in self.cameras:
            if camera.name == name:
                return camera
        raise KeyError(name)

    def with_extras(self, index: int, **values) -> Calibration:
        extras = list(self.extras)
        extras[index] = {**extras[index], **values}
        return replace(self, extras=tuple(extras))

    def joints(self, machine: Machine, camera: int | None = None) -> np.ndarray | None:
        """Joint values (J,) in rad / m at the calibration frame, from the metadata (or, with
        `camera`, from that camera's own table when calibrated per camera); None if absent."""
        table = self.metadata.get("joints")
        if camera is not None and "joints" in self.extras[camera]:
            table = self.extras[camera]["joints"]
        if table is None:
            return None
        return joints_from_table(table, machine)


def joints_to_table(values: np.ndarray, machine: Machine) -> dict[str, float]:
    """Joint values (J,) rad / m -> {name: degrees or metres}."""
    return {
        joint.name: float(np.degrees(v) if joint.type == REVOLUTE else v)
        for joint, v in zip(machine.joints, values)
    }


def joints_from_table(table: dict, machine: Machine) -> np.ndarray:
    missing = [name for name in machine.joint_names if name not in table]
    if missing:
        raise InputError(f"joints table lacks {', '.join(missing)}")
    return np.array(
        [
            np.radians(table[j.name]) if j.type == REVOLUTE else float(table[j.name])
            for j in machine.joints
        ]
    )


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
    return Calibration(tuple(cameras), tuple(extras), metadata)


def _camera_from_table(table: dict, path, where) -> tuple[Camera, dict]:
    missing = sorted(_CAMERA_KEYS - set(table))
    if missing:
        raise InputError(f"missing {', '.join(missing)}", path=path, where=where)

    def array(key, shape):
        try:
            value = np.asarray(table[key], dtype=float)
        except (TypeError, ValueError):
            raise InputError(f"{key!r} must be numbers", path=path, where=where) from None
        if value.shape != shape or not np.all(np.isfinite(value)):
            raise InputError(
                f"{key!r} must be finite numbers of shape {shape}, got {value.shape}",
                path=path,
                where=where,
            )
        return value

    size = array("size", (2,))
    matrix = array("matrix", (3, 3))
    distortions = np.asarray(table["distortions"], dtype=float).reshape(-1)
    if distortions.size > 5:
        raise InputError("'distortions' has more than 5 coefficients", path=path, where=where)
    rotation = array("rotation", (3,))
    translation = array("translation", (3,))
    if not isinstance(table["name"], str):
        raise InputError("'name' must be a string", path=path, where=where)
    camera = Camera(
        table["name"],
        (int(size[0]), int(size[1])),
        matrix,
        distortions,
        Rigid(rotvec_to_matrix(rotation), translation),
    )
    extra = {k: v for k, v in table.items() if k not in _CAMERA_KEYS}
    return camera, extra


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
