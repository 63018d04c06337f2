"""The project's compiled kernels written to numba's on-disk cache before the suite starts,
in two processes at once: `tracking` (a small video labelled, calibrated and tracked) and
`reconstruct` (sync, refine, triangulate and fit on a small session's true tracks). On a
fresh checkout each xdist worker, and each command a test starts as a process, would
otherwise compile every kernel it meets itself, about a minute of CPU each
(tests/conftest.py starts this; a kernel missed here is compiled where it is first met,
as before).

    python tests/warm_kernels.py tracking|reconstruct
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

MACHINE = "hitachi_ex3500"
SMALL = ["--machine", MACHINE, "--cameras", "2", "--cycles", "1", "--size", "480x270", "--fps", "5", "--clean"]


def tracking(root: Path) -> None:
    from mocap import cli
    from mocap.io.session import Session
    from mocap.orchestration.demo import digitise_first_frame
    from mocap.orchestration.pipeline import RunOptions, session_steps

    assert cli.main(["synth", *SMALL, "--out", str(root)]) == 0
    session = Session.open(root)
    digitise_first_frame(session, np.random.default_rng(1))
    steps = session_steps(session, RunOptions(view=False))
    for step in steps[:2]:  # calibrate, then track the first camera
        step.call()


def reconstruct(root: Path) -> None:
    from mocap import cli

    assert cli.main(["synth", *SMALL, "--no-video", "--out", str(root)]) == 0
    truth = root / "truth"
    cameras, tracks = str(truth / "cameras.toml"), str(truth / "tracks.csv")
    commands = [
        ["sync", cameras, tracks, "--machine", MACHINE, "--out", str(root / "synced.toml")],
        ["refine", MACHINE, cameras, tracks, "--frames", "20", "--out", str(root / "refined.toml")],
        ["triangulate", cameras, tracks, "--out", str(root / "points.csv")],
        ["fit", MACHINE, cameras, tracks, "--out", str(root / "motion.csv")],
    ]
    for argv in commands:
        cli.main(argv)  # its exit status does not matter here: only what it compiled on the way


if __name__ == "__main__":
    with tempfile.TemporaryDirectory() as folder:
        {"tracking": tracking, "reconstruct": reconstruct}[sys.argv[1]](Path(folder) / "s")
