"""The dig templates TOML ("software kinematics"): per class the general shape of the dig,
a controls engineer's parameterised trajectory.

    machine = "Hitachi EX3500 front shovel (approximate)"
    samples = 64                       # points over normalised arc length s
    [[templates]]
    class = "Type 1"
    digs = 12                          # digs the template was built from
    start = { reach = 10.6, height = 0.5, angle_deg = -29.0 }   # median dig start
    s = [0.0, ...]                     # normalised arc length, 0..1
    dx = [...]                         # tip displacement from the start, m, away from the machine
    dz = [...]                         # m, up
    angle_deg = [...]                  # bucket angle to the horizontal
    scale_x = [0.91, 1.08]             # range of the digs' horizontal and vertical factors
    scale_z = [0.83, 1.19]
    relation = { slope = 0.45, intercept_deg = -15.3, r = 0.79 }  # angle = intercept + slope * path direction
    joints = { boom = [...], arm = [...], bucket = [...] }  # joint values (deg) following the
    # template from the median start through the machine's inverse kinematics (absent when
    # the model has no boom-arm-bucket linkage or the path leaves its reach)

A dig is reproduced as start + (scale_x · dx, scale_z · dz) with the bucket angle following
`angle_deg` over the same s.
"""

from __future__ import annotations

from pathlib import Path

from mocap.io import toml_writer
from mocap.io.atomic import write_text


def save_templates(data: dict, path: str | Path) -> None:
    """Write the templates TOML from its table (see the module's layout)."""
    write_text(path, toml_writer.dumps(data))
