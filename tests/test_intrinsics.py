"""Known intrinsics from COLMAP, OpenCV YAML/XML and calibration TOML files (tiny golden files)."""

import numpy as np
import pytest
from conftest import write_opencv_intrinsics

from mocap.errors import InputError
from mocap.io.intrinsics import Intrinsics, load_intrinsics

CAMERAS_TXT = """\
# Camera list with one line of data per camera:
#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]
1 SIMPLE_RADIAL 1920 1080 1500.5 960.5 540.5 -0.12
2 OPENCV 1280 720 1000 1010 640 360 -0.2 0.05 0.001 -0.002
3 PINHOLE 640 480 500 501 320 240
4 FULL_OPENCV 800 600 700 710 400.25 300.75 0.1 -0.05 0.002 0.003 0.01 0 0 0
"""

OPENCV_YAML = """\
%YAML:1.0
---
calibration_time: "Tue 01 Dec 2026 10:00:00"
image_width: 1920
image_height: 1080
flags: 0
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 1.6e+03, 0., 9.595e+02, 0., 1.61e+03, 5.395e+02, 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 5
   cols: 1
   dt: d
   data: [ -0.11, 0.07, 1.0e-03, -2.0e-03, -0.01 ]
avg_reprojection_error: 0.31
"""

ANIPOSE_TOML = """\
[cam_0]
name = "left"
size = [ 1280, 720,]
matrix = [ [ 900.0, 0.0, 639.5,], [ 0.0, 905.0, 359.5,], [ 0.0, 0.0, 1.0,],]
distortions = [ -0.2, 0.03, 0.0, 0.0, 0.0,]
rotation = [ 0.1, 0.2, 0.3,]
translation = [ 1.0, 2.0, 3.0,]

[cam_1]
name = "right"
size = [ 1920, 1080,]
matrix = [ [ 1500.0, 0.0, 959.5,], [ 0.0, 1500.0, 539.5,], [ 0.0, 0.0, 1.0,],]
distortions = [ 0.0, 0.0, 0.0, 0.0, 0.0,]
rotation = [ 0.0, 0.0, 0.0,]
translation = [ 0.0, 0.0, 0.0,]

[metadata]
adjusted = true
"""


def check(intrinsics, size, matrix, distortion):
    assert intrinsics.size == size
    np.testing.assert_allclose(intrinsics.matrix, matrix, atol=1e-12)
    np.testing.assert_allclose(intrinsics.distortion, distortion, atol=1e-12)


def test_colmap_cameras_txt_moves_the_pixel_origin(tmp_path):
    (tmp_path / "cameras.txt").write_text(CAMERAS_TXT)
    cameras = load_intrinsics(tmp_path / "cameras.txt")
    assert list(cameras) == ["1", "2", "3", "4"]
    check(cameras["1"], (1920, 1080), [[1500.5, 0, 960], [0, 1500.5, 540], [0, 0, 1]], [-0.12, 0, 0, 0, 0])
    check(cameras["2"], (1280, 720), [[1000, 0, 639.5], [0, 1010, 359.5], [0, 0, 1]], [-0.2, 0.05, 0.001, -0.002, 0])
    check(cameras["3"], (640, 480), [[500, 0, 319.5], [0, 501, 239.5], [0, 0, 1]], np.zeros(5))
    check(cameras["4"], (800, 600), [[700, 0, 399.75], [0, 710, 300.25], [0, 0, 1]], [0.1, -0.05, 0.002, 0.003, 0.01])


@pytest.mark.parametrize(
    "line, message",
    [
        ("1 FISHEYE 100 100 50 50 50 0 0 0 0", "FISHEYE is not supported"),
        ("1 PINHOLE 100 100 50 50 50", "PINHOLE has 4 parameters"),
        ("1 FULL_OPENCV 100 100 50 50 50 50 0 0 0 0 0 0.1 0 0", "k4, k5 or k6"),
        ("one PINHOLE 100 100 50 50 50 50", "line 2: expected CAMERA_ID MODEL"),
    ],
)
def test_colmap_cameras_txt_guards(tmp_path, line, message):
    (tmp_path / "cameras.txt").write_text(f"# cameras\n{line}\n")
    with pytest.raises(InputError, match=message):
        load_intrinsics(tmp_path / "cameras.txt")


def test_colmap_model_folder_names_cameras_by_their_images(tmp_path):
    from mocap.io.colmap import write_model
    from mocap.synthetic.scenes import ring_of_cameras

    cameras = ring_of_cameras(2, np.zeros(3), (5.0, 8.0), np.random.default_rng(2), size=(800, 600))
    cameras[1] = cameras[1].__class__(cameras[1].name, cameras[1].size, cameras[1].matrix,
                                      np.array([0.1, -0.02, 0.001, 0.002, 0.003]), cameras[1].cam_from_world)
    write_model(tmp_path / "model", cameras, ["cam1/000000", "cam2/000000"], np.array([0, 1]),
                [np.zeros((0, 2)), np.zeros((0, 2))], np.zeros((0, 3)), np.zeros((0, 3)))
    loaded = load_intrinsics(tmp_path / "model")
    assert list(loaded) == ["cam1", "cam2"]
    for camera in cameras:
        check(loaded[camera.name], camera.size, camera.matrix, camera.distortion)


def test_not_a_colmap_model_folder(tmp_path):
    with pytest.raises(InputError, match="not a COLMAP model folder"):
        load_intrinsics(tmp_path)


def test_opencv_yaml_as_the_calibration_sample_writes_it(tmp_path):
    (tmp_path / "gopro.yaml").write_text(OPENCV_YAML)
    cameras = load_intrinsics(tmp_path / "gopro.yaml")
    assert list(cameras) == ["gopro"]
    check(cameras["gopro"], (1920, 1080), [[1600, 0, 959.5], [0, 1610, 539.5], [0, 0, 1]],
          [-0.11, 0.07, 0.001, -0.002, -0.01])


@pytest.mark.parametrize("suffix", [".xml", ".yml"])
def test_opencv_file_storage_round_trip(tmp_path, suffix):
    rng = np.random.default_rng(8)
    matrix = np.array([[rng.uniform(500, 2000), 0, rng.uniform(300, 600)], [0, rng.uniform(500, 2000), 200], [0, 0, 1]])
    coefficients = np.r_[rng.normal(0, 0.1, 4), 0.0, 0.0, 0.0, 0.0].reshape(1, -1)  # 8, k4..k6 zero
    path = tmp_path / f"cam3{suffix}"
    write_opencv_intrinsics(path, (1280, 720), matrix, coefficients)
    check(load_intrinsics(path)["cam3"], (1280, 720), matrix, np.r_[coefficients[0, :4], 0.0])


@pytest.mark.parametrize(
    "body, message",
    [
        ("image_width: 10\nimage_height: 10\n", "no 'camera_matrix'"),
        ("image_width: 10\nimage_height: 10\ncamera_matrix: !!opencv-matrix\n   rows: 2\n   cols: 2\n   dt: d\n"
         "   data: [1., 0., 0., 1.]\ndistortion_coefficients: !!opencv-matrix\n   rows: 5\n   cols: 1\n   dt: d\n"
         "   data: [0., 0., 0., 0., 0.]\n", "camera_matrix must be a 3x3"),
        ("image_width: 10\nimage_height: 10\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
         "   data: [1., 0., 5., 0., 1., 5., 0., 0., 1.]\ndistortion_coefficients: !!opencv-matrix\n   rows: 8\n"
         "   cols: 1\n   dt: d\n   data: [0., 0., 0., 0., 0., 0.3, 0., 0.]\n", "k4.. non-zero"),
    ],
)
def test_opencv_yaml_guards(tmp_path, body, message):
    (tmp_path / "bad.yaml").write_text("%YAML:1.0\n---\n" + body)
    with pytest.raises(InputError, match=message):
        load_intrinsics(tmp_path / "bad.yaml")


def test_anipose_calibration_toml(tmp_path):
    (tmp_path / "calibration.toml").write_text(ANIPOSE_TOML)
    cameras = load_intrinsics(tmp_path / "calibration.toml")
    assert list(cameras) == ["left", "right"]
    check(cameras["left"], (1280, 720), [[900, 0, 639.5], [0, 905, 359.5], [0, 0, 1]], [-0.2, 0.03, 0, 0, 0])
    check(cameras["right"], (1920, 1080), [[1500, 0, 959.5], [0, 1500, 539.5], [0, 0, 1]], np.zeros(5))


def test_unknown_or_missing_files(tmp_path):
    (tmp_path / "cam.json").write_text("{}")
    with pytest.raises(InputError, match="unknown intrinsics file"):
        load_intrinsics(tmp_path / "cam.json")
    with pytest.raises(InputError, match="file not found"):
        load_intrinsics(tmp_path / "nothing.yaml")


def test_intrinsics_checks_shapes():
    with pytest.raises(ValueError, match=r"matrix must have shape \(3, 3\)"):
        Intrinsics((10, 10), np.eye(2), np.zeros(5))
    with pytest.raises(ValueError, match=r"distortion must have shape \(5,\)"):
        Intrinsics((10, 10), np.eye(3), np.zeros(4))
    with pytest.raises(ValueError, match="size must be"):
        Intrinsics((0, 10), np.eye(3), np.zeros(5))
