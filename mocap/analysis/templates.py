"""The per-class templates as a table for the templates TOML, with the joint trajectories
that follow each template through the machine's closed-form inverse kinematics.

Shapes: N arc-length samples, J joints.
"""

from __future__ import annotations

import logging

import numpy as np

from mocap.analysis.core import Analysis
from mocap.core.ik import PlanarChain
from mocap.core.machine import Machine
from mocap.errors import InputError

log = logging.getLogger(__name__)


def template_joints(machine: Machine, start: np.ndarray, path: np.ndarray) -> dict[str, list[float]] | None:
    """Joint values (deg) of boom, arm and bucket along a template `path` (N, 3) dx, dz (m),
    angle (rad) from `start` (3,) reach, height (m), angle; None without a planar linkage or
    out of reach."""
    try:
        chain = PlanarChain.from_machine(machine)
    except InputError:
        return None
    tip = np.column_stack([start[0] + path[:, 0], start[1] + path[:, 1] - chain.house_height])
    try:
        joints = chain.inverse(tip, path[:, 2], np.zeros(len(path)))
    except ValueError as exc:
        log.info("template joints skipped: %s", exc)
        return None
    return {machine.joint_names[j]: np.round(np.degrees(joints[:, j]), 3).tolist() for j in chain.joints}


def templates_table(analysis: Analysis, machine: Machine) -> dict:
    """The templates TOML's content."""
    items = []
    relations = {r.label: r for r in analysis.relations}
    labels = analysis.table["class"]
    for label, t in analysis.templates.items():
        pick = labels == label
        item = {
            "class": label,
            "digs": t.count,
            "start": {"reach": round(float(t.start[0]), 4), "height": round(float(t.start[1]), 4),
                      "angle_deg": round(float(np.degrees(t.start[2])), 3)},
            "s": np.round(t.s, 4).tolist(),
            "dx": np.round(t.path[:, 0], 4).tolist(),
            "dz": np.round(t.path[:, 1], 4).tolist(),
            "angle_deg": np.round(np.degrees(t.path[:, 2]), 3).tolist(),
        }
        for axis in ("scale_x", "scale_z") if pick.any() else ():
            item[axis] = np.round([analysis.table[axis][pick].min(), analysis.table[axis][pick].max()], 4).tolist()
        rel = relations.get(label)
        if rel is not None and np.isfinite(rel.slope):
            item["relation"] = {"slope": round(rel.slope, 4), "intercept_deg": round(float(np.degrees(rel.intercept)), 3),
                                "r": round(rel.r, 4)}
        joints = template_joints(machine, t.start, t.path)
        if joints is not None:
            item["joints"] = joints
        items.append(item)
    return {"machine": machine.name, "samples": int(len(analysis.paths.s)), "templates": items}
