"""The replay stage: gather a session's results, log them to Rerun, save and/or show them.

`record_replay` logs a `Replay` into a recording stream; `run_replay` opens the sinks
(an .rrd file written atomically, a running viewer, a served web viewer, a spawned viewer)
and records into them.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rerun as rr

from mocap.core.calibration import Calibration
from mocap.core.cycles import Cycles
from mocap.core.machine import Machine
from mocap.core.motion import Motion
from mocap.core.points import Points
from mocap.core.tracks import Tracks
from mocap.errors import InputError
from mocap.io.atomic import atomic_path
from mocap.progress import progress
from mocap.viewer import record, scene
from mocap.viewer.blueprint import default_blueprint
from mocap.viewer.video import load_video

log = logging.getLogger(__name__)

APPLICATION_ID = "mocap"
TIP = "bucket_tip"


@dataclass(frozen=True)
class Replay:
    """What a replay shows. `fps` (C,) each camera's frame rate, in calibration order;
    `videos` {camera name: mp4 path}; `cycles` None for a single trail over all frames."""

    machine: Machine
    calibration: Calibration
    motion: Motion
    fps: np.ndarray
    points: Points | None = None
    tracks: Tracks | None = None
    videos: dict = field(default_factory=dict)
    cycles: Cycles | None = None

    def __post_init__(self) -> None:
        fps = np.asarray(self.fps, dtype=float)
        if fps.shape != (len(self.calibration.cameras),):
            raise ValueError(f"Replay.fps: expected shape ({len(self.calibration.cameras)},), got {fps.shape}")
        object.__setattr__(self, "fps", fps)

    @property
    def tip(self) -> str | None:
        """The named point whose trail is drawn: the bucket tip, else the first point."""
        names = self.motion.point_names
        return TIP if TIP in names else (names[0] if names else None)

    def trails(self) -> list[scene.Trail]:
        if self.tip is None:
            return []
        cycles = Cycles.whole(self.motion.frame) if self.cycles is None else self.cycles
        return scene.trails(self.motion, self.tip, cycles.start, cycles.end, cycles.name, cycles.label)

    def phases(self) -> np.ndarray | None:
        """The dig-cycle phase of every motion frame (F,), None without phases in the cycles."""
        if self.cycles is None or self.cycles.phases is None:
            return None
        return scene.phase_series(self.motion, self.cycles.start, self.cycles.end, self.cycles.phases)


@dataclass(frozen=True)
class ReplaySummary:
    frames: int
    cameras: int
    videos: tuple[str, ...]
    trails: int


@dataclass(frozen=True)
class Sinks:
    """Where the recording goes: `save` an .rrd path; `connect` a viewer URL ("" for the
    default local viewer); `serve` a web viewer from this process; `spawn` a native viewer."""

    save: Path | None = None
    connect: str | None = None
    serve: bool = False
    spawn: bool = False

    @property
    def any(self) -> bool:
        return self.save is not None or self.connect is not None or self.serve or self.spawn


def record_replay(rec: rr.RecordingStream, replay: Replay) -> ReplaySummary:
    """Log everything the replay shows into `rec` (a progress bar on a terminal)."""
    machine, calibration, motion = replay.machine, replay.calibration, replay.motion
    offsets = calibration.time_offsets
    trails = replay.trails()
    with progress(total=4 + len(calibration.cameras), desc="replay", unit="part") as bar:
        record.log_world(rec, machine)
        links = scene.link_series(machine, motion)
        record.log_machine(rec, machine, motion, links)
        bar.update()
        record.log_markers(rec, machine, motion, links, replay.points, replay.fps[0])
        record.log_points(rec, motion)
        bar.update()
        record.log_trails(rec, trails)
        record.log_cameras(rec, calibration, frustum_depth(calibration))
        bar.update()
        with_video = []
        for k, camera in enumerate(calibration.cameras):
            path = replay.videos.get(camera.name)
            video = None if path is None else load_video(path, camera.name)
            if video is not None:
                record.log_video(rec, camera.name, video, motion, replay.fps[k], offsets[k], camera.size)
                with_video.append(camera.name)
            if replay.tracks is not None:
                clocks = (replay.fps[k], offsets[k], replay.fps[0], offsets[0])
                series = scene.track_series(replay.tracks, camera.name, machine.marker_names, *clocks)
                record.log_tracks(rec, series, camera.name)
            bar.update()
        record.log_plots(rec, machine, motion, replay.tip)
        phases = replay.phases()
        if phases is not None:
            record.log_phases(rec, motion, phases)
        bar.update()
    return ReplaySummary(len(motion), len(calibration.cameras), tuple(with_video), len(trails))


def frustum_depth(calibration: Calibration) -> float:
    """Depth (m) of the drawn camera frustums: a tenth of the cameras' mean distance to the base."""
    distances = [np.linalg.norm(camera.center) for camera in calibration.cameras]
    return max(0.1, 0.1 * float(np.mean(distances)))


GROUP_TITLES = {"joints_m": "joints (m)", "uncertainty": "uncertainty (sd, deg)",
                "uncertainty_m": "uncertainty (sd, m)", "base": "base position (m)",
                "base_angles": "base attitude (deg)"}


def replay_blueprint(replay: Replay):
    fixed = ("joints", "bucket", "speed")
    groups = {}
    for s in scene.plot_series(replay.machine, replay.motion, replay.tip):
        if s.group not in fixed and s.group not in groups:
            groups[s.group] = GROUP_TITLES.get(s.group, s.label)
    eye = scene.working_view(replay.motion, replay.tip)
    return default_blueprint(replay.calibration.names, replay.trails(), list(groups.items()), eye,
                             replay.phases() is not None, fps=float(replay.fps[0]))


def run_replay(replay: Replay, sinks: Sinks, on_serving: Callable[[str], None] | None = None) -> ReplaySummary:
    """Record `replay` into `sinks`. The .rrd file appears only once complete; with `serve`,
    tells `on_serving` where the web viewer is (default: the log) and keeps serving until
    interrupted."""
    if not sinks.any:
        raise ValueError("no sink: give a path to save, a viewer to connect to, serve or spawn")
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=uuid.uuid4())
    blueprint = replay_blueprint(replay)
    if sinks.save is None:
        summary = _record_live(rec, replay, sinks, blueprint)
    else:
        with atomic_path(sinks.save) as tmp:
            summary = _record_live(rec, replay, sinks, blueprint, file=tmp)
        log.info("saved the replay to %s", sinks.save)
    if sinks.serve:
        (on_serving or log.warning)(SERVING)
        _serve_until_interrupted()
    return summary


def _record_live(rec, replay: Replay, sinks: Sinks, blueprint, file: Path | None = None) -> ReplaySummary:
    targets = []
    if file is not None:
        targets.append(rr.FileSink(file))
    if sinks.spawn:
        rr.spawn(connect=False, executable_path=rerun_executable())
        targets.append(rr.GrpcSink())
    if sinks.connect is not None:
        _check_viewer(sinks.connect or DEFAULT_VIEWER)
        targets.append(rr.GrpcSink(sinks.connect or None))
    server = None
    if sinks.serve:
        server = rr.GrpcServerSink()
        targets.append(server)
    rec.set_sinks(*targets, default_blueprint=blueprint)
    try:
        with rec:  # leaving the block flushes every sink and finalises the file
            summary = record_replay(rec, replay)
    except RuntimeError as exc:
        if "gRPC" not in str(exc):
            raise
        raise InputError(
            f"{exc}; is a Rerun viewer running there? Start one with `rerun`, or use --spawn or --save"
        ) from None
    if server is not None:
        rr.serve_web_viewer(open_browser=bool(os.environ.get("DISPLAY") or sys.platform != "linux"),
                            connect_to=server.uri)
    return summary


DEFAULT_VIEWER = "rerun+http://127.0.0.1:9876/proxy"  # where a viewer started with `rerun` listens


def _check_viewer(url: str) -> None:
    """Refuse at once, before the replay is recorded, a viewer URL where nothing listens
    (Rerun's own sink finds out only when it flushes, seconds after the whole replay)."""
    import socket
    from urllib.parse import urlsplit

    parts = urlsplit(url.removeprefix("rerun+"))
    if not parts.hostname:
        return  # a form Rerun reads and this does not: Rerun's sink says what is wrong
    try:
        with socket.create_connection((parts.hostname, parts.port or 80), timeout=2.0):
            pass
    except OSError as exc:
        raise InputError(f"no viewer answers at {url} ({exc.strerror or exc}); is a Rerun viewer running there? "
                         "Start one with `rerun`, or use --spawn or --save") from None


def rerun_executable() -> str | None:
    """The Rerun viewer installed beside this Python (a virtual environment's, whether or not
    it is activated); None: search the PATH."""
    beside = Path(sys.executable).with_name("rerun.exe" if os.name == "nt" else "rerun")
    return str(beside) if beside.exists() else None


def open_viewer(recording: Path) -> subprocess.Popen:
    """Start the native Rerun viewer on a saved recording, detached from this process."""
    return subprocess.Popen([sys.executable, "-m", "rerun", str(recording)], stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)


SERVING = ("web viewer at http://localhost:9090 (from another machine: ssh -L 9090:localhost:9090 -L 9876:localhost:9876 "
           "this machine, then open that address); serving until Ctrl-C")


def _serve_until_interrupted() -> None:
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
