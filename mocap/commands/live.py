"""`mocap live`: the machine's pose, frame by frame, from cameras as they deliver."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from pathlib import Path

from mocap.commands import COMMANDS
from mocap.errors import InputError
from mocap.io.outputs import check_outputs

INTERRUPTED = 130  # Ctrl-C: every row so far written, the summary printed

EXAMPLE = """examples:
  mocap live hitachi_ex3500 calibration/cameras.toml --source cam1=0 --source cam2=1 --out poses.csv
  mocap live hitachi_ex3500 calibration/cameras.toml --source cam1=rtsp://10.0.0.21/stream1 \\
      --source cam2=rtsp://10.0.0.22/stream1 --out poses.csv --feed tcp://127.0.0.1:7400 --record sessions/live1
  mocap live hitachi_ex3500 s/truth/cameras.toml --source cam1=s/videos/cam1.mp4 \\
      --source cam2=s/videos/cam2.mp4 --realtime --duration 20 --out poses.csv   # files played as cameras

exit status: 0 when the sources ended or --duration passed, 130 after Ctrl-C (every row so far
written), 2 on bad input."""


def add_parser(sub) -> None:
    p = sub.add_parser(
        "live",
        help=COMMANDS["live"],
        description="Track every camera's markers as its frames arrive (the tracker of mocap track), fit the "
        "machine to them frame by frame (the kernel of mocap fit, from the frame before) with a fixed-lag "
        "smoother, and append one row per reference-camera frame to --out as soon as it is known, flushed: "
        "frame,time,latency_ms,cameras, the joints, named points, bucket angle and their SDs. Ends with one "
        "summary line: frames in, out and dropped per camera and the latency p50 / p99 / max.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("machine", help="machine model TOML (or a shipped model's name)")
    p.add_argument("calibration", help="camera calibration TOML (fps and time offsets from its cameras)")
    p.add_argument("--source", action="append", required=True, metavar="NAME=SOURCE",
                   help="a calibrated camera and where its frames come from: a video file, a device number "
                   "(0, 1, ...) or a stream URL (rtsp://..., http://...); once per camera")
    p.add_argument("--out", required=True, help="poses CSV to append rows to (or .parquet, written at the end)")
    p.add_argument("--realtime", action="store_true",
                   help="play files as their cameras delivered them: frame f of camera k at f / fps_k + "
                   "time_offset_k after the start, late frames dropped (default: as fast as they are tracked)")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: when the sources end)")
    p.add_argument("--lag", type=int, default=1, metavar="FRAMES",
                   help="the smoother's fixed lag in reference frames, part of the latency (default 1; 0: "
                   "the filter alone)")
    base = p.add_mutually_exclusive_group()
    base.add_argument("--base-motion", action="store_true",
                      help="fit the base's pose every frame (a machine that bounces or walks, cameras moved since "
                      "the calibration); default: per frame while the last 3 s show it moving, tested as mocap fit "
                      "tests it, every second; columns base_x ... as in the motion CSV")
    base.add_argument("--fixed-base", action="store_true",
                      help="hold the base where the calibration saw it, even when the frames show it moving (no "
                      "base columns)")
    p.add_argument("--feed", metavar="tcp://127.0.0.1:PORT",
                   help="also send each row as a JSON line to the programs connected to this loopback port")
    p.add_argument("--follow-clocks", action="store_true",
                   help="re-estimate each other camera's time offset from the last 2 s of motion every 0.5 s (as "
                   "mocap sync does) and place its frames with it: a camera whose clock drifts from its stated fps")
    p.add_argument("--record", metavar="DIR", help="also write a session folder for the offline chain (mocap run)")
    p.add_argument("--view", nargs="?", const="", metavar="URL|FILE.rrd",
                   help="also show the machine, the bucket tip's trail and the joints as they come in a Rerun viewer: "
                   "alone, a viewer started here; a running viewer's URL (rerun+http://HOST:9876/proxy); or an .rrd "
                   "file to write and open later")
    p.set_defaults(run=run, hold_log=False)  # a camera lost or reconnected is said as it happens


def run(args) -> int:
    from mocap.live.feed import parse_feed
    from mocap.live.run import LiveRequest, run_live
    from mocap.live.sources import parse_source
    from mocap.reconstruct.kinfit import FitOptions

    view = None
    if args.view is not None:
        from mocap.live.view import check_target

        view = check_target(args.view)
    if args.duration is not None and not args.duration > 0:
        raise InputError(f"--duration {args.duration}: give a positive number of seconds")
    if args.lag < 0:
        raise InputError(f"--lag {args.lag}: give 0 or more frames")
    sources = tuple(parse_source(text) for text in args.source)
    if args.follow_clocks and len(sources) < 2:
        raise InputError("--follow-clocks follows a camera's clock against the reference camera's; give two "
                         "--source or more")
    files = [s.target for s in sources if not s.live]
    saved = view if view and view.endswith(".rrd") else None
    check_outputs({"--out": args.out, "--view": saved}, {"machine model": args.machine,
                                                         "calibration": args.calibration, "video": files})
    if args.record is not None and Path(args.record).is_file():
        raise InputError("--record names a file; give a folder for the session", path=args.record)
    request = LiveRequest(
        args.machine, Path(args.calibration), sources, Path(args.out), realtime=args.realtime,
        duration=args.duration, lag=args.lag, feed=parse_feed(args.feed) if args.feed else None,
        record=Path(args.record) if args.record else None, fit_options=FitOptions(base_motion=args.base_motion),
        choose_base=not args.fixed_base,
        view=view, follow_clocks=args.follow_clocks,
    )
    stop = threading.Event()
    previous = signal.signal(signal.SIGINT, lambda *_: stop.set())
    try:
        report = run_live(request, stop, announce=lambda text: print(f"mocap live: {text}", file=sys.stderr,
                                                                     flush=True))
    finally:
        signal.signal(signal.SIGINT, previous)
    print(report.summary(args.out), flush=True)
    if args.record:
        print(f"session written to {args.record} (mocap run {args.record} refines it)")
    return INTERRUPTED if report.interrupted else 0
