"""The view stage: the replay's files (a session's, overridden by those given) -> the Rerun
recording into its sinks -> a short report."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from mocap.errors import InputError
from mocap.io.outputs import check_outputs
from mocap.io.session import Session
from mocap.io.video import probe_video
from mocap.viewer.inputs import ReplayFiles, load_replay, with_session
from mocap.viewer.replay import Sinks, run_replay


def run_view(files: ReplayFiles, session: str | Path | None = None, sinks: Sinks = Sinks(),
             on_serving: Callable[[str], None] | None = None) -> str:
    """Record the replay of `files` (completed from the folder `session`) into `sinks`
    (default: a session's results/session.rrd); returns the report line. `on_serving` is
    told where a served web viewer is, before serving until interrupted."""
    asked = list(files.videos.values())
    files = with_session(files, session)
    if not sinks.any:
        if session is None:
            raise InputError("nowhere to send the replay; pass --save FILE.rrd, --connect, --serve or --spawn")
        sinks = Sinks(save=Session.open(session).recording_path)
    if sinks.save is not None and sinks.save.suffix != ".rrd":
        raise InputError(f"--save {sinks.save}: a Rerun recording is a .rrd file; name it FILE.rrd")
    check_outputs({"--save": sinks.save}, {
        "machine model": files.machine, "calibration": files.calibration, "motion": files.motion,
        "points": files.points, "tracks": list(files.tracks), "video": list(files.videos.values()),
        "cycles": files.cycles,
    })
    replay = load_replay(files)
    for path in asked:  # the videos asked for must be videos; a session's may be absent or unplayable
        if not path.is_file():
            raise InputError("video file not found; check --video NAME=PATH", path=path)
        probe_video(path)
    summary = run_replay(replay, sinks, on_serving)
    where = f" to {sinks.save}" if sinks.save is not None else ""
    videos = f", video for {', '.join(summary.videos)}" if summary.videos else ", no video"
    trails = f"{summary.trails} trail(s)"
    return f"replay of {summary.frames} frames, {summary.cameras} cameras{videos}, {trails}{where}"
