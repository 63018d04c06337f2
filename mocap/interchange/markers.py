"""Markers and named points over a session's frames, as marker files (C3D, TRC) hold them."""

from __future__ import annotations

import numpy as np

from mocap.core.marker_table import MarkerTable
from mocap.core.motion import Motion
from mocap.core.points import Points
from mocap.errors import InputError


def marker_table(
    points: Points | None, motion: Motion | None, rate: float, marker_order: tuple[str, ...] = ()
) -> MarkerTable:
    """The triangulated markers, then the motion's named points, over every frame from the
    first to the last either has (frames without data are gaps).

    `marker_order`: the model's marker names, the order the markers are written in; markers
    the model does not name follow in order of first appearance.
    """
    frames = []
    if points is not None and len(points):
        frames.append(points.frame)
    if motion is not None and len(motion):
        frames.append(motion.frame)
    if not frames:
        raise InputError("no triangulated points and no motion to export; run the session first")
    first = int(min(f.min() for f in frames))
    last = int(max(f.max() for f in frames))
    frame = np.arange(first, last + 1)
    marker_names: list[str] = []
    if points is not None and len(points):
        _, index = np.unique(points.marker, return_index=True)
        seen = list(points.marker[np.sort(index)])
        marker_names = [m for m in marker_order if m in set(seen)] + [m for m in seen if m not in set(marker_order)]
    point_names = list(motion.point_names) if motion is not None else []
    clash = sorted(set(marker_names) & set(point_names))
    if clash:
        raise InputError(f"marker(s) and named point(s) share the names {clash}; rename them in the machine model")
    xyz = np.full((len(frame), len(marker_names) + len(point_names), 3), np.nan)
    if marker_names:
        column = {name: k for k, name in enumerate(marker_names)}
        m = np.array([column[name] for name in points.marker], dtype=int)
        xyz[points.frame - first, m] = points.xyz
    if point_names:
        xyz[motion.frame - first, len(marker_names):] = motion.points
    return MarkerTable(tuple(marker_names + point_names), frame, rate, xyz)
