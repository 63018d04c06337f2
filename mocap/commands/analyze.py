"""`mocap analyze`: dig cycles, phases, classes, similarity, templates and deviations."""

from __future__ import annotations

import argparse

from mocap.commands import COMMANDS

EXAMPLE = """example:
  mocap analyze calibrations/machines/hitachi_ex3500.toml results/motion.csv --out results/"""


def add_parser(sub) -> None:
    p = sub.add_parser(
        "analyze",
        help=COMMANDS["analyze"],
        description="Split the motion into dig cycles (dig, swing loaded, dump, swing back), measure "
        "each, classify the digs by the paper's rules (Type 1-3, other), compare them (DTW), fit per-class "
        "templates with scaling and deviations. Writes DIR/cycles.csv, DIR/report.html and DIR/templates.toml.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("machine", help="machine model TOML (or the name of a shipped one)")
    p.add_argument("motion", help="motion CSV (from mocap fit)")
    p.add_argument("--out", required=True, help="folder to write cycles.csv, report.html, templates.toml")
    p.add_argument("--cycles", help="cycles CSV (start_frame,end_frame): analyse only the digs inside these cycles")
    p.set_defaults(run=run)


def run(args) -> int:
    from mocap.analysis.stage import run_analyze

    print(run_analyze(args.machine, args.motion, args.out, args.cycles))
    return 0
