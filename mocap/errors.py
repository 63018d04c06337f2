"""The project's error types.

`InputError` is a user error (a bad file, a bad option, a degenerate set of observations):
the command line turns it into one line on stderr and exit status 2. Anything else is a bug.
"""

from __future__ import annotations

# exit statuses of the command line (README: exit statuses)
EXIT_OK = 0
EXIT_BAD_INPUT = 2  # bad input: one line on stderr, nothing written
EXIT_PARTIAL = 3  # part of the work done and written, the rest not (the output says what); --allow-partial: 0
EXIT_INTERRUPTED = 130  # Ctrl-C (SIGINT)


class InputError(Exception):
    """Bad input: the message says which file, where, what is wrong and what to do."""

    def __init__(self, message: str, *, path: object | None = None, where: str | None = None):
        self.path = None if path is None else str(path)
        self.where = where
        self.detail = message
        prefix = ""
        if self.path is not None:
            prefix = f"{self.path}: "
            if where:
                prefix = f"{self.path}: {where}: "
        elif where:
            prefix = f"{where}: "
        super().__init__(prefix + message)


class DegenerateError(InputError):
    """The observations cannot determine the unknowns (too few markers, degenerate geometry)."""


class ConvergenceError(InputError):
    """A fit did not reach a solution that explains the observations."""


def one_line(message: str) -> str:
    """A message as one line: line breaks (from a file's own text, say) become spaces."""
    return " ".join(message.split())


class Report(str):
    """A stage's report (the lines its command prints on stdout). `partial`: one line on the
    work it could not do ('' when it did the whole of it); its command then exits
    EXIT_PARTIAL, or 0 with --allow-partial, having written what it did."""

    partial: str

    def __new__(cls, text: str, partial: str = "") -> Report:
        report = super().__new__(cls, text)
        report.partial = partial
        return report
