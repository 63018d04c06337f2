"""A synthetic field session with exact ground truth, in memory and on disk.

`make_session` plans the dig cycles, places the cameras and computes every camera's true
marker pixels and visibility at its own frames; `write_truth` writes the session folder
(DESIGN.md) with ``truth/``: cameras.toml, motion.csv (reference-camera frames),
tracks.csv (true centres of visible markers, each camera's own frames; score: the share of
the marker's square in view; with a rolling shutter, each where it is when its own row is
read: `mocap.synthetic.shutter`), markers.csv (3-D
marker positions at reference frames), cycles.csv and scene.toml (pile, truck, options).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from mocap.core.calibration import Calibration, joints_to_table
from mocap.core.camera import project_cam
from mocap.core.machine import Machine
from mocap.core.motion import Motion
from mocap.core.points import Points
from mocap.core.shapes import box_corners, link_boxes
from mocap.core.tracks import Tracks, concatenate
from mocap.core.visibility import marker_cover, marker_normals, marker_outlines, square_outline, visible_markers
from mocap.errors import InputError
from mocap.io import toml_writer
from mocap.io.atomic import write_text
from mocap.io.cameras_toml import save_calibration
from mocap.io.cycles_csv import save_cycles
from mocap.io.machine_toml import MACHINES_DIR
from mocap.io.motion_csv import base_columns, save_motion
from mocap.io.points_csv import save_points
from mocap.io.session_toml import SessionCamera, SessionConfig, save_session_config
from mocap.io.tracks_csv import save_tracks
from mocap.synthetic.cameras import FieldCamera, place_cameras
from mocap.synthetic.meshes import Solids, machine_solids, marker_test_points, solids_in_view
from mocap.synthetic.motion import DigMotion, check_limits, plan_session
from mocap.synthetic.paths import CLASSES, min_jerk
from mocap.synthetic.shutter import rolling_pixels


SHAPES = ("boxes", "meshes")  # how the links are drawn (`SessionOptions.shapes`)


@dataclass(frozen=True)
class SessionOptions:
    """What `make_session` varies. Angles in degrees, sizes in pixels; `readout` the cameras'
    rolling shutter: their rows are read one after another over that share of the frame
    interval, the middle row at the frame's time (0: a global shutter); `shapes` the links'
    solids: "boxes" (the boxes `mocap.core.shapes.link_boxes` guesses, as the tracker does) or
    "meshes" (tapered, kinked links, cab, counterweight, hoses, markers on slanted plates:
    `mocap.synthetic.meshes`)."""

    n_cameras: int = 3
    n_cycles: int = 4
    seed: int = 7
    size: tuple[int, int] = (1920, 1080)
    distortion: bool = False
    shake_deg: float = 0.0
    bounce: float = 1.0
    reactive: float = 1.0
    redirect_probability: float = 0.4
    classes: tuple[str, ...] = CLASSES
    hold: float = 2.0
    readout: float = 0.0
    shapes: str = "boxes"
    fps: float = 30.0

    def __post_init__(self) -> None:
        if self.shapes not in SHAPES:
            raise ValueError(f"shapes must be one of {SHAPES}, got {self.shapes!r}")
        if not 1 <= self.n_cameras <= 8:
            raise ValueError(f"n_cameras must be 1..8, got {self.n_cameras}")
        if self.n_cycles < 1:
            raise ValueError(f"n_cycles must be at least 1, got {self.n_cycles}")
        unknown = [c for c in self.classes if c not in CLASSES]
        if unknown or not self.classes:
            raise ValueError(f"classes must be some of {CLASSES}, got {list(self.classes)}")
        if self.hold < 0.5:
            raise ValueError(f"hold must be at least 0.5 s, got {self.hold}")
        if not 5.0 <= self.fps <= 120.0:
            raise ValueError(f"fps must be 5..120, got {self.fps}")
        if not 0.0 <= self.readout <= 0.9:
            raise ValueError(f"readout must be 0..0.9 of the frame interval, got {self.readout}")


@dataclass(frozen=True)
class SyntheticSession:
    """A planned session and its truth.

    `cameras` the field cameras (first = reference clock); `motion` the truth at the
    reference camera's frames; `tracks` the true pixels of visible markers (each camera's
    own frames, `time` on the reference clock); `markers` (F, M, 3) world positions at the
    reference frames; `views` (F, M) how many cameras see each marker then.
    """

    machine: Machine
    machine_ref: str
    options: SessionOptions
    plan: DigMotion
    cameras: tuple[FieldCamera, ...]
    motion: Motion
    tracks: Tracks
    markers: np.ndarray
    views: np.ndarray
    boxes: np.ndarray
    normals: np.ndarray
    solids: Solids | None = None  # the links' drawn shapes when they are not `boxes`

    @property
    def calibration(self) -> Calibration:
        """The true cameras as a calibration file: clocks in the extras, the joints at the
        calibration frame (reference frame 0) in the metadata."""
        extras = tuple({"fps": c.fps, "time_offset": c.time_offset} for c in self.cameras)
        metadata = {
            "machine": self.machine_ref,
            "frame": 0,
            "joints": joints_to_table(self.motion.joints[0], self.machine),
            "error": 0.0,
        }
        return Calibration(tuple(c.camera for c in self.cameras), extras, metadata)

    @property
    def reach(self) -> float:
        """The machine's reach (m): boom, arm and bucket lengths added."""
        return float(np.linalg.norm(self.plan.chain.offsets, axis=1).sum())

    def marker_outlines(self) -> tuple[np.ndarray, np.ndarray]:
        """The painted markers' square corners (M, 4, 3) and disk outlines (M, N, 3) in
        their link frames (`marker_sizes`)."""
        return marker_outlines(self.machine, self.normals, *marker_sizes(self.reach))

    def plan_tips(self, times: np.ndarray) -> np.ndarray:
        """World positions (T, 3) of the bucket tip at `times` (T,) s."""
        joints = self.plan.joints(times)
        points = self.machine.points(joints, self.plan.world_from_base(times))
        return points[:, self.machine.point_names.index("bucket_tip")]

    def dust_density(self, times: np.ndarray) -> np.ndarray:
        """How thick the dust raised by digging is at `times` (T,): 0 (none) to 1, rising
        over a second from each dig's start, settling over two after it ends."""
        times = np.asarray(times, dtype=float)
        density = np.zeros(len(times))
        for c in self.plan.cycles:
            rise = min_jerk(times - c.dig_start)
            settle = 1.0 - min_jerk((times - c.dig_end - 1.0) / 2.0)
            density = np.maximum(density, rise * settle)
        return density

    def observe(self, camera: FieldCamera, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """True marker pixels (F, M, 2), visibility (F, M) and link poses (F, L, 4, 4) of
        `camera` at its `frames` (F,) (fractional frames allowed)."""
        return observe_camera(self.machine, self.plan, self.boxes, self.normals, camera, frames, self.solids)

    def pixels_at(self, camera: FieldCamera, at: np.ndarray) -> np.ndarray:
        """Pixels (F, M, 2) of each marker m of `camera` at its own fractional frame `at` (F, M)."""
        return marker_pixels_at(self.machine, self.plan, camera, at)


def marker_sizes(reach: float) -> tuple[float, float]:
    """The painted disk's diameter and its white square's side (m) on a machine of `reach`
    (m): 0.3 and 0.5 on one of the EX3500's 15.5 m, scaled with it."""
    return 0.3 * reach / 15.5, 0.5 * reach / 15.5


def observe_camera(machine: Machine, plan: DigMotion, boxes: np.ndarray, normals: np.ndarray,
                   camera: FieldCamera, frames: np.ndarray,
                   solids: Solids | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Marker pixels (F, M, 2), visibility (F, M) and link poses (F, L, 4, 4) at `frames`
    (hidden by `solids` where given, else by the links' `boxes`)."""
    times = camera.times(frames)
    poses = machine.link_poses(plan.joints(times), plan.world_from_base(times))
    lens = (camera.cam_from_world(times), camera.camera.matrix, camera.camera.distortion, camera.camera.size)
    if solids is not None:
        uv, seen = solids_in_view(machine, solids, normals, poses, *lens, machine.marker_positions[:, None])
        return uv[:, :, 0], seen[..., 0], poses
    uv, seen = visible_markers(machine, boxes, normals, poses, *lens)
    return uv, seen, poses


def marker_pixels_at(machine: Machine, plan: DigMotion, camera: FieldCamera, at: np.ndarray) -> np.ndarray:
    """Pixels (F, M, 2) of each marker m at its own fractional frame `at` (F, M) of `camera`."""
    n_frames, n_markers = at.shape
    times = camera.times(at.ravel())
    poses = machine.link_poses(plan.joints(times), plan.world_from_base(times))  # (F M, L, 4, 4)
    index = np.tile(np.arange(n_markers), n_frames)
    on_link = poses[np.arange(len(index)), machine.marker_links[index]]  # (F M, 4, 4)
    # row vectors times transposed rotations, the arithmetic of `visible_markers`: a marker
    # read at its frame's own time lands on the very pixel a global shutter gives it
    points = machine.marker_positions[index][:, None]  # (F M, 1, 3)
    world = points @ np.swapaxes(on_link[:, :3, :3], -1, -2) + on_link[:, None, :3, 3]
    cams = camera.cam_from_world(times)
    p = world @ np.swapaxes(cams[:, :3, :3], -1, -2) + cams[:, None, :3, 3]
    uv = project_cam(p[:, 0], camera.camera.matrix, camera.camera.distortion)
    return uv.reshape(n_frames, n_markers, 2)


def rolling_marker_pixels(machine: Machine, plan: DigMotion, camera: FieldCamera, frames: np.ndarray,
                          readout: float) -> np.ndarray:
    """Marker pixels (F, M, 2) of `camera` at `frames` (F,) under a rolling shutter reading
    its rows over `readout` of the frame interval (`mocap.synthetic.shutter`)."""
    frames = np.broadcast_to(np.asarray(frames, dtype=float)[:, None], (len(frames), len(machine.marker_names)))
    height = camera.camera.size[1]
    uv, _ = rolling_pixels(lambda at: marker_pixels_at(machine, plan, camera, at), frames, height, readout)
    return uv


def make_session(machine: Machine, machine_ref: str | None = None, options: SessionOptions | None = None,
                 **overrides) -> SyntheticSession:
    """Plan a session of `machine` and compute its truth; deterministic for a seed.

    `machine_ref` is how session.toml names the model (a shipped name or a path);
    keyword `overrides` set `SessionOptions` fields, e.g. ``n_cameras=3, n_cycles=4, seed=7``.
    """
    options = SessionOptions(**{**asdict(options or SessionOptions()), **overrides})
    rng = np.random.default_rng(options.seed)
    plan = plan_session(machine, options.n_cycles, rng, classes=options.classes,
                        redirect_probability=options.redirect_probability, reactive=options.reactive,
                        bounce=options.bounce, hold=options.hold)
    coarse = np.arange(0.0, plan.duration, 0.5)
    try:
        check_limits(machine, plan.joints(coarse))
    except ValueError as exc:  # a model whose linkage cannot carry the bucket to the truck
        raise InputError(f"the planned session does not suit this machine: {exc}",
                         path=machine_ref or machine.name) from None
    boxes = link_boxes(machine)
    poses = machine.link_poses(plan.joints(coarse), plan.world_from_base(coarse))
    corners = np.array([box_corners(box) for box in boxes])  # (L, 8, 3)
    working = (np.einsum("tlij,lkj->tlki", poses[..., :3, :3], corners) + poses[:, :, None, :3, 3]).reshape(-1, 3)
    reach = float(np.linalg.norm(plan.chain.offsets, axis=1).sum())
    cameras = place_cameras(options.n_cameras, working, reach, (plan.pile.azimuth, plan.truck.azimuth),
                            plan.duration, rng, size=options.size, distortion=options.distortion,
                            shake_deg=options.shake_deg, fps=options.fps)
    normals = marker_normals(machine, boxes)
    solids = None
    if options.shapes == "meshes":
        solids, normals = machine_solids(machine, np.random.default_rng([options.seed, 9]), marker_sizes(reach)[1])

    reference = cameras[0]
    frames = np.arange(reference.frames)
    times = reference.times(frames)
    joints = plan.joints(times)
    check_limits(machine, joints)
    world_from_base = plan.world_from_base(times)
    motion = Motion(machine.joint_names, machine.point_names, frames, times, joints,
                    machine.points(joints, world_from_base), machine.bucket_angles(joints, world_from_base),
                    extra=base_columns(world_from_base))
    markers = machine.markers(joints, world_from_base)

    # each true row's score: how much of the marker's painted square is in view (1: all)
    squares, disks = marker_outlines(machine, normals, *marker_sizes(reach), n_points=16)
    outline = square_outline(squares)
    # with solids: a grid over the square and the disk's outline (`marker_test_points`)
    disk_outline = marker_test_points(squares, disks)
    parts, views = [], np.zeros(markers.shape[:2], dtype=int)
    names = np.asarray(machine.marker_names, dtype=object)
    for camera in cameras:
        own = np.arange(camera.frames)
        uv, seen, poses = observe_camera(machine, plan, boxes, normals, camera, own, solids)
        lens = (camera.cam_from_world(camera.times(own)), camera.camera.matrix, camera.camera.distortion,
                camera.camera.size)
        if solids is not None:
            cover = np.mean(solids_in_view(machine, solids, normals, poses, *lens, disk_outline)[1], axis=-1)
        else:
            cover = marker_cover(machine, boxes, normals, poses, *lens, outline)
        if options.readout > 0:  # seen as at the frame's time; where: as its row is read
            uv = rolling_marker_pixels(machine, plan, camera, own, options.readout)
        f, m = np.nonzero(seen)
        parts.append(Tracks.from_rows(np.full(len(f), camera.name, dtype=object), own[f], names[m], uv[f, m],
                                      time=camera.times(own[f]), score=cover[f, m]))
        at_reference = (times - camera.time_offset) * camera.fps  # this camera's (fractional) frames
        _, seen_ref, _ = observe_camera(machine, plan, boxes, normals, camera, at_reference, solids)
        views += seen_ref
    return SyntheticSession(machine, machine_ref or machine.name, options, plan, tuple(cameras), motion,
                            concatenate(parts), markers, views, boxes, normals, solids)


def write_truth(session: SyntheticSession, root: str | Path, machine_path: Path | None = None, look=None) -> None:
    """Write session.toml and truth/ under `root`; videos are named, not written here.

    `machine_path`: a model file outside the shipped ones, copied into the folder; `look`
    the videos' `mocap.synthetic.looks.Look`, written into scene.toml.
    """
    root = Path(root)
    truth = root / "truth"
    machine_entry = session.machine_ref
    if machine_path is not None and machine_path.resolve().parent != MACHINES_DIR.resolve():
        write_text(root / "machine.toml", machine_path.read_text(encoding="utf-8"))
        machine_entry = "machine.toml"
    elif machine_path is not None:
        machine_entry = machine_path.stem
    config = SessionConfig(
        machine_entry,
        tuple(SessionCamera(c.name, f"videos/{c.name}.mp4", c.fps) for c in session.cameras),
        {"calibration_frame": 0, "synthetic_seed": session.options.seed},
    )
    save_session_config(config, root / "session.toml")
    save_calibration(session.calibration, truth / "cameras.toml")
    save_motion(session.motion, session.machine, truth / "motion.csv")
    save_tracks(session.tracks, truth / "tracks.csv")
    f, m = np.meshgrid(session.motion.frame, np.arange(len(session.machine.marker_names)), indexing="ij")
    save_points(Points(f.ravel(), np.asarray(session.machine.marker_names, dtype=object)[m.ravel()],
                       session.markers.reshape(-1, 3), np.zeros(f.size), session.views.ravel()),
                truth / "markers.csv")
    save_session_cycles(session, truth / "cycles.csv")
    scene = scene_table(session)
    if look is not None:
        scene["look"] = look.table()
    write_text(truth / "scene.toml", toml_writer.dumps(scene))


def summary(session: SyntheticSession) -> str:
    """A few lines saying what the session holds."""
    cycles = ", ".join(f"{c.label} ({c.scaling}, redirection {c.redirection})" for c in session.plan.cycles)
    lines = [f"{session.machine_ref}: {len(session.plan.cycles)} cycles in {session.plan.duration:.1f} s: {cycles}"]
    for camera in session.cameras:
        rows = session.tracks.of_camera(camera.name)
        lines.append(
            f"  {camera.name}: {camera.fps:g} fps, offset {camera.time_offset:+.3f} s, {camera.frames} frames, "
            f"{np.linalg.norm(camera.camera.center[:2]):.0f} m away, {len(rows) / camera.frames:.1f} markers seen a frame"
        )
    return "\n".join(lines)


def save_session_cycles(session: SyntheticSession, path: Path) -> None:
    """truth/cycles.csv: one row per dig cycle; frames are the reference camera's; scale_x,
    scale_z the dig's stretch against its class's general shape (`Cycle.stretch`); the
    redirection's lift (m) and turn (deg), 0 without one."""
    fps = session.cameras[0].fps
    rows = []
    for c in session.plan.cycles:
        times = (c.start, c.end, c.dig_start, c.dig_end)
        frames = [int(round(t * fps)) for t in times]
        rows.append((c.index, c.label, c.scaling, f"{c.stretch[0]:.4f}", f"{c.stretch[1]:.4f}", c.redirection,
                     *frames, *(f"{t:.4f}" for t in times), f"{c.lift:.4f}", f"{np.degrees(c.turn):.3f}"))
    save_cycles(rows, path)


def scene_table(session: SyntheticSession) -> dict:
    """The scene's truth beyond the cameras and the motion (degrees, metres)."""
    pile, truck = session.plan.pile, session.plan.truck
    options = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(session.options).items()}
    return {
        "machine": session.machine_ref,
        "duration": session.plan.duration,
        "pile": {"toe": pile.toe, "slope_deg": float(np.degrees(pile.slope)), "height": pile.height,
                 "azimuth_deg": float(np.degrees(pile.azimuth)), "width": pile.width},
        "truck": {"azimuth_deg": float(np.degrees(truck.azimuth)), "distance": truck.distance,
                  "height": truck.height},
        "options": options,
    }
