"""`mocap demo`: make a synthetic session, run the whole chain, compare with the truth."""

from __future__ import annotations

from pathlib import Path

from mocap.commands import COMMANDS
from mocap.orchestration.demo import DemoOptions, run_demo


def add_parser(sub) -> None:
    defaults = DemoOptions()
    p = sub.add_parser(
        "demo",
        help=COMMANDS["demo"],
        description="Render a synthetic field session (an EX3500 front shovel filmed by three cameras), "
        "calibrate each camera against the machine, track the markers, synchronise, triangulate, fit "
        "the motion, record the Rerun replay, and print how close it all came to the ground truth.",
    )
    p.add_argument("--out", type=Path, default=defaults.out, help=f"session folder (default {defaults.out})")
    p.add_argument("--machine", default=defaults.machine, help=f"machine model (default {defaults.machine})")
    p.add_argument("--cameras", type=int, default=defaults.cameras, help=f"cameras (default {defaults.cameras})")
    p.add_argument("--cycles", type=int, default=defaults.cycles, help=f"dig cycles (default {defaults.cycles})")
    p.add_argument("--seed", type=int, default=defaults.seed, help=f"random seed (default {defaults.seed})")
    p.add_argument("--scale", type=float, default=defaults.scale,
                   help=f"image scale of the 1920x1080 cameras (default {defaults.scale})")
    p.add_argument("--fps", type=float, default=defaults.fps,
                   help=f"the cameras' frame rate (default {defaults.fps:g}; the others at 1000/1001 of it or at it)")
    p.set_defaults(run=run)


def run(args) -> int:
    return run_demo(DemoOptions(args.out, args.machine, args.cameras, args.cycles, args.seed, args.scale, args.fps))
