"""The `mocap` command line: one sub-command per pipeline stage.

Each command module in `mocap.commands` has ``add_parser(subparsers)`` and ``run(args)``;
a user error (InputError) becomes one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
import warnings

from mocap.errors import InputError

COMMANDS = {  # name: one line of help; each command's module is imported only when it runs
    "calibrate": "calibrate cameras against the machine's markers in one frame",
    "view": "record the 3-D replay of a dig in Rerun",
    "synth": "write a synthetic session (videos and truth) of a machine digging",
    "track": "detect, label and track the machine's markers in one camera's video",
    "sync": "estimate each camera's time offset from the machine's motion",
    "triangulate": "triangulate every marker in every frame seen by two or more cameras",
    "fit": "fit the machine model to all cameras' marker pixels in every frame",
    "analyze": "dig cycles, phases, classes, similarity and templates from the motion",
    "refine": "refine cameras (and marker positions) over many frames",
    "run": "run the whole chain on a session folder",
    "batch": "run every session under the paths through the chain on Dask, skip what is up to date",
    "export": "write markers (C3D, TRC), a machine model (URDF) or a session (COLMAP) for other tools",
    "demo": "make a synthetic session, run the whole chain and score it against the truth",
    "report": "the session report: calibration, tracking, sync and fit quality, and what to fix first",
}


class UsageError(Exception):
    """A command line argparse refuses; its message is the one line to print."""


class _Parser(argparse.ArgumentParser):
    """argparse's parser, its errors one line (the usage is in --help) and raised, not exited."""

    def error(self, message: str):
        raise UsageError(f"{self.prog}: error: {message}; see {self.prog} --help")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser, with the full arguments of `command` (None: of every command)."""
    parser = _Parser(
        prog="mocap",
        description="Motion capture of mining machines, calibrated against the machine itself.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True, parser_class=_Parser)
    for name, summary in COMMANDS.items():
        if command is None or name == command:
            importlib.import_module(f"mocap.commands.{name}").add_parser(sub)
        else:
            sub.add_parser(name, help=summary)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    command = next((arg for arg in argv if not arg.startswith("-")), None)
    try:
        args = build_parser(command if command in COMMANDS else "").parse_args(argv)
    except UsageError as exc:
        print(_one_line(str(exc)), file=sys.stderr)
        return 2
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    _quiet_libraries(args.verbose)
    try:
        return int(args.run(args) or 0)
    except InputError as exc:
        print(_one_line(f"mocap {args.command}: error: {exc}"), file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"mocap {args.command}: interrupted", file=sys.stderr)
        return 130


def _one_line(message: str) -> str:
    """A message as one line: line breaks (from a file's own text, say) become spaces."""
    return " ".join(message.split())


def _quiet_libraries(verbose: bool) -> None:
    """The video library's own log lines (FFmpeg's "moov atom not found" beside our error)
    are silenced: a video that cannot be read is reported once, by us. So are numpy's
    warnings on empty or all-NaN slices (a frame nobody saw), unless --verbose."""
    import av.logging

    av.logging.set_level(av.logging.DEBUG if verbose else None)
    if not verbose:
        warnings.filterwarnings("ignore", category=RuntimeWarning)


if __name__ == "__main__":
    sys.exit(main())
