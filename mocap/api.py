"""mocap's Python API: the command line's chain as functions of typed objects.

    machine = mocap.load_machine("hitachi_ex3500")
    obs = mocap.read_tracks("calibration/labels.csv")
    cams = mocap.calibrate(machine, obs, size=(1920, 1080), frame=0)
    tracks = mocap.track("videos/cam1.mp4", machine, cams, camera="cam1")
    motion = mocap.fit(machine, cams, tracks)             # .to_pandas(), .to_arrow(), .write(path)
    cycles = mocap.analyze(machine, motion)               # .to_pandas(), .write(dir)
    mocap.Session("sessions/day1").run()

Each function calls the same stage function as its sub-command (with the command's
defaults), without touching a file unless asked (`.write`). Errors a user can cause raise
`mocap.InputError`. `import mocap` loads this module only when one of these names is used.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa

from mocap.core.calibration import Calibration
from mocap.core.machine import Machine
from mocap.core.points import Points
from mocap.core.tracks import Tracks, concatenate
from mocap.errors import InputError
from mocap.io.cameras_toml import load_calibration, save_calibration
from mocap.io.machine_toml import load_machine as _load_machine
from mocap.io.machine_toml import save_machine
from mocap.io.points_csv import load_points, points_columns, save_points
from mocap.io.tracks_csv import load_tracks, save_tracks, tracks_columns

__all__ = [
    "Cameras", "Cycles", "InputError", "Motion", "PointsTable", "Refined", "Session", "analyze", "calibrate",
    "concat_tracks", "export", "fit", "load_machine", "motions", "read_calibration", "read_motion", "read_points",
    "read_tracks", "refine", "save_model", "sync", "track", "tracks_to_arrow", "triangulate", "view", "write_tracks",
]


def _to_pandas(table: pa.Table):
    try:
        import pandas  # noqa: F401  (pyarrow's to_pandas needs it)
    except ImportError:
        raise ImportError("to_pandas() needs pandas, which is not installed: `pip install pandas`, or use "
                          ".to_arrow() (a pyarrow Table)") from None
    return table.to_pandas()


def _paths(path_or_paths) -> list[str]:
    if isinstance(path_or_paths, (str, Path)):
        return [str(path_or_paths)]
    return [str(p) for p in path_or_paths]


# --- readers and writers ----------------------------------------------------------------------


def load_machine(name_or_path: str | Path) -> Machine:
    """A machine model: the name of a shipped one ("hitachi_ex3500") or a TOML path."""
    return _load_machine(name_or_path)


def read_tracks(path_or_paths) -> Tracks:
    """2-D observations / tracks from one or several CSV (or Parquet) files."""
    return load_tracks(_paths(path_or_paths))


def write_tracks(tracks: Tracks, path: str | Path) -> None:
    """Write tracks as CSV (or Parquet, by the `.parquet` extension)."""
    save_tracks(tracks, path)


def tracks_to_arrow(tracks: Tracks) -> pa.Table:
    """The tracks as a table with the file's columns."""
    columns = tracks_columns(tracks)
    return pa.table({**columns, "camera": columns["camera"].astype(str), "marker": columns["marker"].astype(str)})


class Cameras(Calibration):
    """A camera calibration (mocap.core.calibration.Calibration) that writes itself."""

    @classmethod
    def of(cls, calibration: Calibration) -> Cameras:
        return cls(calibration.cameras, calibration.extras, calibration.metadata)

    def write(self, path: str | Path) -> None:
        """Write the calibration TOML (atomically)."""
        save_calibration(self, path)


def read_calibration(path: str | Path) -> Cameras:
    """A camera calibration TOML (ours, or anipose's)."""
    return Cameras.of(load_calibration(path))


@dataclass(frozen=True)
class PointsTable:
    """Triangulated points (`points`: mocap.core.points.Points) and the stage's report."""

    points: Points
    report: str = ""

    def __len__(self) -> int:
        return len(self.points)

    def to_arrow(self) -> pa.Table:
        columns = points_columns(self.points)
        return pa.table({**columns, "marker": columns["marker"].astype(str)})

    def to_pandas(self):
        return _to_pandas(self.to_arrow())

    def write(self, path: str | Path) -> None:
        save_points(self.points, path)


def read_points(path: str | Path) -> PointsTable:
    return PointsTable(load_points(path))


@dataclass(frozen=True)
class Motion:
    """A machine's motion (`motion`: mocap.core.motion.Motion, radians and metres inside)
    with its model; the table has the motion file's columns and units (degrees, metres)."""

    motion: object
    machine: Machine
    report: str = ""

    def __len__(self) -> int:
        return len(self.motion)

    def columns(self) -> dict[str, np.ndarray]:
        from mocap.io.motion_csv import motion_columns

        return motion_columns(self.motion, self.machine)

    def to_arrow(self) -> pa.Table:
        return pa.table(self.columns())

    def to_pandas(self):
        return _to_pandas(self.to_arrow())

    def write(self, path: str | Path) -> None:
        """The motion CSV (or Parquet, by the `.parquet` extension)."""
        from mocap.io.motion_csv import save_motion

        save_motion(self.motion, self.machine, path)


def read_motion(path: str | Path, machine: Machine) -> Motion:
    """A motion CSV (or Parquet) of `machine`."""
    from mocap.io.motion_csv import load_motion

    return Motion(load_motion(path, machine), machine)


@dataclass(frozen=True)
class Cycles:
    """The dig cycles of a motion (`analysis`: mocap.analysis.core.Analysis); the table is
    cycles.csv's."""

    analysis: object
    machine: Machine

    def __len__(self) -> int:
        return len(self.analysis.table["cycle"])

    def to_arrow(self) -> pa.Table:
        return pa.table({name: np.asarray(values) if np.asarray(values).dtype.kind != "O"
                         else np.asarray(values).astype(str) for name, values in self.analysis.table.items()})

    def to_pandas(self):
        return _to_pandas(self.to_arrow())

    def write(self, folder: str | Path) -> None:
        """cycles.csv, report.html and templates.toml into `folder`."""
        from mocap.analysis.stage import write_analysis

        write_analysis(self.analysis, self.machine, folder, f"Dig cycles of {self.machine.name}")


# --- the stages ---------------------------------------------------------------------------------


def calibrate(machine: Machine, observations: Tracks, size, frame: int | None = None, *,
              per_camera: bool = False, distortion: str = "auto", intrinsics: str | Path | None = None,
              options=None) -> Cameras:
    """Cameras calibrated against the machine's markers at `frame` (default: the first):
    `size` (w, h) of every camera or {camera: (w, h)}; `distortion` "auto" (chosen by the
    data, as the command's default), "none", "k1", "k1k2" or "full"; `intrinsics` a file of
    known intrinsics; `options` a mocap.calibration.solve.CalibrationOptions (overrides
    `per_camera`)."""
    from mocap.calibration.solve import CalibrationOptions
    from mocap.calibration.stage import calibrate_cameras
    from mocap.io.intrinsics import load_intrinsics

    sizes = {name: tuple(value) for name, value in size.items()} if isinstance(size, dict) else {None: tuple(size)}
    if options is None:
        options = CalibrationOptions(per_camera=per_camera, distortion="none" if distortion == "auto" else distortion)
    known = load_intrinsics(intrinsics) if intrinsics is not None else None
    calibrated = calibrate_cameras(machine, observations, sizes, frame, options, distortion == "auto", known,
                                   intrinsics)
    return Cameras.of(calibrated.calibration)


def track(video: str | Path, machine: Machine, cameras: Calibration | None = None, camera: str | None = None, *,
          labels: Tracks | None = None, start: int = 0, stop: int | None = None, options=None) -> Tracks:
    """One camera's labelled 2-D marker tracks from its video; `labels` the first frame's
    marker pixels (else found by fitting the model, or by the tags)."""
    from mocap.tracking.stage import TrackRequest, track_video
    from mocap.tracking.tracker import TrackOptions

    request = TrackRequest(Path(video), machine.name, None, camera, start=start, stop=stop,
                           options=options or TrackOptions())
    return track_video(request, machine, cameras, labels).tracks


def sync(machine: Machine, cameras: Calibration, tracks: Tracks, *, fps: dict | None = None,
         max_offset: float = 10.0) -> Cameras:
    """The cameras with each one's time_offset and fps, from the machine's motion; `fps`
    {camera: frames per second} where the calibration and the tracks give none."""
    from mocap.clocks.stage import sync_cameras

    synced, _ = sync_cameras(machine, cameras, tracks, [f"{k}={v}" for k, v in (fps or {}).items()], max_offset)
    return Cameras.of(synced)


@dataclass(frozen=True)
class Refined:
    """`refine`'s result: the refined cameras and the model (its markers moved with `markers`)."""

    cameras: Cameras
    machine: Machine
    report: str


def refine(machine: Machine, cameras: Calibration, tracks: Tracks, *, markers: bool = False,
           distortion: str = "auto", options=None) -> Refined:
    """Bundle adjustment of the cameras (and with `markers` the marker positions) over many
    frames; `options` a mocap.reconstruct.refine.RefineOptions (overrides the others)."""
    from mocap.reconstruct.refine import RefineOptions
    from mocap.reconstruct.stage import refine_cameras

    options = options or RefineOptions(markers=markers, distortion=distortion)
    refined = refine_cameras(machine, cameras, tracks, options)
    return Refined(Cameras.of(refined.calibration), refined.machine, refined.report(None))


def triangulate(cameras: Calibration, tracks: Tracks, options=None, *, max_noise_px: float | None = None) -> PointsTable:
    """3-D marker positions in every reference frame seen by two cameras or more. Refused
    (InputError) when one camera's views contradict the others', or the views disagree 5
    times beyond the noise the tracks show by themselves; with `max_noise_px`, also when
    the views imply a pixel noise beyond it, as `mocap triangulate --max-noise-px` does."""
    from mocap.reconstruct.stage import triangulate as triangulate_points
    from mocap.reconstruct.triangulate import TriangulateOptions

    if max_noise_px is not None and not max_noise_px > 0:
        raise InputError(f"max_noise_px {max_noise_px}: give a positive number of pixels")
    result = triangulate_points(cameras, tracks, options or TriangulateOptions(), max_noise_px)
    return PointsTable(result.points, result.report(None))


def fit(machine: Machine, cameras: Calibration, tracks: Tracks, *, smooth: bool = True, fit_options=None,
        smooth_options=None) -> Motion:
    """The machine's motion: the model fitted to every camera's tracks in every frame,
    smoothed (unless `smooth` is False), as `mocap fit` writes it."""
    from mocap.reconstruct.smooth import SmoothOptions
    from mocap.reconstruct.stage import fit_motion

    fitted = fit_motion(machine, cameras, tracks, fit_options, (smooth_options or SmoothOptions()) if smooth else None)
    return Motion(fitted.motion, machine, fitted.report(None))


def analyze(machine: Machine, motion: Motion) -> Cycles:
    """Dig cycles, phases, classes, similarity and templates of a digging machine's motion."""
    from mocap.analysis.stage import analyze_motion

    return Cycles(analyze_motion(motion.motion if isinstance(motion, Motion) else motion), machine)


def view(session: str | Path, save: str | Path | None = None, **files) -> str:
    """Record the Rerun replay of a session folder (to results/session.rrd, or `save`);
    `files` override the session's (machine, calibration, motion, points, tracks, cycles)."""
    from mocap.viewer.inputs import ReplayFiles
    from mocap.viewer.replay import Sinks
    from mocap.viewer.stage import run_view

    return run_view(ReplayFiles(**files), session, Sinks(save=Path(save)) if save is not None else Sinks())


def export(fmt: str, source: str | Path, out: str | Path, calibration: str | Path | None = None) -> str:
    """`mocap export`: "c3d" / "trc" (a session's markers), "urdf" (a machine model file),
    "colmap" (a session as a COLMAP model); returns the report."""
    from mocap.interchange import stage

    if fmt == "urdf":
        return stage.export_urdf(source, out)
    if fmt == "colmap":
        return stage.export_colmap(source, out, calibration)
    if fmt in ("c3d", "trc"):
        return stage.export_markers(source, fmt, out)
    raise InputError(f"export format {fmt!r}: give c3d, trc, urdf or colmap")


# --- a session folder -----------------------------------------------------------------------------


class Session:
    """A session folder (DESIGN.md's layout) with the stages as methods; each reads and
    writes the folder's files exactly as `mocap run` does and returns the stage's report."""

    def __init__(self, path: str | Path) -> None:
        from mocap.io.session import Session as Folder

        self.folder = Folder.open(path)

    @classmethod
    def create(cls, path: str | Path, machine: str | Path, cameras, calibration_frame: int = 0) -> Session:
        """Write `path`/session.toml: `machine` a shipped model's name or a TOML path, `cameras`
        (name, video path, fps) in order (the first is the reference clock)."""
        from mocap.io.session_toml import SessionCamera, SessionConfig, save_session_config

        root = Path(path)
        root.mkdir(parents=True, exist_ok=True)
        machine = str(Path(machine).resolve()) if Path(machine).suffix == ".toml" else str(machine)
        config = SessionConfig(machine, tuple(SessionCamera(str(n), str(v), float(f)) for n, v, f in cameras),
                               {"calibration_frame": int(calibration_frame)})
        save_session_config(config, root / "session.toml")
        return cls(root)

    @property
    def root(self) -> Path:
        return self.folder.root

    @property
    def camera_names(self) -> tuple[str, ...]:
        return self.folder.camera_names

    def write_cameras(self, cameras: Calibration, refined: bool = False) -> None:
        """Write the session's calibration (calibration/cameras.toml, or refined.toml)."""
        path = self.folder.refined_calibration_path if refined else self.folder.calibration_path
        Cameras.of(cameras).write(path)

    def _steps(self, refine: bool = False, view: bool = True, labels: str | Path | None = None) -> dict:
        from mocap.orchestration.pipeline import RunOptions, session_steps

        options = RunOptions(Path(labels) if labels else None, refine, view)
        return {step.name: step for step in session_steps(self.folder, options)}

    def _run(self, name: str, **options) -> str:
        steps = self._steps(**options)
        if name not in steps:
            raise InputError(f"the session has no {name} stage (one camera, a rigid object or no bucket)",
                             path=self.root)
        return steps[name].call()

    def machine(self) -> Machine:
        return self.folder.machine()

    def calibrate(self, labels: str | Path | None = None) -> str:
        return self._run("calibrate", labels=labels)

    def track(self, camera: str | None = None) -> str:
        names = [camera] if camera else list(self.folder.camera_names)
        return "\n".join(self._run(f"track {name}") for name in names)

    def sync(self) -> str:
        return self._run("sync")

    def refine(self) -> str:
        return self._run("refine", refine=True)

    def triangulate(self, refined: bool = False) -> str:
        return self._run("triangulate", refine=refined)

    def fit(self, refined: bool = False) -> str:
        return self._run("fit", refine=refined)

    def analyze(self) -> str:
        return self._run("analyze")

    def view(self, refined: bool = False) -> str:
        return self._run("view", refine=refined)

    def run(self, refine: bool = False, view: bool = True, labels: str | Path | None = None) -> int:
        """The whole chain, as `mocap run` (each stage's report printed); 0, or 2 when a stage
        refused its input (its one line on stderr)."""
        from mocap.orchestration.pipeline import RunOptions, run_session

        return run_session(self.root, RunOptions(Path(labels) if labels else None, refine, view))

    def cameras(self, refined: bool = False) -> Cameras:
        path = self.folder.refined_calibration_path if refined else self.folder.calibration_path
        return read_calibration(path)

    def tracks(self) -> Tracks:
        return read_tracks([self.folder.tracks_path(c) for c in self.folder.camera_names])

    def motion(self) -> Motion:
        """results/motion.csv (`motions` puts several sessions' into one table)."""
        return read_motion(self.folder.motion_path, self.machine())


def motions(sessions, column: str = "session") -> pa.Table:
    """The motion of several sessions as one table, with a column naming each row's session
    (its folder's name); `.to_pandas()` of it gives one DataFrame."""
    tables = []
    for path in sessions:
        session = path if isinstance(path, Session) else Session(path)
        table = session.motion().to_arrow()
        tables.append(table.append_column(column, pa.array([session.root.name] * len(table))))
    return pa.concat_tables(tables, promote_options="default")


def save_model(machine: Machine, path: str | Path) -> None:
    """Write a machine model TOML (e.g. `Refined.machine` with its markers moved)."""
    save_machine(machine, path)


def concat_tracks(parts) -> Tracks:
    """Several cameras' tracks as one."""
    return concatenate(list(parts))
