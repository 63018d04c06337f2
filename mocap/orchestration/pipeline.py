"""The whole chain on a session folder, stage after stage, as the README's commands run it:

    calibrate (from the calibration frame's digitised labels) -> track every camera ->
    sync -> refine (optional) -> triangulate -> fit -> analyze -> view

Each step calls the same stage function as its sub-command, with the command's defaults and
its checks of the output paths, so `mocap run` and a hand-run session give the same files and
print the same lines. `session_steps` is the chain as data (the batch runs the same steps as
tasks); `run_session` runs it in this process.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

from mocap.errors import EXIT_OK, EXIT_PARTIAL, InputError, one_line
from mocap.io.outputs import check_outputs
from mocap.io.session import Session, mark_complete
from mocap.io.tracks_csv import load_tracks
from mocap.io.video import Video

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunOptions:
    """`labels`: the calibration frame's marker pixels (tracks CSV, all cameras), default
    calibration/labels.csv; `refine`: bundle-adjust the cameras over the session's frames
    before the final fit; `view`: write the Rerun recording; `allow_partial`: a stage that did
    part of its work (a camera not synchronised, frames left unexplained) still ends the run
    with status 0 (else 3; either way its line is printed and the chain carries on)."""

    labels: Path | None = None
    refine: bool = False
    view: bool = True
    allow_partial: bool = False


@dataclass(frozen=True)
class Step:
    """One stage of a session's chain: `name` ("track cam1"), `command` the sub-command whose
    error line it gives, `call` a picklable callable of no argument that runs the stage and
    returns its report, `inputs` / `outputs` the files it reads and writes, `camera` the
    camera of a per-camera stage."""

    name: str
    command: str
    call: Callable[[], str]
    inputs: tuple[Path, ...]
    outputs: tuple[Path, ...]
    camera: str | None = None


def labels_path(session: Session, options: RunOptions) -> Path:
    return options.labels or session.root / "calibration" / "labels.csv"


# --- the steps: each as its sub-command runs it with its defaults ------------------------------


def calibrate_step(machine: str, labels: str, sizes: tuple, out: str, frame: int, points: str) -> str:
    from mocap.calibration.solve import CalibrationOptions
    from mocap.calibration.stage import CalibrateRequest, run_calibrate

    check_outputs({"--out": out, "--points": points}, {"machine model": machine, "tracks": [labels]})
    return run_calibrate(CalibrateRequest(machine=machine, tracks=(labels,), sizes=dict(sizes), out=out, frame=frame,
                                          options=CalibrationOptions(), points_out=points, choose_lens=True))


def track_step(video: str, machine: str, calibration: str, camera: str, labels: str, start: int, out: str) -> str:
    from mocap.tracking.stage import TrackRequest, run_track

    check_outputs({"--out": out}, {"video": video, "machine model": machine, "calibration": calibration,
                                   "labels": labels})
    request = TrackRequest(Path(video), machine, Path(calibration), camera, Path(out), Path(labels), None, start,
                           whole_video=True)
    return run_track(request).text(out)


def sync_step(calibration: str, tracks: tuple[str, ...], machine: str, fps: tuple[str, ...], out: str) -> str:
    from mocap.clocks.stage import run_sync

    check_outputs({"--out": out}, {"machine model": machine, "calibration": calibration, "tracks": list(tracks)},
                  may_replace=("calibration",))
    return run_sync(machine, calibration, list(tracks), out, list(fps), 10.0)


def refine_step(machine: str, calibration: str, tracks: tuple[str, ...], out: str) -> str:
    from mocap.reconstruct.refine import RefineOptions
    from mocap.reconstruct.stage import run_refine

    check_outputs({"--out": out}, {"machine model": machine, "calibration": calibration, "tracks": list(tracks)})
    # the lens model chosen by the data over the whole session (one frame cannot fix it)
    return run_refine(machine, calibration, list(tracks), out, None, RefineOptions(distortion="auto"))


def triangulate_step(calibration: str, tracks: tuple[str, ...], out: str) -> str:
    from mocap.reconstruct.stage import run_triangulate
    from mocap.reconstruct.triangulate import TriangulateOptions

    check_outputs({"--out": out}, {"calibration": calibration, "tracks": list(tracks)})
    return run_triangulate(calibration, list(tracks), out, TriangulateOptions())


def fit_step(machine: str, calibration: str, tracks: tuple[str, ...], out: str) -> str:
    from mocap.reconstruct.kinfit import FitOptions
    from mocap.reconstruct.smooth import SmoothOptions
    from mocap.reconstruct.stage import run_fit

    check_outputs({"--out": out}, {"machine model": machine, "calibration": calibration, "tracks": list(tracks)})
    return run_fit(machine, calibration, list(tracks), out, FitOptions(), SmoothOptions())


def analyze_step(machine: str, motion: str, out: str) -> str:
    from mocap.analysis.stage import run_analyze

    return run_analyze(machine, motion, out)


def view_step(root: str, calibration: str) -> str:
    from mocap.viewer.inputs import ReplayFiles
    from mocap.viewer.stage import run_view

    return run_view(ReplayFiles(calibration=Path(calibration)), Path(root))


# --- the chain ----------------------------------------------------------------------------------


def session_steps(session: Session, options: RunOptions) -> list[Step]:
    """The chain of `mocap run` on the session (refine and view as `options` say)."""
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
        sizes.append((camera.name, tuple(Video(video).info.size)))
    calibration = str(session.calibration_path)
    frame = int(config.options.get("calibration_frame", 0))
    tracks = tuple(str(session.tracks_path(c)) for c in cameras)
    model, machine_file = session.machine(), Path(machine)
    steps = [Step("calibrate", "calibrate",
                  partial(calibrate_step, machine, str(labels), tuple(sizes), calibration, frame,
                          str(session.reference_points_path)),
                  (machine_file, labels), (Path(calibration), session.reference_points_path))]
    for camera in cameras:
        video, out = session.video_path(camera), session.tracks_path(camera)
        steps.append(Step(f"track {camera}", "track",
                          partial(track_step, str(video), machine, calibration, camera, str(labels), frame, str(out)),
                          (video, machine_file, Path(calibration), labels), (out,), camera))
    fps = tuple(f"{c.name}={c.fps}" for c in config.cameras)
    track_files = tuple(map(Path, tracks))
    final = calibration
    if len(cameras) > 1 and model.n_joints > 0:  # a rigid object has no joints to sync on
        steps.append(Step("sync", "sync", partial(sync_step, calibration, tracks, machine, fps, calibration),
                          (Path(calibration), *track_files, machine_file), (Path(calibration),)))
    if options.refine:
        final = str(session.refined_calibration_path)
        steps.append(Step("refine", "refine", partial(refine_step, machine, calibration, tracks, final),
                          (machine_file, Path(calibration), *track_files), (Path(final),)))
    if len(cameras) > 1:
        steps.append(Step("triangulate", "triangulate", partial(triangulate_step, final, tracks, str(session.points_path)),
                          (Path(final), *track_files), (session.points_path,)))
    steps.append(Step("fit", "fit", partial(fit_step, machine, final, tracks, str(session.motion_path)),
                      (machine_file, Path(final), *track_files), (session.motion_path,)))
    if model.bucket_angle is not None and "bucket_tip" in model.point_names:  # a digging machine
        steps.append(Step("analyze", "analyze",
                          partial(analyze_step, machine, str(session.motion_path), str(session.results_dir)),
                          (machine_file, session.motion_path), (session.results_dir,)))
    if options.view:
        # the recording is made of the session's files: the model, cameras, videos, results
        reads = [machine_file, Path(final), session.points_path, session.motion_path]
        reads += [p for c in cameras for p in (session.tracks_path(c), session.video_path(c))]
        steps.append(Step("view", "view", partial(view_step, str(session.root), final), tuple(reads),
                          (session.recording_path,)))
    return steps


def run_session(root: str | Path, options: RunOptions = RunOptions()) -> int:
    """Run every stage on the session folder `root`, printing each stage's report; stops at
    the first failing stage (its one line on stderr) and returns its exit status (2). A stage
    that did part of its work prints its partial line on stderr and the chain carries on; the
    run then returns 3 (EXIT_PARTIAL) unless `options.allow_partial`."""
    session = Session.open(root)
    if not session.root.is_dir():
        raise InputError("not a folder; give the session folder (with session.toml)", path=root)
    if session.is_synthetic and not session.complete_path.exists():
        raise InputError("the synthetic session is incomplete (its writing was interrupted); run "
                         "`mocap synth` again with the same --out to finish it", path=root)
    session.results_complete_path.unlink(missing_ok=True)
    steps = session_steps(session, options)
    done: set[str] = set()
    partial: list[str] = []
    while steps:
        step = steps.pop(0)
        print(f"== {step.name}", flush=True)
        try:
            report = step.call()
            print(report, flush=True)
            if getattr(report, "partial", ""):
                partial.append(step.name)
                print(one_line(f"mocap {step.command}: partial: {report.partial}"), file=sys.stderr, flush=True)
        except InputError as exc:
            print(one_line(f"mocap {step.command}: error: {exc}"), file=sys.stderr, flush=True)
            if step.command != "refine":
                return 2
            print("refinement refused: carrying on with the one-frame calibration", file=sys.stderr, flush=True)
            session.refined_calibration_path.unlink(missing_ok=True)  # a stale one from an earlier run
            # the stages after it use the one-frame calibration
            steps = [s for s in session_steps(session, replace(options, refine=False)) if s.name not in done]
        done.add(step.name)
    write_run_report(session)
    mark_complete(session.results_complete_path, "mocap run")
    if partial and not options.allow_partial:
        print(f"mocap run: partial: {', '.join(partial)} did part of the work (the lines above say what), every "
              "stage after them ran; exit status 3 (--allow-partial: 0)", file=sys.stderr, flush=True)
        return EXIT_PARTIAL
    return EXIT_OK


def write_run_report(session: Session) -> None:
    """The session report (results/session_report.html) after the stages: the measurement's quality."""
    from mocap.report.session_report import write_session_report

    print("== report", flush=True)
    print(f"wrote {write_session_report(session.root)}", flush=True)
