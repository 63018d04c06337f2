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
from mocap.core.tracks import Tracks, check_in_images
from mocap.errors import InputError
from mocap.io.cameras_toml import save_calibration
from mocap.io.guess_toml import load_guess
from mocap.io.intrinsics import load_intrinsics, with_known_intrinsics
from mocap.io.machine_toml import load_machine
from mocap.io.points_csv import load_points, save_points
from mocap.io.tracks_csv import load_tracks


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


@dataclass(frozen=True)
class Calibrated:
    """`calibrate_cameras`' result: the fit at the calibration frame and the report's notes."""

    result: object  # mocap.calibration.solve's result
    frame: int
    notes: str = ""  # the lens model chosen, the intrinsics kept

    @property
    def calibration(self):
        """The cameras (mocap.core.calibration.Calibration), with the joints and the frame."""
        return report.to_calibration(self.result, self.frame)

    @property
    def reference_points(self):
        """The markers' 3-D positions at the calibration frame (mocap.core.points.Points)."""
        return report.reference_points(self.result, self.frame)

    def report(self, out, points_out) -> str:
        return report.format_report(self.result, self.frame) + self.notes + f"\nwrote {out} and {points_out}"


def run_calibrate(request: CalibrateRequest) -> str:
    machine = load_machine(request.machine)
    tracks = load_tracks(list(request.tracks))
    # the sizes of the session's videos where they exist (a stated one they contradict is refused)
    request = replace(request, sizes=_sizes_from_videos(request.sizes, video_sizes(request.tracks),
                                                        list(tracks.cameras)))
    if request.method == "dlt":
        return _run_dlt_request(machine, tracks, request)
    guess = (lambda: load_guess(request.guess, machine)) if request.guess else None
    known = load_intrinsics(request.intrinsics) if request.intrinsics is not None else None
    calibrated = calibrate_cameras(machine, tracks, request.sizes, request.frame, request.options,
                                   request.choose_lens, known, request.intrinsics, guess, request.tracks[0],
                                   ", ".join(request.tracks))
    save_calibration(calibrated.calibration, request.out)
    points_out = request.points_out or str(Path(request.out).with_name("reference_points.csv"))
    save_points(calibrated.reference_points, points_out)
    return calibrated.report(request.out, points_out)


def _templates(tracks: Tracks, sizes: dict, frame: int | None, known: dict | None, intrinsics_path, where,
               tracks_where):
    """The calibration frame, its rows and the cameras' templates (known intrinsics put in)."""
    frame, rows = _frame_rows(tracks, frame, where)
    names = list(rows.cameras)
    strange = sorted(name for name in sizes if name is not None and name not in tracks.cameras)
    if strange:
        raise InputError(f"--size names camera(s) {strange} that the tracks lack (they have "
                         f"{list(tracks.cameras)}); check the NAME in --size NAME=WxH")
    templates = [template_camera(n, _size(sizes, n)) for n in names]
    check_size_against_pixels(tracks, {t.name: t.size for t in templates}, tracks_where)
    if known is not None:
        templates = with_known_intrinsics(templates, known, intrinsics_path)
    check_in_images(rows, {t.name: t.size for t in templates}, tracks_where, "--size")
    return frame, rows, templates


def calibrate_cameras(machine, tracks: Tracks, sizes: dict, frame: int | None = None,
                      options: CalibrationOptions = CalibrationOptions(), choose_lens: bool = False,
                      known_intrinsics: dict | None = None, intrinsics_path=None, guess=None,
                      where=None, tracks_where=None) -> Calibrated:
    """Model-based calibration of every camera in `tracks` at `frame` (default: the first):
    `sizes` {camera: (w, h)}, key None for every camera; `known_intrinsics` {camera:
    intrinsics} used and kept; `guess` a Guess (or a callable giving one, read after the
    observations are checked). The paths name the inputs in messages."""
    frame, rows, templates = _templates(tracks, sizes, frame, known_intrinsics, intrinsics_path, where,
                                        tracks_where)
    names = list(rows.cameras)
    if known_intrinsics is not None:
        known = frozenset(names) & frozenset(known_intrinsics)
        options = replace(options, fixed_intrinsics=known)
        choose_lens = choose_lens and len(known) < len(templates)  # a lens model only for the unknown ones
    unknown = sorted(set(rows.marker) - set(machine.marker_names))
    if unknown:
        raise InputError(
            f"marker(s) {', '.join(unknown)} at frame {frame} are not in the machine model "
            f"{machine.name!r}; check the marker names",
            path=where,
        )
    index = {n: i for i, n in enumerate(names)}
    observations = Observations(
        np.array([index[c] for c in rows.camera], dtype=int), machine.marker_index(rows.marker), rows.xy
    )
    guess = guess() if callable(guess) else guess
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
        chosen += f"\nintrinsics of {', '.join(sorted(options.fixed_intrinsics))} kept as given in {intrinsics_path}"
    return Calibrated(result, frame, chosen)


def _run_dlt_request(machine, tracks: Tracks, request: CalibrateRequest) -> str:
    frame, rows, templates = _templates(tracks, request.sizes, request.frame, None, None, request.tracks[0],
                                        ", ".join(request.tracks))
    return _run_dlt(machine, rows, templates, frame, request)


def _frame_rows(tracks: Tracks, frame: int | None, where) -> tuple[int, Tracks]:
    if not len(tracks):
        raise InputError("no observations", path=where)
    frame = int(tracks.frame.min()) if frame is None else int(frame)
    rows = tracks.of_frame(frame)
    if not len(rows):
        raise InputError(
            f"no observations at frame {frame}; frames present run {tracks.frame.min()}..{tracks.frame.max()}",
            path=where,
        )
    pairs = list(zip(rows.camera, rows.marker))
    if len(set(pairs)) != len(pairs):
        dup = next(p for p in pairs if pairs.count(p) > 1)
        raise InputError(
            f"marker {dup[1]!r} appears twice for camera {dup[0]!r} at frame {frame}",
            path=where,
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
    from mocap.io.session import Session
    from mocap.io.video import Video

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
