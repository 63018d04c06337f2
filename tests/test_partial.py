"""Partial work is not whole: `mocap fit` with a stretch of frames that no joint values
explain, and `mocap sync` with a camera it cannot synchronise, write what they did and exit
with status 3 (--allow-partial: 0), one line on stderr saying what was not done."""

from __future__ import annotations

import numpy as np
import pytest

from mocap import cli
from mocap.core.calibration import Calibration, joints_to_table
from mocap.core.tracks import Tracks, concatenate
from mocap.errors import EXIT_OK, EXIT_PARTIAL
from mocap.io.cameras_toml import save_calibration
from mocap.io.machine_toml import load_machine
from mocap.io.motion_csv import load_motion
from mocap.io.tracks_csv import save_tracks
from mocap.synthetic.machines import random_motion
from mocap.synthetic.scenes import observe, ring_of_cameras

FPS, FRAMES = 15.0, 60


def mixed(tracks: Tracks, frames: slice, names, seed: int) -> Tracks:
    """The tracks with every camera's marker labels permuted alike in `frames`."""
    swap = dict(zip(names, np.random.default_rng(seed).permutation(names)))
    inside = (tracks.frame >= frames.start) & (tracks.frame < frames.stop)
    marker = np.array([swap[m] if k else m for m, k in zip(tracks.marker, inside)], dtype=object)
    return Tracks.from_rows(tracks.camera, tracks.frame, marker, tracks.xy)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """Two cameras on a shovel at 15 fps, 0.3 px of noise; the calibration file and the
    tracks with labels mixed in frames 20-39 (1.3 s) and, apart, in frames 30-32."""
    root = tmp_path_factory.mktemp("partial")
    machine = load_machine("hitachi_ex3500")
    rng = np.random.default_rng(5)
    cameras = ring_of_cameras(3, np.array([5.0, 0.0, 5.0]), (30.0, 50.0), rng, fov_deg=(40.0, 55.0))
    joints = random_motion(machine, FRAMES, rng, fps=FPS)
    other = random_motion(machine, FRAMES, rng, fps=FPS)  # what the third camera saw: another session
    tracks = [observe([camera], machine, joints, rng, noise_px=0.3) for camera in cameras]
    metadata = {"machine": "hitachi_ex3500", "frame": 0, "joints": joints_to_table(joints[0], machine)}
    save_calibration(Calibration(tuple(cameras[:2]), ({"fps": FPS},) * 2, metadata), root / "c.toml")
    save_calibration(Calibration(tuple(cameras), ({"fps": FPS},) * 3, metadata), root / "c3.toml")
    for name, frames in (("stretch", slice(20, 40)), ("few", slice(30, 33))):
        save_tracks(mixed(concatenate(tracks[:2]), frames, list(machine.marker_names), 1), root / f"{name}.csv")
    save_tracks(concatenate(tracks[:2] + [observe([cameras[2]], machine, other, rng, noise_px=0.3)]),
                root / "three.csv")
    return root, machine


def fit(root, name, *extra):
    return cli.main(["fit", "hitachi_ex3500", str(root / "c.toml"), str(root / f"{name}.csv"),
                     "--out", str(root / f"{name}_motion.csv"), *extra])


def test_a_stretch_of_unexplained_frames_is_partial(scene, capsys):
    root, machine = scene
    assert fit(root, "stretch") == EXIT_PARTIAL
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("mocap fit: partial: ")
    assert "frames unexplained" in err[0] and "the smoother filled them" in err[0]
    assert "exit status 3 (--allow-partial: 0)" in err[0]
    # the stretch named is the one mixed (its ends may be explained by chance: a label kept)
    first, last = map(int, err[0].split("the longest stretch frames ")[1].split(" ")[0].split("-"))
    assert 20 <= first <= 22 and 37 <= last <= 39
    motion = load_motion(root / "stretch_motion.csv", machine)  # written all the same
    unexplained = motion.extra["unexplained"].astype(bool)
    assert unexplained[first:last + 1].all() and not unexplained[:18].any() and not unexplained[42:].any()


def test_a_few_unexplained_frames_are_not_partial_and_the_flag_accepts_a_stretch(scene, capsys):
    root, _ = scene
    assert fit(root, "few") == EXIT_OK  # 3 frames of 60 (0.2 s): flagged in the motion, not partial
    out, err = capsys.readouterr()
    assert "frame(s) that no joint values explain" in out and "partial" not in err
    assert fit(root, "stretch", "--allow-partial") == EXIT_OK
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("mocap fit: partial: ") and "exit status 3" not in err[0]


def test_a_camera_never_synchronised_is_partial_and_the_others_are_written(scene, capsys):
    import tomllib

    root, _ = scene
    argv = ["sync", str(root / "c3.toml"), str(root / "three.csv"), "--machine", "hitachi_ex3500",
            "--max-offset", "1", "--out", str(root / "synced.toml")]
    assert cli.main(argv) == EXIT_PARTIAL
    out, err = capsys.readouterr()
    err = err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("mocap sync: partial: camera cam3 not synchronised (")
    assert "cam1" not in err[0] and "cam2" not in err[0] and f"written to {root / 'synced.toml'}" in err[0]
    assert "cam3: not synchronised" in out
    data = tomllib.loads((root / "synced.toml").read_text())
    cams = [v for k, v in data.items() if k != "metadata"]
    assert abs(cams[1]["time_offset"]) * FPS < 0.25  # the same clock, found over 4 s to a quarter of a frame
    assert "time_offset" not in cams[2] and cams[2]["fps"] == FPS  # none found: none written
    assert cli.main(argv + ["--allow-partial"]) == EXIT_OK
    assert "exit status 3" not in capsys.readouterr().err


def _half_done(out) -> str:
    from mocap.errors import Report

    out.write_text("what was done\n")
    return Report(f"wrote {out}", "camera cam3 not synchronised")


def test_a_batch_stage_that_did_part_of_its_work_is_partial_also_when_skipped(tmp_path):
    """The batch's stage outcome carries the partial line, and keeps it when a re-run finds the
    stage up to date (the session stays partial, not ok)."""
    from functools import partial

    from mocap.batch.plan import Stage
    from mocap.batch.run import RAN, SKIPPED, run_stages

    (tmp_path / "in.txt").write_text("input\n")
    chain = [Stage("sync", (tmp_path / "in.txt",), (tmp_path / "out.txt",), call=partial(_half_done, tmp_path / "out.txt"))]
    first = run_stages(tmp_path, chain, ["sync"], [], True)
    again = run_stages(tmp_path, chain, ["sync"], [], True)
    assert [(o.status, o.partial) for o in first.outcomes + again.outcomes] == [
        (RAN, "camera cam3 not synchronised"), (SKIPPED, "camera cam3 not synchronised")]
    assert not first.error and (tmp_path / "out.txt").read_text() == "what was done\n"


def test_run_carries_on_after_a_partial_stage_and_exits_3_unless_allowed(tmp_path, monkeypatch, capsys):
    """`mocap run`'s chain: a stage that did part of its work prints its line, the stages
    after it run, the run exits 3; with --allow-partial (as the demo runs it) 0."""
    from mocap.errors import Report
    from mocap.orchestration import pipeline
    from mocap.orchestration.pipeline import RunOptions, Step, run_session

    ran = []

    def stage(name, partial=""):
        def call():
            ran.append(name)
            return Report(f"{name} done", partial)
        return Step(name, name, call, (), ())
    monkeypatch.setattr(pipeline, "session_steps", lambda session, options: [
        stage("sync", "camera cam3 not synchronised"), stage("fit")])
    monkeypatch.setattr(pipeline, "write_run_report", lambda session: None)
    (tmp_path / "results").mkdir()
    assert run_session(tmp_path) == EXIT_PARTIAL
    out, err = capsys.readouterr()
    assert ran == ["sync", "fit"] and "fit done" in out
    assert err.splitlines()[0] == "mocap sync: partial: camera cam3 not synchronised"
    assert err.splitlines()[1].startswith("mocap run: partial: sync did part of the work")
    assert run_session(tmp_path, RunOptions(allow_partial=True)) == EXIT_OK
    assert capsys.readouterr().err == "mocap sync: partial: camera cam3 not synchronised\n"


def test_the_fleet_report_lists_partial_sessions_apart_and_counts_their_results():
    from mocap.batch.fleet import combine, report_text
    from mocap.core.session_summary import SessionSummary

    summaries = [SessionSummary("a", "m", "d", "ok", "", hours=1.0, analysed=True),
                 SessionSummary("b", "m", "d", "partial", "sync: camera cam3 not synchronised", hours=2.0, analysed=True),
                 SessionSummary("c", "m", "d", "failed", "track cam1: corrupt video")]
    total = combine(summaries, "fleet")
    assert total.status == "1/3 ok, 1 partial" and total.hours == 3.0  # a partial session's results count
    text = report_text(summaries, 1.0)
    failed, partial = text.split("## Failed")[1].split("## Partial")
    assert "- c: track cam1: corrupt video" in failed and "- b:" not in failed
    assert "- b: sync: camera cam3 not synchronised" in partial
