"""`mocap track`: labelled 2-D marker tracks from one camera's video."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mocap.commands import COMMANDS
from mocap.errors import EXIT_OK, EXIT_PARTIAL, InputError
from mocap.io.outputs import check_outputs

EXAMPLE = """examples:
  mocap track videos/cam1.mp4 --machine hitachi_ex3500 --calibration calibration/cameras.toml \\
      --camera cam1 --propose-labels tracks/cam1_labels.csv
  mocap track videos/cam1.mp4 --machine hitachi_ex3500 --calibration calibration/cameras.toml \\
      --camera cam1 --labels tracks/cam1_labels.csv --out tracks/cam1.csv --preview tracks/cam1_check.mp4
  mocap track videos/cam2.mp4 --machine board_with_tags.toml --out tracks/cam2.csv   # every marker a tag"""


def add_parser(sub) -> None:
    p = sub.add_parser(
        "track",
        help=COMMANDS["track"],
        description="Find the painted disk markers in every frame, name them with the model's "
        "markers and follow them through the video, guided by the calibrated camera and the "
        "machine model; markers the model gives a tag id (ArUco / AprilTag) are found by their "
        "ids (black on white or printed inverted). The first frame is labelled from --labels (digitised "
        "marker pixels), from the tags, or by fitting the model; --propose-labels writes that proposal for "
        "checking and stops. A model whose markers all carry tags needs no calibration.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("video", help="the camera's video file")
    p.add_argument("--machine", required=True, help="machine model TOML (or a shipped model's name)")
    p.add_argument("--calibration",
                   help="camera calibration TOML; required unless every marker of the model carries a tag")
    p.add_argument("--camera", help="the camera's name in the calibration (default: the calibration's only "
                   "camera, or the video file's name)")
    p.add_argument("--out", help="tracks CSV to write")
    p.add_argument("--labels", help="tracks CSV with the first frame's marker pixels")
    p.add_argument("--preview", metavar="OUT.mp4", help="also write the video with each label drawn on it")
    p.add_argument("--propose-labels", metavar="OUT.csv", help="write proposed first-frame labels and stop")
    p.add_argument("--start", type=int, default=0, help="first frame to track (default 0)")
    p.add_argument("--stop", type=int, help="frame to stop before (default: the end)")
    p.add_argument("--gate", type=float, default=10.0, metavar="PX", help="least search radius (default 10)")
    p.add_argument("--min-contrast", type=float, default=40.0, metavar="GREY",
                   help="least disk-to-background contrast, grey levels (default 40)")
    p.add_argument("--whole-video", action="store_true",
                   help="refuse a video that breaks before its end (default: keep the tracks up to the break, "
                   "exit status 3)")
    p.add_argument("--allow-partial", action="store_true",
                   help="a video that breaks before its end: keep the tracks up to the break and exit 0, not 3")
    p.add_argument("--no-occlusion", action="store_true",
                   help="do not predict markers hidden by the machine's own links")
    p.set_defaults(run=run)


def _locked(out: str | None):
    """The lock of the tracks file `out` (two commands writing it refuse each other), after a
    check that no other command holds its session folder's lock (`mocap run`, `mocap synth`)."""
    import contextlib

    from mocap.io.lock import check_free, folder_lock

    if out is None:
        return contextlib.nullcontext()
    folder = Path(out).resolve().parent
    session = next((p for p in (folder, folder.parent) if (p / "session.toml").is_file()), None)
    if session is not None:
        check_free(session)
    return folder_lock(folder, f"mocap track {out}", name=f".{Path(out).name}.lock")


def run(args) -> int:
    from mocap.tracking.detect import DetectOptions
    from mocap.tracking.stage import TrackRequest, run_track
    from mocap.tracking.tracker import TrackOptions

    if args.propose_labels is None and args.out is None:
        raise InputError("give --out TRACKS.csv (or --propose-labels OUT.csv to check the first frame)")
    if args.preview and Path(args.preview).suffix.lower() != ".mp4":
        raise InputError(f"--preview {args.preview}: give a .mp4 file")
    check_outputs({"--out": args.out, "--propose-labels": args.propose_labels, "--preview": args.preview},
                  {"video": args.video, "machine model": args.machine, "calibration": args.calibration,
                   "labels": args.labels})
    if args.start < 0 or (args.stop is not None and args.stop <= args.start):
        raise InputError(f"--start {args.start} --stop {args.stop}: need 0 <= start < stop")
    if not args.gate > 0 or not args.min_contrast > 0:
        raise InputError("--gate and --min-contrast must be positive")
    if not args.min_contrast < 255:
        raise InputError(f"--min-contrast {args.min_contrast:g}: grey levels end at 255; give a contrast below it "
                         "(default 40)")
    options = TrackOptions(
        gate_px=args.gate,
        occlusion=not args.no_occlusion,
        detect=DetectOptions(min_contrast=args.min_contrast),
    )
    request = TrackRequest(
        Path(args.video), args.machine, Path(args.calibration) if args.calibration else None, args.camera,
        Path(args.out) if args.out else None,
        Path(args.labels) if args.labels else None,
        Path(args.propose_labels) if args.propose_labels else None,
        args.start, args.stop, options, args.whole_video, Path(args.preview) if args.preview else None,
    )
    with _locked(args.out):
        report = run_track(request)
    print(report.text(args.out, args.propose_labels, args.preview))
    if report.summary is not None:
        for name, why in zip(report.summary.unplaced, report.summary.why):
            print(f"mocap track: warning: marker {name}: {why}", file=sys.stderr)
    if report.broken_at is not None:
        print(f"mocap track: partial: {args.video}: the video broke at frame {report.broken_at} (truncated or "
              f"corrupt); tracks of frames {args.start}-{report.broken_at - 1} written to {args.out}"
              + ("" if args.allow_partial else "; exit status 3 (--allow-partial: 0, --whole-video refuses it)"),
              file=sys.stderr)
        return EXIT_OK if args.allow_partial else EXIT_PARTIAL
    return EXIT_OK
