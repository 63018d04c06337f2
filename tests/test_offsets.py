"""The markers' offsets estimated over a session (mocap.reconstruct.offsets): random
machines measured by tape (every marker coordinate off by up to ±5 %, that tolerance
stated), true cameras, pixel noise and wild pixels. The tip is held to the bound that
counts the model's error (`mocap.synthetic.bounds.fit_point_sd`, the offsets marginalised
frame by frame), the offsets to their own stated SDs."""

from dataclasses import replace

import numpy as np
import pytest

from mocap.cli import main
from mocap.core.calibration import Calibration
from mocap.core.machine import Tolerance
from mocap.errors import InputError
from mocap.io.cameras_toml import save_calibration
from mocap.io.machine_toml import load_machine, save_machine
from mocap.io.tracks_csv import save_tracks
from mocap.reconstruct.kinfit import FitOptions, fit_joints
from mocap.reconstruct.offsets import MarkerOffsets, bounded_step, fit_with_offsets, tape_bound, tape_sd
from mocap.reconstruct.timing import tracks_on_reference_clock
from mocap.reconstruct.uncertainty import point_quantities
from mocap.synthetic.bounds import fit_point_sd
from mocap.synthetic.machines import SceneOptions, random_scene

TOLERANCE = 0.05
FIELD = SceneOptions(noise_px=0.8, occlusion=0.15, outliers=0.02, tolerance=TOLERANCE, cameras=(2, 4))


def _scene(seed: int, options: SceneOptions = FIELD, frames: int = 40):
    """A random field scene whose machine has a tip on a moving link."""
    rng = np.random.default_rng(seed)
    while True:
        scene = random_scene(rng, options, n_frames=frames)
        if scene.machine.n_joints and scene.machine.point_names:
            return scene


def _tracked(scene) -> np.ndarray:
    """(C, F, M, 2) the scene's pixels as `mocap fit` takes them: on the reference clock, the
    pixels their own tracks contradict dropped."""
    names = [c.name for c in scene.cameras]
    ones = np.ones(len(names))
    return tracks_on_reference_clock(scene.tracks, names, scene.machine.marker_names, 30.0 * ones, 0.0 * ones).pixels


def _wild_removed(scene) -> np.ndarray:
    """(C, F, M) the observations that are not wild pixels."""
    seen = np.isfinite(scene.pixels()[..., 0])
    names = [c.name for c in scene.cameras]
    rows = scene.outlier
    seen[[names.index(c) for c in scene.tracks.camera[rows]], scene.tracks.frame[rows],
         scene.machine.marker_index(scene.tracks.marker[rows])] = False
    return seen


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_offsets_of_a_field_scene_are_recovered_and_the_tip_reaches_the_bound(seed):
    scene = _scene(seed)
    cameras, machine = list(scene.cameras), scene.machine
    options = FitOptions(tolerance=Tolerance(TOLERANCE))
    result = fit_with_offsets(scene.model, cameras, _tracked(scene), options=options)
    offsets = result.offsets
    assert offsets.settled and offsets.rounds <= 5
    truth = machine.marker_positions - scene.model.marker_positions
    z = (offsets.offsets - truth) / offsets.sd
    assert offsets.fixed.sum() >= 3, "too few markers fixed to test"
    assert np.abs(z[offsets.fixed]).max() < 4.5, f"a well-seen marker's offset {np.abs(z).max():.1f} SDs off"
    assert np.sqrt(np.mean(z**2)) < 1.6  # the stated SDs are honest on the whole
    assert np.all(offsets.observations[offsets.fixed] > 0)
    assert np.all(np.abs(offsets.offsets) <= tape_bound(Tolerance(TOLERANCE), scene.model.marker_positions))
    # the tip: within twice the bound that marginalises the offsets, its stated SDs honest
    coordinate_sd = TOLERANCE * np.abs(scene.model.marker_positions) / np.sqrt(3)  # the scene's error, per coordinate
    bound = fit_point_sd(machine, cameras, scene.joints, _wild_removed(scene), FIELD.noise_px, coordinate_sd)[:, 0]
    shown = np.isfinite(bound)
    tip = point_quantities(scene.model, result.fit.joints, result.fit.covariance + result.shared)
    error = np.linalg.norm(tip.points[:, 0] - machine.points(scene.joints)[:, 0], axis=1)
    ratio = np.sqrt(np.mean(error[shown] ** 2) / np.mean(bound[shown] ** 2))
    assert ratio < 2.0, f"tip RMSE {ratio:.2f} x the bound"
    assert np.all(error[shown] < 5 * tip.points_sd[shown, 0])


def test_wild_pixels_do_not_feed_the_offsets():
    """The same scene with and without its wild pixels: the offsets agree within their SDs."""
    scene = _scene(14, replace(FIELD, outliers=0.05))
    options = FitOptions(tolerance=Tolerance(TOLERANCE))
    cameras = list(scene.cameras)
    wild = fit_with_offsets(scene.model, cameras, scene.pixels(), options=options).offsets
    clean = scene.pixels()
    clean[~_wild_removed(scene)] = np.nan
    kept = fit_with_offsets(scene.model, cameras, clean, options=options).offsets
    assert np.abs((wild.offsets - kept.offsets) / kept.sd).max() < 1.0
    assert wild.observations.sum() <= kept.observations.sum() + 0.05 * scene.outlier.sum()


def test_an_offset_along_a_single_cameras_line_of_sight_stays_at_the_prior():
    """One camera and a base that never moves: a base marker's offset along the line of
    sight leaves the pixels unchanged, so what is known of it there is the prior's alone
    (its information along the sight), and the estimate is where the prior puts it given
    the rest (the prior's pull along the sight is zero)."""
    scene = _scene(21, SceneOptions(noise_px=0.5, tolerance=TOLERANCE, cameras=(1, 1)))
    camera = scene.cameras[0]
    result = fit_with_offsets(scene.model, [camera], scene.pixels(), options=FitOptions(tolerance=Tolerance(TOLERANCE)))
    offsets = result.offsets
    base = np.nonzero(scene.model.marker_links == 0)[0]
    sight = offsets.apply(scene.model).marker_positions[base] - camera.center  # base frame = world
    sight /= np.linalg.norm(sight, axis=1, keepdims=True)
    prior_information = np.einsum("mi,mi->m", sight**2, offsets.prior_sd[base] ** -2)
    information = np.einsum("mi,mij,mj->m", sight, np.linalg.inv(offsets.covariance[base]), sight)
    np.testing.assert_allclose(information, prior_information, rtol=0.02)
    pull = np.einsum("mi,mi->m", sight, offsets.offsets[base] / offsets.prior_sd[base] ** 2)
    assert np.all(np.abs(pull) < 0.1 * np.sqrt(prior_information))
    assert not offsets.fixed[base].any()


def test_the_offsets_need_a_tolerance_and_keep_their_shapes():
    scene = _scene(11, SceneOptions())
    with pytest.raises(ValueError, match="needs a stated tolerance"):
        fit_with_offsets(scene.model, list(scene.cameras), scene.pixels())
    with pytest.raises(ValueError, match=r"MarkerOffsets.offsets must be \(2, 3\)"):
        MarkerOffsets(("a", "b"), np.zeros((3, 3)), np.zeros((2, 3, 3)), np.ones((2, 3)), np.zeros(2), 1, True)
    sd = tape_sd(Tolerance(0.05), np.array([[10.0, 0.0, -2.0]]))
    np.testing.assert_allclose(sd, [[0.5, 0.005, 0.1]] / np.sqrt(3))
    bound = tape_bound(Tolerance(0.05), np.array([[10.0, 0.0, -2.0]]))
    np.testing.assert_allclose(bound, [[0.5, 0.005, 0.1]] / np.float64(0.95))


def test_the_offsets_step_is_the_quadratics_minimum_within_the_tolerance():
    """A step that would take a marker beyond its tolerance is the constrained minimum (the
    Karush-Kuhn-Tucker conditions hold), not the free step clipped per coordinate: a
    marker whose coordinates are correlated, clipped in one, would be left off its valley."""
    rng = np.random.default_rng(3)
    for _ in range(50):
        half = rng.normal(size=(6, 6))
        reduced = half @ half.T + 0.1 * np.eye(6)
        rhs, offsets, bound = 3 * rng.normal(size=6), rng.uniform(-0.5, 0.5, 6), np.ones(6)
        step = bounded_step(reduced, rhs, offsets, bound)
        moved = offsets + step
        assert np.all(np.abs(moved) <= bound + 1e-9)
        gradient = reduced @ step - rhs
        high, low = moved >= bound - 1e-9, moved <= -bound + 1e-9
        inside = ~(high | low)
        np.testing.assert_allclose(gradient[inside], 0.0, atol=1e-7)
        assert np.all(gradient[high] <= 1e-7) and np.all(gradient[low] >= -1e-7)
        clipped = np.clip(offsets + np.linalg.solve(reduced, rhs), -bound, bound) - offsets
        cost = lambda s: 0.5 * s @ reduced @ s - rhs @ s  # noqa: E731
        assert cost(step) <= cost(clipped) + 1e-9
    free = np.linalg.solve(reduced, 1e-3 * rhs)
    np.testing.assert_allclose(bounded_step(reduced, 1e-3 * rhs, np.zeros(6), bound), free)


def test_the_clean_path_is_the_plain_fit():
    """Without a tolerance `mocap fit` runs the per-frame fit alone, unchanged."""
    from mocap.reconstruct.motion import reconstruct_motion

    scene = _scene(11, SceneOptions(), frames=12)
    pixels = scene.pixels()
    frames = np.arange(pixels.shape[1])
    result = reconstruct_motion(scene.model, list(scene.cameras), frames, frames / 30.0, pixels, smoothing=False)
    plain = fit_joints(scene.model, list(scene.cameras), pixels)
    assert result.offsets is None
    np.testing.assert_array_equal(result.fit.joints, plain.joints)
    expected = point_quantities(scene.model, plain.joints, plain.covariance)
    np.testing.assert_array_equal(result.motion.points_sd, expected.points_sd)


def test_the_fit_command_writes_the_model_with_its_markers_moved(tmp_path, capsys):
    scene = _scene(12)
    save_machine(scene.model, tmp_path / "machine.toml")
    save_calibration(Calibration(scene.cameras, ({"fps": 30.0},) * len(scene.cameras)), tmp_path / "cameras.toml")
    save_tracks(scene.tracks, tmp_path / "tracks.csv")
    argv = ["fit", str(tmp_path / "machine.toml"), str(tmp_path / "cameras.toml"), str(tmp_path / "tracks.csv"),
            "--out", str(tmp_path / "motion.csv"), "--out-machine", str(tmp_path / "moved.toml")]
    with pytest.raises(InputError, match="--out-machine needs the markers' tolerance"):
        from mocap.reconstruct.stage import run_fit

        run_fit(tmp_path / "machine.toml", tmp_path / "cameras.toml", [tmp_path / "tracks.csv"],
                tmp_path / "motion.csv", FitOptions(), None, out_machine=tmp_path / "moved.toml")
    assert main(argv) == 2
    assert main(argv + ["--tolerance", "5%"]) == 0
    assert "marker offsets estimated over the session" in capsys.readouterr().out
    moved = load_machine(tmp_path / "moved.toml")
    before = np.linalg.norm(scene.model.marker_positions - scene.machine.marker_positions, axis=1)
    after = np.linalg.norm(moved.marker_positions - scene.machine.marker_positions, axis=1)
    assert np.sqrt(np.mean(after**2)) < 0.6 * np.sqrt(np.mean(before**2))
