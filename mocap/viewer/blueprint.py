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
    eye: tuple[np.ndarray, np.ndarray] | None = None, phases: bool = False, fps: float | None = None,
) -> rrb.Blueprint:
    """`plot_groups` (group under plots/, title with its unit) beyond joints, bucket angle
    and speed that have series; `eye` the 3-D view's position and look target (m), None for
    Rerun's own framing; `phases` whether plots/phase has the dig-cycle phases; `fps` the
    reference camera's frame rate, which the viewer plays the frame timeline at (its own
    default is 30)."""
    controls = None if eye is None else rrb.EyeControls3D(position=eye[0], look_target=eye[1], eye_up=[0, 0, 1])
    scene_3d = rrb.Spatial3DView(
        origin="world",
        name="machine",
        overrides={trail_path(t.name): trail_time_ranges(t) for t in trails},
        eye_controls=controls,
    )
    images = [rrb.Spatial2DView(origin=camera_path(name), name=name) for name in cameras]
    # at most four panels, each one kind of quantity: joints, the bucket, the measurement's
    # quality (and everything else the motion holds), the cycles' phases
    groups = [group for group, _ in plot_groups]
    plots = [
        rrb.TimeSeriesView(origin="plots", contents=["+ plots/joints/**", "+ plots/joints_m/**"],
                           name="joints (deg)" if "joints_m" not in groups else "joints (deg; prismatic m)"),
        rrb.TimeSeriesView(origin="plots", contents=["+ plots/bucket/**", "+ plots/speed/**"],
                           name="bucket angle (deg) and tip speed (m/s)"),
    ]
    others = [g for g in groups if g != "joints_m"]
    if others:
        plots.append(rrb.TimeSeriesView(origin="plots", contents=[f"+ plots/{g}/**" for g in others],
                                        name="measurement quality (sd) and other columns"))
    if phases:
        plots.append(rrb.TimeSeriesView(origin="plots/phase",
                                        name="cycles: phase (1 dig, 2 swing loaded, 3 dump, 4 swing back)"))
    left = rrb.Vertical(scene_3d, rrb.Horizontal(*images), row_shares=[3, 1]) if images else scene_3d
    panel = None
    if trails:
        # The first dig selected, played in a loop. Rerun 0.41's blueprint has no time cursor:
        # playing starts at the timeline's first frame and wraps to the selection's start only
        # at its end, so the replay plays up to the first dig and then loops on it.
        first = trails[0]
        panel = rrb.TimePanel(timeline="frame", play_state="playing", loop_mode="selection", fps=fps,
                              time_selection=rrb.components.AbsoluteTimeRange(int(first.first_frame), int(first.frame[-1])))
    return rrb.Blueprint(rrb.Horizontal(left, rrb.Vertical(*plots), column_shares=[2, 1]),
                         *([panel] if panel is not None else []))
