"""The files a replay is made from, found in a session folder or given one by one, and read.

A session folder supplies every path it has (DESIGN.md layout): the machine named in
session.toml, calibration/cameras.toml, results/motion.csv, results/points.csv,
tracks/<camera>.csv, the videos listed in session.toml, results/cycles.csv. Paths given
explicitly take precedence; optional files that are absent are left out.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mocap.errors import InputError
from mocap.io.cameras_toml import load_calibration
from mocap.io.cycles_csv import load_cycles
from mocap.io.machine_toml import load_machine
from mocap.io.motion_csv import load_motion
from mocap.io.points_csv import load_points
from mocap.io.session import Session
from mocap.io.tracks_csv import load_tracks
from mocap.viewer.replay import Replay

log = logging.getLogger(__name__)

DEFAULT_FPS = 30.0


@dataclass(frozen=True)
class ReplayFiles:
    """Paths of a replay's inputs; `videos` {camera: path}; `fps` {camera: frames per second}
    known from the session, used where the calibration gives none."""

    machine: str | Path | None = None
    calibration: Path | None = None
    motion: Path | None = None
    points: Path | None = None
    tracks: tuple[Path, ...] = ()
    videos: dict = field(default_factory=dict)
    cycles: Path | None = None
    fps: dict = field(default_factory=dict)

    def merged_over(self, base: ReplayFiles) -> ReplayFiles:
        """These paths where given, else `base`'s."""
        return ReplayFiles(
            machine=self.machine or base.machine,
            calibration=self.calibration or base.calibration,
            motion=self.motion or base.motion,
            points=self.points or base.points,
            tracks=self.tracks or base.tracks,
            videos={**base.videos, **self.videos},
            cycles=self.cycles or base.cycles,
            fps={**base.fps, **self.fps},
        )


def session_files(session: Session) -> ReplayFiles:
    """The replay's inputs present in a session folder."""
    config = session.config()

    def present(path: Path) -> Path | None:
        return path if path.is_file() else None

    videos = {}
    for camera in config.cameras:
        path = session.video_path(camera.name)
        if path.is_file():
            videos[camera.name] = path
        else:
            log.info("camera %s: no video at %s", camera.name, path)
    tracks = tuple(p for p in (session.tracks_path(c.name) for c in config.cameras) if p.is_file())
    return ReplayFiles(
        machine=session.machine_path(),
        calibration=session.calibration_path,
        motion=session.motion_path,
        points=present(session.points_path),
        tracks=tracks,
        videos=videos,
        cycles=present(session.results_dir / "cycles.csv"),
        fps={c.name: c.fps for c in config.cameras},
    )


def load_replay(files: ReplayFiles) -> Replay:
    """Read every input of a replay; a missing required one or a bad file is an InputError."""
    missing = [name for name in ("machine", "calibration", "motion") if getattr(files, name) is None]
    if missing:
        raise InputError(
            f"no {', '.join(missing)} given; name a session folder or pass --machine, "
            "--calibration and --motion"
        )
    machine = load_machine(files.machine)
    calibration = load_calibration(files.calibration)
    check_machine(calibration, machine, files)
    if not Path(files.motion).is_file():
        raise InputError("file not found; run the reconstruction first or pass --motion", path=files.motion)
    motion = load_motion(files.motion, machine)
    unknown = sorted(set(files.videos) - set(calibration.names))
    if unknown:
        raise InputError(
            f"no camera {', '.join(unknown)} in the calibration (it has {', '.join(calibration.names)}); "
            "check the NAME in --video NAME=PATH",
            path=files.calibration,
        )
    return Replay(
        machine=machine,
        calibration=calibration,
        motion=motion,
        fps=camera_fps(calibration, files.fps, files.calibration),
        points=None if files.points is None else load_points(files.points),
        tracks=load_tracks(list(files.tracks)) if files.tracks else None,
        videos=dict(files.videos),
        cycles=None if files.cycles is None else load_cycles(files.cycles),
    )


def check_machine(calibration, machine, files: ReplayFiles) -> None:
    """The calibration's metadata names the machine it was made for (its name or model file)."""
    named = calibration.metadata.get("machine")
    known = {machine.name, str(files.machine), Path(str(files.machine)).stem}
    if isinstance(named, str) and named not in known and Path(named).stem not in known:
        raise InputError(
            f"calibrated for machine {named!r}, not {machine.name!r}; pass the matching --machine",
            path=files.calibration,
        )


def camera_fps(calibration, known: dict, path: Path | None = None) -> np.ndarray:
    """(C,) frame rates: the calibration's `fps`, else the session's, else 30 (logged).
    Each camera's `time_offset`, if given, must be a number too."""
    fps = []
    for camera, extra in zip(calibration.cameras, calibration.extras):
        where = f"camera {camera.name}"
        value = extra.get("fps", known.get(camera.name))
        if value is None:
            log.warning("camera %s: frame rate unknown, assuming %g fps", camera.name, DEFAULT_FPS)
            value = DEFAULT_FPS
        if not _number(value) or not value > 0:
            raise InputError(f"fps must be a positive number, got {value!r}", path=path, where=where)
        offset = extra.get("time_offset", 0.0)
        if not _number(offset) or not np.isfinite(offset):
            raise InputError(f"time_offset must be a number of seconds, got {offset!r}", path=path, where=where)
        fps.append(float(value))
    return np.array(fps)


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def with_session(files: ReplayFiles, session_dir: str | Path | None) -> ReplayFiles:
    """`files` completed from the session folder, if one is given."""
    if session_dir is None:
        return files
    return files.merged_over(session_files(Session.open(session_dir)))

