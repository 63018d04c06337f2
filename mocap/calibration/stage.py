"""The calibration stage: load the machine and the observations of one frame, calibrate,
write the calibration file and the reference points, return the report."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from mocap.calibration import report
from mocap.calibration.dlt import dlt_camera
from mocap.calibration.lens_choice import calibrate_choosing_lens
from mocap.calibration.problem import Observations
from mocap.calibration.solve import CalibrationOptions, calibrate, template_camera
from mocap.errors import InputError
from mocap.io.cameras_toml import save_calibration
from mocap.io.guess_toml import load_guess
from mocap.io.intrinsics import load_intrinsics, with_known_intrinsics
from mocap.io.machine_toml import load_machine
from mocap.io.points_csv import load_points, save_points
from mocap.io.tracks_csv import Tracks, check_in_images, load_tracks


@dataclass(frozen=True)
class CalibrateRequest:
    machine: str
    tracks: tuple[str, ...]
    sizes: dict  # camera name -> (w, h); key None for every camera
    out: str
    frame: int | None = None
    method: str = "model"
    options: CalibrationOptions = CalibrationOptions()
    guess: str | None = None
    reference: str | None = None
    points_out: str | None = None
    choose_lens: bool = False  # the distortion model chosen by the data (options.distortion ignored)
    intrinsics: str | None = None  # a file of known intrinsics, used and kept


def run_calibrate(request: CalibrateRequest) -> str:
    machine = load_machine(request.machine)
    tracks = load_tracks(list(request.tracks))
    frame, rows = _frame_rows(tracks, request)
    names = list(rows.cameras)
    strange = sorted(name for name in request.sizes if name is not None and name not in tracks.cameras)
    if strange:
        raise InputError(f"--size names camera(s) {strange} that the tracks lack (they have "
                         f"{list(tracks.cameras)}); check the NAME in --size NAME=WxH")
    templates = [template_camera(n, _size(request.sizes, n)) for n in names]
    options, choose_lens = request.options, request.choose_lens
    if request.intrinsics is not None:
        given = load_intrinsics(request.intrinsics)
        templates = with_known_intrinsics(templates, given, request.intrinsics)
        known = frozenset(names) & frozenset(given)
        options = replace(options, fixed_intrinsics=known)
        choose_lens = choose_lens and len(known) < len(templates)  # a lens model only for the unknown ones
    check_in_images(rows, {t.name: t.size for t in templates}, ", ".join(request.tracks), "--size")
    if request.method == "dlt":
        return _run_dlt(machine, rows, templates, frame, request)
    unknown = sorted(set(rows.marker) - set(machine.marker_names))
    if unknown:
        raise InputError(
            f"marker(s) {', '.join(unknown)} at frame {frame} are not in the machine model "
            f"{machine.name!r}; check the marker names",
            path=request.tracks[0],
        )
    index = {n: i for i, n in enumerate(names)}
    observations = Observations(
        np.array([index[c] for c in rows.camera], dtype=int), machine.marker_index(rows.marker), rows.xy
    )
    guess = load_guess(request.guess, machine) if request.guess else None
    chosen = ""
    if choose_lens:
        result, criterion = calibrate_choosing_lens(machine, observations, templates, options, guess)
        model = next(m for m, v in criterion.items() if v == min(criterion.values()))
        tried = ", ".join(f"{m} {v:.0f}" for m, v in criterion.items())
        chosen = f"\nlens distortion chosen by the data: {model} (BIC {tried}; --distortion overrides)"
    else:
        result = calibrate(machine, observations, templates, options, guess)
    if options.fixed_intrinsics:
        chosen += f"\nintrinsics of {', '.join(sorted(options.fixed_intrinsics))} kept as given in {request.intrinsics}"
    save_calibration(report.to_calibration(result, frame), request.out)
    points_out = request.points_out or str(Path(request.out).with_name("reference_points.csv"))
    save_points(report.reference_points(result, frame), points_out)
    return report.format_report(result, frame) + chosen + f"\nwrote {request.out} and {points_out}"


def _frame_rows(tracks: Tracks, request: CalibrateRequest) -> tuple[int, Tracks]:
    if not len(tracks):
        raise InputError("no observations", path=request.tracks[0])
    frame = int(tracks.frame.min()) if request.frame is None else int(request.frame)
    rows = tracks.of_frame(frame)
    if not len(rows):
        raise InputError(
            f"no observations at frame {frame}; frames present run {tracks.frame.min()}..{tracks.frame.max()}",
            path=request.tracks[0],
        )
    pairs = list(zip(rows.camera, rows.marker))
    if len(set(pairs)) != len(pairs):
        dup = next(p for p in pairs if pairs.count(p) > 1)
        raise InputError(
            f"marker {dup[1]!r} appears twice for camera {dup[0]!r} at frame {frame}",
            path=request.tracks[0],
        )
    return frame, rows


def _size(sizes: dict, name: str) -> tuple[int, int]:
    if name in sizes:
        return sizes[name]
    if None in sizes:
        return sizes[None]
    raise InputError(f"no --size for camera {name!r}; give --size WxH or --size {name}=WxH")


def _run_dlt(machine, rows: Tracks, templates, frame: int, request: CalibrateRequest) -> str:
    if request.reference:
        ref = load_points(request.reference)
        at = ref.frame == frame if np.any(ref.frame == frame) else np.ones(len(ref), dtype=bool)
        known = dict(zip(ref.marker[at], ref.xyz[at]))
        source = request.reference
    elif machine.n_joints == 0:
        known = dict(zip(machine.marker_names, machine.marker_positions))
        source = request.machine
    else:
        raise InputError(
            "--method dlt needs --reference POINTS.csv (the control points' 3-D coordinates, e.g. "
            "the reference_points.csv of a model-based calibration) for a machine with joints"
        )
    results = []
    for template in templates:
        mine = rows.of_camera(template.name)
        keep = np.array([m in known for m in mine.marker], dtype=bool)
        if not np.any(keep):
            raise InputError(f"camera {template.name!r}: none of its markers is in {source}")
        points = np.array([known[m] for m in mine.marker[keep]])
        results.append(dlt_camera(template.name, template.size, points, mine.xy[keep]))
    save_calibration(report.dlt_to_calibration(results, frame, machine.name), request.out)
    return report.format_dlt_report(results, frame) + f"\nwrote {request.out}"
