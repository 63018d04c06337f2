"""`mocap export`: C3D / TRC round trips, URDF forward kinematics, COLMAP reprojection."""

from dataclasses import replace

import numpy as np
import pytest

from mocap import cli
from mocap.core.calibration import Calibration
from mocap.core.motion import Motion
from mocap.core.points import Points
from mocap.core.tracks import Tracks
from mocap.errors import InputError
from mocap.interchange.markers import marker_table
from mocap.io.cameras_toml import save_calibration
from mocap.io.machine_toml import load_machine, machine_from_dict, save_machine
from mocap.io.motion_csv import save_motion
from mocap.io.points_csv import load_points, save_points
from mocap.io.session_toml import SessionCamera, SessionConfig, save_session_config
from mocap.io.tracks_csv import save_tracks
from mocap.io.trc import load_trc
from mocap.synthetic.scenes import random_joints, ring_of_cameras

FPS = 29.97


def make_session(root, machine_name, rng, n_frames=40, cameras=()):
    """A session folder with results: points.csv (markers missing at random, some frames
    without any point) and motion.csv, from random joint values of a shipped model."""
    machine = load_machine(machine_name)
    names = [c.name for c in cameras] or ["cam1", "cam2"]
    config = SessionConfig(machine_name, tuple(SessionCamera(n, f"videos/{n}.mp4", FPS) for n in names))
    save_session_config(config, root / "session.toml")
    frames = np.arange(5, 5 + n_frames)
    joints = random_joints(machine, n_frames, rng)
    markers = machine.markers(joints)  # (F, M, 3)
    seen = rng.random(markers.shape[:2]) > 0.3
    seen[10:13] = False  # frames with no marker at all
    f, m = np.nonzero(seen)
    points = Points(frames[f], np.array(machine.marker_names, dtype=object)[m], markers[f, m],
                    rng.uniform(0, 1, len(f)), np.full(len(f), 2))
    save_points(points, root / "results" / "points.csv")
    named = machine.points(joints)
    named[20] = np.nan  # a frame the fit could not reach
    motion = Motion(machine.joint_names, machine.point_names, frames, frames / FPS, joints, named,
                    machine.bucket_angles(joints))
    save_motion(motion, machine, root / "results" / "motion.csv")
    return machine, frames, markers, seen, named


def expected_table(machine, frames, markers, seen, named):
    """(F, N, 3) markers then named points, NaN where not seen."""
    xyz = np.where(seen[..., None], markers, np.nan)
    return np.concatenate([xyz, named], axis=1)


@pytest.mark.parametrize("machine_name", ["hitachi_ex3500", "bobcat_225"])
def test_c3d_round_trip_through_ezc3d(tmp_path, machine_name):
    ezc3d = pytest.importorskip("ezc3d")
    rng = np.random.default_rng(3)
    machine, frames, markers, seen, named = make_session(tmp_path, machine_name, rng)
    assert cli.main(["export", "c3d", str(tmp_path), "--out", str(tmp_path / "dig.c3d")]) == 0

    c3d = ezc3d.c3d(str(tmp_path / "dig.c3d"))  # read by ezc3d itself, not our reader
    labels = c3d["parameters"]["POINT"]["LABELS"]["value"]
    assert labels == list(machine.marker_names) + list(machine.point_names)
    assert c3d["parameters"]["POINT"]["UNITS"]["value"] == ["mm"]
    assert c3d["header"]["points"]["frame_rate"] == pytest.approx(FPS, abs=1e-4)
    assert c3d["header"]["points"]["first_frame"] == frames[0]
    data = np.transpose(c3d["data"]["points"][:3], (2, 1, 0)) / 1000.0  # (F, N, 3) m
    residuals = c3d["data"]["meta_points"]["residuals"][0].T  # (F, N)
    expected = expected_table(machine, frames, markers, seen, named)
    gap = np.isnan(expected[..., 0])
    assert gap.any() and (~gap).any()
    np.testing.assert_array_equal(np.isnan(data[..., 0]), gap)
    np.testing.assert_array_equal(residuals < 0, gap)  # C3D's invalid-point mark
    assert np.nanmax(np.abs(data - expected)) < 1e-4  # 0.1 mm

    from mocap.io.c3d import load_c3d

    table = load_c3d(tmp_path / "dig.c3d")
    np.testing.assert_array_equal(table.frame, frames)
    assert np.nanmax(np.abs(table.xyz - expected)) < 1e-4


def test_trc_round_trip_keeps_frames_gaps_and_rate(tmp_path, monkeypatch):
    monkeypatch.setattr("mocap.io.trc._CHUNK", 7)  # written in several chunks
    rng = np.random.default_rng(4)
    machine, frames, markers, seen, named = make_session(tmp_path, "hitachi_ex3500", rng)
    assert cli.main(["export", "trc", str(tmp_path), "--out", str(tmp_path / "dig.trc")]) == 0
    lines = (tmp_path / "dig.trc").read_text().splitlines()
    n_columns = 2 + 3 * (len(machine.marker_names) + len(machine.point_names))
    data_lines = lines[6:]
    assert len(data_lines) == len(frames)
    assert all(len(line.split("\t")) == n_columns for line in data_lines)  # gaps are empty fields
    assert data_lines[0].split("\t")[0] == str(frames[0] + 1)  # Frame# counts from 1

    table = load_trc(tmp_path / "dig.trc")
    expected = expected_table(machine, frames, markers, seen, named)
    assert table.names == tuple(machine.marker_names) + tuple(machine.point_names)
    assert table.rate == pytest.approx(FPS)
    np.testing.assert_array_equal(table.frame, frames)
    np.testing.assert_allclose(table.time, frames / FPS, atol=1e-6)
    np.testing.assert_array_equal(np.isnan(table.xyz), np.isnan(expected))
    assert np.nanmax(np.abs(table.xyz - expected)) < 1e-4


def test_marker_table_guards():
    with pytest.raises(InputError, match="no triangulated points and no motion"):
        marker_table(None, None, 30.0)
    points = Points(np.array([0]), np.array(["bucket_tip"], dtype=object), np.zeros((1, 3)), np.zeros(1), np.ones(1))
    motion = Motion((), ("bucket_tip",), np.array([0]), np.zeros(1), np.zeros((1, 0)), np.zeros((1, 1, 3)), np.zeros(1))
    with pytest.raises(InputError, match="share the names"):
        marker_table(points, motion, 30.0)


def test_export_needs_results_and_a_session(tmp_path, capsys):
    assert cli.main(["export", "trc", str(tmp_path), "--out", str(tmp_path / "x.trc")]) == 2
    assert "no session.toml" in capsys.readouterr().err
    save_session_config(SessionConfig("hitachi_ex3500", (SessionCamera("cam1", "v.mp4", 30.0),)),
                        tmp_path / "session.toml")
    assert cli.main(["export", "c3d", str(tmp_path), "--out", str(tmp_path / "x.c3d")]) == 2
    assert "run the session first" in capsys.readouterr().err
    assert cli.main(["export", "colmap", str(tmp_path), "--out", str(tmp_path / "m")]) == 2
    assert "no triangulated points" in capsys.readouterr().err
    assert not (tmp_path / "x.c3d").exists() and not (tmp_path / "m").exists()


# --- URDF --------------------------------------------------------------------------------


def random_chain(rng, n_links):
    """A random machine model (TOML form): a tree of `n_links` moving links, each joint
    revolute or prismatic about an axis of either sign (a unit axis or a random direction),
    with rpy angles up to ±180° (flipped frames), markers and named points on every link."""
    links = [{"name": "base"}]
    markers, points = [], []
    for k in range(1, n_links + 1):
        kind = "prismatic" if rng.random() < 0.35 else "revolute"
        axis = np.eye(3)[rng.integers(3)] * rng.choice([-1, 1]) if rng.random() < 0.5 else rng.normal(size=3)
        rpy = rng.choice([0.0, 90.0, -90.0, 180.0], size=3) if rng.random() < 0.5 else rng.uniform(-180, 180, 3)
        limits = [-1.5, 2.0] if kind == "prismatic" else sorted(rng.uniform(-170, 170, 2).tolist())
        links.append({
            "name": f"link{k}", "parent": links[rng.integers(len(links))]["name"],
            "joint": {"name": f"j{k}", "type": kind, "axis": (axis / np.linalg.norm(axis)).tolist(),
                      "origin": rng.uniform(-3, 3, 3).tolist(), "rpy_deg": rpy.tolist(), "limits": limits},
        })
    for k, link in enumerate(links):
        markers.append({"name": f"M{k}", "link": link["name"], "position": rng.uniform(-2, 2, 3).tolist()})
        points.append({"name": f"p{k}", "link": link["name"], "position": rng.uniform(-2, 2, 3).tolist()})
    return machine_from_dict({"name": "random chain", "links": links, "markers": markers, "points": points})


def check_urdf_kinematics(machine, path, rng, n_samples=5):
    yourdfpy = pytest.importorskip("yourdfpy")
    robot = yourdfpy.URDF.load(str(path), load_meshes=False, build_collision_scene_graph=False)
    assert tuple(robot.actuated_joint_names) == machine.joint_names
    base = machine.link_names[0]
    for q in random_joints(machine, n_samples, rng, margin=0.0):
        robot.update_cfg(dict(zip(machine.joint_names, q)))
        poses = machine.link_poses(q[None])[0]
        theirs = np.array([robot.get_transform(name, base) for name in machine.link_names])
        assert np.abs(theirs - poses).max() < 1e-9
        ours = np.concatenate([machine.markers(q[None])[0], machine.points(q[None])[0]])
        frames = [f"marker_{m}" for m in machine.marker_names] + [f"point_{p}" for p in machine.point_names]
        theirs = np.array([robot.get_transform(name, base)[:3, 3] for name in frames])
        assert np.abs(theirs - ours).max() < 1e-9  # metres


@pytest.mark.parametrize("machine_name", ["hitachi_ex3500", "bobcat_225", "cube_pair"])
def test_urdf_of_shipped_models_gives_our_kinematics(tmp_path, machine_name):
    out = tmp_path / "m.urdf"
    assert cli.main(["export", "urdf", machine_name, "--out", str(out)]) == 0
    check_urdf_kinematics(load_machine(machine_name), out, np.random.default_rng(5))


@pytest.mark.parametrize("seed", range(8))
def test_urdf_of_random_chains_gives_our_kinematics(tmp_path, seed):
    rng = np.random.default_rng(100 + seed)
    machine = random_chain(rng, n_links=seed % 7)
    save_machine(machine, tmp_path / "m.toml")
    out = tmp_path / "m.urdf"
    assert cli.main(["export", "urdf", str(tmp_path / "m.toml"), "--out", str(out)]) == 0
    check_urdf_kinematics(load_machine(tmp_path / "m.toml"), out, rng)


def test_urdf_refuses_clashing_frame_names():
    from mocap.io.urdf import urdf_text

    machine = machine_from_dict({
        "name": "clash",
        "links": [{"name": "base"}, {"name": "marker_A", "parent": "base",
                                     "joint": {"name": "j", "type": "revolute", "axis": [0, 0, 1]}}],
        "markers": [{"name": "A", "link": "base", "position": [1, 0, 0]}],
    })
    with pytest.raises(InputError, match=r"URDF link names \['marker_A'\] would repeat"):
        urdf_text(machine)


# --- COLMAP --------------------------------------------------------------------------------


def make_triangulated_session(root, rng):
    """A session with a calibration of three distorted cameras (one with k3, one without,
    one pinhole), time offsets, tracks from exact projections and the true points."""
    machine = load_machine("bobcat_225")
    rest = machine.markers(np.zeros((1, machine.n_joints)))[0]
    cameras = ring_of_cameras(3, rest.mean(axis=0), (6.0, 9.0), rng, size=(640, 360), height=(1.0, 3.0))
    cameras[0] = replace(cameras[0], distortion=np.array([-0.08, 0.02, 0.001, -0.0005, 0.004]))
    cameras[1] = replace(cameras[1], distortion=np.array([0.05, -0.01, 0.0, 0.0, 0.0]))
    offsets = np.array([0.0, 0.1, -0.05])
    calibration = Calibration(tuple(cameras), tuple({"fps": FPS, "time_offset": o} for o in offsets))
    save_calibration(calibration, root / "calibration" / "cameras.toml")
    make_session(root, "bobcat_225", rng, cameras=cameras)
    n_frames = 60
    joints = random_joints(machine, 1, rng) + np.linspace(0, 0.3, n_frames)[:, None]  # a slow move
    truth = machine.markers(joints)  # (F, M, 3) at each camera's own frames
    for k, camera in enumerate(cameras):
        uv = camera.project(truth)
        inside = np.all((uv >= 0) & (uv <= np.array(camera.size) - 1), axis=-1)
        seen = inside & (rng.random(uv.shape[:2]) > 0.1)
        f, m = np.nonzero(seen)
        tracks = Tracks.from_rows([camera.name] * len(f), f, np.array(machine.marker_names, dtype=object)[m], uv[f, m])
        save_tracks(tracks, root / "tracks" / f"{camera.name}.csv")
    ref = truth[5:50]  # points at reference frames 5..49 (camera 0's frames are the reference)
    f, m = np.nonzero(rng.random(ref.shape[:2]) > 0.2)
    points = Points(f + 5, np.array(machine.marker_names, dtype=object)[m], ref[f, m], np.zeros(len(f)), np.full(len(f), 3))
    save_points(points, root / "results" / "points.csv")
    return calibration


def test_colmap_export_reprojects_like_our_cameras(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    from mocap.reconstruct.stage import load_inputs
    from mocap.reconstruct.timing import on_reference_clock

    calibration = make_triangulated_session(tmp_path, np.random.default_rng(11))
    out = tmp_path / "colmap"
    assert cli.main(["export", "colmap", str(tmp_path), "--out", str(out)]) == 0

    model = pycolmap.Reconstruction(str(out))
    points = load_points(tmp_path / "results" / "points.csv")
    cameras = {c.name: c for c in calibration.cameras}
    assert model.num_cameras() == 3
    assert model.num_images() == 3 * len(np.unique(points.frame))
    assert model.num_points3D() == len(points)
    assert {model.cameras[i].model.name for i in model.cameras} == {"FULL_OPENCV", "OPENCV", "PINHOLE"}
    _, tracks, markers = load_inputs(tmp_path / "calibration" / "cameras.toml",
                                     [tmp_path / "tracks" / f"{c}.csv" for c in cameras])
    marker_names = load_machine("bobcat_225").marker_names
    clock = on_reference_clock(calibration, tracks, marker_names)
    n_checked = 0
    for point in model.points3D.values():
        for element in point.track.elements:
            image = model.images[element.image_id]
            camera_name, frame = image.name.split("/")
            ours = cameras[camera_name].project(point.xyz)
            theirs = image.project_point(point.xyz) - 0.5  # COLMAP pixels -> OpenCV pixels
            assert np.abs(theirs - ours).max() < 1e-6
            stored = image.points2D[element.point2D_idx].xy - 0.5
            c = list(cameras).index(camera_name)
            k = np.searchsorted(clock.frame, int(frame))
            marker = marker_names.index(
                points.marker[(points.frame == int(frame)) & np.all(np.abs(points.xyz - point.xyz) < 1e-9, axis=1)][0])
            np.testing.assert_allclose(stored, clock.pixels[c, k, marker], atol=1e-9)  # the track is the tracks' pixel
            if c == 0:  # the reference camera's own frames: the track is the projection, to the
                # CSVs' rounding (points 5 decimals of a metre, pixels 4 decimals)
                depth = cameras[camera_name].cam_from_world.apply(point.xyz)[2]
                bound = cameras[camera_name].focal / depth * 0.5e-5 * np.sqrt(3) + 0.5e-4 * np.sqrt(2)
                assert np.abs(stored - ours).max() < bound
            n_checked += 1
    assert n_checked > 3 * len(points) * 0.5


def test_colmap_export_never_replaces_other_files(tmp_path, capsys):
    (tmp_path / "session.toml").write_text("")
    assert cli.main(["export", "colmap", str(tmp_path), "--out", str(tmp_path)]) == 2
    assert "holds more than a COLMAP model; choose another --out" in capsys.readouterr().err
    assert cli.main(["export", "colmap", str(tmp_path), "--out", str(tmp_path / "session.toml")]) == 2
    assert "is a file; --out names the folder" in capsys.readouterr().err
    assert (tmp_path / "session.toml").is_file()


def test_colmap_export_refuses_skew(tmp_path):
    from mocap.io.colmap import colmap_params

    camera = ring_of_cameras(1, np.zeros(3), (5.0, 6.0), np.random.default_rng(0))[0]
    matrix = camera.matrix.copy()
    matrix[0, 1] = 0.5
    with pytest.raises(InputError, match="has skew 0.5"):
        colmap_params(replace(camera, matrix=matrix))


@pytest.mark.parametrize(
    "text, message",
    [
        ("Frame#\tTime\n", "not a TRC file"),
        ("PathFileType\t4\t(X/Y/Z)\tx.trc\nDataRate\tNumMarkers\tUnits\n30\t1\tinches\nFrame#\tTime\tA\n\n\n",
         "Units \\(mm, cm or m\\)"),
        ("PathFileType\t4\t(X/Y/Z)\tx.trc\nDataRate\tNumMarkers\tUnits\n30\t2\tmm\nFrame#\tTime\tA\n\n\n",
         "1 marker names, NumMarkers says 2"),
        ("PathFileType\t4\t(X/Y/Z)\tx.trc\nDataRate\tNumMarkers\tUnits\n30\t1\tmm\nFrame#\tTime\tA\n\t\tX1\tY1\tZ1\n\n1\t0\tx\t1\t2\n",
         "line 7: a field is not a number"),
    ],
)
def test_trc_reader_guards(tmp_path, text, message):
    (tmp_path / "x.trc").write_text(text)
    with pytest.raises(InputError, match=message):
        load_trc(tmp_path / "x.trc")


def test_c3d_reader_guards(tmp_path):
    from mocap.io.c3d import load_c3d

    with pytest.raises(InputError, match="file not found"):
        load_c3d(tmp_path / "none.c3d")
    (tmp_path / "bad.c3d").write_bytes(b"not a c3d file at all" * 40)
    with pytest.raises(InputError, match="not a readable C3D file"):
        load_c3d(tmp_path / "bad.c3d")


def test_c3d_reader_refuses_unknown_units(tmp_path):
    ezc3d = pytest.importorskip("ezc3d")
    from mocap.io.c3d import load_c3d

    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [30.0]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = ["A"]
    c3d.add_parameter("POINT", "UNITS", "in")
    c3d["data"]["points"] = np.ones((4, 1, 3))
    c3d.write(str(tmp_path / "inches.c3d"))
    with pytest.raises(InputError, match="POINT:UNITS is 'in'; expected mm, cm or m"):
        load_c3d(tmp_path / "inches.c3d")


def test_atomic_dir_replaces_a_folder_whole(tmp_path):
    from mocap.io.atomic import atomic_dir

    for text in ("first", "second"):
        with atomic_dir(tmp_path / "model") as tmp:
            (tmp / f"{text}.txt").write_text(text)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model"]
    assert [p.name for p in (tmp_path / "model").iterdir()] == ["second.txt"]
    with pytest.raises(RuntimeError, match="interrupted"):
        with atomic_dir(tmp_path / "model") as tmp:
            (tmp / "third.txt").write_text("third")
            raise RuntimeError("interrupted")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model"]
    assert [p.name for p in (tmp_path / "model").iterdir()] == ["second.txt"]
