"""The live poses file: one row per reference frame, written as it comes.

Columns: ``frame,time,latency_ms,cameras`` (the cameras whose pixels the row used,
``;``-separated), then the motion CSV's (mocap.io.motion_csv): the joints (degrees or
metres), ``<point>_x/_y/_z`` (m), ``bucket_angle_deg``, ``<joint>_sd``, ``<point>_sd``,
``bucket_angle_sd_deg``, and ``rms_px``, ``observations`` (2-D observations fitted) and
``filled`` (1 where the smoother predicted the frame without a fit of its own); with
``--base-motion`` the base's pose as in the motion CSV (``base_x`` ..., without SDs). A CSV is
appended and flushed row by row (a reader may follow it); a ``.parquet`` path is written
whole, atomically, when the run ends.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from mocap.core.machine import REVOLUTE, Machine
from mocap.io import columnar
from mocap.io.motion_csv import base_columns
from mocap.io.text import is_parquet
from mocap.live.pose import Pose


def header(machine: Machine, base_motion: bool = False) -> list[str]:
    names = ["frame", "time", "latency_ms", "cameras", *machine.joint_names]
    names += [f"{p}_{a}" for p in machine.point_names for a in "xyz"]
    names += ["bucket_angle_deg", *(f"{j}_sd" for j in machine.joint_names), *(f"{p}_sd" for p in machine.point_names)]
    names += ["bucket_angle_sd_deg", "rms_px", "observations", "filled"]
    if base_motion:
        names += list(base_columns(np.eye(4)[None]))
    return names


def row(machine: Machine, frame: int, time: float, latency_ms: float, cameras: list[str], pose: Pose,
        rms_px: float, observations: int) -> dict:
    """A row's values by column (`header`), in file units; NaN where unknown."""
    scale = np.array([np.degrees(1.0) if j.type == REVOLUTE else 1.0 for j in machine.joints])
    values = {"frame": int(frame), "time": float(time), "latency_ms": float(latency_ms), "cameras": ";".join(cameras)}
    values.update(zip(machine.joint_names, (pose.joints * scale).tolist()))
    for k, name in enumerate(machine.point_names):
        values.update(zip((f"{name}_x", f"{name}_y", f"{name}_z"), pose.points[k].tolist()))
    values["bucket_angle_deg"] = math.degrees(pose.bucket_angle)
    values.update(zip((f"{j}_sd" for j in machine.joint_names), (pose.joints_sd * scale).tolist()))
    values.update(zip((f"{p}_sd" for p in machine.point_names), pose.points_sd.tolist()))
    values["bucket_angle_sd_deg"] = math.degrees(pose.bucket_angle_sd)
    values.update(rms_px=float(rms_px), observations=int(observations), filled=int(pose.filled))
    values.update(pose.base)
    return values


class PoseWriter:
    """Rows to `path`: a CSV line each, flushed; for Parquet kept and written by `close`."""

    def __init__(self, machine: Machine, path: str | Path, base_motion: bool = False):
        self.path, self.columns = Path(path), header(machine, base_motion)
        self.parquet = is_parquet(path)
        self.rows: list[dict] = []
        self.file = None
        if not self.parquet:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.file = open(self.path, "w", encoding="utf-8", newline="")
            self.file.write(",".join(self.columns) + "\n")
            self.file.flush()

    def write(self, values: dict) -> None:
        if self.parquet:
            self.rows.append(values)
            return
        self.file.write(",".join(_text(values[c]) for c in self.columns) + "\n")
        self.file.flush()

    def close(self) -> None:
        if self.file is not None:
            self.file.close()
            self.file = None
        elif self.parquet:
            columns = {c: np.array([r[c] for r in self.rows], dtype=object if c == "cameras" else float)
                       for c in self.columns}
            columns["frame"] = columns["frame"].astype(np.int64)
            columnar.write_parquet(columns, self.path)


def _text(value) -> str:
    if isinstance(value, str):
        return value
    if isinstance(value, int):
        return str(value)
    return "" if not math.isfinite(value) else f"{value:.6f}".rstrip("0").rstrip(".")
