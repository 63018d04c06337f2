"""`mocap live --view`: each row, as it is written, to a Rerun viewer.

The entity paths are the replay's (`mocap.viewer.record`): world/machine/<link> (the link's
box, static, moved by world_from_link of the row's joints through the model's forward
kinematics), world/<point> (the named points), world/trail/live (the bucket tip's path, a
segment a row, shown over the last `TRAIL_S` seconds), world/cameras/<cam> (static),
plots/joints/<joint> (deg; prismatic in plots/joints_m, m) and plots/bucket/bucket_angle
(deg). Timelines `frame` and `time` as in the replay. The work per row is fixed: one
transform per link, the points, one segment, one scalar per joint, done by a thread of its
own (`ViewThread`) from a queue of at most `QUEUE_ROWS` rows, so that the rows' loop only
hands them over; rows that find the queue full are not shown (counted). Rerun sends them
from its own thread.
"""

from __future__ import annotations

import logging
import queue
import threading
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from scipy.spatial.transform import Rotation

from mocap.core.calibration import Calibration
from mocap.core.machine import Machine
from mocap.errors import InputError
from mocap.io.motion_csv import world_from_base_of
from mocap.live.pose import Pose
from mocap.viewer.record import entity, link_path, log_cameras, log_link_boxes, log_world, trail_path
from mocap.viewer.scene import joint_display_units

log = logging.getLogger(__name__)

TRAIL_S = 20.0  # seconds of the tip's path shown behind the time cursor
TRAIL = trail_path("live")
SPAWN = ""  # `--view` without a value: a viewer started on this machine
QUEUE_ROWS = 256  # rows waiting to be shown at most (8 s at 30 fps)


def check_target(target: str) -> str:
    """`--view`'s value: "" (spawn a viewer), a viewer's gRPC URL, or an .rrd file to write."""
    if target == SPAWN or target.startswith(("rerun://", "rerun+http://", "rerun+https://")):
        return target
    if target.endswith(".rrd"):
        if Path(target).is_dir():
            raise InputError("--view names a folder; give an .rrd file or a viewer's URL", path=target)
        return target
    raise InputError(f"--view {target}: expected a viewer's URL (rerun+http://HOST:9876/proxy) or an .rrd file "
                     "to write; give --view alone to start a viewer here")


def open_stream(target: str, blueprint: rrb.Blueprint) -> rr.RecordingStream:
    """A recording stream to a spawned viewer, a running one at a URL, or an .rrd file."""
    rec = rr.RecordingStream("mocap_live")
    if target == SPAWN:
        rec.spawn(default_blueprint=blueprint)
    elif target.endswith(".rrd"):
        Path(target).parent.mkdir(parents=True, exist_ok=True)
        rec.save(target, default_blueprint=blueprint)
    else:
        rec.connect_grpc(target, default_blueprint=blueprint)
    return rec


def live_blueprint(machine: Machine) -> rrb.Blueprint:
    """The 3-D machine with its trail, the joints and the bucket angle, following the newest row."""
    trail = rrb.VisibleTimeRanges([
        rrb.VisibleTimeRange("frame", start=rrb.TimeRangeBoundary.cursor_relative(seq=-int(TRAIL_S * 30)),
                             end=rrb.TimeRangeBoundary.cursor_relative(seq=0)),
        rrb.VisibleTimeRange("time", start=rrb.TimeRangeBoundary.cursor_relative(seconds=-TRAIL_S),
                             end=rrb.TimeRangeBoundary.cursor_relative(seconds=0.0)),
    ])
    prismatic = "m" in joint_display_units(machine)[1]
    plots = rrb.Vertical(
        rrb.TimeSeriesView(origin="plots", contents=["+ plots/joints/**", "+ plots/joints_m/**"],
                           name="joints (deg; prismatic m)" if prismatic else "joints (deg)"),
        rrb.TimeSeriesView(origin="plots", contents=["+ plots/bucket/**"], name="bucket angle (deg)"),
    )
    scene = rrb.Spatial3DView(origin="world", name="machine", overrides={TRAIL: trail})
    return rrb.Blueprint(rrb.Horizontal(scene, plots, column_shares=[2, 1]),
                         rrb.TimePanel(timeline="time", play_state="following"))


class LiveView:
    """Rows to a recording stream: `log(frame, time, pose)` per row, `close()` at the end."""

    def __init__(self, rec: rr.RecordingStream, machine: Machine, calibration: Calibration):
        self.rec, self.machine = rec, machine
        self.scale, units = joint_display_units(machine)
        self.joint_paths = [f"plots/{'joints' if u == 'deg' else 'joints_m'}/" + entity(name)
                            for name, u in zip(machine.joint_names, units)]
        self.point_paths = ["world/" + entity(name) for name in machine.point_names]
        self.tip = machine.point_names.index("bucket_tip") if "bucket_tip" in machine.point_names else (
            0 if machine.point_names else None)
        self.last_tip: np.ndarray | None = None
        log_world(rec, machine)
        log_link_boxes(rec, machine)
        log_cameras(rec, calibration, 0.05 * _extent(machine))
        rec.log(TRAIL, rr.LineStrips3D.from_fields(colors=[(31, 119, 180)], radii=[-2.0]), static=True)
        for path, name, unit in zip(self.joint_paths, machine.joint_names, units):
            rec.log(path, rr.SeriesLines(names=[f"{name} ({unit})"]), static=True)
        rec.log("plots/bucket/bucket_angle", rr.SeriesLines(names=["bucket angle (deg)"]), static=True)
        for path, name in zip(self.point_paths, machine.point_names):
            rec.log(path, rr.Points3D.from_fields(labels=[name], radii=[-8.0], colors=[(255, 255, 255)]), static=True)

    def log(self, frame: int, time: float, pose: Pose) -> None:
        rec = self.rec
        rec.set_time("frame", sequence=int(frame))
        rec.set_time("time", duration=float(time))
        if not np.all(np.isfinite(pose.joints)):
            self.last_tip = None
            return
        base = world_from_base_of({k: np.array([v]) for k, v in pose.base.items()}, 1) if pose.base else None
        world_from_link = self.machine.link_poses(pose.joints[None], base)[0]  # (L, 4, 4)
        quaternion = Rotation.from_matrix(world_from_link[:, :3, :3]).as_quat()
        for i, name in enumerate(self.machine.link_names):
            rec.log(link_path(name), rr.Transform3D(translation=world_from_link[i, :3, 3], quaternion=quaternion[i]))
        for path, xyz in zip(self.point_paths, pose.points):
            if np.all(np.isfinite(xyz)):
                rec.log(path, rr.Points3D.from_fields(positions=[xyz]))
        for path, value, scale in zip(self.joint_paths, pose.joints, self.scale):
            rec.log(path, rr.Scalars(value * scale))
        if np.isfinite(pose.bucket_angle):
            rec.log("plots/bucket/bucket_angle", rr.Scalars(np.degrees(pose.bucket_angle)))
        if self.tip is not None:
            tip = pose.points[self.tip]
            if np.all(np.isfinite(tip)):
                if self.last_tip is not None:
                    rec.log(TRAIL, rr.LineStrips3D.from_fields(strips=[np.stack([self.last_tip, tip])]))
                self.last_tip = tip
            else:
                self.last_tip = None

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()


class ViewThread(threading.Thread):
    """`LiveView.log` on a thread of its own: `submit` never waits; a row that finds
    `QUEUE_ROWS` rows waiting is dropped and counted in `dropped`."""

    def __init__(self, view: LiveView):
        super().__init__(name="view", daemon=True)
        self.view = view
        self.rows: queue.Queue = queue.Queue(maxsize=QUEUE_ROWS)
        self.dropped = 0

    def submit(self, frame: int, time: float, pose: Pose) -> None:
        try:
            self.rows.put_nowait((frame, time, pose))
        except queue.Full:
            self.dropped += 1

    def run(self) -> None:
        while (item := self.rows.get()) is not None:
            try:
                self.view.log(*item)
            except Exception:
                log.exception("the viewer stopped showing rows; the rows carry on")
                break

    def close(self) -> None:
        """Show the rows waiting, then flush and close the stream."""
        self.rows.put(None)
        self.join(timeout=30.0)
        self.view.close()


def _extent(machine: Machine) -> float:
    """The machine's size (m) at rest, for the cameras' frustum depth."""
    origins = machine.link_poses(np.zeros((1, machine.n_joints)))[0, :, :3, 3]
    return max(float(np.ptp(origins, axis=0).max()), 1.0)
