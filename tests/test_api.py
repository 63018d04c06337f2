"""The Python API (`import mocap`) on a small synthetic scene: the chain calibrate ->
triangulate -> fit -> analyze gives the command line's numbers and the truth's, and several
sessions' motion make one table."""

import csv
import subprocess
import sys

import numpy as np
import pytest

import mocap
from mocap.cli import main
from mocap.io.session_toml import SessionCamera, SessionConfig, save_session_config
from mocap.io.tracks_csv import save_tracks
from mocap.synthetic.scenes import observe, random_joints, ring_of_cameras

FRAMES, NOISE_PX, SIZE = 40, 0.5, (1920, 1080)


@pytest.fixture(scope="module")
def scene(tmp_path_factory, ex3500):
    """Three cameras around the EX3500 sweeping from one pose to another over 40 frames,
    observed with 0.5 px of noise; the tracks, the first frame's labels and the true joints."""
    rng = np.random.default_rng(11)
    rest = ex3500.markers(np.zeros((1, ex3500.n_joints)))[0]
    extent = np.ptp(rest, axis=0).max()
    cameras = ring_of_cameras(3, rest.mean(0), (2.5 * extent, 3.5 * extent), rng, size=SIZE,
                              height=(0.3 * extent, 0.6 * extent))
    ends = random_joints(ex3500, 2, rng)
    joints = ends[0] + np.linspace(0, 1, FRAMES)[:, None] * (ends[1] - ends[0])
    tracks = observe(cameras, ex3500, joints, rng, noise_px=NOISE_PX)
    root = tmp_path_factory.mktemp("api")
    save_tracks(tracks, root / "tracks.csv")
    save_tracks(tracks.select(tracks.frame == 0), root / "labels.csv")
    return root, joints, cameras


@pytest.fixture(scope="module")
def chain(scene):
    """The chain through the API only."""
    root = scene[0]
    machine = mocap.load_machine("hitachi_ex3500")
    cams = mocap.calibrate(machine, mocap.read_tracks(root / "labels.csv"), size=SIZE, frame=0)
    cams.write(root / "api_cameras.toml")
    tracks = mocap.read_tracks(root / "tracks.csv")
    cams = mocap.read_calibration(root / "api_cameras.toml")
    points = mocap.triangulate(cams, tracks)
    motion = mocap.fit(machine, cams, tracks)
    motion.write(root / "api_motion.csv")
    return machine, cams, points, motion


def read_columns(path):
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return {name: np.array([float(row[name] or "nan") for row in rows]) for name in rows[0]}


def test_the_api_gives_the_command_lines_numbers(scene, chain):
    root = scene[0]
    _, cams, points, motion = chain
    assert main(["calibrate", "hitachi_ex3500", str(root / "labels.csv"), "--size", "1920x1080", "--frame", "0",
                 "--out", str(root / "cli_cameras.toml")]) == 0
    assert main(["triangulate", str(root / "cli_cameras.toml"), str(root / "tracks.csv"),
                 "--out", str(root / "cli_points.csv")]) == 0
    assert main(["fit", "hitachi_ex3500", str(root / "cli_cameras.toml"), str(root / "tracks.csv"),
                 "--out", str(root / "cli_motion.csv")]) == 0
    cli_cams = mocap.read_calibration(root / "cli_cameras.toml")
    for ours, theirs in zip(cams.cameras, cli_cams.cameras):
        assert np.array_equal(ours.matrix, theirs.matrix)
        assert np.array_equal(ours.cam_from_world.matrix, theirs.cam_from_world.matrix)
    points.write(root / "api_points.csv")
    assert (root / "api_points.csv").read_text() == (root / "cli_points.csv").read_text()
    api, cli = read_columns(root / "api_motion.csv"), read_columns(root / "cli_motion.csv")
    assert list(api) == list(cli) and len(cli["frame"]) == FRAMES
    for name in cli:
        assert np.array_equal(api[name], cli[name], equal_nan=True), name


def test_the_api_reaches_the_truth(scene, chain):
    _, truth, _ = scene
    machine, _, points, motion = chain
    # cameras 2.5-3.5 extents away, 0.5 px of noise, one calibration frame: the joints to a
    # fraction of a degree, the bucket tip to centimetres
    error = np.degrees(np.abs(motion.motion.joints - truth))
    assert np.median(error) < 0.2 and error.max() < 1.5, error.max(0)
    tip = machine.points(truth)[:, machine.point_names.index("bucket_tip")]
    tip_fit = motion.motion.points[:, machine.point_names.index("bucket_tip")]
    assert np.sqrt(np.mean(np.sum((tip - tip_fit) ** 2, axis=1))) < 0.1
    assert np.median(points.points.error_px) < 2 * NOISE_PX
    assert motion.report.startswith(f"{FRAMES} frames; {FRAMES} fitted")  # kept in memory: nothing written
    assert points.report.startswith(f"{len(points)} points in {FRAMES} frames; median reprojection error")
    table = motion.to_arrow()
    assert table.num_rows == FRAMES and table.column_names[:2] == ["frame", "time"]
    assert np.allclose(table["boom"].to_numpy(), np.degrees(motion.motion.joints[:, machine.joint_names.index("boom")]))


def test_analyze_finds_no_cycle_in_one_sweep(chain, tmp_path):
    machine, _, _, motion = chain
    cycles = mocap.analyze(machine, motion)
    assert len(cycles) == 0 and cycles.to_arrow().column_names[:3] == ["cycle", "start_frame", "end_frame"]
    cycles.write(tmp_path / "out")
    assert (tmp_path / "out" / "cycles.csv").read_text().startswith("cycle,start_frame,end_frame")


def test_sessions_motion_in_one_table(scene, chain, tmp_path):
    machine, _, _, motion = chain
    roots = [tmp_path / name for name in ("day1", "day2", "day3")]
    for root in roots:
        save_session_config(SessionConfig("hitachi_ex3500", (SessionCamera("cam1", "videos/cam1.mp4", 30.0),)),
                            root / "session.toml")
        (root / "results").mkdir()
        motion.write(root / "results" / "motion.csv")
    table = mocap.motions(roots)
    assert table.num_rows == 3 * FRAMES
    assert table["session"].to_pylist() == [r.name for r in roots for _ in range(FRAMES)]
    assert np.allclose(table["boom"].to_numpy()[:FRAMES], motion.to_arrow()["boom"].to_numpy(), atol=1e-6)
    try:
        import pandas  # noqa: F401
    except ImportError:
        with pytest.raises(ImportError, match="needs pandas"):
            motion.to_pandas()
    else:
        assert table.to_pandas().shape == (3 * FRAMES, table.num_columns)


def test_api_guards(scene, chain):
    machine, cams, _, _ = chain
    root = scene[0]
    with pytest.raises(mocap.InputError, match="not found"):
        mocap.read_tracks(root / "missing.csv")
    with pytest.raises(mocap.InputError, match="export format 'ply'"):
        mocap.export("ply", root, root / "x.ply")
    with pytest.raises(mocap.InputError, match="no observations at frame 99"):
        mocap.calibrate(machine, mocap.read_tracks(root / "labels.csv"), size=SIZE, frame=99)
    with pytest.raises(AttributeError, match="no attribute 'calibrat'"):
        mocap.calibrat  # noqa: B018


def test_import_mocap_stays_light():
    probe = ("import sys, mocap; mocap.__version__; "
             "print(sorted(m for m in ('numpy', 'scipy', 'pyarrow', 'mocap.api') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_session_stages_as_methods(tmp_path):
    """A still cube pair filmed by two cameras: the stages one by one through `mocap.Session`
    write the session's files; the triangulated markers land on the truth."""
    from test_unusual_input import FPS, static_rigid_video

    from mocap.synthetic.scenes import look_at_camera

    machine = mocap.load_machine("cube_pair")
    rest = machine.markers(np.zeros((1, 0)))[0]
    rng = np.random.default_rng(4)
    (tmp_path / "videos").mkdir()
    labels = []
    for name, offset in (("cam1", [12, -8, 10]), ("cam2", [-6, -14, 8])):
        camera = look_at_camera(name, (480, 270), 430.0, rest.mean(0) + offset, rest.mean(0))
        uv = static_rigid_video(tmp_path / "videos" / f"{name}.mp4", camera, machine, rng, frames=4)
        labels.append(mocap.concat_tracks([mocap.read_tracks(_labels_csv(tmp_path, name, machine, uv, rng))]))
    session = mocap.Session.create(tmp_path, "cube_pair", [(n, f"videos/{n}.mp4", FPS) for n in ("cam1", "cam2")])
    mocap.write_tracks(mocap.concat_tracks(labels), tmp_path / "calibration" / "labels.csv")
    assert "wrote" in session.calibrate()
    assert session.track().count("marker positions written") == 2
    with pytest.raises(mocap.InputError, match="no sync stage"):  # a rigid object: nothing to sync on
        session.sync()
    assert "points in 4 frames" in session.triangulate()
    assert "4 frames written" in session.fit()
    points = mocap.read_points(tmp_path / "results" / "points.csv").points
    error = np.linalg.norm(points.xyz - rest[machine.marker_index(points.marker)], axis=1)
    assert len(points) == 4 * 8 and np.median(error) < 0.03  # a metre-scale object 15-20 m away, 0.3 px labels
    assert len(session.motion()) == 4


def _labels_csv(root, name, machine, uv, rng):
    path = root / f"{name}_labels.csv"
    rows = "".join(f"{name},0,{m},{x + rng.normal(0, 0.3):.3f},{y + rng.normal(0, 0.3):.3f}\n"
                   for m, (x, y) in zip(machine.marker_names, uv))
    path.write_text("camera,frame,marker,x,y\n" + rows)
    return path
