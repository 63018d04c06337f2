"""`mocap calibrate`: cameras calibrated against the machine itself (or by the DLT)."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from mocap.commands import COMMANDS
from mocap.commands.arguments import DISTORTION_CHOICES, TOLERANCE_HELP, tolerance
from mocap.errors import InputError
from mocap.io.outputs import check_outputs

EXAMPLE = """example:
  mocap calibrate calibrations/machines/hitachi_ex3500.toml tracks/cam1.csv tracks/cam2.csv \\
      --size 1920x1080 --out calibration/cameras.toml --frame 0"""


def add_parser(sub) -> None:
    p = sub.add_parser(
        "calibrate",
        help=COMMANDS["calibrate"],
        description="Fit each camera's parameters and the machine's joint values together to the "
        "marker pixels of one frame (no surveyed control points), or calibrate by the classic DLT.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("machine", help="machine model TOML (or the name of a shipped one)")
    p.add_argument("tracks", nargs="+", help="observations / tracks CSV file(s)")
    p.add_argument("--size", action="append", default=[], metavar="[NAME=]WxH",
                   help="image size, for every camera or per camera (repeatable); default: read from the "
                   "session's videos, when the tracks lie in a session folder")
    p.add_argument("--out", required=True, help="calibration TOML to write")
    p.add_argument("--frame", type=int, help="the calibration frame (default: the first frame)")
    p.add_argument("--per-camera", action="store_true", help="each camera with its own joint values")
    p.add_argument("--method", choices=("model", "dlt"), default="model",
                   help="model-based (default) or the 11-parameter DLT from >= 6 known points")
    p.add_argument("--reference", help="points CSV of known 3-D marker positions, for --method dlt")
    p.add_argument("--points", help="reference points CSV to write (default: reference_points.csv "
                   "beside --out)")
    p.add_argument("--guess", help="initial guess TOML in the paper's parameters (optional)")
    p.add_argument("--fit-principal-point", action="store_true", help="fit cx, cy too")
    p.add_argument("--distortion", choices=DISTORTION_CHOICES, default="auto",
                   help="distortion coefficients to fit; auto (default): none, k1, k1 k2 in turn while the "
                   "Bayesian information criterion of the residuals falls")
    p.add_argument("--loss-scale", type=float, default=2.0, metavar="PX",
                   help="robust loss scale in pixels (default 2)")
    p.add_argument("--outlier-px", type=float, help="residual beyond which an observation is "
                   "dropped (default max(4 px, 5 sigma))")
    p.add_argument("--tolerance", type=tolerance, help=TOLERANCE_HELP + "; the markers are then "
                   "fitted within it (default: the model file's tolerance, else exact)")
    p.add_argument("--intrinsics", metavar="FILE", help="known intrinsics, used and kept (focal length, "
                   "principal point, distortion): a calibration TOML (ours or anipose's), an OpenCV YAML/XML or "
                   "a COLMAP cameras.txt / model folder; cameras it does not name are fitted")
    p.add_argument("--max-rms", type=float, metavar="PX", help="residual RMS beyond which the fit "
                   "counts as not converged (default 1 %% of the image diagonal)")
    p.set_defaults(run=run)


def parse_sizes(values: list[str]) -> dict:
    from mocap.io.cameras_toml import MAX_IMAGE_SIDE

    sizes = {}
    for value in values:
        match = re.fullmatch(r"(?:([^=]+)=)?(\d+)x(\d+)", value.strip())
        if not match or int(match[2]) <= 0 or int(match[3]) <= 0:
            raise InputError(f"--size {value!r}: expected WxH or NAME=WxH, e.g. 1920x1080")
        if max(int(match[2]), int(match[3])) > MAX_IMAGE_SIDE:
            raise InputError(f"--size {value!r}: an image side is at most {MAX_IMAGE_SIDE} pixels")
        sizes[match[1]] = (int(match[2]), int(match[3]))
    return sizes


def run(args) -> int:
    from mocap.calibration.solve import CalibrationOptions
    from mocap.calibration.stage import CalibrateRequest, run_calibrate

    for option, value in (("--loss-scale", args.loss_scale), ("--outlier-px", args.outlier_px),
                          ("--max-rms", args.max_rms)):
        if value is not None and not 0 < value < float("inf"):
            raise InputError(f"{option} {value}: must be a positive number of pixels")
    if args.intrinsics and args.method == "dlt":
        raise InputError("--intrinsics keeps known intrinsics in the model-based calibration; the DLT fits "
                         "its own: leave out --method dlt or --intrinsics")
    points = args.points or str(Path(args.out).with_name("reference_points.csv"))
    check_outputs({"--out": args.out, "--points": None if args.method == "dlt" else points},
                  {"machine model": args.machine, "tracks": args.tracks, "--guess": args.guess,
                   "--reference": args.reference, "--intrinsics": args.intrinsics})
    options = CalibrationOptions(
        per_camera=args.per_camera,
        fit_principal_point=args.fit_principal_point,
        distortion="none" if args.distortion == "auto" else args.distortion,
        f_scale_px=args.loss_scale,
        outlier_px=args.outlier_px,
        max_rms_px=args.max_rms,
        tolerance=args.tolerance,
    )
    request = CalibrateRequest(
        machine=args.machine, tracks=tuple(args.tracks), sizes=parse_sizes(args.size), out=args.out,
        frame=args.frame, method=args.method, options=options, guess=args.guess,
        reference=args.reference, points_out=args.points, choose_lens=args.distortion == "auto",
        intrinsics=args.intrinsics,
    )
    print(run_calibrate(request))
    return 0
