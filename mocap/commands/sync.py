"""`mocap sync`: each camera's time offset from the motion itself, written into the calibration."""

from __future__ import annotations

import argparse
import re

import numpy as np

from mocap.errors import InputError
from mocap.io.cameras_toml import Calibration, load_calibration, save_calibration
from mocap.io.machine_toml import load_machine
from mocap.io.tracks_csv import Tracks, load_tracks
from mocap.sync import joint_curves, synchronise

EXAMPLE = """example:
  mocap sync calibration/cameras.toml tracks/cam1.csv tracks/cam2.csv tracks/cam3.csv \\
      --machine hitachi_ex3500 --out calibration/cameras.toml"""


def add_parser(sub) -> None:
    p = sub.add_parser(
        "sync",
        help="estimate each camera's time offset from the machine's motion",
        description="Fit the machine model to each camera's tracks alone (joint values over the "
        "camera's own clock) and align the joint-value curves with the first camera's, to a "
        "fraction of a frame. Writes the calibration with each camera's time_offset (s) and fps; "
        "camera k's frame f shows time f / fps_k + time_offset_k.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("calibration", help="camera calibration TOML (the first camera is the reference)")
    p.add_argument("tracks", nargs="+", help="tracks CSV file(s) of the cameras")
    p.add_argument("--machine", required=True, help="machine model TOML (or a shipped model's name)")
    p.add_argument("--out", required=True, help="calibration TOML to write (may be the input)")
    p.add_argument("--fps", action="append", default=[], metavar="NAME=FPS",
                   help="a camera's frame rate (default: the calibration's fps, else the tracks' time column)")
    p.add_argument("--max-offset", type=float, default=10.0, metavar="S",
                   help="search offsets within ± this many seconds (default 10)")
    p.set_defaults(run=run)


def run(args) -> int:
    if not args.max_offset > 0:
        raise InputError(f"--max-offset {args.max_offset}: must be positive")
    machine = load_machine(args.machine)
    calibration = load_calibration(args.calibration)
    tracks = load_tracks(args.tracks)
    missing = [name for name in calibration.names if name not in tracks.cameras]
    if missing:
        raise InputError(f"no tracks of camera {missing[0]!r} in {', '.join(args.tracks)}; give its tracks CSV")
    fps = frame_rates(calibration, tracks, parse_fps(args.fps, calibration.names))
    curves = []
    for k, camera in enumerate(calibration.cameras):
        rows = tracks.of_camera(camera.name)
        frames = np.arange(rows.frame.min(), rows.frame.max() + 1)
        pixels = rows.dense([camera.name], machine.marker_names, frames)[0]
        curves.append(joint_curves(machine, camera, frames, pixels, calibration.joints(machine, k)))
    result = synchronise(curves, fps, args.max_offset)
    failed = [f"{calibration.names[k]}: {r}" for k, r in enumerate(result.reasons) if r]
    if failed:
        raise InputError("cannot synchronise: " + "; ".join(failed))
    out: Calibration = calibration
    for k in range(len(calibration.cameras)):
        out = out.with_extras(k, time_offset=float(result.offsets[k]), fps=float(fps[k]))
    save_calibration(out, args.out)
    for k, name in enumerate(calibration.names):
        print(f"{name}: time_offset {result.offsets[k]:+.4f} s ({result.offsets[k] * fps[0]:+.3f} frames), "
              f"fps {fps[k]:g}, residual {result.residual[k]:.3f}")
    return 0


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
