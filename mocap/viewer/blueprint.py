"""The replay's default layout: the 3-D scene, one 2-D view per camera, the plots."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import rerun.blueprint as rrb

from mocap.viewer.record import camera_path, trail_path
from mocap.viewer.scene import Trail


def trail_time_ranges(trail: Trail) -> rrb.VisibleTimeRanges:
    """Show a trail's segments from its cycle's start up to the time cursor, on both timelines."""
    return rrb.VisibleTimeRanges(
        [
            rrb.VisibleTimeRange(
                "frame",
                start=rrb.TimeRangeBoundary.absolute(seq=trail.first_frame),
                end=rrb.TimeRangeBoundary.cursor_relative(seq=0),
            ),
            rrb.VisibleTimeRange(
                "time",
                start=rrb.TimeRangeBoundary.absolute(seconds=trail.first_time),
                end=rrb.TimeRangeBoundary.cursor_relative(seconds=0.0),
            ),
        ]
    )


def default_blueprint(
    cameras: Sequence[str], trails: Sequence[Trail], plot_groups: Sequence[tuple[str, str]],
    eye: tuple[np.ndarray, np.ndarray] | None = None, phases: bool = False,
) -> rrb.Blueprint:
    """`plot_groups` (group under plots/, title with its unit) beyond joints, bucket angle
    and speed that have series; `eye` the 3-D view's position and look target (m), None for
    Rerun's own framing; `phases` whether plots/phase has the dig-cycle phases."""
    controls = None if eye is None else rrb.EyeControls3D(position=eye[0], look_target=eye[1], eye_up=[0, 0, 1])
    scene_3d = rrb.Spatial3DView(
        origin="world",
        name="machine",
        overrides={trail_path(t.name): trail_time_ranges(t) for t in trails},
        eye_controls=controls,
    )
    images = [rrb.Spatial2DView(origin=camera_path(name), name=name) for name in cameras]
    plots = [
        rrb.TimeSeriesView(origin="plots/joints", name="joints (deg / m)"),
        rrb.TimeSeriesView(origin="plots/bucket", name="bucket angle (deg)"),
        rrb.TimeSeriesView(origin="plots/speed", name="speed (m/s)"),
    ]
    if phases:
        plots.append(rrb.TimeSeriesView(origin="plots/phase", name="dig-cycle phase"))
    plots += [rrb.TimeSeriesView(origin=f"plots/{group}", name=title) for group, title in plot_groups]
    left = rrb.Vertical(scene_3d, rrb.Horizontal(*images), row_shares=[3, 1]) if images else scene_3d
    return rrb.Blueprint(rrb.Horizontal(left, rrb.Vertical(*plots), column_shares=[2, 1]))
