"""Solid shapes of a machine's links, stated in the model or derived from it, for rendering and replay.

Each link is drawn as the box in its own frame that holds its joint origin, its markers and
points and its children's joint origins, so that markers at the extremes lie on its faces;
boxes thinner than a minimum are thickened about their middle. A plain stand-in for the
manufacturer's geometry, enough to hide markers behind links and to see the machine move.
"""

from __future__ import annotations

import numpy as np

from mocap.core.machine import Machine


def link_boxes(machine: Machine, thickness: float | None = None) -> np.ndarray:
    """Axis-aligned boxes in each link's frame: (L, 2, 3) = (min corner, max corner), metres.

    `thickness`, the least size of a box along any axis, defaults to 3 % of the machine's
    extent (at least 5 cm). A link whose box the model states (`Machine.link_boxes`, the
    machine file's `box`) has that one instead.
    """
    extent = np.ptp(machine.markers(np.zeros((1, machine.n_joints)))[0], axis=0).max()
    thickness = max(0.05, 0.03 * extent) if thickness is None else thickness
    boxes = np.empty((len(machine.links), 2, 3))
    for i, link in enumerate(machine.links):
        pts = [np.zeros((1, 3)) if i else np.empty((0, 3))]
        pts.append(machine.marker_positions[machine.marker_links == i])
        pts.append(machine.point_positions[machine.point_links == i])
        for child in machine.links:
            if child.parent == i:
                pts.append(child.joint.origin[None])
        pts = np.concatenate(pts)
        if i == 0:
            pts = np.concatenate([pts, [[pts[:, 0].mean(), pts[:, 1].mean(), 0.0]]])
        low, high = pts.min(axis=0), pts.max(axis=0)
        grow = np.maximum(thickness - (high - low), 0.0) / 2
        boxes[i, 0], boxes[i, 1] = low - grow, high + grow
    if machine.link_boxes is not None:
        stated = np.all(np.isfinite(machine.link_boxes), axis=(1, 2))
        boxes[stated] = machine.link_boxes[stated]
    return boxes


def box_corners(box: np.ndarray) -> np.ndarray:
    """Corners of a box (2, 3) -> (8, 3), index bits (x, y, z) = (k & 1, k & 2, k & 4)."""
    k = np.arange(8)
    return np.stack([box[(k >> 0) & 1, 0], box[(k >> 1) & 1, 1], box[(k >> 2) & 1, 2]], axis=-1)


# faces of `box_corners` as quads, outward normals by the right-hand rule
BOX_FACES = np.array(
    [[0, 4, 6, 2], [1, 3, 7, 5], [0, 1, 5, 4], [2, 6, 7, 3], [0, 2, 3, 1], [4, 5, 7, 6]]
)
