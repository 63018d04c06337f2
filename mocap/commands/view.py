"""`mocap view`: the Rerun 3-D replay of a session's dig (an .rrd file and/or a viewer)."""

from __future__ import annotations

import argparse
from pathlib import Path

from mocap.commands import COMMANDS
from mocap.errors import InputError

EXAMPLES = """examples:
  mocap view SESSION_DIR                       # writes SESSION_DIR/results/session.rrd
  mocap view SESSION_DIR --open                # ... and opens it in the Rerun viewer
  mocap view SESSION_DIR --serve               # ... serves a web viewer (a headless or remote machine)
  mocap view --machine hitachi_ex3500 --calibration cameras.toml --motion motion.csv \\
      --points points.csv --tracks tracks/cam1.csv tracks/cam2.csv --video cam1=cam1.mp4 \\
      --save dig.rrd
"""


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "view",
        help=COMMANDS["view"],
        description="Record the machine, markers, cameras with their videos and 2-D tracks, "
        "the bucket tip's trail per dig cycle and time series into a Rerun recording.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("session", nargs="?", type=Path, help="session folder (paths below override its files)")
    p.add_argument("--machine", help="machine model: a shipped name or a TOML path")
    p.add_argument("--calibration", type=Path, help="cameras TOML")
    p.add_argument("--motion", type=Path, help="motion CSV")
    p.add_argument("--points", type=Path, help="triangulated points CSV")
    p.add_argument("--tracks", type=Path, nargs="+", default=[], help="2-D tracks CSV file(s)")
    p.add_argument("--video", action="append", default=[], metavar="NAME=PATH", help="a camera's H.264 video")
    p.add_argument(
        "--cycles", type=Path, help="dig cycles CSV (start_frame,end_frame[,cycle]); one trail if absent"
    )
    out = p.add_argument_group("output (a session saves to results/session.rrd unless told otherwise)")
    out.add_argument("--save", type=Path, metavar="FILE.rrd", help="write the recording to this file")
    out.add_argument("--connect", nargs="?", const="", metavar="URL", help="stream to a running viewer")
    out.add_argument("--serve", action="store_true", help="serve a web viewer until Ctrl-C")
    out.add_argument("--spawn", action="store_true", help="start the native viewer and stream to it")
    out.add_argument("--open", action="store_true",
                     help="save the recording (a session's results/session.rrd by default) and open it in the native viewer")
    p.set_defaults(run=run)


def run(args) -> int:
    from mocap.viewer import Sinks
    from mocap.viewer.inputs import ReplayFiles
    from mocap.viewer.stage import run_view

    if args.open:
        check_display()
    files = ReplayFiles(
        machine=args.machine,
        calibration=args.calibration,
        motion=args.motion,
        points=args.points,
        tracks=tuple(args.tracks),
        videos=parse_videos(args.video),
        cycles=args.cycles,
    )
    sinks = Sinks(args.save, args.connect, args.serve, args.spawn)
    if args.open and sinks.save is None:
        if args.session is None:
            raise InputError("--open opens a saved recording: pass --save FILE.rrd or a session folder")
        from mocap.io.session import Session

        sinks = Sinks(Session.open(args.session).recording_path, args.connect, args.serve, args.spawn)
    print(run_view(files, args.session, sinks, on_serving=lambda where: print(where, flush=True)))
    if args.open:
        from mocap.viewer.replay import open_viewer

        open_viewer(sinks.save)
        print(f"opening {sinks.save} in the Rerun viewer")
    return 0


def check_display() -> None:
    """InputError on a Linux machine without a display: the native viewer cannot open there."""
    import os
    import sys

    if sys.platform == "linux" and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise InputError("--open: this machine has no display; serve the web viewer instead with "
                         "`mocap view SESSION_DIR --serve` (the README says how to reach it from another machine)")


def parse_videos(items: list[str]) -> dict[str, Path]:
    videos = {}
    for item in items:
        name, sep, path = item.partition("=")
        if not sep or not name.strip() or not path.strip():
            raise InputError(f"--video {item!r}: expected NAME=PATH, e.g. --video cam1=videos/cam1.mp4")
        videos[name.strip()] = Path(path.strip())
    return videos
