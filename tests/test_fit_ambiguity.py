"""Frames two far-apart solutions explain equally: one camera sees one marker on a link,
and the link can turn to a mirror value that puts every marker on the same pixels. The
fit cannot know which is true; it must say so, and one of the two must be the truth."""

import numpy as np
import pytest

from mocap.cli import main
from mocap.core.calibration import Calibration
from mocap.core.machine import Tolerance
from mocap.io.cameras_toml import save_calibration
from mocap.io.machine_toml import save_machine
from mocap.io.tracks_csv import save_tracks
from mocap.reconstruct.ambiguity import second_solutions
from mocap.reconstruct.kinfit import FitOptions, fit_joints
from mocap.reconstruct.uncertainty import point_quantities
from mocap.synthetic.machines import SceneOptions, random_scene

ONE_CAMERA_MIRROR = 1000279  # a field scene: one camera, one marker on each moving link


def _scene(seed: int, options: SceneOptions):
    return random_scene(np.random.default_rng(seed), options, n_frames=40)


def test_a_mirror_solution_is_found_and_one_of_the_two_is_the_truth():
    scene = _scene(ONE_CAMERA_MIRROR, SceneOptions.field())
    assert len(scene.cameras) == 1
    options = FitOptions(tolerance=Tolerance(0.05))
    pixels = scene.pixels()
    fit = fit_joints(scene.model, list(scene.cameras), pixels, options=options)
    found = second_solutions(scene.model, list(scene.cameras), pixels, fit, options)
    frames = np.nonzero(found.ambiguous)[0]
    assert found.share > 0.5
    truth = scene.machine.points(scene.joints[frames])[:, 0]
    sd = point_quantities(scene.model, fit.joints, fit.covariance).points_sd[frames, 0]
    ours = np.linalg.norm(scene.model.points(fit.joints[frames])[:, 0] - truth, axis=1)
    other = np.linalg.norm(scene.model.points(found.alternative[frames])[:, 0] - truth, axis=1)
    assert np.all(np.minimum(ours, other) < 5 * sd), "neither solution is the truth"
    assert np.all(np.maximum(ours, other) > 5 * sd), "the two solutions are not far apart"


@pytest.mark.parametrize("seed", [100, 101, 102])
def test_two_or_more_cameras_leave_no_second_solution(seed):
    scene = _scene(seed, SceneOptions(cameras=(2, 4)))
    if scene.machine.n_joints == 0:
        pytest.skip("a rigid machine has no joints to mirror")
    fit = fit_joints(scene.machine, list(scene.cameras), scene.pixels())
    found = second_solutions(scene.machine, list(scene.cameras), scene.pixels(), fit)
    assert found.checked.sum() == 40 and not found.ambiguous.any()


def test_the_fit_command_reports_the_second_solution(tmp_path, capsys):
    scene = _scene(ONE_CAMERA_MIRROR, SceneOptions.field())
    save_machine(scene.model, tmp_path / "machine.toml")
    save_calibration(Calibration(scene.cameras, ({"fps": 30.0},)), tmp_path / "cameras.toml")
    save_tracks(scene.tracks, tmp_path / "tracks.csv")
    assert main(["fit", str(tmp_path / "machine.toml"), str(tmp_path / "cameras.toml"), str(tmp_path / "tracks.csv"),
                 "--out", str(tmp_path / "motion.csv"), "--tolerance", "5%"]) == 0
    report = capsys.readouterr().out
    assert "frames checked have a second solution that explains the pixels as well (tip up to" in report


def test_a_stretch_on_the_mirror_between_frames_on_the_truth_takes_the_continuous_solution():
    """The pixels cannot tell the two apart, but a machine moving smoothly cannot have jumped
    to the mirror and back: the stretch (started there) is carried on from its neighbours."""
    scene = _scene(ONE_CAMERA_MIRROR, SceneOptions.field())
    options = FitOptions(tolerance=Tolerance(0.05))
    pixels, cameras = scene.pixels(), list(scene.cameras)
    at_truth = fit_joints(scene.model, cameras, pixels, initial=scene.joints, options=options)
    mirror = second_solutions(scene.model, cameras, pixels, at_truth, options)
    stretch = np.arange(22, 30)
    assert mirror.ambiguous[stretch].all()
    start = scene.joints.copy()
    start[stretch] = mirror.alternative[stretch]
    fit = fit_joints(scene.model, cameras, pixels, initial=start, options=options)
    truth = scene.machine.points(scene.joints)[:, 0]
    sd = point_quantities(scene.model, fit.joints, fit.covariance).points_sd[:, 0]
    error = np.linalg.norm(scene.model.points(fit.joints)[:, 0] - truth, axis=1)
    started_there = np.linalg.norm(scene.model.points(mirror.alternative[stretch])[:, 0] - truth[stretch], axis=1)
    assert np.all(started_there > 5 * sd[stretch])  # the start was the far solution
    assert np.all(error[stretch] < 5 * sd[stretch]), error[stretch] / sd[stretch]
