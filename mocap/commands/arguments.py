"""Argument types shared by several commands."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # mocap.core.machine (and scipy with it) only when the option is given
    from mocap.core.machine import Tolerance


DISTORTION_CHOICES = ("auto", "none", "k1", "k1k2", "full")  # the calibration's models and auto, without scipy


def tolerance(text: str) -> Tolerance:
    """--tolerance: "5%" or 0.05 (a fraction of each marker's distance from its link's
    origin), or "0.03m" / "3cm" / "30mm" (a length)."""
    from mocap.core.machine import Tolerance

    try:
        return Tolerance.parse(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: expected a fraction (0.05 or 5%) or a length (0.03m, 3cm, 30mm) in [0, 100 m)"
        ) from None


TOLERANCE_HELP = ("how far the model's marker positions may be off: a fraction (0.05 or 5%%) of "
                  "each marker's distance from its link's origin, or a length (0.03m, 3cm)")


def add_allow_partial(parser: argparse.ArgumentParser, what: str) -> None:
    parser.add_argument("--allow-partial", action="store_true",
                        help=f"exit 0 when {what} (default: exit status 3, partial; the line on stderr says what)")


def partial_status(command: str, report: str, allow_partial: bool) -> int:
    """Print a stage's report; when it did part of its work (a `mocap.errors.Report` with
    `partial`), its one line on stderr and exit status 3, or 0 with --allow-partial."""
    import sys

    from mocap.errors import EXIT_OK, EXIT_PARTIAL

    print(report)
    partial = getattr(report, "partial", "")
    if not partial:
        return EXIT_OK
    print(f"mocap {command}: partial: {partial}" + ("" if allow_partial else "; exit status 3 (--allow-partial: 0)"),
          file=sys.stderr)
    return EXIT_OK if allow_partial else EXIT_PARTIAL
