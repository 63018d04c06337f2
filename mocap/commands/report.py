"""`mocap report`: the session report (the measurement's quality at a glance) as one HTML page."""

from __future__ import annotations

from pathlib import Path

from mocap.commands import COMMANDS


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "report", help=COMMANDS["report"],
        description="Per camera its calibration residual, parameter SDs, place in a plan of the site and the "
        "share of each marker tracked over time; the sync offsets; the fit's residuals and SDs over time with "
        "its unexplained and filled frames; and what to fix first.",
    )
    p.add_argument("session", type=Path, help="session folder")
    p.add_argument("--out", type=Path, metavar="FILE.html", help="default SESSION/results/session_report.html")
    p.set_defaults(run=run)


def run(args) -> int:
    from mocap.errors import InputError
    from mocap.report.session_report import write_session_report

    if args.out is not None and args.out.suffix.lower() not in (".html", ".htm"):
        raise InputError(f"--out {args.out}: the report is an HTML page; name it FILE.html")
    print(f"wrote {write_session_report(args.session, args.out)}")
    return 0
