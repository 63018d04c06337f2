"""The motion CSV: per-frame joint values, named points and bucket angle.

Columns: ``frame,time``, one column per joint (degrees for revolute, metres for
prismatic joints), ``<point>_x,<point>_y,<point>_z`` for every named point (metres, world
frame), ``bucket_angle_deg``; then, where computed, uncertainty columns (``<joint>_sd``,
``<point>_sd`` — the standard deviation of the 3-D position, metres, the root of the
covariance's trace — and ``bucket_angle_sd_deg``) and extra per-frame columns (e.g.
``filled`` for gap-filled frames, ``<point>_speed`` in m/s). A base that moves (bouncing,
walking) adds its pose ``world_from_base`` as ``base_x, base_y, base_z`` (m) and
``base_roll_deg, base_pitch_deg, base_yaw_deg`` with their SDs (`base_columns`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa

from mocap.core.geometry import matrix_to_rpy, rotvec_to_matrix, rpy_to_matrix
from mocap.core.machine import REVOLUTE, Machine
from mocap.core.motion import Motion
from mocap.errors import InputError
from mocap.io import columnar
from mocap.io.text import csv_rows, is_parquet, read_text


BASE_POSITION = ("base_x", "base_y", "base_z")  # m
BASE_ANGLES = ("base_roll_deg", "base_pitch_deg", "base_yaw_deg")  # R = Rz(yaw) Ry(pitch) Rx(roll)


def base_columns(world_from_base: np.ndarray, covariance: np.ndarray | None = None) -> dict:
    """Motion columns of base poses (F, 4, 4): ``base_x, base_y, base_z`` (m) and
    ``base_roll_deg, base_pitch_deg, base_yaw_deg`` (the model's rpy convention); with the
    covariance (F, 6, 6) of a left rotation increment (rad) and the translation (m), their
    SDs ``base_x_sd`` ... ``base_roll_sd_deg`` ... by first-order propagation."""
    rotation = world_from_base[:, :3, :3]
    rpy = matrix_to_rpy(rotation)
    out = {name: world_from_base[:, k, 3] for k, name in enumerate(BASE_POSITION)}
    out.update({name: np.degrees(rpy[:, k]) for k, name in enumerate(BASE_ANGLES)})
    if covariance is not None:
        step = 1e-6
        gradient = np.stack([  # (F, 3 rpy, 3 increment): d rpy / d w
            (matrix_to_rpy(rotvec_to_matrix(step * np.eye(3)[i]) @ rotation) - rpy) / step for i in range(3)
        ], axis=-1)
        gradient = (gradient + np.pi) % (2 * np.pi) - np.pi
        angle_cov = gradient @ covariance[:, :3, :3] @ np.swapaxes(gradient, 1, 2)
        for k, name in enumerate(BASE_POSITION):
            out[f"{name}_sd"] = np.sqrt(covariance[:, 3 + k, 3 + k])
        for k, name in enumerate(BASE_ANGLES):
            out[name.replace("_deg", "_sd_deg")] = np.degrees(np.sqrt(angle_cov[:, k, k]))
    return out


def world_from_base_of(extra: dict, n_frames: int) -> np.ndarray | None:
    """(F, 4, 4) base poses from motion columns (`base_columns`; missing ones 0), or None
    if the motion has none."""
    names = BASE_POSITION + BASE_ANGLES
    if not any(name in extra for name in names):
        return None
    value = {name: np.asarray(extra.get(name, np.zeros(n_frames)), dtype=float) for name in names}
    poses = np.tile(np.eye(4), (n_frames, 1, 1))
    poses[:, :3, :3] = rpy_to_matrix(np.radians(np.stack([value[n] for n in BASE_ANGLES], axis=1)))
    poses[:, :3, 3] = np.stack([value[n] for n in BASE_POSITION], axis=1)
    return poses


def _joint_scale(machine: Machine) -> np.ndarray:
    return np.array([np.degrees(1.0) if j.type == REVOLUTE else 1.0 for j in machine.joints])


def motion_columns(motion: Motion, machine: Machine) -> dict[str, np.ndarray]:
    """The motion file's columns in order, {name: (F,) array} (joint values in degrees /
    metres; `frame` integers, the rest floats)."""
    scale = _joint_scale(machine)
    header = ["frame", "time", *motion.joint_names]
    columns = [motion.frame, motion.time, *(motion.joints * scale).T]
    for k, name in enumerate(motion.point_names):
        header += [f"{name}_x", f"{name}_y", f"{name}_z"]
        columns += list(motion.points[:, k].T)
    header.append("bucket_angle_deg")
    columns.append(np.degrees(motion.bucket_angle))
    if motion.joints_sd is not None:
        header += [f"{n}_sd" for n in motion.joint_names]
        columns += list((motion.joints_sd * scale).T)
    if motion.points_sd is not None:
        header += [f"{n}_sd" for n in motion.point_names]
        columns += list(motion.points_sd.T)
    if motion.bucket_angle_sd is not None:
        header.append("bucket_angle_sd_deg")
        columns.append(np.degrees(motion.bucket_angle_sd))
    header += list(motion.extra)
    columns += [np.asarray(v, dtype=float) for v in motion.extra.values()]
    values = {h: np.asarray(c, dtype=float) for h, c in zip(header, columns)}
    return values | {"frame": np.asarray(motion.frame, dtype=np.int64)}


def save_motion(motion: Motion, machine: Machine, path: str | Path) -> None:
    """Write the motion CSV (joint values converted to degrees / metres), or Parquet with
    the same columns for a ``.parquet`` path."""
    values = motion_columns(motion, machine)
    if is_parquet(path):
        columnar.write_parquet(values, path)
        return
    columnar.write_csv(values, path, dict.fromkeys([h for h in values if h != "frame"], 6))


def _is_number(text: str) -> bool:
    try:
        float(text or "nan")
    except ValueError:
        return False
    return True


def _columns(col: dict, names: list[str], n: int) -> np.ndarray:
    """(n, len(names)) of the named columns; (n, 0) when there are none."""
    return np.column_stack([col[c] for c in names]) if names else np.zeros((n, 0))


def _row_problem(col: dict[str, np.ndarray]) -> tuple[str, int] | None:
    """The first reason why the rows are not a motion's and the row it shows in: a frame
    that is not a frame number, a time that is not finite, frames that do not increase."""
    frame = col["frame"]
    bad = np.flatnonzero(~np.isfinite(frame) | (frame < 0) | (frame != np.round(frame)) | (frame > 1e8))
    if len(bad):
        return f"frame {frame[bad[0]]:g} is not a frame number (a whole number >= 0)", int(bad[0])
    bad = np.flatnonzero(~np.isfinite(col["time"]))
    if len(bad):
        return "time must be a finite number of seconds", int(bad[0])
    bad = np.flatnonzero(np.diff(frame) <= 0)
    if len(bad):
        return "frames must increase from row to row", int(bad[0]) + 1
    return None


def _read_columnar(path: Path, check_header) -> tuple[list[str], np.ndarray] | None:
    """The header and values (R, K) of a plain numeric CSV read by pyarrow (ten times as fast
    as the csv module and a float per field), None when the file is anything else or a
    row has a problem to report: the checked reader then reads it and names the line."""
    table = columnar.read_csv_strict(path, {}, default=pa.float64())
    if table is None or "frame" not in table.column_names or "time" not in table.column_names:
        return None
    header = table.column_names
    check_header(header, "line 1")
    values = columnar.float_columns([table[h] for h in header])
    if values is None or _row_problem({h: values[:, i] for i, h in enumerate(header)}) is not None:
        return None
    return header, values


def _read_csv(path: Path, check_header) -> tuple[list[str], np.ndarray, np.ndarray, str]:
    """The header (checked by `check_header`(header, where)), the values (R, K) (NaN where
    empty) and the rows' line numbers (R,). A file read columnar has no row to report
    (`_read_columnar`), so its line numbers, counted from line 2 as if no line were blank,
    are never asked for."""
    fast = _read_columnar(path, check_header)
    if fast is not None:
        return fast[0], fast[1], np.arange(2, len(fast[1]) + 2), "line"
    text = read_text(path, "check the motion path")
    reader = iter(csv_rows(text, path))
    header = [h.strip() for h in next(reader, [])]
    check_header(header, "line 1")
    rows = [(line, row) for line, row in enumerate(reader, start=2) if row]
    if not rows:
        return header, np.zeros((0, len(header))), np.zeros(0, dtype=int), "line"
    bad = [(line, len(row)) for line, row in rows if len(row) != len(header)]
    if bad:
        raise InputError(f"{bad[0][1]} fields, the header has {len(header)}", path=path, where=f"line {bad[0][0]}")
    text = np.char.strip(np.array([row for _, row in rows], dtype=str).reshape(len(rows), len(header)))
    try:  # whole columns at once; only on the way to an error row by row
        table = np.where(text == "", "nan", text).astype(float)
    except ValueError:
        line = next(line for line, row in rows if not all(_is_number(v) for v in row))
        raise InputError("a field is not a number", path=path, where=f"line {line}") from None
    return header, table, np.array([line for line, _ in rows], dtype=int), "line"


def _read_parquet(path: Path, check_header) -> tuple[list[str], np.ndarray, np.ndarray, str]:
    table = columnar.read_parquet(path, "check the motion path")
    check_header(table.column_names, None)
    values = []
    for name in table.column_names:
        column = columnar.floats(table[name])
        if column is None:
            raise InputError(f"column {name!r} is not numeric", path=path)
        values.append(column)
    array = np.column_stack(values) if values else np.zeros((table.num_rows, 0))
    return table.column_names, array, np.arange(1, table.num_rows + 1), "row"


def load_motion(path: str | Path, machine: Machine) -> Motion:
    """Read a motion CSV written for `machine` (columns beyond the known ones go to `extra`),
    or Parquet with the same columns for a ``.parquet`` path."""
    path = Path(path)
    joint_cols = list(machine.joint_names)
    point_cols = [f"{p}_{a}" for p in machine.point_names for a in "xyz"]
    bucket = ["bucket_angle_deg"] if machine.bucket_angle is not None else []  # else NaN, optional
    required = ["frame", "time", *joint_cols, *point_cols, *bucket]

    def check_header(header: list[str], where: str | None) -> None:
        missing = [c for c in required if c not in header]
        if missing:
            raise InputError(f"header lacks {', '.join(missing)} (is it the motion of {machine.name!r}?)",
                             path=path, where=where)

    header, table, lines, unit = (_read_parquet if is_parquet(path) else _read_csv)(path, check_header)
    col = {h: table[:, i] for i, h in enumerate(header)}
    problem = _row_problem(col)
    if problem is not None:
        raise InputError(problem[0], path=path, where=f"{unit} {lines[problem[1]]}")
    scale = _joint_scale(machine)
    n_points = len(machine.point_names)

    def optional(names):
        return np.column_stack([col[n] for n in names]) if names and all(n in col for n in names) else None

    joints_sd = optional([f"{n}_sd" for n in machine.joint_names])
    points_sd = optional([f"{n}_sd" for n in machine.point_names])
    known = set(required) | {f"{n}_sd" for n in machine.joint_names + machine.point_names}
    known.add("bucket_angle_sd_deg")
    return Motion(
        joint_names=machine.joint_names,
        point_names=machine.point_names,
        frame=col["frame"].astype(int),
        time=col["time"],
        joints=_columns(col, joint_cols, len(table)) / scale,  # (F, 0) for a rigid model
        points=_columns(col, point_cols, len(table)).reshape(len(table), n_points, 3),
        bucket_angle=np.radians(col.get("bucket_angle_deg", np.full(len(table), np.nan))),
        joints_sd=None if joints_sd is None else joints_sd / scale,
        points_sd=points_sd,
        bucket_angle_sd=np.radians(col["bucket_angle_sd_deg"]) if "bucket_angle_sd_deg" in col else None,
        extra={h: col[h] for h in header if h not in known},
    )
