"""The demo: a synthetic field session made, processed by the whole chain and scored
against its ground truth."""

from __future__ import annotations

import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from typing import TYPE_CHECKING

from mocap.errors import InputError
from mocap.io.outputs import check_output_folder

if TYPE_CHECKING:  # the chain's modules are imported when the demo runs, not for `mocap demo --help`
    import numpy as np

    from mocap.io.session import Session

DIGITISING_NOISE_PX = 0.5


@dataclass(frozen=True)
class DemoOptions:
    out: Path = Path("mocap-demo")
    machine: str = "hitachi_ex3500"
    cameras: int = 3
    cycles: int = 5
    seed: int = 7
    scale: float = 0.5
    fps: float = 15.0


def digitise_first_frame(session: Session, rng: np.random.Generator) -> Path:
    """Stand in for the person who clicks each camera's markers in its first frame: the true
    centres of the visible markers with 0.5 px of clicking noise, written as the labels CSV."""
    from mocap.core.tracks import Tracks
    from mocap.io.tracks_csv import load_tracks, save_tracks

    truth = load_tracks(session.truth_dir / "tracks.csv")
    frame = int(session.config().options.get("calibration_frame", 0))
    first = truth.select(truth.frame == frame)
    labels = Tracks.from_rows(
        first.camera, first.frame, first.marker, first.xy + rng.normal(0, DIGITISING_NOISE_PX, first.xy.shape)
    )
    path = session.root / "calibration" / "labels.csv"
    save_tracks(labels, path)
    return path


def cycle_times(found: Path, truth: Path) -> str:
    """The line on the cycles' times: how many have one (a cycle runs from its dig to the
    next), their median, and the truth's."""
    import numpy as np

    from mocap.io.cycles_csv import load_cycle_table

    def numbers(column) -> np.ndarray:
        return np.array([float(v) if str(v).strip() else np.nan for v in column])

    times = numbers(load_cycle_table(found)["cycle_time_s"])
    true_times = np.diff(numbers(load_cycle_table(truth)["dig_start_time"]))
    if not np.isfinite(times).any():
        return "no cycle time: a cycle's time runs from its dig to the next"
    n = int(np.isfinite(times).sum())
    return (f"{n} cycle time{'s' if n != 1 else ''}, median {np.nanmedian(times):.1f} s "
            f"(truth {np.median(true_times):.1f} s)")


def run_demo(options: DemoOptions) -> int:
    import numpy as np

    from mocap.analysis.score import format_analysis_score, score_files
    from mocap.io.session import Session
    from mocap.orchestration.evaluate import format_score, score_session
    from mocap.orchestration.pipeline import RunOptions, run_session
    from mocap.synthetic.stage import SynthRequest, run_synth

    start = time.perf_counter()
    out = options.out
    check_output_folder(out)
    if out.exists() and any(out.iterdir()):
        if not Session.open(out).is_synthetic:
            raise InputError("exists and is not a synthetic session folder; choose another --out", path=out)
        shutil.rmtree(out)  # an earlier demo's folder: made again from scratch
    print(f"== synth: {options.machine}, {options.cameras} cameras, {options.cycles} dig cycle(s), "
          f"{options.fps:g} fps, seed {options.seed}")
    print(run_synth(SynthRequest(options.machine, out, cameras=options.cameras, cycles=options.cycles,
                                 seed=options.seed, scale=options.scale, fps=options.fps)))
    session = Session.open(out)
    digitise_first_frame(session, np.random.default_rng(options.seed))
    # a stage that did part of its work (frames unexplained) prints its line; the demo goes on to the score
    code = run_session(out, RunOptions(refine=True, allow_partial=True))
    if code:
        return code
    print("== how close it came to the ground truth")
    print(format_score(score_session(out), session.machine()))
    print(format_analysis_score(score_files(session.results_dir / "cycles.csv", session.truth_dir / "cycles.csv")))
    print(cycle_times(session.results_dir / "cycles.csv", session.truth_dir / "cycles.csv"))
    mocap = Path(sys.executable).with_name("mocap")
    mocap = str(mocap) if mocap.exists() else f"{sys.executable} -m mocap"
    print(f"\nresults in {out}/: calibration/cameras.toml, tracks/, results/points.csv, "
          f"results/motion.csv, results/cycles.csv, results/report.html, results/session_report.html, "
          f"results/session.rrd\nopen the replay: {mocap} view {out} --open  "
          f"(a headless or remote machine: {mocap} view {out} --serve)")
    print(f"demo took {time.perf_counter() - start:.0f} s")
    return 0
