"""`mocap fit`: the machine's joint values in every frame, smoothed, with uncertainties."""

from __future__ import annotations

import argparse

from mocap.commands import COMMANDS
from mocap.commands.arguments import TOLERANCE_HELP, add_allow_partial, partial_status, tolerance
from mocap.errors import InputError
from mocap.io.outputs import check_outputs

EXAMPLE = """example:
  mocap fit calibrations/machines/hitachi_ex3500.toml calibration/cameras.toml \\
      tracks/cam1.csv tracks/cam2.csv tracks/cam3.csv --out results/motion.csv"""


def add_parser(sub) -> None:
    p = sub.add_parser(
        "fit",
        help=COMMANDS["fit"],
        description="Per frame, the joint values that best explain every camera's observations "
        "(one camera is enough), robust to wrong detections; then a smoother fills short gaps. "
        "Writes joint values, named points (bucket tip), bucket angle, their standard deviations, "
        "tip speed and acceleration, and which frames were filled.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("machine", help="machine model TOML (or the name of a shipped one)")
    p.add_argument("calibration", help="camera calibration TOML")
    p.add_argument("tracks", nargs="+", help="tracks CSV file(s), one per camera or all in one")
    p.add_argument("--out", required=True, help="motion CSV to write")
    base = p.add_mutually_exclusive_group()
    base.add_argument("--base-motion", action="store_true",
                      help="also fit the base's 6-DoF pose per frame (bouncing, or moved since calibration); "
                      "default: when a sample of frames shows it moving (the report says so)")
    base.add_argument("--fixed-base", action="store_true",
                      help="hold the base where the calibration saw it, even when the frames show it moving")
    p.add_argument("--loss", choices=("huber", "cauchy", "linear"), default="huber",
                   help="robust loss (default huber)")
    p.add_argument("--loss-scale", type=float, default=2.0, metavar="PX", help="robust loss scale (default 2 px)")
    p.add_argument("--noise-px", type=float, help="pixel noise SD for the uncertainties "
                   "(default: estimated from the residuals)")
    p.add_argument("--tolerance", type=tolerance, help=TOLERANCE_HELP + "; each marker's offset from its "
                   "measured position is then estimated over the session (default: the model file's tolerance, "
                   "else exact)")
    p.add_argument("--out-machine", metavar="TOML", help="with a tolerance: also write the machine model with its "
                   "markers at their estimated positions")
    p.add_argument("--no-smooth", action="store_true", help="per-frame fit only, no smoothing or gap filling")
    p.add_argument("--max-gap", type=float, default=2.0, metavar="S",
                   help="longest gap the smoother fills, seconds (default 2)")
    p.add_argument("--process-noise", type=float, metavar="Q",
                   help="smoother's acceleration noise density, unit²/s³ (default: estimated)")
    p.add_argument("--max-noise-px", type=float, default=5.0, metavar="PX",
                   help="refuse (exit 2, nothing written) when the tracks imply a pixel noise beyond this: a wrong "
                   "model, calibration or labels (default 5)")
    add_allow_partial(p, "a stretch of frames is left unexplained (a run of 1 s or more, or over a tenth of the "
                      "fitted frames; the motion is written either way)")
    p.set_defaults(run=run)


def run(args) -> int:
    from mocap.reconstruct.kinfit import FitOptions
    from mocap.reconstruct.smooth import SmoothOptions
    from mocap.reconstruct.stage import run_fit

    if not args.max_noise_px > 0:
        raise InputError(f"--max-noise-px {args.max_noise_px}: give a positive number of pixels")
    check_outputs({"--out": args.out, "--out-machine": args.out_machine},
                  {"machine model": args.machine, "calibration": args.calibration, "tracks": args.tracks})
    try:
        fit_options = FitOptions(loss=args.loss, scale_px=args.loss_scale, noise_px=args.noise_px,
                                 base_motion=args.base_motion, tolerance=args.tolerance)
        smooth_options = None if args.no_smooth else SmoothOptions(
            process_noise=args.process_noise, max_gap_s=args.max_gap
        )
    except ValueError as exc:
        raise InputError(f"bad option: {exc}") from None
    report = run_fit(args.machine, args.calibration, args.tracks, args.out, fit_options, smooth_options,
                     args.max_noise_px, args.out_machine, choose_base=not args.fixed_base)
    return partial_status("fit", report, args.allow_partial)
