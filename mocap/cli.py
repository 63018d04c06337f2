"""The `mocap` command line: one sub-command per pipeline stage.

Each command module in `mocap.commands` has ``add_parser(subparsers)`` and ``run(args)``;
a user error (InputError) becomes one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from mocap.commands import COMMANDS
from mocap.errors import InputError, one_line


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
        print(one_line(str(exc)), file=sys.stderr)
        return 2
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    from mocap.progress import quiet_libraries  # the video library with it, only once a command runs

    quiet_libraries(args.verbose)
    try:
        return int(args.run(args) or 0)
    except InputError as exc:
        print(one_line(f"mocap {args.command}: error: {exc}"), file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"mocap {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
