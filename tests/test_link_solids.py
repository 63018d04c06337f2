"""Link shapes stated in the machine file (cylinders, mesh files), against geometry worked by
hand: which markers they hide from a camera, and the normals of the markers painted on them."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import trimesh

from mocap.cli import main
from mocap.core.camera import Camera
from mocap.core.geometry import Rigid, rpy_to_matrix
from mocap.core.shapes import link_boxes
from mocap.core.visibility import marker_normals, visible_markers
from mocap.errors import InputError
from mocap.io import toml_writer
from mocap.io.machine_toml import load_machine, machine_from_dict, machine_to_dict
from mocap.tracking import CameraModel
from mocap.tracking.labels import _prior

SIZE = (640, 480)


def _camera_at(centre: np.ndarray, target: np.ndarray) -> Camera:
    """A pinhole camera at `centre` looking at `target` (world), up the world's z."""
    forward = (target - centre) / np.linalg.norm(target - centre)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])  # cam_from_world
    matrix = np.array([[500.0, 0, SIZE[0] / 2], [0, 500.0, SIZE[1] / 2], [0, 0, 1]])
    return Camera("cam1", SIZE, matrix, np.zeros(5), Rigid(rotation, -rotation @ centre))


def test_a_marker_behind_a_stated_cylinder_is_ranked_hidden():
    """A cylinder stated on the base link, put across the line from a boom marker to a camera
    that marker faces: the tracker's model and the visibility module call the marker hidden
    (the proposal then matches it only at a price), the cylinder moved 3 radii aside along
    its own normal plane calls it seen again, and without the cylinder it is seen."""
    machine = load_machine("hitachi_ex3500")
    joints = np.zeros((1, machine.n_joints))
    plain = CameraModel(machine, _camera_at(np.zeros(3), np.ones(3)))  # only for the guessed normals
    m = int(np.flatnonzero(machine.marker_links == 2)[0])  # a boom marker
    world = machine.markers(joints)[0, m]
    normal = machine.link_poses(joints)[0, 2, :3, :3] @ plain.normals[m]
    centre = world + 12.0 * normal + np.array([0.0, 0.0, 1.0])
    camera = _camera_at(centre, world)
    assert CameraModel(machine, camera).view(joints).visible[0, m]
    middle = 0.5 * (world + centre)  # the base link's frame is the world's at joints 0
    across = np.cross(centre - world, [0.0, 0.0, 1.0])
    across /= np.linalg.norm(across)
    data = machine_to_dict(machine)
    for shift, hidden in ((0.0, True), (3 * 0.4, False)):
        moved = middle + shift * np.cross(across, (centre - world) / np.linalg.norm(centre - world))
        data["links"][0]["cylinder"] = {"a": (moved - across).tolist(), "b": (moved + across).tolist(), "radius": 0.4}
        stated = machine_from_dict(data)
        model = CameraModel(stated, camera)
        view = model.view(joints)
        assert view.visible[0, m] == (not hidden)
        _, seen = visible_markers(stated, link_boxes(stated), model.normals, stated.link_poses(joints),
                                  camera.cam_from_world.matrix[None], camera.matrix, camera.distortion, SIZE)
        assert seen[0, m] == (not hidden)
        candidates, penalty = _prior(model, view, 0, 4.0)
        assert candidates[m] and penalty[m] > 0 if hidden else penalty[m] == 0
    assert not np.array_equal(link_boxes(stated)[0], link_boxes(machine)[0])  # the viewer's box holds it


def test_a_stated_mesh_gives_its_faces_normals(tmp_path):
    """A slanted plate as an STL file (a box 2 x 1 x 0.1 m, in millimetres), stated on the boom
    with a scale, a turn and an offset as a URDF visual: a marker put on each of its two broad
    faces takes that face's normal, turned as stated (to 1e-9), and the file round-trips."""
    trimesh.creation.box(extents=[2000.0, 1000.0, 100.0]).export(tmp_path / "plate.stl")
    machine = load_machine("hitachi_ex3500")
    data = machine_to_dict(machine)
    boom = [link["name"] for link in data["links"]].index(machine.links[2].name)
    rpy_deg, origin = np.array([20.0, -35.0, 10.0]), np.array([3.0, 0.2, 1.5])
    data["links"][boom]["mesh"] = {"file": "plate.stl", "scale": 0.001, "origin": origin.tolist(),
                                   "rpy_deg": rpy_deg.tolist()}
    turn = rpy_to_matrix(np.radians(rpy_deg))
    on_boom = [k for k, marker in enumerate(data["markers"]) if marker["link"] == machine.links[2].name][:2]
    for k, side in zip(on_boom, (1.0, -1.0)):
        data["markers"][k]["position"] = (origin + turn @ [0.3, -0.2, side * 0.05]).tolist()
    (tmp_path / "m.toml").write_text(toml_writer.dumps(data))
    stated = load_machine(tmp_path / "m.toml")
    normals = marker_normals(stated, link_boxes(stated))
    names = [data["markers"][k]["name"] for k in on_boom]
    for name, side in zip(names, (1.0, -1.0)):
        assert np.allclose(normals[stated.marker_names.index(name)], side * turn[:, 2], atol=1e-9)
    again = machine_from_dict(machine_to_dict(stated))
    assert np.allclose(again.link_solids[0].triangles, stated.link_solids[0].triangles)


@pytest.mark.parametrize(("shape", "message"), [
    ({"cylinder": {"a": [0, 0, 0], "b": [0, 0, 0], "radius": 0.5}}, "the same point"),
    ({"cylinder": {"a": [0, 0, 0], "b": [0, 0, 1], "radius": -1}}, "radius -1 must be a number of metres"),
    ({"cylinder": {"a": [0, 0, 0], "b": [0, 0, 1]}}, "radius None"),
    ({"cylinder": {"a": [0, 0, 0], "b": [0, 0, 1], "radius": 1, "length": 2}}, "unknown key"),
    ({"mesh": {"file": "nowhere.stl"}}, "not found"),
    ({"mesh": {"file": "junk.stl"}}, "junk.stl"),
    ({"mesh": {"file": "plate.stl", "scale": 0}}, "scale"),
    ({"mesh": "plate.stl"}, "array of them"),
])
def test_bad_shapes_are_refused_in_one_line(tmp_path, shape, message, capsys, monkeypatch):
    """A stated shape that is not one: `mocap fit` exits 2 with one line naming the file,
    the link and what is wrong, and writes nothing (the first case in a process of its own,
    the others in this one)."""
    trimesh.creation.box(extents=[1.0, 1.0, 1.0]).export(tmp_path / "plate.stl")
    (tmp_path / "junk.stl").write_bytes(b"solid x\nthis is no mesh\n")
    machine = load_machine("bobcat_225")
    data = machine_to_dict(machine)
    data["links"][1].update(shape)
    (tmp_path / "m.toml").write_text(toml_writer.dumps(data))
    with pytest.raises(InputError, match=message):
        load_machine(tmp_path / "m.toml")
    argv = ["fit", str(tmp_path / "m.toml"), "c.toml", "t.csv", "--out", str(tmp_path / "out.csv")]
    if message == "the same point":
        run = subprocess.run([sys.executable, "-m", "mocap.cli", *argv], capture_output=True, text=True, cwd=tmp_path)
        status, stderr = run.returncode, run.stderr
    else:
        monkeypatch.chdir(tmp_path)
        status, stderr = main(argv), capsys.readouterr().err
    assert status == 2
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and "m.toml" in lines[0] and machine.links[1].name in lines[0], stderr
    assert not (tmp_path / "out.csv").exists()
