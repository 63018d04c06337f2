"""The demo: a synthetic field session made, processed by the whole chain and scored
against its ground truth."""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass
from pathlib import Path

from typing import TYPE_CHECKING

from mocap.errors import InputError
from mocap.io.outputs import check_output_folder

if TYPE_CHECKING:  # the chain's modules are imported when the demo runs, not for `mocap demo --help`
    import numpy as np

    from mocap.session import Session

DIGITISING_NOISE_PX = 0.5


@dataclass(frozen=True)
class DemoOptions:
    out: Path = Path("mocap-demo")
    machine: str = "hitachi_ex3500"
    cameras: int = 3
    cycles: int = 1
    seed: int = 7
    scale: float = 0.5


def digitise_first_frame(session: Session, rng: np.random.Generator) -> Path:
    """Stand in for the person who clicks each camera's markers in its first frame: the true
    centres of the visible markers with 0.5 px of clicking noise, written as the labels CSV."""
    from mocap.io.tracks_csv import Tracks, load_tracks, save_tracks

    truth = load_tracks(session.truth_dir / "tracks.csv")
    frame = int(session.config().options.get("calibration_frame", 0))
    first = truth.select(truth.frame == frame)
    labels = Tracks.from_rows(
        first.camera, first.frame, first.marker, first.xy + rng.normal(0, DIGITISING_NOISE_PX, first.xy.shape)
    )
    path = session.root / "calibration" / "labels.csv"
    save_tracks(labels, path)
    return path


def run_demo(options: DemoOptions) -> int:
    import numpy as np

    from mocap.analysis.score import format_analysis_score, score_files
    from mocap.evaluate import format_score, score_session
    from mocap.pipeline import RunOptions, run_session
    from mocap.session import Session
    from mocap.synthetic.stage import SynthRequest, run_synth

    start = time.perf_counter()
    out = options.out
    check_output_folder(out)
    if out.exists() and any(out.iterdir()):
        if not Session.open(out).is_synthetic:
            raise InputError("exists and is not a synthetic session folder; choose another --out", path=out)
        shutil.rmtree(out)  # an earlier demo's folder: made again from scratch
    print(f"== synth: {options.machine}, {options.cameras} cameras, {options.cycles} dig cycle(s), seed {options.seed}")
    print(run_synth(SynthRequest(options.machine, out, cameras=options.cameras, cycles=options.cycles,
                                 seed=options.seed, scale=options.scale)))
    session = Session.open(out)
    digitise_first_frame(session, np.random.default_rng(options.seed))
    code = run_session(out, RunOptions(refine=True))
    if code:
        return code
    print("== how close it came to the ground truth")
    print(format_score(score_session(out), session.machine()))
    print(format_analysis_score(score_files(session.results_dir / "cycles.csv", session.truth_dir / "cycles.csv")))
    print(f"\nresults in {out}/: calibration/cameras.toml, tracks/, results/points.csv, "
          f"results/motion.csv, results/cycles.csv, results/report.html, results/session.rrd (open with: rerun {session.recording_path})")
    print(f"demo took {time.perf_counter() - start:.0f} s")
    return 0
