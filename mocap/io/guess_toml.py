"""The initial-guess TOML: a user's guess in the paper's parameters (optional).

    [cam1]                      # one table per camera, by name
    azimuth_deg = 190.0         # R = Rz(azimuth) Ry(elevation) Rx(tilt), PAPER.md
    elevation_deg = 8.0
    tilt_deg = 0.0
    position = [42.0, 6.0, 9.0] # camera position in the base frame, metres
    focal_px = 2400.0           # pseudo-focal length M = m f, pixels

    [joints]                    # optional, degrees / metres by joint name
    swing = 0.0
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mocap.core.calibration import joints_from_table
from mocap.core.camera import PaperCamera
from mocap.core.guess import Guess
from mocap.core.machine import Machine
from mocap.errors import InputError
from mocap.io.cameras_toml import numbers
from mocap.io.text import read_toml

_KEYS = {"azimuth_deg", "elevation_deg", "tilt_deg", "position", "focal_px"}


def load_guess(path: str | Path, machine: Machine) -> Guess:
    path = Path(path)
    data = read_toml(path, "check the --guess path")
    cameras = {}
    for name, table in data.items():
        if name == "joints":
            continue
        where = f"[{name}]"
        if not isinstance(table, dict):
            raise InputError("must be a table of the paper's camera parameters", path=path, where=where)
        if set(table) != _KEYS:
            missing, unknown = sorted(_KEYS - set(table)), sorted(set(table) - _KEYS)
            raise InputError(
                f"expected exactly {', '.join(sorted(_KEYS))}"
                + (f"; missing {', '.join(missing)}" if missing else "")
                + (f"; unknown {', '.join(unknown)}" if unknown else ""),
                path=path,
                where=where,
            )
        position = numbers(table["position"], (3,), path, where, "position")
        values = [float(numbers(table[k], (), path, where, k)) for k in ("azimuth_deg", "elevation_deg", "tilt_deg",
                                                                          "focal_px")]
        if not values[3] > 0:
            raise InputError("focal_px must be positive", path=path, where=where)
        az, el, tilt = np.radians(values[:3])
        cameras[name] = PaperCamera(az, el, tilt, position, values[3])
    joints = None
    if "joints" in data:
        try:
            joints = joints_from_table(data["joints"], machine)
        except InputError as exc:
            raise InputError(exc.detail, path=path, where="[joints]") from None
    return Guess(cameras, joints)
