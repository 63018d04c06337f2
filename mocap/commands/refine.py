"""`mocap refine`: bundle adjustment of the cameras (and marker positions) over many frames."""

from __future__ import annotations

import argparse

from mocap.commands import COMMANDS
from mocap.commands.arguments import DISTORTION_CHOICES, TOLERANCE_HELP, tolerance
from mocap.errors import InputError
from mocap.io.outputs import check_outputs

EXAMPLE = """example:
  mocap refine calibrations/machines/hitachi_ex3500.toml calibration/cameras.toml tracks/*.csv \\
      --out calibration/refined.toml --markers --out-machine calibration/machine_refined.toml"""


def add_parser(sub) -> None:
    p = sub.add_parser(
        "refine",
        help=COMMANDS["refine"],
        description="Bundle adjustment over many frames of the session: the cameras calibrated "
        "from one frame, the per-frame joint values and, with --markers, the tape-measured marker "
        "positions within --tolerance. Writes the refined calibration and, with --out-machine, model.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("machine", help="machine model TOML (or the name of a shipped one)")
    p.add_argument("calibration", help="camera calibration TOML")
    p.add_argument("tracks", nargs="+", help="tracks CSV file(s), one per camera or all in one")
    p.add_argument("--out", required=True, help="refined calibration TOML to write")
    p.add_argument("--markers", action="store_true", help="also refine the marker positions")
    p.add_argument("--out-machine", help="refined machine model TOML to write (with --markers)")
    p.add_argument("--tolerance", type=tolerance, help=TOLERANCE_HELP + "; the markers are then refined "
                   "within it (default: the model file's tolerance; 5%% with --markers)")
    p.add_argument("--frames", type=int, default=120, help="frames used, at most (default 120)")
    p.add_argument("--fixed-focal", action="store_true", help="keep the focal lengths")
    p.add_argument("--distortion", choices=DISTORTION_CHOICES, default="auto",
                   help="lens distortion coefficients to free: none, k1, k1k2, full, or auto (default): "
                   "none, k1, k1 k2 in turn while the Bayesian information criterion falls")
    p.add_argument("--fit-principal-point", action="store_true", help="free each camera's principal point")
    p.add_argument("--base-motion", action="store_true", help="the base moves every frame (a hand-held board, "
                   "a bouncing or walking machine): fit its 6-DoF pose per frame")
    p.add_argument("--intrinsics", metavar="FILE", help="known intrinsics, used and kept: a calibration TOML "
                   "(ours or anipose's), an OpenCV YAML/XML (camera named after the file) or COLMAP cameras")
    p.add_argument("--loss-scale", type=float, default=2.0, metavar="PX", help="robust loss scale (default 2 px)")
    p.add_argument("--max-median", type=float, default=None, metavar="PX",
                   help="refuse the refinement when a camera's tracks lie further than this from the refined "
                   "cameras, median (default: no such gate; the tracks' noise is estimated and reported, and "
                   "only wrong labels or a wrong sync are refused)")
    p.set_defaults(run=run)


def run(args) -> int:
    from mocap.reconstruct.refine import RefineOptions
    from mocap.reconstruct.stage import run_refine

    check_outputs({"--out": args.out, "--out-machine": args.out_machine},
                  {"machine model": args.machine, "calibration": args.calibration, "tracks": args.tracks,
                   "intrinsics": args.intrinsics})
    if args.out_machine and not args.markers:
        raise InputError("--out-machine needs --markers (without it the model is not changed)")
    try:
        options = RefineOptions(frames=args.frames, markers=args.markers, tolerance=args.tolerance,
                                fit_focal=not args.fixed_focal, scale_px=args.loss_scale,
                                max_median_px=args.max_median, distortion=args.distortion,
                                fit_principal_point=args.fit_principal_point, base_motion=args.base_motion)
    except ValueError as exc:
        raise InputError(f"bad option: {exc}") from None
    print(run_refine(args.machine, args.calibration, args.tracks, args.out, args.out_machine, options, args.intrinsics))
    return 0
