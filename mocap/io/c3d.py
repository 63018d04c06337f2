"""The C3D marker file (Vicon Nexus, Mokka, OpenSim, Visual3D), read and written with ezc3d.

Points in millimetres (`POINT:UNITS = "mm"`) in the machine's world frame (z up), at
`POINT:RATE` frames per second; the header's first frame is our first frame (counted from
0, as ezc3d counts). A marker not seen in a frame is a gap: NaN coordinates and residual -1,
the C3D mark of an invalid point.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mocap.errors import InputError
from mocap.core.marker_table import MarkerTable
from mocap.io.atomic import atomic_path

_UNITS_TO_METRES = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}


def save_c3d(table: MarkerTable, path: str | Path) -> None:
    import ezc3d

    c3d = ezc3d.c3d()
    n_frames, n_markers = len(table.frame), len(table.names)
    c3d["parameters"]["POINT"]["RATE"]["value"] = [float(table.rate)]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = list(table.names)
    c3d.add_parameter("POINT", "UNITS", "mm")
    points = np.ones((4, n_markers, n_frames))
    points[:3] = np.transpose(table.xyz, (2, 1, 0)) * 1000.0
    seen = np.all(np.isfinite(points[:3]), axis=0)  # (N, F)
    points[:3, ~seen] = np.nan
    c3d["data"]["points"] = points
    c3d["data"]["meta_points"]["residuals"] = np.where(seen, 0.0, -1.0)[None]
    c3d["header"]["points"]["first_frame"] = int(table.frame[0]) if n_frames else 0
    with atomic_path(path) as tmp:
        written = tmp.with_name(tmp.name + ".c3d")  # ezc3d adds .c3d to any other name
        try:
            c3d.write(str(written))
            os.replace(written, tmp)
        finally:
            written.unlink(missing_ok=True)


def load_c3d(path: str | Path) -> MarkerTable:
    """Read a C3D file's points into metres; gaps (residual < 0) are NaN."""
    import ezc3d

    path = Path(path)
    if not path.is_file():
        raise InputError("file not found; check the C3D path", path=path)
    try:
        c3d = ezc3d.c3d(str(path))
    except (RuntimeError, IOError) as exc:
        raise InputError(f"not a readable C3D file ({exc})", path=path) from None
    point = c3d["parameters"]["POINT"]
    units = point["UNITS"]["value"][0].strip() if "UNITS" in point and point["UNITS"]["value"] else "mm"
    if units not in _UNITS_TO_METRES:
        raise InputError(f"POINT:UNITS is {units!r}; expected mm, cm or m", path=path)
    data = c3d["data"]["points"][:3]  # (3, N, F)
    residuals = c3d["data"]["meta_points"]["residuals"][0]
    xyz = np.transpose(data, (2, 1, 0)) * _UNITS_TO_METRES[units]
    xyz[(residuals < 0).T] = np.nan
    header = c3d["header"]["points"]
    frame = header["first_frame"] + np.arange(xyz.shape[0])
    names = tuple(label.strip() for label in point["LABELS"]["value"])
    return MarkerTable(names, frame, float(header["frame_rate"]), xyz)
