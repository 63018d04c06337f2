import cv2
import numpy as np
import pytest

from mocap.core.camera import Camera, PaperCamera, project, project_cam
from mocap.synthetic.scenes import look_at_camera


def _camera(distortion=None):
    return look_at_camera(
        "c", (1920, 1080), 1800.0, [40.0, -25.0, 9.0], [0.0, 0.0, 3.0], roll=0.05,
        distortion=distortion,
    )


def test_projection_matches_opencv_with_distortion():
    dist = np.array([-0.12, 0.05, 0.001, -0.0015, 0.01])
    camera = _camera(dist)
    rng = np.random.default_rng(0)
    points = rng.uniform([-5, -5, 0], [5, 5, 8], (50, 3))
    ours = camera.project(points)
    theirs = cv2.projectPoints(
        points, camera.cam_from_world.rotvec, camera.cam_from_world.translation, camera.matrix, dist
    )[0].reshape(-1, 2)
    assert np.max(np.abs(ours - theirs)) < 1e-8


def test_projection_is_batched_and_nan_behind_the_camera():
    camera = _camera()
    points = np.array([[[0.0, 0.0, 3.0], [80.0, -50.0, 18.0]], [[np.nan, 0, 0], [1.0, 1.0, 1.0]]])
    uv = camera.project(points)
    assert uv.shape == (2, 2, 2)
    assert np.allclose(uv[0, 0], [959.5, 539.5], atol=1e-6)  # the target is at the principal point
    assert np.all(np.isnan(uv[0, 1])) and np.all(np.isnan(uv[1, 0]))
    assert project([camera, camera], points).shape == (2, 2, 2, 2)


@pytest.mark.parametrize("dist", [np.array([-0.2, 0.08, 0.002, -0.001, 0.02]), np.zeros(5)], ids=["distorted", "pinhole"])
def test_projection_jacobian_matches_finite_differences(dist):
    matrix = np.array([[1500.0, 0.5, 950.0], [0.0, 1490.0, 530.0], [0, 0, 1]])
    rng = np.random.default_rng(1)
    points = np.c_[rng.uniform(-3, 3, (10, 2)), rng.uniform(8, 20, 10)]
    _, jac = project_cam(points, matrix, dist, with_jacobian=True)
    h = 1e-6
    for k in range(3):
        step = np.zeros(3)
        step[k] = h
        numeric = (project_cam(points + step, matrix, dist) - project_cam(points - step, matrix, dist)) / (2 * h)
        assert np.allclose(jac[..., k], numeric, rtol=1e-5, atol=1e-4)


def test_paper_view_round_trips_exactly():
    rng = np.random.default_rng(2)
    for _ in range(20):
        paper = PaperCamera(
            rng.uniform(-np.pi, np.pi), rng.uniform(-1.2, 1.2), rng.uniform(-0.5, 0.5),
            rng.uniform(-50, 50, 3), rng.uniform(500, 5000),
        )
        camera = Camera.from_paper("c", (1920, 1080), paper)
        back = camera.to_paper()
        assert np.allclose(back.as_vector(), paper.as_vector(), atol=1e-9)


def test_paper_equations_give_the_opencv_pixels():
    """x = M y_C / x_C and y = M z_C / x_C, measured from the principal point leftward and
    upward, with C_P = R^T (A_P - A_P_C) and R = Rz(a) Ry(e) Rx(t)."""
    from mocap.core.geometry import rot_x, rot_y, rot_z

    paper = PaperCamera(np.radians(170), np.radians(12), np.radians(-3), np.array([45.0, -6, 10]), 2200.0)
    camera = Camera.from_paper("c", (1920, 1080), paper)
    rotation = rot_z(paper.azimuth) @ rot_y(paper.elevation) @ rot_x(paper.tilt)
    rng = np.random.default_rng(3)
    points = rng.uniform([-4, -4, 0], [4, 4, 8], (30, 3))
    c_p = (points - paper.position) @ rotation  # rows of R^T (A_P - A_P_C)
    x = paper.focal * c_p[:, 1] / c_p[:, 0]
    y = paper.focal * c_p[:, 2] / c_p[:, 0]
    uv = camera.project(points)
    cx, cy = camera.matrix[0, 2], camera.matrix[1, 2]
    assert np.allclose(cx - uv[:, 0], x) and np.allclose(cy - uv[:, 1], y)


def test_camera_checks_shapes():
    with pytest.raises(ValueError, match="matrix must be \\(3, 3\\)"):
        Camera("c", (10, 10), np.eye(2))
    with pytest.raises(ValueError, match="at most 5 distortion"):
        Camera("c", (10, 10), np.eye(3), np.zeros(8))
