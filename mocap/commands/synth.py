"""`mocap synth`: write a synthetic field session with exact ground truth."""

from __future__ import annotations

import argparse
from pathlib import Path

from mocap.commands import COMMANDS
CODECS = ("h264", "mp4v")  # mocap.synthetic.encode's, named here so that --help needs no video library


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "synth",
        help=COMMANDS["synth"],
        description="Plan dig cycles of a machine model, place field cameras around it and write "
        "a session folder: session.toml, videos/<camera>.mp4 and truth/ (cameras.toml, motion.csv, "
        "tracks.csv, markers.csv, cycles.csv, scene.toml). Deterministic for a seed.",
    )
    p.add_argument("--machine", required=True, help="shipped model name or machine TOML path")
    p.add_argument("--cameras", type=int, default=3, help="number of cameras (default 3)")
    p.add_argument("--cycles", type=int, default=4, help="number of dig cycles (default 4)")
    p.add_argument("--seed", type=int, default=7, help="random seed (default 7)")
    p.add_argument("--out", required=True, type=Path, help="session folder to write")
    p.add_argument("--size", default="1920x1080", help="image size WxH (default 1920x1080)")
    p.add_argument("--classes", default="1,2,3", help="dig classes to use, e.g. 1,3 (default 1,2,3)")
    p.add_argument("--distortion", action="store_true", help="give the lenses radial distortion")
    p.add_argument("--shake", type=float, default=0.0, metavar="DEG", help="camera shake SD in degrees")
    p.add_argument("--bounce", type=float, default=1.0, help="base bouncing, times nominal (0: none)")
    p.add_argument("--reactive", type=float, default=1.0, help="reactive dig noise, times nominal (0: none)")
    p.add_argument("--redirect", type=float, default=0.4, metavar="P",
                   help="probability of an operator's redirection per dig (default 0.4)")
    p.add_argument("--fps", type=float, default=30.0,
                   help="the first camera's frame rate; the others run at it or 1000/1001 of it (default 30)")
    p.add_argument("--hold", type=float, default=2.0, help="seconds the machine holds still at the start")
    p.add_argument("--scale", type=float, default=1.0, help="scale the image size, e.g. 0.5 for fast tests")
    p.add_argument("--codec", choices=CODECS, default="h264", help="h264 (PyAV) or mp4v (OpenCV); default h264")
    p.add_argument("--noise", type=float, default=2.5, help="sensor noise SD in grey levels (0: none)")
    p.add_argument("--blur", type=float, default=0.5,
                   help="motion blur: the exposure as a share of the frame interval, 0..0.9 (default 0.5)")
    p.add_argument("--exposure", type=float, default=0.08, help="SD of the exposure's slow drift (0: none)")
    p.add_argument("--dust", type=float, default=0.55, help="opacity of the densest dust, 0..0.9 (0: none)")
    p.add_argument("--clean", action="store_true", help="no camera effects at all (noise, blur, exposure, dust)")
    p.add_argument("--rolling-shutter", type=float, metavar="SHARE",
                   help="rows read one after another over this share of the frame interval, 0..0.9 "
                   "(default 0: a global shutter; with --look random, the look's); the truth follows it")
    p.add_argument("--look", choices=("default", "random"), default="default",
                   help="random: machine paint, light, marker paint, haze, defocus, compression, noise, size, lens, "
                   "shake and rolling shutter drawn from the seed (written to truth/scene.toml); "
                   "default: the usual look")
    p.add_argument("--no-video", action="store_true", help="write the truth only")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from mocap.synthetic.stage import SynthRequest, run_synth

    request = SynthRequest(
        machine=args.machine, out=args.out, cameras=args.cameras, cycles=args.cycles, seed=args.seed,
        size=args.size, classes=args.classes, distortion=args.distortion, shake=args.shake, bounce=args.bounce,
        reactive=args.reactive, redirect=args.redirect, hold=args.hold, scale=args.scale, codec=args.codec,
        noise=args.noise, blur=args.blur, exposure=args.exposure, dust=args.dust, clean=args.clean,
        rolling_shutter=args.rolling_shutter, look=args.look, no_video=args.no_video, fps=args.fps,
    )
    print(run_synth(request))
    return 0
