"""The sync stage: load the machine, calibration and tracks; fit each camera alone and align
its joint-value curves with the reference camera's; refine each offset on the pixels; write the calibration with each
camera's time offset and frame rate; return the report."""

from __future__ import annotations


import numpy as np

from mocap.clocks.align import SMOOTH_S, SyncResult, joint_curves, pose_curves, synchronise, window_frames
from mocap.clocks.pixels import CameraPixels, refine_offsets
from mocap.core.calibration import Calibration
from mocap.core.machine import Machine
from mocap.core.tracks import Tracks, check_in_images
from mocap.errors import InputError, Report
from mocap.io.cameras_toml import MAX_FPS, MAX_TIME_OFFSET_S, load_calibration, save_calibration
from mocap.io.machine_toml import load_machine
from mocap.io.tracks_csv import load_tracks


def run_sync(machine_path, calibration_path, tracks_paths, out, fps_values: list[str], max_offset: float) -> str:
    if not 0 < max_offset <= MAX_TIME_OFFSET_S:
        raise InputError(f"--max-offset {max_offset}: must be positive seconds, at most {MAX_TIME_OFFSET_S:g} "
                         "(cameras started within a day of each other)")
    machine = load_machine(machine_path)
    calibration = load_calibration(calibration_path)
    tracks = load_tracks(tracks_paths)
    synced, report = sync_cameras(machine, calibration, tracks, fps_values, max_offset, machine_path, calibration_path,
                                  ", ".join(map(str, tracks_paths)), partial_ok=True)
    save_calibration(synced, out)
    partial = getattr(report, "partial", "")
    return Report(report, f"{partial}; the others' offsets written to {out}" if partial else "")


def sync_cameras(machine: Machine, calibration: Calibration, tracks: Tracks, fps_values=(), max_offset: float = 10.0,
                 machine_path=None, calibration_path=None, tracks_where=None,
                 partial_ok: bool = False) -> tuple[Calibration, str]:
    """The calibration with each camera's time_offset (s) and fps, found by aligning each
    camera's own joint-value curves with the reference camera's; and the report. `fps_values`
    "NAME=FPS" strings (default: the calibration's fps, else the tracks' time column).

    A camera that cannot be synchronised (no overlap in motion, no offset that makes the
    motions agree) is an InputError; with `partial_ok`, when another camera was synchronised,
    it keeps the calibration's time_offset (0 if none) and the report is a `Report` whose
    `partial` line names it."""
    if not max_offset > 0:
        raise InputError(f"--max-offset {max_offset}: must be positive")
    check_in_images(tracks, {c.name: c.size for c in calibration.cameras}, tracks_where)
    unknown = sorted(set(tracks.cameras) - set(calibration.names))
    if unknown:
        raise InputError(f"tracks name camera(s) {unknown} that the calibration lacks (it has "
                         f"{list(calibration.names)}); calibrate them or rename the tracks' camera column",
                         path=calibration_path)
    strange = sorted(set(tracks.markers) - set(machine.marker_names))
    if strange:
        raise InputError(f"marker(s) {strange[:5]} are not in the machine model {machine.name!r}; check the "
                         "model or the tracks' marker names", path=tracks_where)
    present = tracks.cameras
    missing = [name for name in calibration.names if name not in present]
    if missing:
        raise InputError(f"no tracks of camera {missing[0]!r} in {tracks_where}; give its tracks CSV")
    fps = frame_rates(calibration, tracks, parse_fps(list(fps_values), calibration.names))
    spans = []
    for camera in calibration.cameras:
        frame = tracks.frame[tracks.rows_of_camera(camera.name)]
        spans.append((int(frame.min()), int(frame.max())))
    # offsets longer than the recordings together leave no overlap: the search ends there
    max_offset = min(max_offset, sum((last - first + 1) / rate for (first, last), rate in zip(spans, fps)))
    curves = []
    for k, (camera, frames) in enumerate(zip(calibration.cameras, window_frames(spans, fps, max_offset))):
        pixels = tracks.dense_of_camera(camera.name, machine.marker_names, frames)
        if machine.n_joints:
            curves.append(joint_curves(machine, camera, frames, pixels, calibration.joints(machine, k)))
        else:  # a rigid object: its pose is the motion to align
            curves.append(pose_curves(machine, camera, frames, pixels))
    result = synchronise(curves, fps, max_offset)
    offsets, pixel_rms = on_pixels(machine, calibration, tracks, fps, result)
    if machine.n_joints == 0 and any("do not vary" in r for r in result.reasons):
        raise InputError(f"the rigid object {machine.name!r} does not move in {calibration.names[0]}'s view: "
                         "no motion to synchronise on; give each camera's time_offset in the calibration "
                         "instead", path=machine_path)
    failed = [k for k, r in enumerate(result.reasons) if r]
    if failed and (not partial_ok or len(failed) == len(calibration.names) - 1 or 0 in failed):
        raise InputError("cannot synchronise: " + "; ".join(f"{calibration.names[k]}: {result.reasons[k]}"
                                                            for k in failed))
    synced: Calibration = calibration
    lines = []
    for k, name in enumerate(calibration.names):
        if k in failed:  # not synchronised: the calibration's offset, if any, stays
            kept = float(calibration.extras[k].get("time_offset", 0.0))
            synced = synced.with_extras(k, fps=float(fps[k]))
            lines.append(f"{name}: not synchronised ({result.reasons[k]}); time_offset {kept:+.4f} s kept, "
                         f"fps {fps[k]:g}")
            continue
        synced = synced.with_extras(k, time_offset=float(offsets[k]), fps=float(fps[k]))
        pixels = f", {pixel_rms[k]:.2f} px from the pair's fit" if np.isfinite(pixel_rms[k]) else ""
        lines.append(f"{name}: time_offset {offsets[k]:+.4f} s ({offsets[k] * fps[0]:+.3f} frames), "
                     f"fps {fps[k]:g}, residual {result.residual[k]:.3f}{pixels}")
    partial = "; ".join(
        f"camera {calibration.names[k]} not synchronised ({result.reasons[k]}): its time_offset "
        f"{float(calibration.extras[k].get('time_offset', 0.0)):+.4f} s kept" for k in failed)
    return synced, Report("\n".join(lines), partial)


def on_pixels(machine: Machine, calibration: Calibration, tracks: Tracks, fps: np.ndarray, result: SyncResult,
              span_s: float = 60.0) -> tuple[np.ndarray, np.ndarray]:
    """The offsets (C,) s of `result` refined on the pixels (`mocap.clocks.pixels`; every
    camera's tracks smoothed over SMOOTH_S alike), each
    within a frame of the reference's, over up to `span_s` of the reference camera's first
    frames; and (C,) each camera's RMS reprojection residual (px) fitted with the reference
    (NaN for the reference and a camera not synchronised). A refined offset that runs to
    the edge of its window (the pixels do not pin it there) keeps the curves' offset."""
    found = np.isfinite(result.offsets)
    r = result.reference
    if found.sum() < 2 or not found[r]:
        return result.offsets, np.full(len(found), np.nan)
    width = 1.0 / fps[r]
    names = calibration.names
    own = np.unique(tracks.frame[tracks.rows_of_camera(names[r])])
    own = own[own <= own[0] + span_s * fps[r]]
    first, last = own[0] / fps[r] + result.offsets[r], own[-1] / fps[r] + result.offsets[r]  # camera 0's clock
    recordings = []
    for k, name in enumerate(names):
        frame = tracks.frame[tracks.rows_of_camera(name)]
        reach = 2 * width if k != r else 0.0
        low = int(np.floor((first - np.nan_to_num(result.offsets[k]) - reach) * fps[k]))
        high = int(np.ceil((last - np.nan_to_num(result.offsets[k]) + reach) * fps[k]))
        frames = np.arange(max(low, int(frame.min())), min(high, int(frame.max())) + 1)
        if len(frames) < 2:
            frames = np.arange(int(frame.min()), int(frame.min()) + 2)
        pixels = tracks.dense_of_camera(name, machine.marker_names, frames)
        recordings.append(CameraPixels.smoothed(frames, pixels, float(fps[k]), SMOOTH_S))
    refined, rms = refine_offsets(machine, list(calibration.cameras), recordings, result.offsets, r, width)
    edge = np.abs(refined - result.offsets) > 0.95 * width
    refined = np.where(edge | ~np.isfinite(refined), result.offsets, refined)
    return refined - refined[0], np.where(edge, np.nan, rms)  # camera 0 may have moved: onto its clock again


def parse_fps(values: list[str], names) -> dict[str, float]:
    out = {}
    for value in values:
        name, sep, number = (part.strip() for part in value.partition("="))
        if not sep:
            raise InputError(f"--fps {value!r}: expected NAME=FPS, e.g. --fps {names[0]}=30")
        if name not in names:
            raise InputError(f"--fps {value!r}: no camera {name!r} in the calibration (it has {', '.join(names)})")
        try:
            fps = float(number)
        except ValueError:
            raise InputError(f"--fps {value!r}: {number!r} is not a number of frames per second") from None
        if not 0 < fps <= MAX_FPS:
            raise InputError(f"--fps {value!r}: a frame rate must be positive (at most {MAX_FPS:g})")
        out[name] = fps
    return out


def frame_rates(calibration: Calibration, tracks: Tracks, given: dict[str, float]) -> np.ndarray:
    """(C,) frame rates: given, else the calibration's `fps`, else the tracks' time column:
    the inverse of the least-squares slope of time over frame (a clock that does not start
    at 0 does not matter)."""
    fps = []
    for camera, extra in zip(calibration.cameras, calibration.extras):
        if camera.name in given:
            fps.append(given[camera.name])
            continue
        if "fps" in extra:
            fps.append(float(extra["fps"]))
            continue
        mine = tracks.rows_of_camera(camera.name)
        timed = mine & np.isfinite(tracks.time)
        frames, times = tracks.frame[timed].astype(float), tracks.time[timed]
        if len(np.unique(frames)) < 2:
            raise InputError(f"no frame rate for camera {camera.name!r} (its tracks have no time column "
                             f"over two frames or more): pass --fps {camera.name}=FPS")
        slope = np.polyfit(frames, times, 1)[0]  # seconds per frame
        if not slope >= 1 / MAX_FPS:
            raise InputError(f"camera {camera.name!r}: the tracks' time falls or stands still over the "
                             f"frames (slope {slope:g} s per frame); fix the time column or pass --fps "
                             f"{camera.name}=FPS")
        fps.append(float(1 / slope))
    return np.array(fps)
