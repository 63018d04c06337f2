"""The whole chain on a session folder, stage after stage, as the README's commands run it:

    calibrate (from the calibration frame's digitised labels) -> track every camera ->
    sync -> refine (optional) -> triangulate -> fit -> analyze -> view

Each stage is the same sub-command a user would type, so `mocap run` and a hand-run session
give the same files.
"""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass
from pathlib import Path

from mocap.errors import InputError
from mocap.io.tracks_csv import load_tracks
from mocap.io.video import Video
from mocap.session import Session, mark_complete

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunOptions:
    """`labels`: the calibration frame's marker pixels (tracks CSV, all cameras), default
    calibration/labels.csv; `refine`: bundle-adjust the cameras over the session's frames
    before the final fit; `view`: write the Rerun recording."""

    labels: Path | None = None
    refine: bool = False
    view: bool = True


def labels_path(session: Session, options: RunOptions) -> Path:
    return options.labels or session.root / "calibration" / "labels.csv"


def stage_commands(session: Session, options: RunOptions) -> list[tuple[str, list[str]]]:
    """The chain as (name, mocap arguments) pairs."""
    config = session.config()
    machine = str(session.machine_path())
    labels = labels_path(session, options)
    if not labels.exists():
        raise InputError(
            "no labels for the calibration frame: digitise each camera's markers in its first "
            "frame (a tracks CSV: camera,frame,marker,x,y) or let `mocap track --propose-labels` "
            "propose them, and save them here",
            path=labels,
        )
    cameras = [c.name for c in config.cameras]
    labelled = set(load_tracks(labels).cameras)
    missing = [c for c in cameras if c not in labelled]
    if missing:
        raise InputError(f"no labels for camera(s) {', '.join(missing)}", path=labels)
    sizes = []
    for camera in config.cameras:
        video = session.video_path(camera.name)
        if not video.exists():
            raise InputError("video not found; check session.toml", path=video)
        width, height = Video(video).info.size
        sizes += ["--size", f"{camera.name}={width}x{height}"]
    calibration = str(session.calibration_path)
    frame = str(config.options.get("calibration_frame", 0))
    tracks = [str(session.tracks_path(c)) for c in cameras]
    commands = [(
        "calibrate",
        ["calibrate", machine, str(labels), *sizes, "--out", calibration, "--frame", frame,
         "--points", str(session.reference_points_path)],
    )]
    for camera in cameras:
        commands.append((
            f"track {camera}",
            ["track", str(session.video_path(camera)), "--machine", machine, "--calibration", calibration,
             "--camera", camera, "--labels", str(labels), "--start", frame, "--whole-video", "--out", str(session.tracks_path(camera))],
        ))
    fps = [f"{c.name}={c.fps}" for c in config.cameras]
    fps_args = [arg for value in fps for arg in ("--fps", value)]
    final = calibration
    if len(cameras) > 1 and session.machine().n_joints > 0:  # a rigid object has no joints to sync on
        commands.append(("sync", ["sync", calibration, *tracks, "--machine", machine, *fps_args, "--out", calibration]))
    if options.refine:
        final = str(session.refined_calibration_path)
        # the lens model chosen by the data over the whole session (one frame cannot fix it)
        commands.append(("refine", ["refine", machine, calibration, *tracks, "--distortion", "auto", "--out", final]))
    if len(cameras) > 1:
        commands.append(("triangulate", ["triangulate", final, *tracks, "--out", str(session.points_path)]))
    commands.append(("fit", ["fit", machine, final, *tracks, "--out", str(session.motion_path)]))
    model = session.machine()
    if model.bucket_angle is not None and "bucket_tip" in model.point_names:  # a digging machine
        commands.append(("analyze", ["analyze", machine, str(session.motion_path), "--out", str(session.results_dir)]))
    if options.view:
        commands.append(("view", ["view", str(session.root), "--calibration", final]))
    return commands


def run_session(root: str | Path, options: RunOptions = RunOptions()) -> int:
    """Run every stage on the session folder `root`; stops at the first failing stage (whose
    own message has gone to stderr) and returns its exit status."""
    from mocap import cli  # the stages are the sub-commands

    session = Session.open(root)
    if not session.root.is_dir():
        raise InputError("not a folder; give the session folder (with session.toml)", path=root)
    if session.is_synthetic and not session.complete_path.exists():
        raise InputError("the synthetic session is incomplete (its writing was interrupted); run "
                         "`mocap synth` again with the same --out to finish it", path=root)
    session.results_complete_path.unlink(missing_ok=True)
    refined, calibration = str(session.refined_calibration_path), str(session.calibration_path)
    fallback = False
    for name, args in stage_commands(session, options):
        if fallback:  # the refinement was refused: the stages after it use the one-frame calibration
            args = [calibration if arg == refined else arg for arg in args]
        print(f"== {name}", flush=True)
        code = cli.main(args)
        if code != 0 and name == "refine":
            print("refinement refused: carrying on with the one-frame calibration", file=sys.stderr, flush=True)
            session.refined_calibration_path.unlink(missing_ok=True)  # a stale one from an earlier run
            fallback = True
        elif code != 0:
            return code
    write_run_report(session)
    mark_complete(session.results_complete_path, "mocap run")
    return 0


def write_run_report(session: Session) -> None:
    """The session report (results/session_report.html) after the stages: the measurement's quality."""
    from mocap.report.session_report import write_session_report

    print("== report", flush=True)
    print(f"wrote {write_session_report(session.root)}", flush=True)
