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
    videos = video_sizes(request.tracks)
    sizes = _sizes_from_videos(request.sizes, videos, names)
    templates = [template_camera(n, _size(sizes, n)) for n in names]
    check_size_against_pixels(tracks, {t.name: t.size for t in templates}, ", ".join(request.tracks))
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
        freed = {name.rsplit(".", 1)[-1] for name in result.parameter_names}
        model = "k1k2" if "k2" in freed else "k1" if "k1" in freed else "none"
        tried = ", ".join(f"{m} {v:.0f}" for m, v in criterion.items())
        lowest = min(criterion, key=criterion.get)
        note = "" if lowest == model else f"; {lowest} not carried: its coefficients within their SDs"
        chosen = f"\nlens distortion chosen by the data: {model} (BIC {tried}{note}; --distortion overrides)"
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
    raise InputError(f"no --size for camera {name!r} and no session video of it to read the size from; give "
                     f"--size WxH or --size {name}=WxH")


def video_sizes(tracks_paths) -> dict:
    """{camera: ((w, h), video path)} of the videos of the session the tracks files lie in
    (a folder with session.toml, the tracks in it or in its tracks/), where they exist."""
    from mocap.io.video import Video
    from mocap.session import Session

    for path in tracks_paths:
        here = Path(path).resolve().parent
        for root in (here, here.parent):
            if not (root / "session.toml").exists():
                continue
            session, found = Session.open(root), {}
            for name in session.camera_names:
                video = session.video_path(name)
                if video.exists():
                    found[name] = (tuple(Video(video).info.size), video)
            return found
    return {}


def _sizes_from_videos(stated: dict, videos: dict, names: list[str]) -> dict:
    """The image sizes: stated ones, where a session video exists the same as its size
    (refused otherwise), and the videos' where none is stated."""
    for name in names:
        if name in videos and (name in stated or None in stated):
            given = stated.get(name, stated.get(None))
            if tuple(given) != videos[name][0]:
                w, h = videos[name][0]
                raise InputError(f"--size {given[0]}x{given[1]} for camera {name!r}, but its video "
                                 f"{videos[name][1]} is {w}x{h}: leave out --size (the video's is read) or "
                                 "give the size the tracks were measured in")
    return {**{name: size for name, (size, _) in videos.items()}, **stated}


MIN_OBSERVATIONS_FOR_SIZE = 8  # a camera's observations before one quadrant of its image counts against the size


def check_size_against_pixels(tracks: Tracks, sizes: dict, source: str) -> None:
    """Refuse a stated image size that a camera's pixels (all its frames) contradict: every
    observation in one quadrant of the image, so the image centre, where the principal point
    is taken, lies outside all of them (the tracks were measured in another image size, e.g.
    half of it)."""
    for name, (width, height) in sizes.items():
        xy = tracks.xy[tracks.camera == name]
        if len(xy) < MIN_OBSERVATIONS_FOR_SIZE:
            continue
        left, top = np.all(xy[:, 0] < width / 2), np.all(xy[:, 1] < height / 2)
        right, bottom = np.all(xy[:, 0] > width / 2), np.all(xy[:, 1] > height / 2)
        if (left or right) and (top or bottom):
            corner = ("top" if top else "bottom") + "-" + ("left" if left else "right")
            low, high = xy.min(0), xy.max(0)
            hint = (f"; the pixels fit {width // 2}x{height // 2}" if left and top else "")
            raise InputError(
                f"camera {name!r}: all {len(xy)} observations lie in the {corner} quadrant of the stated "
                f"{width}x{height} image (x {low[0]:.0f}..{high[0]:.0f}, y {low[1]:.0f}..{high[1]:.0f}), far from "
                f"its centre{hint}: give the size of the images the tracks were measured in (--size)", path=source)


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
