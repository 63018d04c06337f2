"""The bad-input corpus: every command fed bad or hostile input must exit 2 with exactly one
line on stderr, no traceback, no output file left and every input unchanged.

Cases are named ``command/case``; the summary at the end of the run counts them per
command (tests/conftest.py). The files are made in the test (badinput_files.py): a
two-camera rig around the Bobcat model, its calibration and tracks, a tiny video and a
session folder; each case spoils one thing.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from badinput_files import FPS, snapshot, write_rig, write_session, write_video

from mocap.cli import main
from mocap.io.machine_toml import MACHINES_DIR
from mocap.synthetic.encode import video_writer

# --- the valid inputs, made once ---------------------------------------------------------


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("base")
    write_rig(root)
    assert main(["triangulate", str(root / "cameras.toml"), str(root / "tracks.csv"), "--out", str(root / "points.csv")]) == 0
    assert main(["fit", str(root / "machine.toml"), str(root / "cameras.toml"), str(root / "tracks.csv"),
                 "--out", str(root / "motion.csv"), "--no-smooth"]) == 0
    write_session(root / "session", root)
    return root


@pytest.fixture(scope="module", autouse=True)
def parsers_built_once():
    """The parser of each command built once for the corpus, not once per case: building one
    (argparse looks up a translation of every help string) is a third of a refused command
    line's time. The parsers are those `main` builds (its commands are not patched here)."""
    import functools

    import mocap.cli

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(mocap.cli, "build_parser", functools.cache(mocap.cli.build_parser))
        yield


@pytest.fixture
def work(base, tmp_path) -> Path:
    """A fresh copy of the valid inputs."""
    shutil.copytree(base, tmp_path / "w")
    return tmp_path / "w"


# --- how a file is spoiled -----------------------------------------------------------------


def set_camera_key(d: Path, key: str, value: str) -> None:
    """Set `key = value` (TOML) in the calibration's first camera table."""
    path = d / "cameras.toml"
    text = path.read_text()
    new, n = re.subn(rf"^{key} = .*$", f"{key} = {value}", text, count=1, flags=re.M)
    if not n:
        new = text.replace('name = "cam1"\n', f'name = "cam1"\n{key} = {value}\n', 1)
    path.write_text(new)


def drop_camera_key(d: Path, key: str) -> None:
    path = d / "cameras.toml"
    path.write_text(re.sub(rf"^{key} = .*\n", "", path.read_text(), count=1, flags=re.M))


def set_track_field(d: Path, name: str, column: str, value: str, row: int = 3) -> None:
    """Set one field of a data row of the tracks CSV `name`."""
    path = d / name
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    fields = lines[row].split(",")
    fields[header.index(column)] = value
    lines[row] = ",".join(fields)
    path.write_text("\n".join(lines) + "\n")


def append_row(d: Path, name: str, row: str) -> None:
    with open(d / name, "a") as fh:
        fh.write(row + "\n")


CAMERA_SPOILS = {  # case: (key, TOML value) of the first camera
    "k22-is-5": ("matrix", "[[600.0, 0.0, 160.0], [0.0, 600.0, 120.0], [0.0, 0.0, 5.0]]"),
    "k-all-zero": ("matrix", "[[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]"),
    "negative-focal": ("matrix", "[[-600.0, 0.0, 160.0], [0.0, 600.0, 120.0], [0.0, 0.0, 1.0]]"),
    "k-2x2": ("matrix", "[[600.0, 0.0], [0.0, 600.0]]"),
    "k-ragged": ("matrix", "[[600.0, 0.0, 160.0], [0.0, 600.0], [0.0, 0.0, 1.0]]"),
    "k-string": ("matrix", '[["1200.7", 0.0, 160.0], [0.0, 600.0, 120.0], [0.0, 0.0, 1.0]]'),
    "k-nan": ("matrix", "[[nan, 0.0, 160.0], [0.0, 600.0, 120.0], [0.0, 0.0, 1.0]]"),
    "k-inf": ("matrix", "[[inf, 0.0, 160.0], [0.0, 600.0, 120.0], [0.0, 0.0, 1.0]]"),
    "k-lower-left": ("matrix", "[[600.0, 0.0, 160.0], [3.0, 600.0, 120.0], [0.0, 0.0, 1.0]]"),
    "three-distortions": ("distortions", "[0.1, 0.0, 0.0]"),
    "six-distortions": ("distortions", "[0.1, 0.0, 0.0, 0.0, 0.0, 0.0]"),
    "rational-distortions": ("distortions", "[0.1, 0.0, 0.0, 0.0, 0.0, 0.2, 0.0, 0.0]"),
    "distortion-string": ("distortions", '["0.1", 0.0, 0.0, 0.0, 0.0]'),
    "distortion-nan": ("distortions", "[nan, 0.0, 0.0, 0.0, 0.0]"),
    "distortions-number": ("distortions", "0.1"),
    "size-negative": ("size", "[-320, 240]"),
    "size-zero": ("size", "[0, 240]"),
    "size-fraction": ("size", "[320.5, 240]"),
    "size-three": ("size", "[320, 240, 3]"),
    "size-string": ("size", '"320x240"'),
    "rotation-nan": ("rotation", "[nan, 0.0, 0.0]"),
    "rotation-short": ("rotation", "[0.0, 0.0]"),
    "rotation-1e300": ("rotation", "[1e300, 0.0, 0.0]"),
    "translation-string": ("translation", '["0", "0", "10"]'),
    "translation-inf": ("translation", "[0.0, 0.0, inf]"),
    "name-number": ("name", "7"),
    "name-empty": ("name", '""'),
    "fps-zero": ("fps", "0.0"),
    "fps-negative": ("fps", "-30.0"),
    "fps-nan": ("fps", "nan"),
    "fps-string": ("fps", '"30"'),
    "fps-bool": ("fps", "true"),
    "offset-nan": ("time_offset", "nan"),
    "offset-huge": ("time_offset", "1e300"),
    "offset-string": ("time_offset", '"0.5"'),
    "offset-hours": ("time_offset", "-20000.0"),
    "joints-not-table": ("joints", "5"),
}

TRACK_SPOILS = {  # case: (column, value) of one row
    "frame-text": ("frame", "zero"),
    "frame-negative": ("frame", "-3"),
    "frame-fraction": ("frame", "2.5"),
    "frame-superscript": ("frame", "²"),
    "frame-huge": ("frame", "999999999999"),
    "frame-beyond-limit": ("frame", "200000000"),
    "x-text": ("x", "left"),
    "x-nan": ("x", "nan"),
    "x-inf": ("x", "inf"),
    "x-empty": ("x", ""),
    "y-1e300": ("y", "1e300"),
    "x-1e9": ("x", "1e9"),
    "x-outside-image": ("x", "900"),
    "y-negative-far": ("y", "-500"),
    "camera-empty": ("camera", ""),
    "marker-empty": ("marker", ""),
    "camera-unknown": ("camera", "cam9"),
    "marker-unknown": ("marker", "Z9"),
    "time-text": ("time", "noon"),
    "time-inf": ("time", "inf"),
    "huge-field": ("marker", "M" * 200_000),
    "long-name": ("marker", "M" * 300),
}

TRACK_EXPECT = {  # case: what the line says (default: it names the tracks file)
    "frame-text": r"line 4: frame 'zero' is not an integer", "frame-negative": r"line 4: frame -3 is negative",
    "frame-fraction": r"line 4: frame '2\.5' is not an integer", "frame-superscript": r"line 4: frame '²'", "frame-huge": r"line 4: frame .* beyond",
    "frame-beyond-limit": r"line 4: frame .* beyond", "x-text": r"line 4: x 'left' is not a number",
    "x-nan": r"line 4: x and y must be finite", "x-inf": r"line 4: x and y must be finite",
    "x-empty": r"line 4: x is empty", "y-1e300": r"line 4: pixel .* far outside", "x-1e9": r"line 4: pixel .* far outside",
    "x-outside-image": r"frame 0, marker .* outside the 320x240 image", "y-negative-far": r"outside the 320x240 image",
    "camera-empty": r"line 4: camera and marker must not be empty", "marker-empty": r"line 4: camera and marker",
    "camera-unknown": r"camera\(s\) \['cam9'\]", "marker-unknown": r"Z9", "time-text": r"line 4: time 'noon'",
    "time-inf": r"line 4: time must be a finite number", "huge-field": r"line 4: not a readable CSV \(field larger",
    "long-name": r"line 4: a camera or marker name longer than 200",
}
PLACE_EXPECT = {"a-folder": "is a folder", "in-proc": "/proc is not writable", "under-a-file": "is a file, not a folder",
                "trailing-slash": "ends in a separator"}

TRACK_FILES = {  # case: whole-file contents
    "empty-file": "",
    "header-only-wrong": "cam,frame,marker,x,y\n",
    "header-missing-y": "camera,frame,marker,x\ncam1,0,U1,1\n",
    "too-few-fields": "camera,frame,marker,x,y\ncam1,0,U1,1\n",
    "too-many-fields": "camera,frame,marker,x,y\ncam1,0,U1,1,2,3\n",
    "nul-byte": "camera,frame,marker,x,y\ncam1,0,U1,1\x00,2\n",
    "not-utf8": None,  # bytes, below
    "binary": None,
}


def spoil_tracks_file(d: Path, case: str) -> None:
    path = d / "tracks.csv"
    if case == "not-utf8":
        path.write_bytes(b"camera,frame,marker,x,y\ncam1,0,U\xe91,1,2\n")
    elif case == "binary":
        path.write_bytes(bytes(range(256)) * 4)
    else:
        path.write_text(TRACK_FILES[case])


def duplicate_row(d: Path, name: str = "tracks.csv") -> None:
    lines = (d / name).read_text().splitlines()
    append_row(d, name, lines[5])


def lone_far_row(d: Path, name: str = "tracks.csv") -> None:
    append_row(d, name, "cam1,3000000,U1,100.0,100.0,100000.5")


# --- the commands, each reading the (spoiled) inputs -----------------------------------------


def argv_for(command: str, d: Path, tracks: str = "tracks.csv") -> list[str]:
    t = str(d / tracks)
    m, c = str(d / "machine.toml"), str(d / "cameras.toml")
    out = str(d / "out" / "result")
    return {
        "calibrate": ["calibrate", m, t, "--size", "320x240", "--out", out + ".toml"],
        "triangulate": ["triangulate", c, t, "--out", out + ".csv"],
        "fit": ["fit", m, c, t, "--out", out + ".csv"],
        "refine": ["refine", m, c, t, "--out", out + ".toml"],
        "sync": ["sync", c, t, "--machine", m, "--out", out + ".toml"],
        "track": ["track", str(d / "video.mp4"), "--machine", m, "--calibration", c, "--camera", "cam1",
                  "--labels", str(d / "labels.csv"), "--out", out + ".csv"],
        "view": ["view", "--machine", m, "--calibration", c, "--motion", str(d / "motion.csv"),
                 "--points", str(d / "points.csv"), "--tracks", t, "--save", out + ".rrd"],
    }[command]


CALIBRATION_READERS = ("triangulate", "fit", "refine", "sync", "track", "view")
TRACKS_READERS = ("calibrate", "triangulate", "fit", "refine", "sync", "view")

CASES: dict[str, object] = {}
EXPECT: dict[str, str] = {}  # case: a regex its one line must match (the families below)


def case(name: str, expect: str | None = None):
    def register(fn):
        assert name not in CASES, name
        CASES[name] = fn
        if expect is not None:
            EXPECT[name] = expect
        return fn
    return register


for _command in CALIBRATION_READERS:
    for _name, (_key, _value) in CAMERA_SPOILS.items():
        if _command == "view" and _key == "joints":
            continue  # the replay does not read the calibration frame's joints
        if _command in ("track", "view", "sync") and _name == "offset-hours":
            continue  # tracking one camera and the replay place nothing on the reference clock; sync finds offsets anew

        def _spoil(d, key=_key, value=_value, command=_command):
            set_camera_key(d, key, value)
            return argv_for(command, d)
        case(f"{_command}/camera-{_name}", rf"cameras\.toml: (\[cam_00\]: )?.*'?{_key}'?")(_spoil)
    for _key in ("matrix", "size", "rotation"):
        def _missing(d, key=_key, command=_command):
            drop_camera_key(d, key)
            return argv_for(command, d)
        case(f"{_command}/camera-missing-{_key}", rf"\[cam_00\]: missing {_key}")(_missing)

    def _not_toml(d, command=_command):
        (d / "cameras.toml").write_text("[cam_00\nname = 1\n")
        return argv_for(command, d)
    case(f"{_command}/camera-not-toml")(_not_toml)

    def _bom_bad(d, command=_command):
        (d / "cameras.toml").write_bytes(b"\xef\xbb\xbf[metadata]\nframe = 0\n")
        return argv_for(command, d)
    case(f"{_command}/camera-no-tables")(_bom_bad)

for _command in TRACKS_READERS:
    for _name, (_column, _value) in TRACK_SPOILS.items():
        if _command == "calibrate" and _name in ("camera-unknown", "time-text", "time-inf"):
            continue  # calibrate names its cameras from the tracks; the time column is optional there
        if _command == "view" and _name in ("marker-unknown", "camera-unknown", "x-outside-image", "y-negative-far"):
            continue  # the replay shows such tracks as they are
        if _command == "triangulate" and _name == "marker-unknown":
            continue  # triangulation knows no machine: any marker name is a point

        def _spoil(d, column=_column, value=_value, command=_command):
            set_track_field(d, "tracks.csv", column, value)
            return argv_for(command, d)
        case(f"{_command}/tracks-{_name}", TRACK_EXPECT.get(_name, "tracks.csv"))(_spoil)
    for _name in TRACK_FILES:
        def _file(d, name=_name, command=_command):
            spoil_tracks_file(d, name)
            return argv_for(command, d)
        case(f"{_command}/tracks-{_name}")(_file)

    def _dup(d, command=_command):
        duplicate_row(d)
        return argv_for(command, d)
    case(f"{_command}/tracks-duplicate-row")(_dup)

    def _dup_across(d, command=_command):
        return argv_for(command, d, "cam1.csv")[:2] + [str(d / "cam1.csv")] + argv_for(command, d, "cam1.csv")[2:] \
            if command == "calibrate" else _with_two(argv_for(command, d, "cam1.csv"), d)
    case(f"{_command}/tracks-same-file-twice")(_dup_across)

    def _far(d, command=_command):
        lone_far_row(d)
        return argv_for(command, d)
    case(f"{_command}/tracks-lone-row-at-frame-3000000")(_far)

    def _missing(d, command=_command):
        return argv_for(command, d, "nope.csv")
    case(f"{_command}/tracks-missing-file")(_missing)

    def _folder(d, command=_command):
        return argv_for(command, d, "session")
    case(f"{_command}/tracks-is-a-folder")(_folder)


def _with_two(argv: list[str], d: Path) -> list[str]:
    """The same tracks file given twice (every row duplicated)."""
    k = argv.index(str(d / "cam1.csv"))
    return argv[: k + 1] + [str(d / "cam1.csv")] + argv[k + 1:]


# --- outputs over inputs, onto folders, unwritable places --------------------------------------

OUTPUT_OPTIONS = {  # command: (argv with OUT as the output, {input name: path relative to the folder})
    "calibrate": (["calibrate", "machine.toml", "tracks.csv", "--size", "320x240", "--out", "OUT"],
                  {"machine": "machine.toml", "tracks": "tracks.csv"}),
    "calibrate-points": (["calibrate", "machine.toml", "tracks.csv", "--size", "320x240", "--out", "o.toml",
                          "--points", "OUT"], {"machine": "machine.toml", "tracks": "tracks.csv"}),
    "triangulate": (["triangulate", "cameras.toml", "tracks.csv", "--out", "OUT"],
                    {"calibration": "cameras.toml", "tracks": "tracks.csv"}),
    "fit": (["fit", "machine.toml", "cameras.toml", "tracks.csv", "--out", "OUT"],
            {"machine": "machine.toml", "calibration": "cameras.toml", "tracks": "tracks.csv"}),
    "refine": (["refine", "machine.toml", "cameras.toml", "tracks.csv", "--out", "OUT"],
               {"machine": "machine.toml", "calibration": "cameras.toml", "tracks": "tracks.csv"}),
    "refine-machine": (["refine", "machine.toml", "cameras.toml", "tracks.csv", "--out", "o.toml", "--markers",
                        "--out-machine", "OUT"], {"machine": "machine.toml", "calibration": "cameras.toml",
                                                  "tracks": "tracks.csv"}),
    "sync": (["sync", "cameras.toml", "tracks.csv", "--machine", "machine.toml", "--out", "OUT"],
             {"machine": "machine.toml", "tracks": "tracks.csv"}),
    "track": (["track", "video.mp4", "--machine", "machine.toml", "--calibration", "cameras.toml", "--camera",
               "cam1", "--labels", "labels.csv", "--out", "OUT"],
              {"video": "video.mp4", "machine": "machine.toml", "calibration": "cameras.toml", "labels": "labels.csv"}),
    "track-propose": (["track", "video.mp4", "--machine", "machine.toml", "--calibration", "cameras.toml",
                       "--camera", "cam1", "--propose-labels", "OUT"],
                      {"video": "video.mp4", "machine": "machine.toml", "calibration": "cameras.toml"}),
}


def _resolve(d: Path, argv: list[str], out: str) -> list[str]:
    return [out if a == "OUT" else str(d / a) if (d / a).exists() or a.endswith((".toml", ".csv")) else a
            for a in argv]


for _option, (_argv, _inputs) in OUTPUT_OPTIONS.items():
    _command = _option.split("-")[0]
    for _what, _rel in _inputs.items():
        def _over(d, argv=_argv, rel=_rel):
            return _resolve(d, argv, str(d / rel))
        case(f"{_command}/{_option}-over-{_what}", "writing it would destroy the input")(_over)

        def _over_dotted(d, argv=_argv, rel=_rel):
            return _resolve(d, argv, str(d / "session" / ".." / rel))
        case(f"{_command}/{_option}-over-{_what}-by-another-path", "writing it would destroy the input")(_over_dotted)
    for _where, _target in {"a-folder": "session", "in-proc": "/proc/mocap-out", "under-a-file": "tracks.csv/x",
                            "trailing-slash": "newdir/"}.items():
        def _bad_place(d, argv=_argv, target=_target):
            return _resolve(d, argv, target if target.startswith("/") else str(d / target) + ("/" if target.endswith("/") else ""))
        case(f"{_command}/{_option}-{_where}", PLACE_EXPECT[_where])(_bad_place)


def _view_save(target):
    def make(d):
        argv = argv_for("view", d)
        argv[-1] = target(d)
        return argv
    return make


for _name, _target in {
    "save-over-motion": lambda d: str(d / "motion.csv"),
    "save-not-rrd": lambda d: str(d / "out.txt"),
    "save-a-folder": lambda d: (d / "folder.rrd").mkdir() or str(d / "folder.rrd"),
    "save-in-proc": lambda _: "/proc/mocap.rrd",
    "save-under-a-file": lambda d: str(d / "tracks.csv" / "x.rrd"),
}.items():
    case(f"view/{_name}")(_view_save(_target))


@case("calibrate/out-and-points-the-same-file")
def _(d):
    return argv_for("calibrate", d) + ["--points", str(d / "out" / "result.toml")]


@case("refine/out-and-out-machine-the-same-file")
def _(d):
    return argv_for("refine", d) + ["--markers", "--out-machine", str(d / "out" / "result.toml")]


@case("calibrate/default-points-over-tracks")
def _(d):
    (d / "reference_points.csv").write_text((d / "tracks.csv").read_text())
    return ["calibrate", str(d / "machine.toml"), str(d / "reference_points.csv"), "--size", "320x240",
            "--out", str(d / "cameras2.toml")]


@case("fit/out-a-symlink-to-tracks", "writing it would destroy the input")
def _(d):
    (d / "link.csv").symlink_to(d / "tracks.csv")
    return argv_for("fit", d)[:-1] + [str(d / "link.csv")]


@case("triangulate/out-a-hard-link-to-tracks", "writing it would destroy the input")
def _(d):
    (d / "hard.csv").hardlink_to(d / "tracks.csv")
    return argv_for("triangulate", d)[:-1] + [str(d / "hard.csv")]


@case("sync/out-over-tracks")
def _(d):
    return ["sync", str(d / "cameras.toml"), str(d / "tracks.csv"), "--machine", str(d / "machine.toml"),
            "--out", str(d / "tracks.csv")]


# --- videos --------------------------------------------------------------------------------


def _track_video(spoil):
    def make(d):
        spoil(d / "video.mp4")
        return argv_for("track", d)
    return make


VIDEO_SPOILS = {
    "png-renamed-mp4": lambda p: p.write_bytes(bytes.fromhex("89504e470d0a1a0a0000000d49484452000000010000000108060000001f15c4890000000d49444154789c6360000002000001e221bc330000000049454e44ae426082")),
    "truncated-mp4": lambda p: p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2]),
    "text-file": lambda p: p.write_text("not a video\n"),
    "empty-file": lambda p: p.write_bytes(b""),
    "missing": lambda p: p.unlink(),
    "random-bytes": lambda p: p.write_bytes(np.random.default_rng(1).integers(0, 256, 5000, dtype=np.uint8).tobytes()),
    "wrong-size": lambda p: write_video(p, (160, 120), 3),
}
def truncated_h264(path: Path) -> None:
    """An H.264 MP4 cut in half: its index (moov atom) is lost."""
    with video_writer(path, (64, 48), FPS, "h264", 1) as write:
        for k in range(20):
            write(np.full((48, 64, 3), 10 * k, np.uint8))
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


VIDEO_SPOILS["truncated-h264"] = truncated_h264


def h264_cut_at_the_tail(path: Path) -> None:
    """An H.264 MP4 that the video library still opens but whose last bytes are lost."""
    with video_writer(path, (64, 48), FPS, "h264", 1) as write:
        for k in range(20):
            write(np.full((48, 64, 3), 10 * k, np.uint8))
    path.write_bytes(path.read_bytes()[: path.stat().st_size * 99 // 100])


@case("view/video-h264-cut-at-the-tail", r"video\.mp4: camera cam1: the MP4 cannot be read to its end")
def _(d):
    h264_cut_at_the_tail(d / "video.mp4")
    return argv_for("view", d) + ["--video", f"cam1={d / 'video.mp4'}"]
for _name, _spoil in VIDEO_SPOILS.items():
    case(f"track/video-{_name}", "video.mp4: ")(_track_video(_spoil))
    if _name != "wrong-size":  # the replay shows a video of any size
        def _view_video(d, spoil=_spoil):
            spoil(d / "video.mp4")
            return argv_for("view", d) + ["--video", f"cam1={d / 'video.mp4'}"]
        case(f"view/video-{_name}", "video.mp4: ")(_view_video)


def _track_args(extra: list[str], keep_out: bool = True):
    def make(d):
        argv = argv_for("track", d)
        if not keep_out:
            argv = argv[:-2]
        return argv + extra
    return make


for _name, _extra in {
    "camera-unknown": ["--camera", "cam9"],
    "start-negative": ["--start", "-1"],
    "stop-before-start": ["--start", "3", "--stop", "2"],
    "gate-zero": ["--gate", "0"],
    "contrast-nan": ["--min-contrast", "nan"],
    "contrast-beyond-grey-levels": ["--min-contrast", "300"],
    "start-beyond-video": ["--start", "50"],
}.items():
    case(f"track/{_name}")(_track_args(_extra))
case("track/no-out")(_track_args([], keep_out=False))


def _labels(spoil):
    def make(d):
        spoil(d)
        return argv_for("track", d)
    return make


for _name, _spoil in {
    "labels-other-camera": lambda d: (d / "labels.csv").write_text(
        (d / "labels.csv").read_text().replace("cam1,", "cam7,")),
    "labels-outside-image": lambda d: set_track_field(d, "labels.csv", "x", "5000", row=1),
    "labels-duplicate": lambda d: duplicate_row(d, "labels.csv"),
    "labels-marker-unknown": lambda d: set_track_field(d, "labels.csv", "marker", "Z9", row=1),
    "labels-frame-text": lambda d: set_track_field(d, "labels.csv", "frame", "first", row=1),
    "labels-missing": lambda d: (d / "labels.csv").unlink(),
}.items():
    case(f"track/{_name}")(_labels(_spoil))


# --- points files (the replay's, and the DLT's reference) ---------------------------------------

POINTS_SPOILS = {
    "frame-text": lambda lines: lines.__setitem__(2, "one" + lines[2][lines[2].index(","):]),
    "frame-negative": lambda lines: lines.__setitem__(2, "-" + lines[2]),
    "x-nan": lambda lines: lines.__setitem__(2, ",".join(lines[2].split(",")[:2] + ["nan"] + lines[2].split(",")[3:])),
    "z-text": lambda lines: lines.__setitem__(2, ",".join(lines[2].split(",")[:4] + ["deep"] + lines[2].split(",")[5:])),
    "duplicate-row": lambda lines: lines.append(lines[2]),
    "too-few-fields": lambda lines: lines.__setitem__(2, ",".join(lines[2].split(",")[:4])),
    "header-lacks-z": lambda lines: lines.__setitem__(0, lines[0].replace(",z,", ",depth,")),
    "views-text": lambda lines: lines.__setitem__(2, ",".join(lines[2].split(",")[:6] + ["two"])),
}


def _points(spoil, command):
    def make(d):
        lines = (d / "points.csv").read_text().splitlines()
        spoil(lines)
        (d / "points.csv").write_text("\n".join(lines) + "\n")
        if command == "view":
            return argv_for("view", d)
        return argv_for("calibrate", d) + ["--method", "dlt", "--reference", str(d / "points.csv")]
    return make


for _name, _spoil in POINTS_SPOILS.items():
    for _command in ("view", "calibrate"):
        case(f"{_command}/points-{_name}", r"points\.csv: line \d+: ")(_points(_spoil, _command))


# --- the initial guess of calibrate ------------------------------------------------------------

GUESS = """[cam1]
azimuth_deg = 100.0
elevation_deg = 12.0
tilt_deg = 0.0
position = [16.0, -58.0, 17.0]
focal_px = 600.0
"""

for _name, (_old, _new) in {
    "position-strings": ("[16.0, -58.0, 17.0]", '["16", "-58", "17"]'),
    "position-short": ("[16.0, -58.0, 17.0]", "[16.0, -58.0]"),
    "focal-negative": ("focal_px = 600.0", "focal_px = -600.0"),
    "azimuth-nan": ("azimuth_deg = 100.0", "azimuth_deg = nan"),
    "tilt-string": ("tilt_deg = 0.0", 'tilt_deg = "level"'),
    "key-missing": ("tilt_deg = 0.0\n", ""),
    "key-unknown": ("tilt_deg = 0.0", "tilt_deg = 0.0\nroll_deg = 1.0"),
    "not-a-table": ("[cam1]\n", "cam1 = 5\n[cam0]\n"),
}.items():
    def _guess(d, old=_old, new=_new):
        (d / "guess.toml").write_text(GUESS.replace(old, new))
        return argv_for("calibrate", d) + ["--guess", str(d / "guess.toml")]
    case(f"calibrate/guess-{_name}")(_guess)


# --- options of the reconstruction commands ---------------------------------------------------


def _options(command: str, extra: list[str]):
    def make(d):
        return argv_for(command, d) + extra
    return make


for _command, _extras in {
    "calibrate": {"size-text": ["--size", "big"], "size-zero": ["--size", "0x240"],
                  "size-huge": ["--size", "99999999999999999999x240"], "frame-absent": ["--frame", "77"],
                  "loss-scale-negative": ["--loss-scale", "-1"], "max-rms-zero": ["--max-rms", "0"],
                  "method-unknown": ["--method", "magic"], "guess-missing": ["--guess", "nope.toml"],
                  "dlt-without-reference": ["--method", "dlt"], "size-camera-unknown": ["--size", "cam9=320x240"]},
    "triangulate": {"min-views-one": ["--min-views", "1"], "min-views-beyond-cameras": ["--min-views", "3"], "max-error-negative": ["--max-error-px", "-2"],
                    "max-error-nan": ["--max-error-px", "nan"], "min-views-text": ["--min-views", "two"]},
    "fit": {"loss-unknown": ["--loss", "square"], "loss-scale-zero": ["--loss-scale", "0"],
            "noise-negative": ["--noise-px", "-1"], "max-gap-negative": ["--max-gap", "-1"],
            "process-noise-nan": ["--process-noise", "nan"]},
    "refine": {"frames-zero": ["--frames", "0"], "tolerance-negative": ["--tolerance", "-0.1"],
               "out-machine-without-markers": ["--out-machine", "m.toml"], "max-median-nan": ["--max-median", "nan"]},
    "sync": {"fps-zero": ["--fps", "cam1=0"], "fps-negative": ["--fps", "cam1=-30"], "fps-text": ["--fps", "cam1=fast"],
             "fps-camera-unknown": ["--fps", "cam9=30"], "fps-no-name": ["--fps", "30"],
             "max-offset-zero": ["--max-offset", "0"], "fps-nan": ["--fps", "cam1=nan"],
             "max-offset-huge": ["--max-offset", "1e12"]},
    "view": {"video-no-name": ["--video", "cam1.mp4"], "video-camera-unknown": ["--video", "cam9=x.mp4"],
             "cycles-missing": ["--cycles", "nope.csv"]},
}.items():
    for _name, _extra in _extras.items():
        case(f"{_command}/{_name}")(_options(_command, _extra))

for _name, _text in {
    "cycles-huge-frame": "start_frame,end_frame\n0,99999999999999999999999\n",
    "cycles-negative": "start_frame,end_frame\n-5,10\n",
    "cycles-reversed": "start_frame,end_frame\n10,5\n",
    "cycles-text": "start_frame,end_frame\nfirst,10\n",
    "cycles-no-header": "0,10\n",
}.items():
    def _cycles(d, text=_text):
        (d / "cycles.csv").write_text(text)
        return argv_for("view", d) + ["--cycles", str(d / "cycles.csv")]
    case(f"view/{_name}")(_cycles)

for _name, _spoil in {
    "motion-text": lambda lines: lines.__setitem__(3, lines[3].replace(",", ",abc,", 1).rsplit(",", 1)[0]),
    "motion-too-few-fields": lambda lines: lines.__setitem__(3, lines[3].rsplit(",", 2)[0]),
    "motion-frames-repeat": lambda lines: lines.append(lines[-1]),
    "motion-frame-fraction": lambda lines: lines.__setitem__(3, "2.5" + lines[3][lines[3].index(","):]),
    "motion-header-lacks-joint": lambda lines: lines.__setitem__(0, lines[0].replace(",boom,", ",beam,")),
    "motion-time-nan": lambda lines: lines.__setitem__(3, lines[3].split(",")[0] + ",nan," + ",".join(lines[3].split(",")[2:])),
}.items():
    def _motion(d, spoil=_spoil):
        lines = (d / "motion.csv").read_text().splitlines()
        spoil(lines)
        (d / "motion.csv").write_text("\n".join(lines) + "\n")
        return argv_for("view", d)
    case(f"view/{_name}")(_motion)

for _command, _extras in {
}.items():
    for _name, _extra in _extras.items():
        case(f"{_command}/{_name}")(_options(_command, _extra))


# --- wrong machine model ------------------------------------------------------------------------

_ARM = ('name = "arm", type = "revolute", axis = [0, -1, 0], origin = [2.4, 0, 0], rpy_deg = [0, 0, 0], '
        'limits = [-160, -10]')
MACHINE_SPOILS = {  # case: (text of the rig's model, its replacement, what the line says)
    "marker-at-1e300-m": ("position = [0.9, 0.76, 0.3]", "position = [1e300, 0.76, 0.3]",
                          r"machine\.toml: marker 'U1': 'position' .* beyond 10000 m"),
    "joint-origin-at-1e300-m": ("origin = [2.4, 0, 0]", "origin = [1e300, 0, 0]",
                                r"machine\.toml: link 'arm' joint 'arm': 'origin' .* beyond 10000 m"),
    "prismatic-stroke-absurd": (_ARM, _ARM.replace('"revolute", axis = [0, -1, 0]', '"prismatic", axis = [1, 0, 0]')
                                .replace("[-160, -10]", "[0, 1e6]"), r"prismatic limits .* beyond 10000 m"),
}


for _command in ("calibrate", "fit", "refine", "sync", "track", "view"):
    for _name, _text in {
        "machine-limits-reversed": 'name = "x"\n[[links]]\nname = "base"\n[[links]]\nname = "arm"\nparent = "base"\n'
                                   'joint = { name = "j", type = "revolute", axis = [0, 0, 1], limits = [75.0, -75.0] }\n',
        "machine-limits-radians": 'name = "x"\n[[links]]\nname = "base"\n[[links]]\nname = "arm"\nparent = "base"\n'
                                  'joint = { name = "j", type = "revolute", axis = [0, 0, 1], limits = [-500, 500] }\n',
        "machine-empty": "",
        "machine-no-markers": 'name = "x"\n[[links]]\nname = "base"\n',
        "machine-not-toml": "name = \n",
    }.items():
        def _machine(d, text=_text, command=_command):
            (d / "machine.toml").write_text(text)
            return argv_for(command, d)
        case(f"{_command}/{_name}", r"machine\.toml: ")(_machine)

    for _name, (_old, _new, _expect) in MACHINE_SPOILS.items():
        def _spoiled(d, old=_old, new=_new, command=_command):
            text = (d / "machine.toml").read_text()
            assert old in text
            (d / "machine.toml").write_text(text.replace(old, new, 1))
            return argv_for(command, d)
        case(f"{_command}/machine-{_name}", _expect)(_spoiled)

    def _other(d, command=_command):
        shutil.copy(MACHINES_DIR / "hitachi_ex3500.toml", d / "machine.toml")
        # refine finds the wrong model only after its fit: on 8 of the 45 frames (2 s, not 9 s)
        return argv_for(command, d) + (["--frames", "8"] if command == "refine" else [])
    if _command in ("refine", "sync", "view"):
        case(f"{_command}/machine-another-model",
             r"wrong machine model" if _command == "refine" else None)(_other)


# --- command lines argparse refuses ----------------------------------------------------------

for _name, _argv in {
    "none": [],
    "unknown-command": ["explode"],
    "calibrate/no-size": ["calibrate", "m.toml", "t.csv", "--out", "c.toml"],
    "calibrate/frame-text": ["calibrate", "m.toml", "t.csv", "--size", "1x1", "--out", "c.toml", "--frame", "x"],
    "track/no-machine": ["track", "v.mp4", "--calibration", "c.toml", "--camera", "cam1"],
    "sync/no-machine": ["sync", "c.toml", "t.csv", "--out", "c.toml"],
    "triangulate/no-tracks": ["triangulate", "c.toml", "--out", "p.csv"],
    "fit/unknown-option": ["fit", "m.toml", "c.toml", "t.csv", "--out", "o.csv", "--fast"],
    "refine/frames-text": ["refine", "m.toml", "c.toml", "t.csv", "--out", "o.toml", "--frames", "many"],
    "view/save-twice-missing-value": ["view", "--save"],
    "synth/cameras-text": ["synth", "--out", "s", "--cameras", "two"],
    "run/no-session": ["run"],
    "demo/seed-text": ["demo", "--seed", "x"],
}.items():
    _command = _name.split("/")[0] if "/" in _name else "cli"
    case(_name if "/" in _name else f"cli/{_name}")(lambda d, argv=_argv: argv)


# --- synth, demo and run --------------------------------------------------------------------------


for _name, _extra in {
    "out-existing-file": ["--out", "tracks.csv"],
    "out-nonempty-folder": ["--out", "session"],
    "out-in-proc": ["--out", "/proc/mocap-session"],
    "out-under-a-file": ["--out", "tracks.csv/s"],
    "cameras-zero": ["--cameras", "0", "--out", "new"],
    "cycles-zero": ["--cycles", "0", "--out", "new"],
    "size-text": ["--size", "wide", "--out", "new"],
    "size-tiny": ["--size", "10x10", "--out", "new"],
    "size-huge": ["--size", "100000x100000", "--out", "new"],
    "cycles-million": ["--cycles", "1000000", "--out", "new"],
    "scale-zero": ["--scale", "0", "--out", "new"],
    "machine-unknown": ["--machine", "nope", "--out", "new"],
    "hold-short": ["--hold", "0.1", "--out", "new"],
    "fps-huge": ["--fps", "1000", "--out", "new"],
    "classes-bad": ["--classes", "4", "--out", "new"],
    "noise-negative": ["--noise", "-1", "--out", "new"],
    "redirect-not-a-probability": ["--redirect", "2", "--out", "new"],
}.items():
    def _synth(d, extra=_extra):
        return ["synth", "--machine", "bobcat_225",
                *[str(d / a) if a in ("tracks.csv", "session", "new", "tracks.csv/s") else a for a in extra], "--no-video"]
    case(f"synth/{_name}")(_synth)

for _name, _extra in {
    "out-existing-file": ["--out", "tracks.csv"],
    "out-foreign-folder": ["--out", "session"],
    "out-in-proc": ["--out", "/proc/mocap-demo"],
    "cameras-zero": ["--cameras", "0"],
    "scale-huge": ["--scale", "100"],
    "fps-zero": ["--fps", "0"],
}.items():
    def _demo(d, extra=_extra):
        return ["demo", *[str(d / a) if a in ("tracks.csv", "session") else a for a in extra]] + \
            ([] if "--out" in extra else ["--out", str(d / "new")])
    case(f"demo/{_name}")(_demo)


def _run(spoil):
    def make(d):
        spoil(d / "session")
        return ["run", str(d / "session")]
    return make


for _name, _spoil in {
    "no-session-toml": lambda s: (s / "session.toml").unlink(),
    "session-not-a-folder": lambda s: None,
    "fps-zero": lambda s: (s / "session.toml").write_text((s / "session.toml").read_text().replace("fps = 30.0", "fps = 0", 1)),
    "fps-string": lambda s: (s / "session.toml").write_text((s / "session.toml").read_text().replace("fps = 30.0", 'fps = "30"', 1)),
    "unknown-key": lambda s: (s / "session.toml").write_text("colour = 1\n" + (s / "session.toml").read_text()),
    "no-labels": lambda s: (s / "calibration" / "labels.csv").unlink(),
    "labels-one-camera": lambda s: (s / "calibration" / "labels.csv").write_text(
        "".join(l + "\n" for l in (s / "calibration" / "labels.csv").read_text().splitlines() if not l.startswith("cam2"))),
    "video-missing": lambda s: (s / "videos" / "cam2.mp4").unlink(),
    "video-not-a-video": lambda s: (s / "videos" / "cam2.mp4").write_text("hello\n"),
    "video-truncated": lambda s: (s / "videos" / "cam1.mp4").write_bytes((s / "videos" / "cam1.mp4").read_bytes()[:300]),
    "machine-missing": lambda s: (s / "machine.toml").unlink(),
    "labels-outside-image": lambda s: set_track_field(s / "calibration", "labels.csv", "x", "1e5", row=1),
}.items():
    case(f"run/{_name}")(_run(_spoil))
CASES["run/session-not-a-folder"] = lambda d: ["run", str(d / "tracks.csv")]


# --- the test -----------------------------------------------------------------------------------


@pytest.mark.parametrize("command", ["calibrate", "calibrate-dlt", "triangulate", "fit", "refine", "sync", "track",
                                     "view"])
def test_control_the_unspoiled_inputs_succeed(command, work, capsys):
    """Each case spoils one thing of inputs that, unspoiled, go through (so a case fails for
    its own reason, not for the rig's)."""
    argv = argv_for(command.split("-")[0], work)
    if command == "calibrate-dlt":
        argv += ["--method", "dlt", "--reference", str(work / "points.csv")]
    if command == "track":
        # the rig's video is plain grey: every input is accepted and read, and what stops the
        # command is that the video shows no marker (an empty result is an error)
        assert main(argv) == 2
        assert "no marker found" in capsys.readouterr().err
        return
    assert main(argv) == 0, capsys.readouterr().err
    assert (work / "out").is_dir()


@pytest.mark.parametrize("name", sorted(CASES))
def test_bad_input(name, work, capsys):
    capsys.readouterr()
    argv = CASES[name](work)
    before = snapshot(work)
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2, f"exit {code}, stderr: {err!r}"
    assert "Traceback" not in err
    lines = err.strip("\n").split("\n")
    assert len(lines) == 1 and lines[0].startswith("mocap"), f"stderr not one line: {err!r}"
    assert "np.float64" not in err and "np.str_" not in err
    if name in EXPECT:
        assert re.search(EXPECT[name], lines[0]), f"{lines[0]!r} does not say {EXPECT[name]!r}"
    assert snapshot(work) == before, "an input changed or an output was left behind"


def test_the_corpus_is_large():
    assert len(CASES) >= 250


@pytest.mark.parametrize("name", ["track/video-truncated-h264", "fit/unknown-option"])
def test_one_line_in_a_real_process(name, work):
    """In its own process (logging, the video library's own log, argparse as a user meets
    them) a case still prints exactly one line."""
    argv = CASES[name](work)
    done = subprocess.run([sys.executable, "-m", "mocap.cli", *argv], capture_output=True, text=True,
                          cwd=Path(__file__).resolve().parents[1], timeout=120)
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "Traceback" not in done.stderr, done.stderr
