"""`mocap run`: the whole chain on a session folder."""

from __future__ import annotations

import argparse
from pathlib import Path

from mocap.commands import COMMANDS
from mocap.commands.arguments import add_allow_partial

EXAMPLE = """example:
  mocap run SESSION_DIR          # needs SESSION_DIR/calibration/labels.csv (the first frame's markers)"""


def add_parser(sub) -> None:
    p = sub.add_parser(
        "run",
        help=COMMANDS["run"],
        description="Calibrate every camera against the machine from the calibration frame's labels, "
        "track every video, synchronise the cameras, triangulate, fit the machine's motion and "
        "record the replay, inside the session folder.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("session", type=Path, help="session folder (with session.toml)")
    p.add_argument("--labels", type=Path, help="calibration frame labels CSV (default calibration/labels.csv)")
    p.add_argument("--refine", action="store_true", help="bundle-adjust the cameras over the session first")
    p.add_argument("--no-view", action="store_true", help="skip the Rerun recording")
    add_allow_partial(p, "a stage did part of its work (a camera not synchronised, a stretch of frames "
                      "unexplained; the chain carries on after it either way)")
    p.set_defaults(run=run)


def run(args) -> int:
    from mocap.io.lock import folder_lock
    from mocap.orchestration.pipeline import RunOptions, run_session

    with folder_lock(args.session, "mocap run"):  # one command at a time writes the session
        return run_session(args.session, RunOptions(args.labels, args.refine, not args.no_view, args.allow_partial))
