"""Progress bars: shown on a terminal, quiet in CI and when output is redirected."""

from __future__ import annotations

import os
import sys

from tqdm import tqdm


def progress_enabled() -> bool:
    return sys.stderr.isatty() and not os.environ.get("CI")


def progress(iterable=None, *, total: int | None = None, desc: str = "", unit: str = "it"):
    """A tqdm bar on stderr, disabled unless stderr is a terminal outside CI."""
    return tqdm(
        iterable, total=total, desc=desc, unit=unit, disable=not progress_enabled(), leave=False
    )
