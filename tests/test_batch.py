"""`mocap batch` core on truth-only synthetic sessions: Dask scheduling, per-camera tasks,
skipping by content hashes, in-place outputs, failures, the fleet summary."""

import csv
import datetime
import shutil
import sys
from functools import partial
from pathlib import Path

import numpy as np
import pytest

from mocap import cli
from mocap.batch.fleet import CLASSES
from mocap.batch.plan import ANALYSIS_DIR, Stage, find_sessions, split_tasks, stage_from_command
from mocap.batch.stage import BatchOptions, run_batch
from mocap.core.calibration import Calibration
from mocap.errors import InputError
from mocap.io.cameras_toml import load_calibration, save_calibration
from mocap.io.cycles_csv import load_cycles
from mocap.io.motion_csv import load_motion
from mocap.io.session import Session
from mocap.io.session_toml import load_session_config, save_session_config
from mocap.io.tracks_csv import load_tracks, save_tracks
from mocap.orchestration.pipeline import sync_step, triangulate_step

pytest.importorskip("distributed")
cloudpickle = pytest.importorskip("cloudpickle")
cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the test's stages, for worker processes


# --- the test chain: truth tracks stand in for tracking, the truth cycles for the analysis ---


def forget_offsets(root: Path) -> None:
    """The truth calibration without time offsets: sync must find them."""
    truth = load_calibration(root / "truth" / "cameras.toml")
    extras = tuple({**e, "time_offset": 0.0} for e in truth.extras)
    save_calibration(Calibration(truth.cameras, extras, truth.metadata), root / "calibration" / "cameras.toml")


def camera_tracks(root: Path, camera: str) -> None:
    """One camera's truth tracks; like tracking, it reads the calibration made before sync."""
    if np.any(load_calibration(root / "calibration" / "cameras.toml").time_offsets != 0):
        raise RuntimeError("read the synchronised calibration, not the one made before sync")
    save_tracks(load_tracks(root / "truth" / "tracks.csv").of_camera(camera), root / "tracks" / f"{camera}.csv")


def truth_cycles(root: Path) -> None:
    (root / ANALYSIS_DIR).mkdir(parents=True, exist_ok=True)
    shutil.copyfile(root / "truth" / "cycles.csv", root / ANALYSIS_DIR / "cycles.csv")


def fit_gap(machine: str, calibration: str, tracks: tuple, out: str, max_gap) -> str:
    """`mocap fit` with --max-gap: a stage whose argument a test changes."""
    from mocap.reconstruct.kinfit import FitOptions
    from mocap.reconstruct.smooth import SmoothOptions
    from mocap.reconstruct.stage import run_fit

    return run_fit(machine, calibration, list(tracks), out, FitOptions(), SmoothOptions(max_gap_s=float(max_gap)))


def chain(root: Path, max_gap=2.0) -> list[Stage]:
    session = Session.open(root)
    config = session.config()
    calibration = root / "calibration" / "cameras.toml"
    tracks = [session.tracks_path(c) for c in session.camera_names]
    machine = str(session.machine_path())
    fps = tuple(f"{c.name}={c.fps}" for c in config.cameras)
    names = tuple(map(str, tracks))
    return [
        Stage("prepare", (root / "truth" / "cameras.toml",), (calibration,), call=partial(forget_offsets, root)),
        *[Stage(f"tracks {c}", (root / "truth" / "tracks.csv", calibration), (session.tracks_path(c),),
                call=partial(camera_tracks, root, c), camera=c) for c in session.camera_names],
        Stage("sync", (calibration, *tracks), (calibration,),
              call=partial(sync_step, str(calibration), names, machine, fps, str(calibration))),
        Stage("triangulate", (calibration, *tracks), (session.points_path,),
              call=partial(triangulate_step, str(calibration), names, str(session.points_path))),
        Stage("fit", (calibration, *tracks), (session.motion_path,),
              call=partial(fit_gap, machine, str(calibration), names, str(session.motion_path), max_gap)),
        Stage("analysis", (root / "truth" / "cycles.csv", session.motion_path), (root / ANALYSIS_DIR,),
              call=partial(truth_cycles, root)),
    ]


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """Three copies of one truth-only session (one dig cycle at 5 fps: what the batch does
    with a session does not depend on its length), on two machines and two days; the third
    has lost its truth calibration, so its first stage fails."""
    base = tmp_path_factory.mktemp("base") / "s"
    assert cli.main(["synth", "--machine", "hitachi_ex3500", "--cycles", "1", "--fps", "5", "--no-video", "--out", str(base)]) == 0
    top = tmp_path_factory.mktemp("fleet")
    roots = [top / "site_a" / "s1", top / "site_a" / "s2", top / "site_b" / "deep" / "s3"]
    metadata = [{"machine_id": "EX3500 #1", "date": datetime.date(2026, 11, 30)},
                {"machine_id": "EX3500 #2", "date": datetime.date(2026, 11, 30)},
                {"machine_id": "EX3500 #1", "date": datetime.date(2026, 12, 1)}]
    for root, meta in zip(roots, metadata):
        shutil.copytree(base, root)
        config = load_session_config(root / "session.toml")
        save_session_config(config.__class__(config.machine, config.cameras, config.options, meta),
                            root / "session.toml")
    (roots[2] / "truth" / "cameras.toml").unlink()
    return top, roots


@pytest.fixture(scope="module")
def threads_cluster():
    """The address of a Dask cluster of two single-threaded workers inside this process: its
    stages run on the modules and compiled kernels loaded here, with no worker process to
    start (a local cluster of processes, the default, is the test of a killed worker's)."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=":0") as cluster:
        yield cluster.scheduler_address


def read_fleet(out: Path) -> dict[str, dict]:
    with open(out / "fleet.csv", newline="") as fh:
        return {row["session"]: row for row in csv.DictReader(fh)}


@pytest.mark.long
def test_batch_runs_skips_reruns_and_reports(fleet, threads_cluster, tmp_path):
    top, roots = fleet
    assert find_sessions([top, roots[0]]) == sorted(r.resolve() for r in roots)

    report, failed = run_batch([top], BatchOptions(scheduler=threads_cluster, out=tmp_path), chain_for=chain)
    assert failed == 1, report
    rows = read_fleet(tmp_path)
    assert list(rows) == ["site_a/s1", "site_a/s2", "site_b/deep/s3"]  # below the sessions' common folder
    rows = {name.split("/")[-1]: row for name, row in rows.items()}
    assert [rows[r.name]["status"] for r in roots] == ["ok", "ok", "failed"]
    assert rows["s3"]["error"].startswith("prepare: ") and "truth/cameras.toml: file not found" in rows["s3"]["error"]
    assert rows["s1"]["stages_run"] == str(len(chain(roots[0]))) and rows["s1"]["stages_skipped"] == "0"

    # the summary against the truth: sync found the offsets, the cycles are the truth's
    truth = load_calibration(roots[0] / "truth" / "cameras.toml")
    synced = load_calibration(roots[0] / "calibration" / "cameras.toml")
    assert np.abs(synced.time_offsets - truth.time_offsets).max() < 0.5 / 30  # within half a frame
    config = load_session_config(roots[0] / "session.toml")
    fps = config.cameras[0].fps
    phases = load_cycles(roots[0] / "truth" / "cycles.csv")
    hours = len(load_motion(roots[0] / "results" / "motion.csv", Session.open(roots[0]).machine())) / fps / 3600
    row = rows["s1"]
    assert (row["machine"], row["day"]) == ("EX3500 #1", "2026-11-30")
    assert float(row["hours"]) == pytest.approx(hours, abs=1e-4)
    assert int(row["cycles"]) == len(phases) >= 1
    assert float(row["cycles_per_hour"]) == pytest.approx(len(phases) / hours, rel=1e-3)
    cycle_s = np.mean((phases.end - phases.start + 1) / fps)
    dig_s = np.mean((phases.phases[:, 1] - phases.phases[:, 0] + 1) / fps)
    assert float(row["mean_cycle_s"]) == pytest.approx(cycle_s, abs=1e-3)
    assert float(row["mean_dig_s"]) == pytest.approx(dig_s, abs=1e-3)
    assert float(row["mean_rest_s"]) == pytest.approx(cycle_s - dig_s, abs=2e-3)
    counts = [int(row[c.lower().replace(" ", "_")]) for c in CLASSES]
    assert counts == [sum(label == c for label in phases.label) for c in CLASSES[:3]] + [0]
    report_md = (tmp_path / "fleet_report.md").read_text()
    assert "| EX3500 #1 | 1/2 ok |" in report_md and "| 2026-11-30 | 2/2 ok |" in report_md
    assert "- site_b/deep/s3: prepare: " in report_md

    # a re-run with nothing changed does no work
    outputs = [roots[0] / p for p in ("calibration/cameras.toml", "tracks/cam2.csv", "results/motion.csv")]
    before = {p: (p.stat().st_mtime_ns, p.read_bytes()) for p in outputs}
    options = BatchOptions(scheduler=threads_cluster, out=tmp_path)
    _, failed = run_batch([top], options, chain_for=chain)
    assert failed == 1
    rows = read_fleet(tmp_path)
    assert rows["site_a/s1"]["stages_run"] == rows["site_a/s2"]["stages_run"] == "0"
    assert rows["site_a/s1"]["stages_skipped"] == str(len(chain(roots[0])))
    assert {p: (p.stat().st_mtime_ns, p.read_bytes()) for p in outputs} == before

    # a lost camera output: that camera's stage runs again on the calibration it read before
    # (sync rewrote it in place: put back from the store), then sync, whose output the restore
    # undid; the later stages see the same content and are skipped
    (roots[0] / "tracks" / "cam2.csv").unlink()
    _, _ = run_batch([roots[0]], options, chain_for=chain)
    row = read_fleet(tmp_path)["s1"]
    assert (row["status"], row["stages_run"]) == ("ok", "2"), row
    assert {p: p.read_bytes() for p in outputs} == {p: b for p, (_, b) in before.items()}

    # changed arguments (the default made explicit) re-run fit only: its output is the same, so the analysis is skipped
    run_batch([roots[0]], options, chain_for=partial(chain, max_gap=2))
    row = read_fleet(tmp_path)["s1"]
    assert row["stages_run"] == "1", row


def test_split_tasks_gives_each_camera_its_own_task(fleet):
    groups = split_tasks(chain(fleet[1][0]))
    assert [[s.name for s in g] for g in groups] == [
        ["prepare"], ["tracks cam1"], ["tracks cam2"], ["tracks cam3"], ["sync", "triangulate", "fit", "analysis"]]


def test_stage_inputs_come_from_arguments(tmp_path):
    a, b = tmp_path / "a.toml", tmp_path / "b.csv"
    a.write_text("")
    made = {b}
    stage = stage_from_command("sync", ["sync", str(a), str(b), "--fps", "cam1=30", "--out", str(a)], made)
    assert stage.inputs == (a, b) and stage.outputs == (a,)
    later = stage_from_command("fit", ["fit", str(tmp_path / "nothing.toml"), str(a), "--out", str(tmp_path / "m.csv")], made)
    assert later.inputs == (a,) and tmp_path / "m.csv" in made


def test_stage_and_option_guards(tmp_path, capsys):
    with pytest.raises(ValueError, match="either mocap arguments or a callable"):
        Stage("x", (), (tmp_path,))
    with pytest.raises(ValueError, match="must write something"):
        Stage("x", (), (), args=("fit",))
    with pytest.raises(ValueError, match="workers must be at least 1"):
        BatchOptions(workers=0)
    with pytest.raises(InputError, match="not found"):
        find_sessions([tmp_path / "missing"])
    assert cli.main(["batch", str(tmp_path), "--out", str(tmp_path)]) == 2
    assert "no session folder (with session.toml)" in capsys.readouterr().err
    assert cli.main(["batch", str(tmp_path), "--workers", "0"]) == 2
    assert "workers must be at least 1" in capsys.readouterr().err


def test_a_failing_stage_gives_its_one_line(tmp_path):
    """A stage of `mocap` arguments (run as that command) and a callable stage fail with the
    command's one line; their reports and errors go to the stage's log."""
    from mocap.batch import run

    missing = tmp_path / "nothing.toml"
    stages = [Stage("fit", (), (tmp_path / "m.csv",), args=("fit", "hitachi_ex3500", missing, missing, "--out", tmp_path / "m.csv")),
              Stage("refine", (), (tmp_path / "r.toml",), args=("refine", "--no-such-option")),
              Stage("triangulate", (), (tmp_path / "p.csv",),
                    call=partial(triangulate_step, str(missing), (str(missing),), str(tmp_path / "p.csv")))]
    assert run.execute(stages[0], tmp_path) == f"mocap fit: error: {missing}: file not found; check the calibration path"
    assert run.execute(stages[1], tmp_path).startswith("mocap refine: error: the following arguments are required")
    assert run.execute(stages[2], tmp_path) == f"{missing}: file not found; check the calibration path"
    logs = tmp_path / "batch" / "logs"
    assert "file not found" in (logs / "fit.log").read_text() and "file not found" in (logs / "triangulate.log").read_text()


def test_an_unreachable_scheduler_is_one_line(tmp_path, capsys, monkeypatch):
    from mocap.batch import stage

    monkeypatch.setattr(stage, "CONNECT_TIMEOUT_S", 0.5)  # nothing listens: no need to wait 5 s to be sure
    (tmp_path / "s1").mkdir()
    (tmp_path / "s1" / "session.toml").write_text('machine = "hitachi_ex3500"\n')
    assert cli.main(["batch", str(tmp_path), "--scheduler", "tcp://127.0.0.1:9", "--out", str(tmp_path)]) == 2
    assert "cannot reach the Dask scheduler" in capsys.readouterr().err


def test_session_metadata_round_trip_and_guard(tmp_path):
    from mocap.batch.fleet import machine_and_day
    from mocap.io.session_toml import SessionCamera, SessionConfig

    config = SessionConfig("bobcat_225", (SessionCamera("cam1", "v.mp4", 25.0),), {},
                           {"machine_id": "B7", "date": datetime.datetime(2026, 12, 1, 6, 30)})
    save_session_config(config, tmp_path / "session.toml")
    loaded = load_session_config(tmp_path / "session.toml")
    assert loaded.metadata == config.metadata
    assert machine_and_day(loaded.metadata, loaded.machine) == ("B7", "2026-12-01")
    assert machine_and_day({}, "bobcat_225") == ("bobcat_225", "unknown")
    (tmp_path / "session.toml").write_text(
        'machine = "bobcat_225"\nmetadata = "x"\n[[cameras]]\nname = "cam1"\nvideo = "v.mp4"\nfps = 25\n')
    with pytest.raises(InputError, match=r"\[metadata\] must be a table"):
        load_session_config(tmp_path / "session.toml")


def tracks_killing_the_worker_once(root: Path, camera: str) -> None:
    """The camera's tracks, but the first time its worker process is killed mid-task (as the
    kernel's out-of-memory killer would)."""
    import os
    import signal

    mark = root / "batch" / f"killed-{camera}"
    if not mark.exists():
        mark.parent.mkdir(parents=True, exist_ok=True)
        mark.write_text("")
        os.kill(os.getpid(), signal.SIGKILL)
    camera_tracks(root, camera)


def chain_with_a_killed_worker(root: Path) -> list[Stage]:
    stages = chain(root)
    if root.name != "s2":
        return stages
    return [Stage(s.name, s.inputs, s.outputs, call=partial(tracks_killing_the_worker_once, root, s.camera),
                  camera=s.camera) if s.camera == "cam1" else s for s in stages]


@pytest.mark.long
@pytest.mark.processes
def test_batch_under_faults_a_killed_worker_and_a_broken_session(fleet, threads_cluster, tmp_path, capsys):
    """A worker killed mid-task costs only that task's re-run (Dask's own): its session's
    results equal those of a session that ran untouched; the broken session is listed with
    its one-line reason, the exit status says partial (3); the re-run after the fix does only
    the broken session."""
    top = tmp_path / "fleet"
    shutil.copytree(fleet[0], top)
    roots = [top / "site_a" / "s1", top / "site_a" / "s2", top / "site_b" / "deep" / "s3"]
    for root in roots:  # from scratch: no manifest, no results of the test before
        for made in ("batch", "results", "tracks", "analysis"):
            shutil.rmtree(root / made, ignore_errors=True)
        (root / "calibration" / "cameras.toml").unlink(missing_ok=True)
    report, failed = run_batch([top], BatchOptions(workers=1, out=tmp_path), chain_for=chain_with_a_killed_worker)
    assert failed == 1, report
    assert (roots[1] / "batch" / "killed-cam1").exists()  # the worker was killed once
    rows = {name.split("/")[-1]: row for name, row in read_fleet(tmp_path).items()}
    assert [rows[r.name]["status"] for r in roots] == ["ok", "ok", "failed"]
    assert "site_b/deep/s3: prepare: " in report and "truth/cameras.toml: file not found" in report
    for name in ("calibration/cameras.toml", "tracks/cam1.csv", "results/points.csv", "results/motion.csv"):
        assert (roots[1] / name).read_bytes() == (roots[0] / name).read_bytes(), name

    shutil.copy(roots[0] / "truth" / "cameras.toml", roots[2] / "truth" / "cameras.toml")  # the fix
    # (its worker was killed once: no worker process is needed to see the re-run do only the fixed session)
    _, failed = run_batch([top], BatchOptions(scheduler=threads_cluster, out=tmp_path),
                          chain_for=chain_with_a_killed_worker)
    assert failed == 0
    rows = {name.split("/")[-1]: row for name, row in read_fleet(tmp_path).items()}
    assert rows["s1"]["stages_run"] == rows["s2"]["stages_run"] == "0"
    assert rows["s3"]["stages_run"] == str(len(chain(roots[2]))) and rows["s3"]["status"] == "ok"
    assert (roots[2] / "results" / "motion.csv").read_bytes() == (roots[0] / "results" / "motion.csv").read_bytes()


# --- a cluster across machines: TLS ----------------------------------------------------------


@pytest.fixture(scope="module")
def certificates(tmp_path_factory):
    """A CA of the cluster's own and one certificate it signed, for the scheduler, the worker
    and the client (Dask checks the CA, not the host name), made with openssl."""
    import shutil
    import subprocess

    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed")
    d = tmp_path_factory.mktemp("tls")

    def openssl(*args):
        subprocess.run(["openssl", *args], cwd=d, check=True, capture_output=True)
    openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem", "-days", "2",
            "-subj", "/CN=mocap test CA")
    openssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", "node.key", "-out", "node.csr", "-subj", "/CN=localhost")
    (d / "node.ext").write_text("basicConstraints=CA:FALSE\nsubjectAltName=DNS:localhost,IP:127.0.0.1\n")
    openssl("x509", "-req", "-in", "node.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial", "-days", "2",
            "-extfile", "node.ext", "-out", "node.pem")
    return d / "ca.pem", d / "node.pem", d / "node.key"


@pytest.mark.long
def test_batch_through_a_tls_scheduler(fleet, certificates, tmp_path, capsys):
    """A scheduler and a worker that speak TLS only, on loopback: the batch reaches them with
    the cluster's CA and a certificate it signed, and its session's results are those of its
    stages run one after the other here (a session another command holds is listed failed
    with its one line, its lock left to its holder); without the certificates it is refused
    in one line, and a missing, unreadable or not-PEM file is one line naming it (exit 2)."""
    import os
    import socket

    from distributed import LocalCluster
    from distributed.security import Security

    from mocap.batch.run import run_stages
    from mocap.io.lock import LOCK_NAME

    ca, cert, key = certificates
    top, serial = tmp_path / "fleet", tmp_path / "serial"
    for copy in (top, serial):  # from scratch: no manifest, no results of another test
        shutil.copytree(fleet[1][0], copy / "s1", ignore=shutil.ignore_patterns("batch", "results", "tracks"))
        (copy / "s1" / "calibration" / "cameras.toml").unlink(missing_ok=True)
    stages = chain(serial / "s1")
    assert not run_stages(serial / "s1", stages, [s.name for s in stages], [], True).error  # in this process, no Dask
    security = Security(tls_ca_file=str(ca), tls_scheduler_cert=str(cert), tls_scheduler_key=str(key),
                        tls_worker_cert=str(cert), tls_worker_key=str(key), tls_client_cert=str(cert),
                        tls_client_key=str(key), require_encryption=True)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tls://", host="127.0.0.1",
                      security=security, dashboard_address=":0") as cluster:
        address = cluster.scheduler_address
        assert address.startswith("tls://127.0.0.1:")
        options = BatchOptions(scheduler=address, out=tmp_path, tls_ca_file=ca, tls_cert=cert, tls_key=key)
        (top / "s2").mkdir()  # and a session another command writes (its lock held by a live process)
        shutil.copy(top / "s1" / "session.toml", top / "s2" / "session.toml")
        (top / "s2" / LOCK_NAME).write_text(f"{os.getppid()} {socket.gethostname()} mocap run s2\n")
        report, failed = run_batch([top], options, chain_for=chain)
        assert failed == 1 and "  s2: " in report and "in use by `mocap run s2`" in report, report
        assert (top / "s2" / LOCK_NAME).is_file() and not (top / "s1" / LOCK_NAME).exists()
        shutil.rmtree(top / "s2")
        assert read_fleet(tmp_path)["s1"]["stages_run"] == str(len(chain(top / "s1")))
        for name in ("calibration/cameras.toml", "tracks/cam1.csv", "results/motion.csv"):
            assert (top / "s1" / name).read_bytes() == (serial / "s1" / name).read_bytes(), name

        argv = ["batch", str(top), "--scheduler", address, "--out", str(tmp_path)]
        assert cli.main(argv) == 2  # no certificate: neither flags nor Dask's configuration
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "needs the cluster's CA and this client's certificate" in err
        for flags, named in [(["--tls-ca-file", str(tmp_path / "none.pem"), "--tls-cert", str(cert)], "none.pem"),
                             (["--tls-ca-file", str(ca), "--tls-cert", str(cert), "--tls-key", str(tmp_path)],
                              str(tmp_path)),
                             (["--tls-ca-file", str(key), "--tls-cert", str(cert), "--tls-key", str(key)], str(key))]:
            assert cli.main(argv + flags) == 2
            err = capsys.readouterr().err
            assert err.count("\n") == 1 and f"{named}: " in err, err
    tcp = ["batch", str(top), "--scheduler", "tcp://127.0.0.1:9", "--tls-ca-file", str(ca), "--out", str(tmp_path)]
    assert cli.main(tcp) == 2 and "give --scheduler tls://HOST:PORT" in capsys.readouterr().err
