"""Faults a field user meets besides bad input: a base pose with no value in some frames,
Ctrl-C inside compiled code, log warnings before an error, partial work, concurrent runs,
a full disk."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from mocap import cli
from mocap.core.geometry import rpy_to_matrix
from mocap.errors import EXIT_INTERRUPTED, InputError
from mocap.io.motion_csv import base_columns

from kills import kill_at, run_killed, timed_warm, visible


def test_a_base_pose_without_value_gives_nan_columns_not_a_crash():
    """Frames the smoother leaves without a pose (after the last explained frame) reach the
    motion writer as NaN matrices: their base columns are NaN, the others exact."""
    rpy = np.array([[0.1, -0.2, 0.3], [0.0, 0.0, 0.0], [-0.3, 0.25, 2.0]])
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, :3, :3] = rpy_to_matrix(rpy)
    poses[:, :3, 3] = [[1, 2, 3], [4, 5, 6], [7, 8, 9]]
    poses[1] = np.nan
    covariance = np.tile(np.eye(6) * 1e-4, (3, 1, 1))
    covariance[1] = np.nan
    columns = base_columns(poses, covariance)
    assert np.isnan(columns["base_roll_deg"][1]) and np.isnan(columns["base_yaw_sd_deg"][1])
    got = np.c_[columns["base_roll_deg"], columns["base_pitch_deg"], columns["base_yaw_deg"]][[0, 2]]
    assert np.allclose(got, np.degrees(rpy[[0, 2]]), atol=1e-9)
    assert np.allclose(columns["base_z"][[0, 2]], [3, 9])
    assert np.all(np.isfinite(columns["base_roll_sd_deg"][[0, 2]]))


def _command_raising(monkeypatch, exc: BaseException, warn: bool = True):
    import mocap.commands.demo as demo

    def run(args):
        if warn:
            logging.getLogger("mocap.calibration.doubts").warning("camera cam3: its position is hardly fixed")
        raise exc
    monkeypatch.setattr(demo, "run", run)


def _interrupt_in_compiled_code() -> SystemError:
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise SystemError("CPUDispatcher(<function refine>) returned a result with an exception set")
    except SystemError as exc:
        return exc


@pytest.mark.parametrize("exc", [KeyboardInterrupt(), _interrupt_in_compiled_code()], ids=["python", "compiled"])
def test_ctrl_c_is_one_line_even_after_warnings(exc, monkeypatch, capsys):
    """Ctrl-C during `mocap demo` (in numba-compiled tracking it surfaces as a SystemError
    around the KeyboardInterrupt) is one line, exit 130; the warnings logged before it are
    not printed."""
    _command_raising(monkeypatch, exc)
    assert cli.main(["demo"]) == EXIT_INTERRUPTED
    assert capsys.readouterr().err == "mocap demo: interrupted\n"


def test_warnings_before_an_error_are_not_printed(monkeypatch, capsys):
    _command_raising(monkeypatch, InputError("bad", path="m.toml"))
    assert cli.main(["demo"]) == 2
    assert capsys.readouterr().err == "mocap demo: error: m.toml: bad\n"


def test_warnings_of_a_command_that_ends_are_printed(monkeypatch, caplog):
    import mocap.commands.demo as demo

    def run(args):
        logging.getLogger("mocap.x").warning("camera cam3: its position is hardly fixed")
        return 0
    monkeypatch.setattr(demo, "run", run)
    assert cli.main(["demo"]) == 0
    assert [r.getMessage() for r in caplog.records] == ["camera cam3: its position is hardly fixed"]


def test_a_bug_is_still_a_traceback(monkeypatch):
    _command_raising(monkeypatch, ZeroDivisionError("bug"), warn=False)
    with pytest.raises(ZeroDivisionError):
        cli.main(["demo"])


# --- partial work, concurrent runs, a full disk ----------------------------------------------


def test_a_second_command_on_a_locked_folder_refuses_naming_the_first(tmp_path, capsys):
    """A live holder (this test's parent process stands in for another `mocap run`) is named
    in one line; the folder is left as it was."""
    import os
    import socket

    from mocap.io.lock import LOCK_NAME

    session = tmp_path / "s"
    session.mkdir()
    (session / LOCK_NAME).write_text(f"{os.getppid()} {socket.gethostname()} mocap run {session}\n")
    assert cli.main(["run", str(session)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert f"in use by `mocap run {session}` (process {os.getppid()} on {socket.gethostname()}" in err
    assert (session / LOCK_NAME).is_file()
    argv = ["synth", "--machine", "bobcat_225", "--no-video", "--out", str(session)]
    assert cli.main(argv) == 2 and "in use by `mocap run" in capsys.readouterr().err


def test_a_stale_lock_is_taken_over_and_a_held_one_is_reentrant(tmp_path):
    import os
    import socket
    import subprocess
    import sys

    from mocap.io.lock import LOCK_NAME, folder_lock

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    pid = int(dead.stdout)  # a process that has ended
    (tmp_path / LOCK_NAME).write_text(f"{pid} {socket.gethostname()} mocap synth\n")
    with folder_lock(tmp_path, "mocap run"):
        assert (tmp_path / LOCK_NAME).read_text().split()[0] == str(os.getpid())
        with folder_lock(tmp_path, "mocap track"):  # a command inside another, same process
            pass
        assert (tmp_path / LOCK_NAME).is_file()
    assert not (tmp_path / LOCK_NAME).exists()


def test_two_tracks_writing_one_file_refuse_each_other(tmp_path):
    import os
    import socket

    from mocap.commands.track import _locked

    (tmp_path / ".t.csv.lock").write_text(f"{os.getppid()} {socket.gethostname()} mocap track t.csv\n")
    with pytest.raises(InputError, match=r"in use by `mocap track t\.csv`"):
        with _locked(str(tmp_path / "t.csv")):
            pass
    with _locked(str(tmp_path / "u.csv")):  # another camera's tracks beside it: free
        assert (tmp_path / ".u.csv.lock").is_file()


FULL_DISK = """
import resource, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write fails with EFBIG instead of killing the process
resource.setrlimit(resource.RLIMIT_FSIZE, (BYTES, BYTES))
from mocap.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_a_full_disk_is_one_line_and_keeps_earlier_results(tmp_path):
    """A write that runs out of room (a file-size limit) names the file and the room it
    needed; no file is left half written and the earlier result is intact."""
    import subprocess
    import sys
    from pathlib import Path

    from badinput_files import snapshot, write_rig

    write_rig(tmp_path)
    out = tmp_path / "points.csv"
    argv = ["triangulate", str(tmp_path / "cameras.toml"), str(tmp_path / "tracks.csv"), "--out", str(out)]
    assert cli.main(argv) == 0
    before = snapshot(tmp_path)
    assert out.stat().st_size > 8000
    script = FULL_DISK.replace("BYTES", "4000")
    done = subprocess.run([sys.executable, "-c", script, *argv], capture_output=True, text=True, timeout=120,
                          cwd=Path(__file__).resolve().parents[1])
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr
    assert f"{out}: the disk is full or over the file-size limit" in done.stderr
    assert "needs more than the 4.0 kB written" in done.stderr
    assert snapshot(tmp_path) == before  # the earlier points intact, no temporary file left


# --- killed and resumed -------------------------------------------------------------------------


KILL_SCHEDULE = np.random.default_rng(34).uniform(0.2, 1.0, 3)  # fractions of an uninterrupted run's time


def test_track_killed_at_random_moments_then_run_again_equals_an_uninterrupted_run(tmp_path):
    """SIGKILL of `mocap track` at seeded random moments: no tracks file that looks whole is
    left half written, the inputs are byte-identical, and the same command run again writes
    the tracks of an uninterrupted run, digit for digit."""
    from test_track import make_scene, write_video

    from mocap.core.calibration import Calibration, joints_to_table
    from mocap.io.cameras_toml import save_calibration

    frames, uv, seen, model, joints = make_scene(n_frames=16, clutter=4, seed=3)
    inputs = tmp_path / "in"
    inputs.mkdir()
    write_video(inputs / "cam1.avi", frames, codec="MJPG")
    save_calibration(Calibration((model.camera,), ({"fps": 30.0},), {
        "machine": "bobcat_225", "frame": 0, "joints": joints_to_table(joints[0], model.machine)}), inputs / "c.toml")
    before = visible(inputs)

    def argv(out):
        return ["track", str(inputs / "cam1.avi"), "--machine", "bobcat_225", "--calibration", str(inputs / "c.toml"),
                "--camera", "cam1", "--out", str(out / "t.csv")]
    def tracked(out):
        out.mkdir()
        assert cli.main(argv(out)) == 0
    first = tmp_path / "first"
    took, compiled = timed_warm(lambda: tracked(first))
    whole = first
    if compiled:  # a fresh checkout: the kills' moments are shares of a run that compiles nothing
        whole = tmp_path / "whole"
        took, _ = timed_warm(lambda: tracked(whole))
        assert visible(whole) == visible(first)
    took = max(took, 0.5)  # the children are forks of this process: no start (imports) on top
    killed = tmp_path / "killed"
    killed.mkdir()
    codes = []
    for fraction in KILL_SCHEDULE:
        codes.append(run_killed(argv(killed), tmp_path, fraction * took, fork=True))
        assert codes[-1] in (None, 0)
        files = visible(killed)
        assert not files or files == visible(whole)  # absent, or whole: never half written
        assert visible(inputs) == before
        (killed / "t.csv").unlink(missing_ok=True)  # the next kill starts from scratch again
    codes.append(run_killed(argv(killed), tmp_path, 0.3 * took, fork=True))  # one more kill, then the re-run
    assert None in codes and codes[-1] in (None, 0)  # killed mid-way at least once
    assert cli.main(argv(killed)) == 0
    assert visible(killed) == visible(whole)
    assert not list(killed.glob(".*"))  # the killed writers' temporaries and locks are gone
    assert visible(inputs) == before


SYNTH_KILLS = np.random.default_rng(34).uniform(0.55, 0.85, 2)  # after the imports: inside the writing


def test_synth_killed_at_random_moments_then_run_again_equals_an_uninterrupted_run(tmp_path):
    """SIGKILL of `mocap synth` (one camera, a tiny video) at seeded moments, each run resuming
    the folder the last one left: every file a reader sees is whole (as the uninterrupted
    run's), COMPLETE only once all are, and the command run again writes the same session
    byte for byte, the video too."""
    import shutil
    import time

    def argv(out):
        return ["synth", "--machine", "bobcat_225", "--cycles", "1", "--cameras", "1", "--scale", "0.05",
                "--fps", "5", "--out", str(out)]
    start = time.perf_counter()  # here, as the killed ones (forks of this process) run it
    assert cli.main(argv(tmp_path / "whole")) == 0
    took = time.perf_counter() - start
    whole = visible(tmp_path / "whole")
    assert "COMPLETE" in whole and "videos/cam1.mp4" in whole
    killed = tmp_path / "killed"
    for fraction in SYNTH_KILLS:
        delay = fraction * took
        for _ in range(4):  # a loaded machine may run it faster than timed: a finished run, again sooner
            code = run_killed(argv(killed), tmp_path, delay, fork=True)
            if code is None:
                break
            assert code == 0 and visible(killed) == whole
            shutil.rmtree(killed)
            delay /= 2
        assert code is None  # killed mid-way
        files = visible(killed) if killed.exists() else {}
        assert all(whole[name] == digest for name, digest in files.items())  # whole, or absent
        assert ("COMPLETE" in files) == (files == whole)  # COMPLETE last
        if "COMPLETE" in files:  # killed as it ended (its lock left, for the next command to take over)
            break
    else:
        assert cli.main(argv(killed)) == 0
        assert not [p for p in killed.rglob(".*")]  # no temporary or lock of the killed runs left
    assert visible(killed) == whole


def test_a_folder_synth_left_at_any_moment_is_resumed_and_others_refused(tmp_path, capsys):
    """Killed just after session.toml (no truth/ yet) or inside an atomic write (its hidden
    temporary): `mocap synth` takes the folder up again; a folder holding anything else, or
    COMPLETE, is refused in one line."""
    from mocap.synthetic.stage import _interrupted_synth

    (tmp_path / "session.toml").write_text("machine = 'bobcat_225'\n")
    (tmp_path / ".motion.csv.tmp").write_text("half")
    assert _interrupted_synth(tmp_path)
    (tmp_path / "notes.txt").write_text("mine")
    assert not _interrupted_synth(tmp_path)
    assert cli.main(["synth", "--machine", "bobcat_225", "--no-video", "--out", str(tmp_path)]) == 2
    assert "exists and is not empty" in capsys.readouterr().err
    (tmp_path / "notes.txt").unlink()
    (tmp_path / "COMPLETE").write_text("done\n")
    assert not _interrupted_synth(tmp_path)


# --- killed and resumed: run, batch, live --record on one small session -----------------------


@pytest.fixture(scope="module")
def small_session(tmp_path_factory):
    """A session as a user brings it to `mocap run`: two cameras at 480x270 and 5 fps, one dig
    cycle, the calibration frame's labels digitised."""
    from kills import make_small_session

    return make_small_session(tmp_path_factory.mktemp("small") / "s")


@pytest.fixture(scope="module")
def whole_run(small_session, tmp_path_factory):
    """`mocap run --no-view` uninterrupted on a copy (named as the session: the report names
    its folder): {file: sha256} of the folder after it, its seconds, and the calibration the
    calibrate stage writes before sync rewrites it in place (a state the run passes through)."""
    import shutil

    from mocap.io.session import Session
    from mocap.orchestration.pipeline import RunOptions, session_steps

    def run(name):
        root = tmp_path_factory.mktemp(name) / "s"
        shutil.copytree(small_session, root)
        assert cli.main(["run", str(root), "--no-view"]) == 0
        return root
    roots = []
    took, compiled = timed_warm(lambda: roots.append(run("first")))
    if compiled:  # a fresh checkout: the kills' moments are shares of a run that compiles nothing
        took, _ = timed_warm(lambda: roots.append(run("whole")))
        assert visible(roots[1]) == visible(roots[0])
    root = roots[-1]
    between = tmp_path_factory.mktemp("between") / "s"
    shutil.copytree(small_session, between)
    session_steps(Session.open(between), RunOptions(view=False))[0].call()  # the calibrate stage alone
    return visible(root), took, visible(between)["calibration/cameras.toml"]


def _whole_or_passed_through(files: dict, whole: dict, calibrated: str) -> None:
    """Every file as the uninterrupted run left it, or the calibration as the calibrate stage
    wrote it (sync rewrites it in place later): none half written."""
    for name, digest in files.items():
        assert digest == whole.get(name) or (name == "calibration/cameras.toml" and digest == calibrated), name


# where the kills fall: a seeded random moment after the killed run has written one stage's output, within a
# share of an uninterrupted run's time: in tracking (after calibrate), in sync (which rewrites the calibration in
# place) or the stages after it, and in the analysis or the report (before COMPLETE)
RUN_KILLS = [(name, share) for name, share in zip(
    ("calibration/cameras.toml", "tracks/cam2.csv", "results/motion.csv"),
    np.random.default_rng(341).uniform(0.0, [0.2, 0.15, 0.06]))]


def written(path: Path):
    """Whether `path` has been written since this call: by the run started after it (the
    files the runs killed before it left are older)."""
    import time

    start = time.time_ns()

    def holds() -> bool:
        try:
            return path.stat().st_mtime_ns >= start
        except FileNotFoundError:
            return False
    return holds


@pytest.mark.long
def test_run_killed_at_random_moments_then_run_again_equals_an_uninterrupted_run(small_session, whole_run, tmp_path):
    """SIGKILL of `mocap run` at seeded random moments (one in tracking, one in sync or after,
    one in the analysis or the report), each run taking up the folder the last one left (its
    lock a dead process's: taken over): the inputs stay byte-identical, every file is whole,
    results/COMPLETE only once all are, and the same command run again leaves the folder of
    an uninterrupted run, byte for byte."""
    import shutil

    whole, took, calibrated = whole_run
    inputs = visible(small_session)
    killed = tmp_path / "killed" / "s"
    shutil.copytree(small_session, killed)
    argv = ["run", str(killed), "--no-view"]

    def check():
        files = visible(killed)
        assert {name: files.get(name) for name in inputs} == inputs
        _whole_or_passed_through(files, whole, calibrated)
        assert ("results/COMPLETE" in files) == (files == whole)

    for name, share in RUN_KILLS:  # forks of this process: no start (imports) on top
        kill_at(argv, tmp_path, [share * took], check, after=written(killed / name), fork=True)
    assert cli.main(argv) == 0
    assert visible(killed) == whole
    assert not list(killed.rglob(".*"))  # no temporary or lock of the killed runs left


@pytest.mark.long
def test_batch_killed_at_random_moments_then_run_again_equals_a_serial_run(small_session, whole_run, tmp_path):
    """SIGKILL of `mocap batch` (and its Dask workers) at a seeded random moment of the whole
    and another after the first stage is in the manifest: every file whole, the inputs
    byte-identical; the batch run again skips the stages the manifest holds and leaves each
    result as `mocap run` does, byte for byte."""
    import shutil
    import tomllib

    from test_batch import read_fleet

    whole, took, calibrated = whole_run
    inputs = visible(small_session)
    fleet = tmp_path / "fleet"
    root = fleet / "s"
    shutil.copytree(small_session, root)
    out = tmp_path / "out"
    argv = ["batch", str(fleet), "--workers", "1", "--out", str(out)]
    manifest = root / "batch" / "manifest.toml"

    def check():
        files = {k: v for k, v in visible(root).items() if not k.startswith("batch/")}
        assert {name: files.get(name) for name in inputs} == inputs
        _whole_or_passed_through(files, whole, calibrated)
        if manifest.exists():
            tomllib.loads(manifest.read_text())  # whole
        for name in ("fleet.csv", "fleet_report.md"):
            assert not (out / name).exists() or (out / name).read_text().endswith("\n")

    kills = np.random.default_rng(342).uniform(0.2, 0.8, 2)
    kill_at(argv, tmp_path, [kills[0] * (took + 4.0)], check)  # Dask's start on top of the stages
    kill_at(argv, tmp_path, [kills[1] * took], check, after=manifest.exists)
    recorded = set(tomllib.loads(manifest.read_text())["stages"])
    assert recorded
    # run again on a scheduler of this process's, whose worker finds the kernels loaded (the killed runs
    # started local clusters of worker processes)
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0") as cluster:
        assert cli.main(["batch", str(fleet), "--scheduler", cluster.scheduler_address, "--out", str(out)]) == 0
    row = read_fleet(out)["s"]
    assert row["status"] == "ok" and int(row["stages_skipped"]) == len(recorded), (row, recorded)
    results = {k: v for k, v in visible(root).items() if not k.startswith("batch/")}
    serial = {k: v for k, v in whole.items() if k not in ("results/session_report.html", "results/COMPLETE")}
    assert results == serial  # `mocap run`'s files but its report and COMPLETE
    assert not list(root.rglob(".*"))  # no temporary of the killed runs left


LIVE_KILLS = np.random.default_rng(343).uniform(0.3, 0.95, 3)


@pytest.mark.long
def test_live_record_killed_at_random_moments_then_run_again_equals_an_uninterrupted_run(small_session, tmp_path):
    """SIGKILL of `mocap live --record DIR` (files read as fast as tracked) at seeded moments,
    into a folder holding an earlier, other recording: a killed run leaves no session.toml
    (the earlier one's would name files of two runs as one session), every file is whole, and
    the same command run again records what an uninterrupted run does, byte for byte."""
    import shutil

    from mocap.io.session_toml import load_session_config, save_session_config

    def argv(record):
        return ["live", "hitachi_ex3500", str(small_session / "truth" / "cameras.toml"),
                "--source", f"cam1={small_session / 'videos' / 'cam1.mp4'}",
                "--source", f"cam2={small_session / 'videos' / 'cam2.mp4'}",
                "--out", str(tmp_path / "poses.csv"), "--record", str(record)]
    def record(folder):
        assert cli.main(argv(folder)) == 0
    inputs = visible(small_session)
    took, compiled = timed_warm(lambda: record(tmp_path / "first"))
    recorded = visible(tmp_path / "first")
    if compiled:  # a fresh checkout: the kills' moments are shares of a run that compiles nothing
        took, _ = timed_warm(lambda: record(tmp_path / "whole"))
        assert visible(tmp_path / "whole") == recorded
    killed = tmp_path / "killed"
    shutil.copytree(tmp_path / "first", killed)  # an earlier recording: of cam1 alone
    config = load_session_config(killed / "session.toml")
    save_session_config(config.__class__(config.machine, config.cameras[:1], config.options, config.metadata),
                        killed / "session.toml")
    (killed / "videos" / "cam2.mp4").unlink()
    (killed / "tracks" / "cam2.csv").unlink()
    earlier = visible(killed)

    def check():
        files = visible(killed)
        assert all(recorded[name] == digest for name, digest in files.items() if name != "session.toml")
        if files != earlier:  # (killed before it took up the folder: the earlier recording as it was)
            assert ("session.toml" in files) == (files == recorded)  # written last, and only then
        assert visible(small_session) == inputs

    def writing():  # the run has begun to write the recording's files (cam2's video the first new one)
        return any("cam2" in p.name for p in (killed / "videos").iterdir())
    assert run_killed(argv(killed), tmp_path, LIVE_KILLS[0] * 0.005, after=writing, fork=True) is None  # inside the writing
    check()
    kill_at(argv(killed), tmp_path, LIVE_KILLS[1:] * took, check, fork=True)
    assert cli.main(argv(killed)) == 0
    assert visible(killed) == recorded
    assert not list(killed.rglob(".*"))
