"""The `mocap` command line: one sub-command per pipeline stage.

Each command module in `mocap.commands` has ``add_parser(subparsers)`` and ``run(args)``;
a user error (InputError) becomes one line on stderr and exit status 2, work done in part
exit status 3 (EXIT_PARTIAL), an interruption exit status 130. Log warnings are held until
the command ends: an error's or an interruption's one line is not preceded by them.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import os
import sys

from mocap.commands import COMMANDS
from mocap.errors import EXIT_BAD_INPUT, EXIT_INTERRUPTED, InputError, one_line


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


BLAS_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _one_blas_thread():
    """A command's linear algebra on one BLAS thread, unless the user's environment says how
    many: its matrices are small (a bundle of a few hundred parameters), it decodes and tracks
    on threads of its own, and on a busy machine a BLAS that spins a thread per core makes a
    5 ms Cholesky take a third of a second."""
    if any(os.environ.get(name) for name in BLAS_THREAD_VARIABLES):
        return contextlib.nullcontext()
    import scipy.linalg  # noqa: F401  (loads scipy's own BLAS, so that the limit reaches it too)
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1, user_api="blas")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    command = next((arg for arg in argv if not arg.startswith("-")), None)
    try:
        args = build_parser(command if command in COMMANDS else "").parse_args(argv)
    except UsageError as exc:
        print(one_line(str(exc)), file=sys.stderr)
        return EXIT_BAD_INPUT
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    from mocap.progress import quiet_libraries  # the video library with it, only once a command runs

    quiet_libraries(args.verbose)
    # the log as it happens with --verbose, or for a command that runs until stopped (hold_log False)
    held = _HeldWarnings(hold=not args.verbose and getattr(args, "hold_log", True))
    try:
        with _one_blas_thread():
            code = int(args.run(args) or 0)
    except InputError as exc:
        held.discard()
        print(one_line(f"mocap {args.command}: error: {exc}"), file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        held.discard()
        print(f"mocap {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as exc:
        if not _interrupted(exc):
            held.show()
            raise
        held.discard()  # Ctrl-C inside compiled code surfaces as another exception around it
        print(f"mocap {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    if code == EXIT_INTERRUPTED:
        held.discard()  # a stage interrupted: its one line is said
    else:
        held.show()
    return code


class _HeldWarnings(logging.Handler):
    """The log records of a command, held until it ends: shown when it ends otherwise than in
    an error or an interruption (whose one line then stands alone), dropped else. Held
    records of a command run inside another go to the outer command's hold. Without `hold`
    (--verbose) they go out as they come."""

    def __init__(self, hold: bool = True):
        super().__init__(logging.NOTSET)
        self.records: list[logging.LogRecord] = []
        self.root = logging.getLogger()
        self.handlers = self.root.handlers[:]
        if hold:
            self.root.handlers = [self]

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)

    def _restore(self) -> None:
        self.root.handlers = self.handlers

    def discard(self) -> None:
        self._restore()

    def show(self) -> None:
        self._restore()
        for record in self.records:
            if record.levelno >= self.root.getEffectiveLevel():
                self.root.handle(record)


def _interrupted(exc: BaseException) -> bool:
    """Whether a KeyboardInterrupt is among the causes of `exc`."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


if __name__ == "__main__":
    sys.exit(main())
