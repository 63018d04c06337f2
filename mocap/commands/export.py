"""`mocap export`: a session's markers as C3D or TRC, a machine model as URDF, a session as a COLMAP model."""

from __future__ import annotations

import argparse

from mocap.commands import COMMANDS

EXAMPLE = """examples:
  mocap export c3d SESSION_DIR --out dig.c3d          # markers and named points, mm, for Nexus / Mokka
  mocap export trc SESSION_DIR --out dig.trc          # the same as OpenSim's TRC text
  mocap export urdf calibrations/machines/hitachi_ex3500.toml --out ex3500.urdf
  mocap export colmap SESSION_DIR --out SESSION_DIR/colmap   # cameras, images, points (text model)"""


def add_parser(sub) -> None:
    p = sub.add_parser(
        "export",
        help=COMMANDS["export"],
        description="Write a session's triangulated markers and the model's named points as a C3D or TRC "
        "marker file, a machine model as URDF, or a session as a COLMAP reconstruction.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("format", choices=("c3d", "trc", "urdf", "colmap"), help="what to write")
    p.add_argument("source", help="session folder (c3d, trc, colmap) or machine model TOML (urdf)")
    p.add_argument("--out", required=True, help="file (c3d, trc, urdf) or folder (colmap) to write")
    p.add_argument("--calibration", help="colmap: camera calibration TOML (default: the session's, refined if present)")
    p.set_defaults(run=run)


def run(args) -> int:
    from mocap.interchange import stage

    if args.format == "urdf":
        print(stage.export_urdf(args.source, args.out))
    elif args.format == "colmap":
        print(stage.export_colmap(args.source, args.out, args.calibration))
    else:
        print(stage.export_markers(args.source, args.format, args.out))
    return 0
