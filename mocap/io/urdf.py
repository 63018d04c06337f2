"""URDF of a machine model: the same kinematic tree for ROS, MoveIt, PyBullet, Pinocchio.

Each link of the model is a URDF link; each joint a `revolute` or `prismatic` joint whose
`<origin xyz rpy>` is the model's `origin` and `rpy_deg` (in radians; URDF's rpy is ours:
R = Rz(yaw) Ry(pitch) Rx(roll)), whose `<axis>` is the model's axis in the child link's frame
and whose `<limit>` is the model's limits (rad or m). Markers and named points become fixed
child links named ``marker_<name>`` and ``point_<name>``, so a URDF library can give their
positions by forward kinematics. Numbers are written with full precision (repr), so the
file reproduces the model's kinematics to the last bit of a double.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from mocap.core.machine import Machine
from mocap.errors import InputError
from mocap.io.atomic import write_text

MARKER_PREFIX = "marker_"
POINT_PREFIX = "point_"


def _numbers(values) -> str:
    return " ".join(repr(float(v)) for v in np.asarray(values, dtype=float).reshape(-1))


def _fixed_frame(robot: ET.Element, name: str, parent: str, position: np.ndarray) -> None:
    ET.SubElement(robot, "link", name=name)
    joint = ET.SubElement(robot, "joint", name=f"{name}_fixed", type="fixed")
    ET.SubElement(joint, "parent", link=parent)
    ET.SubElement(joint, "child", link=name)
    ET.SubElement(joint, "origin", xyz=_numbers(position), rpy="0.0 0.0 0.0")


def urdf_text(machine: Machine, robot_name: str | None = None) -> str:
    """The URDF document of `machine`; raises InputError if a marker's or named point's
    frame name would clash with a link's."""
    names = list(machine.link_names)
    names += [MARKER_PREFIX + m for m in machine.marker_names]
    names += [POINT_PREFIX + p for p in machine.point_names]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise InputError(
            f"URDF link names {repeated} would repeat; rename the link, marker or point in the model"
        )
    robot = ET.Element("robot", name=robot_name or machine.name)
    for link in machine.links:
        ET.SubElement(robot, "link", name=link.name)
    for link in machine.links[1:]:
        joint = link.joint
        element = ET.SubElement(robot, "joint", name=joint.name, type=joint.type)
        ET.SubElement(element, "parent", link=machine.links[link.parent].name)
        ET.SubElement(element, "child", link=link.name)
        ET.SubElement(element, "origin", xyz=_numbers(joint.origin), rpy=_numbers(joint.rpy))
        ET.SubElement(element, "axis", xyz=_numbers(joint.axis))
        lower, upper = joint.limits
        ET.SubElement(element, "limit", lower=repr(float(lower)), upper=repr(float(upper)), effort="0.0", velocity="0.0")
    for name, link, position in zip(machine.marker_names, machine.marker_links, machine.marker_positions):
        _fixed_frame(robot, MARKER_PREFIX + name, machine.links[link].name, position)
    for name, link, position in zip(machine.point_names, machine.point_links, machine.point_positions):
        _fixed_frame(robot, POINT_PREFIX + name, machine.links[link].name, position)
    ET.indent(robot)
    return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"


def save_urdf(machine: Machine, path: str | Path) -> None:
    write_text(path, urdf_text(machine))
