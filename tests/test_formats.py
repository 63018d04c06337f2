import tomllib

import numpy as np
import pytest

from mocap.core.calibration import Calibration
from mocap.core.camera import Camera
from mocap.core.geometry import Rigid
from mocap.core.points import Points
from mocap.core.tracks import Tracks
from mocap.errors import InputError
from mocap.io import toml_writer
from mocap.io.cameras_toml import load_calibration, save_calibration
from mocap.io.points_csv import load_points, save_points
from mocap.io.session_toml import SessionCamera, SessionConfig, load_session_config, save_session_config
from mocap.io.tracks_csv import load_tracks, save_tracks


def _calibration(n=11):
    rng = np.random.default_rng(0)
    cameras = [
        Camera(
            f"cam{k}", (1920, 1080), np.array([[2000.0 + k, 0, 960], [0, 2000.0 + k, 540], [0, 0, 1]]),
            rng.normal(0, 0.01, 5), Rigid.from_rotvec(rng.normal(size=3), rng.normal(size=3)),
        )
        for k in range(n)
    ]
    extras = tuple({"time_offset": 0.01 * k, "fps": 30.0} for k in range(n))
    return Calibration(tuple(cameras), extras, {"machine": "m", "frame": 3, "joints": {"swing": 12.5}})


def test_calibration_round_trip_keeps_order_and_values(tmp_path):
    calibration = _calibration()
    path = tmp_path / "cameras.toml"
    save_calibration(calibration, path)
    again = load_calibration(path)
    assert again.names == calibration.names
    for a, b in zip(again.cameras, calibration.cameras):
        assert np.allclose(a.matrix, b.matrix) and np.allclose(a.distortion, b.distortion)
        assert np.allclose(a.cam_from_world.matrix, b.cam_from_world.matrix)
    assert np.allclose(again.time_offsets, calibration.time_offsets)
    assert again.metadata["joints"] == {"swing": 12.5}


def test_calibration_file_is_what_aniposelib_reads(tmp_path):
    """aniposelib's CameraGroup.load sorts the table keys, skips `metadata` and reads name,
    size, matrix, distortions, rotation and translation from each table."""
    path = tmp_path / "cameras.toml"
    save_calibration(_calibration(11), path)
    data = tomllib.loads(path.read_text())
    keys = sorted(k for k in data if k != "metadata")
    assert [data[k]["name"] for k in keys] == [f"cam{k}" for k in range(11)]  # sorted = file order
    for k in keys:
        table = data[k]
        assert np.shape(table["size"]) == (2,)
        assert np.shape(table["matrix"]) == (3, 3)
        assert np.shape(table["distortions"]) == (5,)
        assert np.shape(table["rotation"]) == (3,)
        assert np.shape(table["translation"]) == (3,)


@pytest.mark.parametrize(
    "text, message",
    [
        ("[cam_00]\nname = 'a'\n", "missing distortions, matrix, rotation, size, translation"),
        ("[cam_00]\nname='a'\nsize=[1,2]\nmatrix=[[1,0],[0,1]]\ndistortions=[0]\nrotation=[0,0,0]\ntranslation=[0,0,0]\n",
         "'matrix' must be finite numbers of shape \\(3, 3\\)"),
        ("[metadata]\nframe = 1\n", "no camera tables"),
        ("[cam_00\n", "not valid TOML"),
    ],
)
def test_bad_calibration_files(tmp_path, text, message):
    path = tmp_path / "c.toml"
    path.write_text(text)
    with pytest.raises(InputError, match=message):
        load_calibration(path)


def test_tracks_round_trip_and_dense_view(tmp_path):
    tracks = Tracks.from_rows(
        ["a", "a", "b"], [0, 1, 1], ["M1", "M2", "M1"], [[1.5, 2.5], [3, 4], [5, 6]], score=[0.9, 0.8, 0.7]
    )
    path = tmp_path / "t.csv"
    save_tracks(tracks, path)
    assert path.read_text().splitlines()[0] == "camera,frame,marker,x,y,score"
    again = load_tracks([path])
    assert again.cameras == ("a", "b")
    dense = again.dense(["a", "b"], ["M1", "M2"], [0, 1])
    assert dense.shape == (2, 2, 2, 2)
    assert np.allclose(dense[0, 1, 1], [3, 4]) and np.all(np.isnan(dense[1, 0]))


@pytest.mark.parametrize(
    "text, message",
    [
        ("camera,frame,x,y\n", "line 1: header lacks marker"),
        ("camera,frame,marker,x,y\na,zero,M1,1,2\n", "line 2: frame 'zero' is not an integer"),
        ("camera,frame,marker,x,y\na,0,M1,1\n", "line 2: 4 fields, the header has 5"),
        ("camera,frame,marker,x,y\na,0,M1,1,2\na,1,M1,nan,2\n", "line 3: x and y must be finite"),
        ("camera,frame,marker,x,y\na,-1,M1,1,2\n", "line 2: frame -1 is negative"),
        ("", "empty file"),
    ],
)
def test_bad_tracks_name_the_line(tmp_path, text, message):
    path = tmp_path / "t.csv"
    path.write_text(text)
    with pytest.raises(InputError, match=message):
        load_tracks(path)


def test_points_round_trip(tmp_path):
    points = Points(np.array([0, 0]), np.array(["A", "B"], dtype=object), np.array([[1.0, 2, 3], [4, 5, 6]]),
                    np.array([0.5, np.nan]), np.array([2, 1]))
    path = tmp_path / "p.csv"
    save_points(points, path)
    again = load_points(path)
    assert list(again.marker) == ["A", "B"] and np.allclose(again.xyz, points.xyz)
    assert np.isnan(again.error_px[1]) and list(again.views) == [2, 1]


def test_session_config_round_trip_and_errors(tmp_path):
    config = SessionConfig("hitachi_ex3500", (SessionCamera("c1", "videos/c1.mp4", 29.97),), {"frame": 0})
    path = tmp_path / "session.toml"
    save_session_config(config, path)
    assert load_session_config(path) == config
    path.write_text('machine = "m"\n[[cameras]]\nname = "c1"\nvideo = "v.mp4"\nfps = 0\n')
    with pytest.raises(InputError, match="cameras\\[0\\]: 'fps' must be a positive number"):
        load_session_config(path)


def test_toml_writer_round_trips_through_tomllib():
    data = {
        "name": 'a "quoted"\nname',
        "numbers": [1, 2.5, -3e-9],
        "matrix": [[1.0, 0.0], [0.0, 1.0]],
        "flag": True,
        "table": {"x": 1, "inner": {"y": [1, 2]}},
        "items": [{"name": "p", "position": [1, 2, 3]}, {"name": "q", "position": [4, 5, 6]}],
        "inline": {"joint": {"axis": [0, 0, 1], "type": "revolute"}},
    }
    assert tomllib.loads(toml_writer.dumps(data)) == data
