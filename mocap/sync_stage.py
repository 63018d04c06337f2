"""The sync stage: load the machine, calibration and tracks; fit each camera alone and align
its joint-value curves with the reference camera's; write the calibration with each
camera's time offset and frame rate; return the report."""

from __future__ import annotations

import re

import numpy as np

from mocap.errors import InputError
from mocap.io.cameras_toml import Calibration, load_calibration, save_calibration
from mocap.io.machine_toml import load_machine
from mocap.io.tracks_csv import Tracks, load_tracks
from mocap.sync import joint_curves, synchronise


def run_sync(machine_path, calibration_path, tracks_paths, out, fps_values: list[str], max_offset: float) -> str:
    if not max_offset > 0:
        raise InputError(f"--max-offset {max_offset}: must be positive")
    machine = load_machine(machine_path)
    calibration = load_calibration(calibration_path)
    tracks = load_tracks(tracks_paths)
    missing = [name for name in calibration.names if name not in tracks.cameras]
    if missing:
        raise InputError(f"no tracks of camera {missing[0]!r} in {', '.join(map(str, tracks_paths))}; give its tracks CSV")
    fps = frame_rates(calibration, tracks, parse_fps(fps_values, calibration.names))
    curves = []
    for k, camera in enumerate(calibration.cameras):
        rows = tracks.of_camera(camera.name)
        frames = np.arange(rows.frame.min(), rows.frame.max() + 1)
        pixels = rows.dense([camera.name], machine.marker_names, frames)[0]
        curves.append(joint_curves(machine, camera, frames, pixels, calibration.joints(machine, k)))
    result = synchronise(curves, fps, max_offset)
    failed = [f"{calibration.names[k]}: {r}" for k, r in enumerate(result.reasons) if r]
    if failed:
        raise InputError("cannot synchronise: " + "; ".join(failed))
    synced: Calibration = calibration
    for k in range(len(calibration.cameras)):
        synced = synced.with_extras(k, time_offset=float(result.offsets[k]), fps=float(fps[k]))
    save_calibration(synced, out)
    return "\n".join(
        f"{name}: time_offset {result.offsets[k]:+.4f} s ({result.offsets[k] * fps[0]:+.3f} frames), "
        f"fps {fps[k]:g}, residual {result.residual[k]:.3f}"
        for k, name in enumerate(calibration.names)
    )


def parse_fps(values: list[str], names) -> dict[str, float]:
    out = {}
    for value in values:
        match = re.fullmatch(r"([^=]+)=([0-9.]+)", value.strip())
        if not match or match[1] not in names or not float(match[2]) > 0:
            raise InputError(f"--fps {value!r}: expected NAME=FPS with NAME one of {', '.join(names)}")
        out[match[1]] = float(match[2])
    return out


def frame_rates(calibration: Calibration, tracks: Tracks, given: dict[str, float]) -> np.ndarray:
    """(C,) frame rates: given, else the calibration's `fps`, else frame / time of the tracks."""
    fps = []
    for camera, extra in zip(calibration.cameras, calibration.extras):
        if camera.name in given:
            fps.append(given[camera.name])
            continue
        if "fps" in extra:
            fps.append(float(extra["fps"]))
            continue
        rows = tracks.of_camera(camera.name)
        timed = np.isfinite(rows.time) & (rows.time > 0)
        if not np.any(timed):
            raise InputError(f"no frame rate for camera {camera.name!r}: pass --fps {camera.name}=FPS")
        fps.append(float(np.median(rows.frame[timed] / rows.time[timed])))
    return np.array(fps)
