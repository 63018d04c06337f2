"""`mocap triangulate`: 3-D marker positions from every camera that sees them."""

from __future__ import annotations

import argparse

from mocap.commands import COMMANDS
from mocap.errors import InputError
from mocap.io.outputs import check_outputs

EXAMPLE = """example:
  mocap triangulate calibration/cameras.toml tracks/cam1.csv tracks/cam2.csv tracks/cam3.csv \\
      --out results/points.csv"""


def add_parser(sub) -> None:
    p = sub.add_parser(
        "triangulate",
        help=COMMANDS["triangulate"],
        description="Multi-view triangulation (the APAS replacement): tracks resampled to the "
        "reference camera's frames with the calibration's time offsets, undistorted, DLT, then "
        "reprojection-error refinement; with three or more views a wrong view is found and dropped.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("calibration", help="camera calibration TOML")
    p.add_argument("tracks", nargs="+", help="tracks CSV file(s), one per camera or all in one")
    p.add_argument("--out", required=True, help="points CSV to write")
    p.add_argument("--max-error-px", type=float, default=None, metavar="PX",
                   help="a view off by more than this is dropped when 3+ views remain, and a point whose "
                   "two views disagree by more is dropped (default: --sigmas times the pixel noise the "
                   "data have)")
    p.add_argument("--sigmas", type=float, default=5.0,
                   help="outlier threshold in units of the estimated pixel noise (default 5)")
    p.add_argument("--min-views", type=int, default=2, help="views needed for a point (default 2)")
    p.add_argument("--max-noise-px", type=float, default=None, metavar="PX",
                   help="refuse (exit 2, nothing written) when the views imply a pixel noise beyond this (default: "
                   "refused only when one camera contradicts the others, or the views disagree 5 times beyond the "
                   "noise the tracks show by themselves)")
    p.set_defaults(run=run)


def run(args) -> int:
    from mocap.reconstruct.stage import run_triangulate
    from mocap.reconstruct.triangulate import TriangulateOptions

    if args.max_noise_px is not None and not args.max_noise_px > 0:
        raise InputError(f"--max-noise-px {args.max_noise_px}: give a positive number of pixels")
    check_outputs({"--out": args.out},
                  {"calibration": args.calibration, "tracks": args.tracks})
    try:
        options = TriangulateOptions(max_error_px=args.max_error_px, sigmas=args.sigmas, min_views=args.min_views)
    except ValueError as exc:
        raise InputError(f"bad option: {exc}") from None
    print(run_triangulate(args.calibration, args.tracks, args.out, options, args.max_noise_px))
    return 0
