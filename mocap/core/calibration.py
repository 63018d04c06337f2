"""A camera calibration: the cameras in order, their extra keys and the metadata (the joint
values at the calibration frame, by joint name in file units); the type the cameras TOML
reads and writes and the stages compute with."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from mocap.core.camera import Camera
from mocap.core.machine import REVOLUTE, Machine
from mocap.errors import InputError


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
    bad = [name for name in machine.joint_names if not finite_number(table[name])]
    if bad:
        raise InputError(f"joint value {bad[0]} = {table[bad[0]]!r} is not a finite number")
    return np.array(
        [
            np.radians(table[j.name]) if j.type == REVOLUTE else float(table[j.name])
            for j in machine.joints
        ]
    )


def finite_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and bool(np.isfinite(value))
