"""`mocap synth`: write a synthetic field session with exact ground truth."""

from __future__ import annotations

import argparse
import logging
from dataclasses import replace
from pathlib import Path

from mocap.cli import COMMANDS
from mocap.errors import InputError
from mocap.io.outputs import check_output_folder

log = logging.getLogger(__name__)

MAX_CYCLES = 100  # about an hour of digging
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


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--size {text!r}: expected WIDTHxHEIGHT, e.g. 1920x1080") from None
    if w < 64 or h < 64 or w > 7680 or h > 4320:
        raise InputError(f"--size {text!r}: from 64x64 to 7680x4320 pixels")
    return w, h


def parse_classes(text: str) -> tuple[str, ...]:
    from mocap.synthetic import CLASSES

    picks = [v.strip() for v in text.split(",") if v.strip()]
    if not picks or any(v not in ("1", "2", "3") for v in picks):
        raise InputError(f"--classes {text!r}: expected a comma list of 1, 2, 3")
    return tuple(CLASSES[int(v) - 1] for v in dict.fromkeys(picks))


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from mocap.io.machine_toml import load_machine, resolve_machine_path
    from mocap.session import Session, mark_complete
    from mocap.synthetic import SessionOptions, make_session, summary, write_truth
    from mocap.synthetic.effects import EffectOptions
    from mocap.synthetic.looks import Look, random_look
    from mocap.synthetic.render import RenderOptions, render_videos

    machine_path = resolve_machine_path(args.machine)
    machine = load_machine(machine_path)
    if not 1 <= args.cameras <= 8:
        raise InputError(f"--cameras {args.cameras}: give 1 to 8 cameras")
    if not 1 <= args.cycles <= MAX_CYCLES:
        raise InputError(f"--cycles {args.cycles}: give 1 to {MAX_CYCLES} dig cycles")
    if args.hold < 0.5:
        raise InputError(f"--hold {args.hold}: the machine must hold still at least 0.5 s")
    if not 5.0 <= args.fps <= 120.0:
        raise InputError(f"--fps {args.fps}: give a frame rate from 5 to 120")
    check_output_folder(args.out)
    session = Session.open(args.out)
    if args.out.exists() and any(args.out.iterdir()) and not (session.is_synthetic and not session.complete_path.exists()):
        raise InputError("the output folder exists and is not empty; choose a new folder", path=args.out)
    if not 0.05 <= args.scale <= 4.0:
        raise InputError(f"--scale {args.scale}: give a factor between 0.05 and 4")
    width, height = parse_size(args.size)
    look = random_look(np.random.default_rng([args.seed, 2])) if args.look == "random" else Look()
    if args.rolling_shutter is not None:
        if not 0.0 <= args.rolling_shutter <= 0.9:
            raise InputError(f"--rolling-shutter {args.rolling_shutter}: give a share of the frame interval, 0..0.9")
        look = replace(look, readout=args.rolling_shutter)
    scale = args.scale * look.scale
    size = (max(16, round(width * scale)), max(16, round(height * scale)))
    try:
        if args.clean:
            effects = EffectOptions.none()
        elif args.look == "random":
            effects = EffectOptions(look.noise, look.blur, look.exposure, look.dust)
        else:
            effects = EffectOptions(args.noise, args.blur, args.exposure, args.dust)
    except ValueError as exc:
        raise InputError(f"{exc}; noise and exposure take 0..50, blur and dust 0..0.9") from None
    options = SessionOptions(
        n_cameras=args.cameras, n_cycles=args.cycles, seed=args.seed, size=size,
        distortion=args.distortion or look.distortion, shake_deg=args.shake or look.shake_deg, bounce=args.bounce,
        reactive=args.reactive,
        redirect_probability=args.redirect, classes=parse_classes(args.classes), hold=args.hold,
        readout=look.readout, fps=args.fps,
    )
    session = make_session(machine, str(args.machine), options)
    args.out.mkdir(parents=True, exist_ok=True)  # an interrupted earlier run's folder is written over
    write_truth(session, args.out, machine_path, look)
    log.info("wrote the truth of %d cycles, %d cameras to %s", args.cycles, args.cameras, args.out)
    if not args.no_video:
        paths = render_videos(session, args.out, RenderOptions(codec=args.codec, effects=effects, look=look))
        log.info("wrote %d videos", len(paths))
    mark_complete(Session.open(args.out).complete_path, "mocap synth")
    print(summary(session))
    if args.look == "random":
        print(f"look: {look.name}")
    print(f"wrote {args.out}" + ("" if args.no_video else f" with {args.codec} videos"))
    return 0
