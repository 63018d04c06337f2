"""The chain on machines nobody designed by hand: random articulated machines (0-6 moving
links, revolute and prismatic joints, flipped frames, axes of either sign, 1-4 markers per
link) seen by 1-4 random cameras at 10-90 m. Errors are held to the Cramér–Rao bound at
the truth (`mocap.synthetic.bounds`), 0.5 px noise."""

import numpy as np
import pytest

from mocap.calibration import CalibrationOptions, calibrate, template_camera
from mocap.core.machine import Tolerance
from mocap.errors import DegenerateError
from mocap.io.machine_toml import machine_from_dict, machine_to_dict
from mocap.reconstruct.kinfit import FitOptions, fit_joints
from mocap.reconstruct.timing import tracks_on_reference_clock
from mocap.reconstruct.triangulate import triangulate, triangulate_tracks
from mocap.reconstruct.uncertainty import point_quantities
from mocap.synthetic.bounds import calibration_centre_sd, fit_point_sd, triangulation_sd
from mocap.synthetic.machines import SceneOptions, random_machine_document, random_scene

SCENES = range(20)  # benchmarks/bench_robustness.py holds the same bounds over 1000 scenes
NOISE_PX = 0.5


def test_random_machine_documents_load_round_trip_and_vary():
    joints, prismatic, flipped = [], 0, 0
    for seed in range(60):
        rng = np.random.default_rng(seed)
        document = random_machine_document(rng)
        machine = machine_from_dict(document)
        again = machine_from_dict(machine_to_dict(machine))
        q = rng.uniform(-0.5, 0.5, (3, machine.n_joints))
        np.testing.assert_allclose(again.markers(q), machine.markers(q), atol=1e-9)
        np.testing.assert_allclose(again.points(q), machine.points(q), atol=1e-9)
        assert not set(machine.joint_names) & set(machine.link_names)
        assert 4 <= int(np.sum(machine.marker_links == 0)) <= 8
        assert np.all(np.bincount(machine.marker_links, minlength=len(machine.links))[1:] >= 1)
        assert np.linalg.norm(document["bucket_angle"]["direction"]) != pytest.approx(1.0)
        joints.append(machine.n_joints)
        prismatic += sum(j.type == "prismatic" for j in machine.joints)
        flipped += sum(abs(abs(link["joint"]["rpy_deg"][0]) - 180) < 15 for link in document["links"][1:])
    assert min(joints) == 0 and max(joints) == 6
    assert prismatic > 5 and flipped > 2


def test_one_frame_calibration_of_random_machines_reaches_the_bound():
    ratios = []
    for seed in SCENES:
        scene = random_scene(np.random.default_rng(seed), SceneOptions(noise_px=NOISE_PX))
        obs = scene.observations()
        templates = [template_camera(c.name, c.size) for c in scene.cameras]
        result = calibrate(scene.model, obs, templates)
        assert not result.outliers, f"scene {seed}: good observations dropped"
        assert result.rms_px < 2 * NOISE_PX, f"scene {seed}: rms {result.rms_px:.2f} px"
        bound = calibration_centre_sd(scene.machine, list(scene.cameras), scene.joints[0], obs, NOISE_PX)
        error = np.array([np.linalg.norm(a.center - b.center) for a, b in zip(result.cameras, scene.cameras)])
        assert np.all(error < 5 * bound), f"scene {seed}: camera centres {error / bound} x the bound"
        ratios += list(error / bound)
    assert np.median(ratios) < 1.3


def test_kinematic_fit_of_random_machines_keeps_no_wrong_minimum():
    """Two or more cameras: every frame within 5 of its stated SDs and the tip near the
    bound. (One camera can leave two solutions that explain the pixels equally well.)"""
    for seed in SCENES:
        scene = random_scene(np.random.default_rng(100 + seed), SceneOptions(noise_px=NOISE_PX, cameras=(2, 4)), n_frames=40)
        machine = scene.machine
        if not machine.point_names or machine.n_joints == 0:
            continue
        pixels = scene.pixels()
        fit = fit_joints(machine, list(scene.cameras), pixels)
        assert fit.explained.all(), f"scene {seed}: frames left unexplained"
        assert fit.noise_px == pytest.approx(NOISE_PX, rel=0.25)
        tip = point_quantities(machine, fit.joints, fit.covariance)
        error = np.linalg.norm(tip.points[:, 0] - machine.points(scene.joints)[:, 0], axis=1)
        assert np.all(error < 5 * tip.points_sd[:, 0] + 1e-9), f"scene {seed}: tip {np.max(error / tip.points_sd[:, 0]):.1f} SDs off"
        bound = fit_point_sd(machine, list(scene.cameras), scene.joints, np.isfinite(pixels[..., 0]), NOISE_PX)[:, 0]
        ratio = np.sqrt(np.mean(error**2) / np.mean(bound**2))
        assert ratio < 1.6, f"scene {seed}: tip RMSE {ratio:.2f} x the bound"


@pytest.mark.long
def test_long_sessions_of_random_machines_keep_no_wrong_stretch():
    """3,000 frames: a stretch of frames whose robust residual is low enough to pass for a few
    wild pixels, on a wrong minimum, is mended from its neighbours (before: 3 of these 10 scenes
    at 3.4-24 times the bound, up to 217 frames beyond 5 SDs)."""
    for seed in range(10):
        scene = random_scene(np.random.default_rng(seed), SceneOptions(noise_px=NOISE_PX), n_frames=3000)
        machine = scene.machine
        if not machine.point_names or machine.n_joints == 0:
            continue
        pixels = scene.pixels()
        fit = fit_joints(machine, list(scene.cameras), pixels)
        tip = point_quantities(machine, np.nan_to_num(fit.joints), fit.covariance)
        error = np.linalg.norm(tip.points[:, 0] - machine.points(scene.joints)[:, 0], axis=1)
        bound = fit_point_sd(machine, list(scene.cameras), scene.joints, np.isfinite(pixels[..., 0]), NOISE_PX)[:, 0]
        shown = np.isfinite(bound)
        ratio = np.sqrt(np.mean(error[shown] ** 2) / np.mean(bound[shown] ** 2))
        assert ratio < 1.3, f"scene {seed}: tip RMSE {ratio:.2f} x the bound"
        beyond = int((error[shown] > 5 * tip.points_sd[shown, 0]).sum())
        # one camera may leave a frame two solutions explain equally (reported by the fit's stage)
        assert beyond <= (0 if len(scene.cameras) > 1 else 3), f"scene {seed}: {beyond} frames beyond 5 SDs"


def test_one_camera_fit_of_random_machines_ends_no_worse_than_at_the_truth():
    for seed in range(20):
        scene = random_scene(np.random.default_rng(300 + seed), SceneOptions(noise_px=NOISE_PX, cameras=(1, 1)), n_frames=40)
        machine = scene.machine
        if machine.n_joints == 0:
            continue
        pixels = scene.pixels()
        options = FitOptions(noise_px=NOISE_PX)
        fit = fit_joints(machine, list(scene.cameras), pixels, options=options)
        at_truth = fit_joints(machine, list(scene.cameras), pixels, initial=scene.joints, options=options)
        cost = np.nansum(fit.residuals**2, axis=(0, 2, 3))
        cost_at_truth = np.nansum(at_truth.residuals**2, axis=(0, 2, 3))
        worse = cost > cost_at_truth + 9 * NOISE_PX**2  # 9: a chi-square difference of 9
        assert not worse.any(), f"scene {seed}: frames {np.nonzero(worse)[0]} kept a worse minimum"


def test_triangulation_of_random_machines_reaches_the_bound():
    for seed in SCENES:
        scene = random_scene(np.random.default_rng(500 + seed), SceneOptions(noise_px=NOISE_PX, cameras=(2, 4)), n_frames=5)
        pixels = scene.pixels()
        result = triangulate(list(scene.cameras), pixels)
        truth = scene.machine.markers(scene.joints)
        seen = np.isfinite(pixels[..., 0]).reshape(len(scene.cameras), -1)
        bound = triangulation_sd(list(scene.cameras), truth.reshape(-1, 3), seen, NOISE_PX)
        error = np.linalg.norm(result.xyz.reshape(-1, 3) - truth.reshape(-1, 3), axis=1)
        ok = np.isfinite(bound)
        assert np.all(np.isfinite(error[ok]))
        ratio = np.sqrt(np.mean(error[ok] ** 2) / np.mean(bound[ok] ** 2))
        assert ratio < 1.5, f"scene {seed}: triangulation RMSE {ratio:.2f} x the bound"


def good_pixels(scene) -> np.ndarray:
    """The scene's pixels (C, F, M, 2) with its wild ones NaN: what the bound counts."""
    good, names, rows = scene.pixels(), [c.name for c in scene.cameras], scene.outlier
    good[[names.index(c) for c in scene.tracks.camera[rows]], scene.tracks.frame[rows],
         scene.machine.marker_index(scene.tracks.marker[rows])] = np.nan
    return good


def test_field_triangulation_drops_wild_pixels_even_with_two_views():
    """2 % wild pixels (10-100 px), 15 % occlusion, 0.8 px noise: pixels their own tracks
    contradict are dropped before triangulating, views that disagree after; the points stay
    near the bound of the good views alone."""
    ratios = []
    for seed in range(20):
        scene = random_scene(np.random.default_rng(700 + seed), SceneOptions(noise_px=0.8, occlusion=0.15, outliers=0.02, cameras=(2, 4)), n_frames=60)
        names = [c.name for c in scene.cameras]
        clock = tracks_on_reference_clock(scene.tracks, names, scene.machine.marker_names, np.full(len(names), 30.0), np.zeros(len(names)))
        assert clock.dropped <= scene.outlier.sum() + 0.01 * len(scene.tracks)  # few good pixels lost
        result = triangulate(list(scene.cameras), clock.pixels)
        good = good_pixels(scene)
        truth = scene.machine.markers(scene.joints).reshape(-1, 3)
        bound = triangulation_sd(list(scene.cameras), truth, np.isfinite(good[..., 0]).reshape(len(names), -1), 0.8)
        error = np.linalg.norm(result.xyz.reshape(-1, 3) - truth, axis=1)
        ok = np.isfinite(bound) & np.isfinite(error)
        assert ok.sum() > 0.97 * np.isfinite(bound).sum()
        ratios.append(np.sqrt(np.mean(error[ok] ** 2) / np.mean(bound[ok] ** 2)))
    assert max(ratios) < 1.5 and np.median(ratios) < 1.1


def test_field_triangulation_asks_the_markers_3d_tracks():
    """The benchmark's field scenes (40 frames), as `mocap triangulate` runs them: a wild
    pixel whose track has a gap around it is not judged by its own 2-D track, and along the
    epipolar line of the only other view (or of one of two, which leave-one-out then drops)
    one frame cannot tell it; the marker's 3-D track does. Per frame alone, this range holds
    scenes 6 times their bound."""
    ratios, alone, lost = [], [], []
    for seed in range(1_000_200, 1_000_300):
        scene = random_scene(np.random.default_rng(seed), SceneOptions.field(), n_frames=40)
        if len(scene.cameras) < 2:
            continue
        names, cameras = [c.name for c in scene.cameras], list(scene.cameras)
        pixels = tracks_on_reference_clock(scene.tracks, names, scene.machine.marker_names, np.full(len(names), 30.0),
                                           np.zeros(len(names))).pixels
        good = good_pixels(scene)
        truth = scene.machine.markers(scene.joints).reshape(-1, 3)
        bound = triangulation_sd(cameras, truth, np.isfinite(good[..., 0]).reshape(len(names), -1), 0.8)
        tracked = triangulate_tracks(cameras, pixels)
        for out, result in ((ratios, tracked), (alone, triangulate(cameras, pixels))):
            error = np.linalg.norm(result.xyz.reshape(-1, 3) - truth, axis=1)
            ok = np.isfinite(bound) & np.isfinite(error)
            out.append(np.sqrt(np.mean(error[ok] ** 2) / np.mean(bound[ok] ** 2)))
        lost.append(1 - np.isfinite(tracked.xyz[..., 0]).sum() / np.isfinite(bound).sum())
    assert len(ratios) > 60
    assert max(alone) > 5  # what the scenes hold: per frame alone, wrong views kept
    assert max(ratios) < 1.5 and np.median(ratios) < 1.05, f"worst {max(ratios):.2f}"
    assert np.median(lost) < 0.01  # a point is dropped only with a wrong view and no second good one


@pytest.mark.long
def test_field_calibration_fits_the_markers_within_the_tolerance():
    """Field conditions (every marker coordinate off by up to 5 %, 2 % wild pixels, 15 %
    occlusion, 0.8 px): with the tolerance stated, the markers are fitted within it, the
    errors stay near the bound that counts the model's error, and few good observations are
    taken for outliers; with the model stated exact (tried on the first 4 scenes: the slow
    part), model error is taken for outliers. (With none stated the tolerance is estimated
    from the residuals: tests/test_tolerance_estimated.py.) 6 scenes; bench_robustness.py
    --kind field holds hundreds to the same bound."""
    ratios, false_with, false_without, caught, wild = [], 0, 0, 0, 0
    for seed in range(6):
        compared = seed < 4
        scene = random_scene(np.random.default_rng(900 + seed), SceneOptions(**{**SceneOptions.field().__dict__, "cameras": (2, 4)}))
        obs, truly = scene.observations(), scene.outlier[scene.tracks.frame == 0]
        templates = [template_camera(c.name, c.size) for c in scene.cameras]
        try:
            result = calibrate(scene.model, obs, templates, CalibrationOptions(tolerance=Tolerance(0.05)))
        except DegenerateError:
            continue  # occlusion left a view that cannot fix its camera: refused, not answered
        dropped = np.array([r.outlier for r in result.residuals])
        false_with += int((dropped & ~truly).sum()) if compared else 0
        caught += int((dropped & truly).sum())
        wild += int(truly.sum())
        bound = calibration_centre_sd(scene.machine, list(scene.cameras), scene.joints[0], scene.observations(inliers_only=True),
                                      0.8, marker_sd=0.05 * np.abs(scene.machine.marker_positions) / np.sqrt(3))
        ratios.append(np.median([np.linalg.norm(a.center - b.center) for a, b in zip(result.cameras, scene.cameras)] / bound))
        if not compared:
            continue
        try:
            plain = calibrate(scene.model, obs, templates, CalibrationOptions(tolerance=Tolerance()))
            false_without += sum(r.outlier and not t for r, t in zip(plain.residuals, truly))
        except DegenerateError:
            false_without += 1
    assert len(ratios) >= 5
    assert np.median(ratios) < 1.5
    print(f"good observations dropped: {false_with} with the tolerance, {false_without} with the model exact; "
          f"wild ones caught {caught} of {wild}")
    assert false_without > 3 * max(false_with, 1)
    assert caught >= 0.6 * wild  # a wild pixel within what the tolerance explains cannot be told
