"""`mocap sync`: each camera's time offset from the motion itself, written into the calibration."""

from __future__ import annotations

import argparse

from mocap.commands import COMMANDS
from mocap.commands.arguments import add_allow_partial, partial_status
from mocap.io.outputs import check_outputs

EXAMPLE = """example:
  mocap sync calibration/cameras.toml tracks/cam1.csv tracks/cam2.csv tracks/cam3.csv \\
      --machine hitachi_ex3500 --out calibration/cameras.toml"""


def add_parser(sub) -> None:
    p = sub.add_parser(
        "sync",
        help=COMMANDS["sync"],
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
    add_allow_partial(p, "a camera could not be synchronised while others were (it keeps the calibration's "
                      "time_offset; the others' offsets are written either way)")
    p.set_defaults(run=run)


def run(args) -> int:
    from mocap.clocks.stage import run_sync

    check_outputs({"--out": args.out},
                  {"machine model": args.machine, "calibration": args.calibration, "tracks": args.tracks},
                  may_replace=("calibration",))
    report = run_sync(args.machine, args.calibration, args.tracks, args.out, args.fps, args.max_offset)
    return partial_status("sync", report, args.allow_partial)
