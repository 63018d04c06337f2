"""`mocap calibrate` end to end, as a user runs it, and its answers to bad input."""

import contextlib
import io
import subprocess
import sys
import tomllib

import numpy as np
import pytest
from conftest import scene

from mocap.cli import main
from mocap.io.cameras_toml import load_calibration
from mocap.io.points_csv import load_points
from mocap.io.tracks_csv import save_tracks


@pytest.fixture()
def observations(tmp_path, ex3500):
    cameras, q, obs, tracks = scene(ex3500, 2, seed=3)
    paths = []
    for camera in cameras:
        path = tmp_path / f"{camera.name}.csv"
        save_tracks(tracks.of_camera(camera.name), path)
        paths.append(path)
    return cameras, q, paths


def run_cli(*args, fresh: bool = False):
    """Run the command line: with `fresh`, the installed entry point in a fresh interpreter,
    as a user would; else `mocap.cli.main` in this process, its stdout and stderr caught (a
    second of imports saved per case; tests/test_bad_input.py runs its cases in processes too)."""
    argv = list(map(str, args))
    if fresh:
        return subprocess.run([sys.executable, "-m", "mocap.cli", *argv], capture_output=True, text=True, timeout=120)
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main(argv)
    return subprocess.CompletedProcess(argv, status, out.getvalue(), err.getvalue())


def test_calibrate_end_to_end(tmp_path, observations, ex3500):
    cameras, q, paths = observations
    out = tmp_path / "calibration" / "cameras.toml"
    before = [p.read_bytes() for p in paths]
    done = run_cli("calibrate", "hitachi_ex3500", *paths, "--size", "1920x1080", "--out", out, fresh=True)
    assert done.returncode == 0, done.stderr
    assert "identifiability: rank 18 of 18" in done.stdout
    assert [p.read_bytes() for p in paths] == before  # inputs untouched
    calibration = load_calibration(out)
    assert calibration.names == ("cam1", "cam2")
    for fitted, truth in zip(calibration.cameras, cameras):
        assert np.linalg.norm(fitted.center - truth.center) < 3.0  # metres at 30-60 m, one frame
    joints = calibration.joints(ex3500)
    assert np.max(np.abs(np.degrees(joints - q))) < 2.0
    data = tomllib.loads(out.read_text())
    assert set(data["cam_00"]["paper"]) >= {"azimuth_deg", "elevation_deg", "tilt_deg", "position", "focal_px", "sd"}
    assert data["metadata"]["frame"] == 0 and data["metadata"]["error"] < 1.0
    reference = load_points(out.with_name("reference_points.csv"))
    assert len(reference) == len(ex3500.marker_names)
    truth_points = ex3500.markers(q[None])[0]
    assert np.max(np.linalg.norm(reference.xyz - truth_points, axis=1)) < 0.3


def test_dlt_from_the_reference_points(tmp_path, observations):
    cameras, q, paths = observations
    out = tmp_path / "cameras.toml"
    assert main(["calibrate", "hitachi_ex3500", *map(str, paths), "--size", "1920x1080", "--out", str(out)]) == 0
    dlt_out = tmp_path / "dlt.toml"
    code = main([
        "calibrate", "hitachi_ex3500", *map(str, paths), "--size", "1920x1080", "--out", str(dlt_out),
        "--method", "dlt", "--reference", str(tmp_path / "reference_points.csv"),
    ])
    assert code == 0
    dlt = load_calibration(dlt_out)
    assert dlt.metadata["method"] == "dlt"
    for fitted, truth in zip(dlt.cameras, cameras):
        assert np.linalg.norm(fitted.center - truth.center) < 10.0


def test_per_camera_writes_joints_per_camera(tmp_path, observations):
    _, q, paths = observations
    out = tmp_path / "cameras.toml"
    assert main(["calibrate", "hitachi_ex3500", *map(str, paths), "--size", "1920x1080", "--out", str(out), "--per-camera"]) == 0
    data = tomllib.loads(out.read_text())
    assert "joints" in data["cam_00"] and "joints" in data["cam_01"] and "joints" not in data["metadata"]


def one_error_line(done):
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert "Traceback" not in done.stderr
    return lines[0]


def test_bad_model_file(tmp_path, observations):
    _, _, paths = observations
    model = tmp_path / "bad.toml"
    model.write_text('name = "x"\n[[links]]\nname = "base"\n[[markers]]\nname = "U1"\nlink = "nowhere"\nposition = [0, 0, 0]\n')
    out = tmp_path / "out.toml"
    line = one_error_line(run_cli("calibrate", model, *paths, "--size", "1920x1080", "--out", out))
    assert str(model) in line and "marker 'U1': unknown link 'nowhere'" in line
    assert not out.exists()


def test_bad_tracks_file(tmp_path):
    bad = tmp_path / "obs.csv"
    bad.write_text("camera,frame,marker,x,y\ncam1,0,U1,12.5,oops\n")
    out = tmp_path / "out.toml"
    line = one_error_line(run_cli("calibrate", "hitachi_ex3500", bad, "--size", "1920x1080", "--out", out))
    assert f"{bad}: line 2: y 'oops' is not a number" in line
    assert not out.exists()


def test_too_few_markers_and_bad_size(tmp_path, observations):
    _, _, paths = observations
    few = tmp_path / "few.csv"
    few.write_text("camera,frame,marker,x,y\ncam1,0,U1,100,100\ncam1,0,U2,200,100\ncam1,0,U3,200,200\n")
    line = one_error_line(run_cli("calibrate", "hitachi_ex3500", few, "--size", "1920x1080", "--out", tmp_path / "o.toml"))
    assert "sees 3 marker(s)" in line
    line = one_error_line(run_cli("calibrate", "hitachi_ex3500", *paths, "--size", "big", "--out", tmp_path / "o.toml"))
    assert "--size 'big': expected WxH" in line
    line = one_error_line(run_cli("calibrate", "hitachi_ex3500", *paths, "--size", "1920x1080", "--frame", "9", "--out", tmp_path / "o.toml"))
    assert "no observations at frame 9" in line


def test_unknown_marker_names(tmp_path):
    obs = tmp_path / "obs.csv"
    obs.write_text("camera,frame,marker,x,y\n" + "".join(f"cam1,0,Z{k},{100 + k},{100 + 2 * k}\n" for k in range(6)))
    line = one_error_line(run_cli("calibrate", "hitachi_ex3500", obs, "--size", "1920x1080", "--out", tmp_path / "o.toml"))
    assert "Z0" in line and "not in the machine model" in line


def test_guess_file(tmp_path, observations, ex3500):
    cameras, q, paths = observations
    lines = []
    for camera in cameras:
        p = camera.to_paper()
        lines += [
            f"[{camera.name}]",
            f"azimuth_deg = {np.degrees(p.azimuth) + 5}",
            f"elevation_deg = {np.degrees(p.elevation) - 3}",
            f"tilt_deg = {np.degrees(p.tilt) + 2}",
            f"position = [{p.position[0] * 1.1}, {p.position[1] * 0.9}, {p.position[2]}]",
            f"focal_px = {p.focal * 1.3}",
        ]
    guess = tmp_path / "guess.toml"
    guess.write_text("\n".join(lines) + "\n")
    out = tmp_path / "cameras.toml"
    assert main(["calibrate", "hitachi_ex3500", *map(str, paths), "--size", "1920x1080", "--out", str(out), "--guess", str(guess)]) == 0
    joints = load_calibration(out).joints(ex3500)
    assert np.max(np.abs(np.degrees(joints - q))) < 2.0
    guess.write_text("[cam1]\nazimuth_deg = 1\n")
    line = one_error_line(run_cli("calibrate", "hitachi_ex3500", *paths, "--size", "1920x1080", "--out", out, "--guess", guess))
    assert f"{guess}: [cam1]: expected exactly" in line
