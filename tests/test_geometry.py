import numpy as np
import pytest

from mocap.core.geometry import (
    Rigid,
    matrix_to_rpy,
    rot_x,
    rot_y,
    rot_z,
    rotation_angle_between,
    rpy_to_matrix,
)


def test_rpy_is_z_y_x_and_round_trips():
    rng = np.random.default_rng(0)
    rpy = rng.uniform(-1.5, 1.5, (20, 3))
    matrix = rpy_to_matrix(rpy)
    expected = rot_z(rpy[:, 2]) @ rot_y(rpy[:, 1]) @ rot_x(rpy[:, 0])
    assert np.allclose(matrix, expected)
    assert np.allclose(matrix_to_rpy(matrix), rpy)


def test_elementary_rotations_follow_the_right_hand_rule():
    assert np.allclose(rot_z(np.pi / 2) @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(rot_x(np.pi / 2) @ [0, 1, 0], [0, 0, 1])
    assert np.allclose(rot_y(np.pi / 2) @ [0, 0, 1], [1, 0, 0])


def test_rigid_composition_and_inverse():
    rng = np.random.default_rng(2)
    c_from_b = Rigid.from_rotvec(rng.normal(size=3), rng.normal(size=3))
    b_from_a = Rigid.from_rotvec(rng.normal(size=3), rng.normal(size=3))
    points = rng.normal(size=(5, 3))
    c_from_a = c_from_b @ b_from_a
    assert np.allclose(c_from_a.apply(points), c_from_b.apply(b_from_a.apply(points)))
    assert np.allclose((c_from_a.inverse() @ c_from_a).matrix, np.eye(4))
    assert np.allclose(Rigid.from_matrix(c_from_a.matrix).matrix, c_from_a.matrix)


def test_rigid_checks_shapes():
    with pytest.raises(ValueError, match="rotation \\(3, 3\\)"):
        Rigid(np.eye(2), np.zeros(3))


def test_rotation_angle_between():
    assert np.isclose(rotation_angle_between(np.eye(3), rot_z(0.3)), 0.3)
