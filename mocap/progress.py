"""Progress bars: shown on a terminal, quiet in CI and when output is redirected."""

from __future__ import annotations

import os
import sys
import warnings

from tqdm import tqdm


def progress_enabled() -> bool:
    return sys.stderr.isatty() and not os.environ.get("CI")


def progress(iterable=None, *, total: int | None = None, desc: str = "", unit: str = "it"):
    """A tqdm bar on stderr, disabled unless stderr is a terminal outside CI."""
    return tqdm(
        iterable, total=total, desc=desc, unit=unit, disable=not progress_enabled(), leave=False
    )


def quiet_libraries(verbose: bool = False) -> None:
    """The video library's own log lines (FFmpeg's "moov atom not found" beside our error)
    are silenced: a video that cannot be read is reported once, by us. So are numpy's
    warnings on empty or all-NaN slices (a frame nobody saw), unless `verbose`."""
    import av.logging

    av.logging.set_level(av.logging.DEBUG if verbose else None)
    if not verbose:
        warnings.filterwarnings("ignore", category=RuntimeWarning)
