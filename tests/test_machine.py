import textwrap

import numpy as np
import pytest

from mocap.errors import InputError
from mocap.io.machine_toml import load_machine, machine_from_dict, machine_to_dict, save_machine

ARM = """
name = "two-link arm"
[[links]]
name = "base"
[[links]]
name = "turret"
parent = "base"
joint = { name = "turn", type = "revolute", axis = [0, 0, 1], origin = [0, 0, 1], limits = [-90, 90] }
[[links]]
name = "slide"
parent = "turret"
joint = { name = "reach", type = "prismatic", axis = [1, 0, 0], origin = [0.5, 0, 0], rpy_deg = [0, 0, 90], limits = [0, 2] }
[[markers]]
name = "M1"
link = "base"
position = [1, 0, 0]
[[markers]]
name = "M2"
link = "slide"
position = [1, 0, 0]
[[points]]
name = "tip"
link = "slide"
position = [2, 0, 0]
[bucket_angle]
link = "slide"
direction = [1, 0, 1]
"""


def write(tmp_path, text, name="m.toml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def test_forward_kinematics_of_revolute_and_prismatic_joints(tmp_path):
    machine = load_machine(write(tmp_path, ARM))
    assert machine.joint_names == ("turn", "reach")
    q = np.array([[0.0, 0.0], [np.pi / 2, 1.5]])
    markers = machine.markers(q)
    # frame 0: turret at z=1; slide at x=0.5 turned 90 deg about z: its x axis is world y
    assert np.allclose(markers[0], [[1, 0, 0], [0.5, 1, 1]])
    # frame 1: turn 90 deg; slide along its own x (world -x after both turns) by 1.5 m
    assert np.allclose(markers[1], [[1, 0, 0], [-2.5, 0.5, 1]])
    assert np.allclose(machine.points(q)[1], [[-3.5, 0.5, 1]])


def test_bucket_angle_is_measured_from_the_horizontal_in_the_house_plane(tmp_path):
    machine = load_machine(write(tmp_path, ARM))
    # the slide is turned 90 deg from the turret (the house): its direction (1, 0, 1) points
    # up and sideways, so in the house's vertical plane it stands at 90 deg whatever the joints
    assert np.allclose(np.degrees(machine.bucket_angles(np.array([[0.3, 0.2], [-1.0, 1.0]]))), 90.0)
    straight = load_machine(write(tmp_path, ARM.replace("rpy_deg = [0, 0, 90]", "rpy_deg = [0, 0, 0]")))
    assert np.allclose(np.degrees(straight.bucket_angles(np.array([[0.3, 0.2], [-1.0, 1.0]]))), 45.0)


def test_excavator_bucket_angle_sums_the_chain(bobcat):
    q = np.radians([[20.0, 40.0, -70.0, 10.0]])
    assert np.isclose(np.degrees(machine_angle := bobcat.bucket_angles(q)[0]), -20.0), machine_angle


def test_marker_jacobian_matches_finite_differences(ex3500):
    q = np.radians([[15.0, 40.0, -80.0, 20.0], [-30.0, 60.0, -40.0, 70.0]])
    markers, jac = ex3500.markers_with_jacobian(q)
    h = 1e-6
    for j in range(4):
        step = np.zeros(4)
        step[j] = h
        numeric = (ex3500.markers(q + step) - ex3500.markers(q - step)) / (2 * h)
        assert np.allclose(jac[..., j], numeric, atol=1e-6)
    assert np.allclose(markers, ex3500.markers(q))


def test_kinematics_is_vectorised_over_frames(ex3500):
    rng = np.random.default_rng(0)
    q = rng.uniform(-1, 1, (100, 4))
    batch = ex3500.markers(q)
    assert batch.shape == (100, len(ex3500.marker_names), 3)
    assert np.allclose(batch[37], ex3500.markers(q[37])[0])
    with pytest.raises(ValueError, match="shape \\(F, 4\\)"):
        ex3500.markers(np.zeros((3, 2)))


def test_shipped_models_meet_the_marker_rules(ex3500, bobcat, cube_pair):
    for machine in (ex3500, bobcat, cube_pair):
        base = machine.marker_positions[machine.marker_links == 0]
        assert len(base) >= 4
        s = np.linalg.svd(base - base.mean(axis=0), compute_uv=False)
        assert s[2] / s[0] > 0.05, "base markers must be non-coplanar"
        for link in range(1, len(machine.links)):
            assert np.sum(machine.marker_links == link) >= 2
        assert machine.source


def test_joint_limits_are_in_internal_units(ex3500):
    limits = np.degrees(ex3500.joint_limits)
    assert limits.shape == (4, 2) and np.all(limits[:, 0] < limits[:, 1])


def test_round_trip(tmp_path, ex3500):
    path = tmp_path / "out.toml"
    save_machine(ex3500, path)
    again = load_machine(path)
    q = np.radians([[10.0, 30.0, -60.0, 15.0]])
    assert np.allclose(again.markers(q), ex3500.markers(q))
    assert again.marker_names == ex3500.marker_names
    assert machine_to_dict(again) == machine_to_dict(ex3500)


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda t: t.replace('parent = "turret"', 'parent = "tower"'), "link 'slide': unknown parent 'tower'"),
        (lambda t: t.replace('parent = "base"', 'parent = "slide"'), "form a cycle"),
        (lambda t: t.replace('name = "M2"', 'name = "M1"'), "duplicate name 'M1'"),
        (lambda t: t.replace('link = "base"\nposition', 'link = "boom"\nposition'), "marker 'M1': unknown link 'boom'"),
        (lambda t: t.replace("axis = [0, 0, 1]", "axis = [0, 0, 0]"), "'axis' is a zero vector"),
        (lambda t: t.replace('[[links]]\nname = "base"\n', ""), "the first link is the base"),
        (lambda t: t.replace("limits = [-90, 90]", "limits = [-1000, 1000]"), "exceed ±360: they are degrees"),
        (lambda t: t.replace("position = [2, 0, 0]", "position = [2, 0]"), "'position' must be a list of 3 numbers"),
        (lambda t: t.replace('type = "revolute"', 'type = "hinge"'), "type 'hinge' is not 'revolute' or 'prismatic'"),
        (lambda t: t.replace('name = "two-link arm"', 'name = "x"\ncolour = "red"'), "unknown key\\(s\\) 'colour'"),
        (lambda t: t.replace("limits = [0, 2]", "limits = [2, 0]"), "lower < upper"),
        (lambda t: t + "\n[[links]]\nname = \"extra\"\nparent = \"base\"\n", "link 'extra': no joint"),
        (lambda t: t.replace("position = [1, 0, 0]", "position = [1, 0, 0]\ntag = 50", 1), "tag 50 is not in DICT_4X4_50"),
        (lambda t: t.replace("position = [1, 0, 0]", "position = [1, 0, 0]\ntag = 3"), "tag 3 is on markers\\[0\\] too"),
        (lambda t: t.replace("position = [1, 0, 0]", "position = [1, 0, 0]\ntag = -2", 1), "tag -2 must be a whole number"),
        (lambda t: t.replace("position = [1, 0, 0]", "position = [1, 0, 0]\ntag = 1", 1) + '[tags]\ndictionary = "DICT_9X9"\n',
         "unknown tag dictionary 'DICT_9X9'"),
        (lambda t: t.replace("position = [2, 0, 0]", "position = [2, 0, 0]\ntag = 1"), "points\\[0\\]: unknown key\\(s\\) 'tag'"),
    ],
)
def test_bad_models_are_rejected_naming_file_and_entry(tmp_path, change, message):
    path = write(tmp_path, change(textwrap.dedent(ARM)))
    with pytest.raises(InputError, match=message) as info:
        load_machine(path)
    assert str(path) in str(info.value)


def test_tags_round_trip(tmp_path):
    text = textwrap.dedent(ARM).replace("position = [1, 0, 0]", "position = [1, 0, 0]\ntag = 7", 1)
    machine = load_machine(write(tmp_path, text + '[tags]\ndictionary = "DICT_APRILTAG_36h11"\n'))
    assert machine.tags.tolist() == [7, -1] and machine.tag_dictionary == "DICT_APRILTAG_36h11"
    save_machine(machine, tmp_path / "again.toml")
    again = load_machine(tmp_path / "again.toml")
    assert again.tags.tolist() == [7, -1] and again.tag_dictionary == "DICT_APRILTAG_36h11"
    plain = load_machine(write(tmp_path, ARM, "plain.toml"))
    assert plain.tags.tolist() == [-1, -1] and plain.tag_dictionary is None


def test_unreadable_and_unknown_models(tmp_path):
    with pytest.raises(InputError, match="not valid TOML"):
        load_machine(write(tmp_path, "name = \n"))
    with pytest.raises(InputError, match="no machine model named 'nosuch'"):
        load_machine("nosuch")
    with pytest.raises(InputError, match="no \\[\\[links\\]\\]"):
        machine_from_dict({"name": "x"})
    with pytest.raises(InputError, match="no \\[\\[markers\\]\\]"):
        machine_from_dict({"name": "x", "links": [{"name": "b"}]})
