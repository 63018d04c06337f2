"""The live fit and smoother on short synthetic sessions with their truth: the base held or
fitted per frame as the data say (`mocap fit`'s test, run as the frames come), and the
rows' SDs against their errors where the fits' errors are larger than their information
says and correlated from frame to frame."""

import numpy as np
import pytest

from mocap import cli
from mocap.core.tracks import Tracks
from mocap.io.cameras_toml import load_calibration
from mocap.io.machine_toml import load_machine
from mocap.io.motion_csv import load_motion
from mocap.io.tracks_csv import load_tracks
from mocap.live.pose import BASE_WINDOW, CameraHistory, FixedLagSmoother, FrameFit, WarmFit, warm_up
from mocap.reconstruct.timing import on_reference_clock

NOISE = 0.5  # px
FRAMES = 300  # 10 s: the tests of the base after 60 and 210 frames (on a recent window: every 30 from 60 to 300)


def live_rows(root, choose_base: bool, base_window: int | None = None, frames: int = FRAMES):
    """The session's first `frames` reference frames (its true tracks with NOISE px added)
    through the live fit and smoother: the fitter, the rows' tips (F, 3), their SDs (F,)
    and the truth's tips (F, 3)."""
    machine = load_machine("hitachi_ex3500")
    calibration = load_calibration(root / "truth" / "cameras.toml")
    truth = load_tracks([root / "truth" / "tracks.csv"])
    rng = np.random.default_rng(1)
    tracks = Tracks.from_rows(truth.camera, truth.frame, truth.marker, truth.xy + rng.normal(0, NOISE, truth.xy.shape),
                              truth.time)
    clock = on_reference_clock(calibration, tracks, tracks.checked_against(calibration, machine))
    fit = WarmFit(machine, list(calibration.cameras), choose_base=choose_base, background=False,
                  base_window=base_window)
    smoother = FixedLagSmoother(machine, 1, base_motion=choose_base)
    poses = [smoother.push(t, fit(clock.pixels[:, k])) for k, t in enumerate(clock.time[:frames])]
    poses = poses[1:] + smoother.flush()
    tip = machine.point_names.index("bucket_tip")
    motion = load_motion(root / "truth" / "motion.csv", machine)
    rows = np.searchsorted(motion.frame, clock.frame[:frames])
    return (fit, np.array([p.points[tip] for p in poses]), np.array([p.points_sd[tip] for p in poses]),
            motion.point("bucket_tip")[rows])


@pytest.fixture(scope="module")
def bouncing(tmp_path_factory):
    """bounce (m) -> the session of seed 7 with that bounce and the tips of its rows with the
    base held, each made once for the tests of both base windows."""
    made = {}

    def session(bounce: float):
        if bounce not in made:
            root = tmp_path_factory.mktemp("bounce") / "s"
            assert cli.main(["synth", "--machine", "hitachi_ex3500", "--cycles", "1", "--seed", "7", "--bounce",
                             str(bounce), "--out", str(root), "--no-video"]) == 0
            made[bounce] = root, live_rows(root, choose_base=False)[1] if bounce else None
        return made[bounce]
    return session


@pytest.mark.parametrize("base_window", [BASE_WINDOW, None])
@pytest.mark.parametrize("bounce", [0.0, 2.0])
def test_live_holds_the_base_or_fits_it_per_frame_as_the_data_say(bouncing, bounce, base_window):
    """A still base is held at every test; a bouncing one is fitted per frame from the test
    that finds it moving (the choice `mocap fit` makes on these sessions, tests/test_smooth.py;
    the first 2 s, their half-second still start, may not show it yet), and its rows then
    follow the tip closer than with the base held; the rows' tips lie within 3 of their SDs."""
    root, held = bouncing(bounce)
    fit, tips, sds, truth = live_rows(root, choose_base=True, base_window=base_window)
    answers = [moves for _, moves in fit.base_tests]
    assert len(answers) == (9 if base_window else 2) and answers[-1] == bool(bounce) and (bounce or not any(answers))
    since = [frames for frames, moves in fit.base_tests if moves == bool(bounce)][0] + 30
    error = np.linalg.norm(tips - truth, axis=1)
    after = slice(max(since, 90), None)  # the answer taken, the smoother's process noise estimated
    assert np.mean(error[after] <= 3 * sds[after]) > 0.95
    if bounce:
        held_error = np.linalg.norm(held - truth, axis=1)
        assert np.sqrt(np.mean(error[after] ** 2)) < 0.7 * np.sqrt(np.mean(held_error[after] ** 2))


def test_the_base_is_fitted_per_frame_until_the_first_test(tmp_path):
    """Before the first test (2 s) the base is fitted per frame: a base bouncing from the
    start (ramped up over the second after the half-second still start) is followed there,
    where held it puts the tip 5.8 cm off over frames 30-60 (measured: 0.75 cm fitted per
    frame), the rows' tips within 3 of their SDs; the first test, on those frames, finds it
    moving."""
    root = tmp_path / "s"
    assert cli.main(["synth", "--machine", "hitachi_ex3500", "--cycles", "1", "--seed", "7", "--bounce", "4",
                     "--hold", "0.5", "--out", str(root), "--no-video"]) == 0
    fit, tips, sds, truth = live_rows(root, choose_base=True, base_window=BASE_WINDOW, frames=60)
    _, held, _, _ = live_rows(root, choose_base=False, frames=60)
    bouncing = slice(30, 60)  # the bounce ramped up, no test yet
    error = np.linalg.norm(tips - truth, axis=1)[bouncing]
    held_error = np.linalg.norm(held - truth, axis=1)[bouncing]
    assert np.sqrt(np.mean(error**2)) < 0.3 * np.sqrt(np.mean(held_error**2))
    assert np.mean(error <= 3 * sds[bouncing]) > 0.9
    assert fit.base_tests == [(60, True)]


def overconfident_rows(seed: int = 11):
    """A swing moving at a varying pace, its fits 3 times further off than their information
    says and each error shared with the frame before (the same other camera's frames
    interpolated for both), through the live smoother: its rows' swing errors (F,), their
    SDs (F,) and the smoother."""
    machine = load_machine("hitachi_ex3500")
    rng = np.random.default_rng(seed)
    fps, sd, n = 30.0, 0.002, machine.n_joints
    time = np.arange(450) / fps
    truth = np.tile(machine.joint_limits.mean(axis=1), (len(time), 1))
    truth[:, 0] = 0.5 * np.sin(0.4 * time) + 0.1 * np.sin(1.3 * time)
    white = rng.normal(size=(len(time) + 1, n))
    errors = 3 * sd * (white[1:] + white[:-1]) / np.sqrt(2)
    smoother = FixedLagSmoother(machine, 1)
    poses = [smoother.push(t, FrameFit(v, np.eye(n) / sd**2, True, 0.5, 40)) for t, v in zip(time, truth + errors)]
    poses = poses[1:] + smoother.flush()
    return np.array([p.joints[0] for p in poses]) - truth[:, 0], np.array([p.joints_sd[0] for p in poses]), smoother


def test_the_rows_sds_cover_fits_overconfident_and_correlated():
    """The fits 3 times off their information and correlated (`overconfident_rows`): the
    rows' joint SDs are within 0.67-1.6 times their RMS error once the scales are measured
    (measured 1.17-1.39 over four draws: the scatter about the smoothed values sees only part
    of the shared error), where the smoothed covariance alone is more than 3 times too small."""
    error, sds, smoother = overconfident_rows()
    late = slice(240, None)  # the process noise estimated, the scales settled
    ratio = error[late] / sds[late]
    assert 0.67 < np.sqrt(np.mean(ratio**2)) < 1.6
    scale = smoother.variance_factor * (1 + 2 * max(smoother.correlation, 0.0))
    assert np.sqrt(np.mean(ratio**2) * scale) > 3  # the smoothed covariance without the scales


def test_the_first_rows_sds_lean_on_the_prior_until_the_scales_are_measured():
    """The same fits' first 6 s (the process noise first estimated after 2 s, the scales
    measured from then on): the rows' swing within 3 of their SDs of the truth 96-99 % of the
    time, e/SD 1.27-1.41 over seeds 11-14 (with the fits' own covariance until the scales
    were measured, and those first measurements in their medians: 87-91 %, e/SD 1.79-2.00)."""
    error, sds, _ = overconfident_rows(13)  # the worst of seeds 11-14
    first = slice(0, 180)
    ratio = error[first] / sds[first]
    assert np.mean(np.abs(ratio) <= 3) > 0.92 and np.sqrt(np.mean(ratio**2)) < 1.7


def test_a_camera_far_ahead_of_the_rows_keeps_the_frames_they_have_not_reached():
    """Files read as fast as they are tracked: a camera's tracker may run 1,000 frames ahead of
    the rows. With no depth its history still gives the pixels of a time the rows reach late
    (interpolated between its frames either side); a history of 256 frames has lost them."""
    fps, markers = 30.0, 4
    unbounded, bounded = CameraHistory(fps, depth=None), CameraHistory(fps)
    for k in range(1000):
        pixels = np.tile([[float(k), 2.0 * k]], (markers, 1))
        unbounded.add(k / fps, pixels)
        bounded.add(k / fps, pixels)
    at = 100.5 / fps
    np.testing.assert_allclose(unbounded.pixels_at(at), np.tile([[100.5, 201.0]], (markers, 1)))
    assert bounded.pixels_at(at) is None


def test_a_marker_seen_in_one_of_a_cameras_frames_either_side_is_not_taken_half_a_frame_old():
    """A camera whose frames fall 0.4 of an interval after the reference frames (29.97 fps
    against 30 drifts through every phase), its markers moving 8 px a frame (a swing, the base
    bouncing), one going out of sight and one coming into it: every marker given at a time is
    within 5 SDs of the noise of where it is then (those in both frames either side
    interpolated); the one in a single frame, 0.4 or 0.6 of a frame away, is left out, where it
    was taken from that frame 3.2 px off (as a marker leaving the view of seed 7's second
    camera put the live tip 6 cm off for a few frames)."""
    fps, speed, noise, markers = 30.0, 8.0, 0.1, 5
    rng = np.random.default_rng(3)

    def truth(t):  # (M, 2) where the markers are at time t
        return np.stack([100.0 + 40 * np.arange(markers) + speed * fps * t, 200.0 + 0 * np.arange(markers)], 1)

    history = CameraHistory(fps)
    for k in range(40):
        t = (k + 0.4) / fps
        pixels = truth(t) + rng.normal(0, noise, (markers, 2))
        if k > 20:
            pixels[0] = np.nan  # out of sight from the camera's frame 21 on
        if k < 20:
            pixels[1] = np.nan  # in sight from frame 20 on
        history.add(t, pixels)
    for frame in range(2, 39):  # reference frame `frame` lies 0.6 after camera frame frame - 1, 0.4 before frame
        at = history.pixels_at(frame / fps)
        given = np.isfinite(at[:, 0])
        error = np.linalg.norm(at[given] - truth(frame / fps)[given], axis=1)
        assert error.max() < 5 * noise, (frame, error)
        assert given[2:].all()  # the markers in every frame are always given
        assert given[0] == (frame <= 20) and given[1] == (frame >= 21), (frame, given)


def test_the_smoothers_warm_up_runs_for_every_lag_and_base():
    """`mocap live` gives a throwaway smoother a few still frames before the cameras' clock
    starts (its compiled kernel and first-use imports out of the first rows): it runs for a
    filter alone and longer lags, the base held or moving."""
    machine = load_machine("hitachi_ex3500")
    for lag in (0, 1, 3):
        for base_motion in (False, True):
            warm_up(machine, lag, base_motion)


def test_a_joint_still_for_the_whole_estimate_then_swinging_is_followed():
    """The swing still for the first 12 s (the process noise estimated several times: its own
    near 0) while the other joints move, then a swing of 1.5 rad in 3 s: no multiple of the
    estimate that the pace test tries follows it. Before, the rows coasted behind the truth
    (0.03-0.11 rad at most over seeds 3-6, e/SD 4-53; a random digger's swing did so live:
    2 m at the tip). Its newest fits contradict the smoothing frame after frame, so the swing is
    smoothed as little as before the first estimate: 0.006-0.011 rad at most, e/SD 2.0-2.3."""
    machine = load_machine("hitachi_ex3500")
    rng = np.random.default_rng(5)
    fps, sd, n = 30.0, 0.002, machine.n_joints
    time = np.arange(480) / fps
    truth = machine.joint_limits.mean(axis=1) + 0.2 * np.sin(0.5 * time[:, None] + np.arange(n))
    swing = np.clip((time - 12.0) / 3.0, 0.0, 1.0)
    truth[:, 0] = 0.3 + 0.75 * (1 - np.cos(np.pi * swing))
    smoother = FixedLagSmoother(machine, 1)
    poses = [smoother.push(t, FrameFit(v, np.eye(n) / sd**2, True, 0.5, 40))
             for t, v in zip(time, truth + rng.normal(0, sd, truth.shape))]
    poses = poses[1:] + smoother.flush()
    error = np.array([p.joints[0] for p in poses]) - truth[:, 0]
    sds = np.array([p.joints_sd[0] for p in poses])
    swinging = slice(360, 480)
    assert np.abs(error[swinging]).max() < 10 * sd
    assert np.sqrt(np.mean((error[swinging] / sds[swinging]) ** 2)) < 3.0


def mislabelled_fits(mislabel, seed: int = 2):
    """Three cameras, 0.5 px noise, the swing turning over 70 frames; `mislabel(pixels)` changes
    frame 65's pixels (C, M, 2) in place. The live fit's FrameFits, the fitter, the true
    joints (F, J) and frame 65's observations."""
    from mocap.core.camera import project
    from conftest import scene

    machine = load_machine("hitachi_ex3500")
    cameras, q, _, _ = scene(machine, 3, seed=2)
    rng = np.random.default_rng(seed)
    joints = np.tile(q, (70, 1))
    joints[:, 0] += np.linspace(0.0, 0.4, 70)
    pixels = project(cameras, machine.markers(joints))
    pixels = pixels + rng.normal(0, 0.5, pixels.shape)
    mislabel(pixels[:, 65])
    fit = WarmFit(machine, cameras)
    return [fit(pixels[:, f]) for f in range(70)], fit, joints, int(np.isfinite(pixels[:, 65, :, 0]).sum())


def test_a_frames_wrong_observations_are_left_out_and_it_is_fitted_from_the_others():
    """In one frame one camera labels a marker where nothing of the machine is (a random
    digger's camera labelled a hidden marker on a blob 255 px from it for two frames, and its
    fits, from 9 observations, went 61 deg off) and another takes two markers one for the other.
    Those three observations are left out and the frame is fitted from the others, as close to
    the truth as its neighbours, at their information (before: none left out, its information
    divided by its cost per observation over the usual one, 0.009 of its neighbours')."""
    wrong = {}

    def mislabel(pixels):
        seen = np.flatnonzero(np.isfinite(pixels[..., 0]).all(0))  # markers every camera sees
        first, last, middle = seen[0], seen[-1], seen[len(seen) // 2]  # far apart along the machine
        pixels[0, middle] += [230.0, -120.0]  # a blob taken for the marker
        pixels[1, [first, last]] = pixels[1, [last, first]]  # two markers labelled one for the other
        wrong["n"] = len(seen)

    fits, fit, joints, n_obs = mislabelled_fits(mislabel, seed=3)
    error = np.array([np.abs(f.values[:len(t)] - t).max() for f, t in zip(fits, joints)])
    weight = np.array([np.trace(f.information) for f in fits])
    assert wrong["n"] >= 3 and fit.left_out == 1 and fits[65].observations == n_obs - 3
    assert error[65] < 3 * np.max(error[55:65]), (error[65], error[55:65])
    assert weight[65] > 0.5 * np.median(weight[55:65])


def test_a_frame_whose_bucket_markers_are_all_mislabelled_is_fitted_without_them():
    """The bucket's four markers labelled one for another in every camera (12 of 93
    observations: a tracker's slip): all twelve are left out (the frame explained with some of
    them left in put the bucket 20 deg off, their residuals 46-50 px), the bucket's joint is
    unobserved in that frame's fit and the other joints are fitted as close as in the frames
    around it, with what the other markers tell of them (the bucket's also told of them: 0.19-0.45
    of their information is left). Before, the frame was weighed as a whole by its cost per
    observation, a tenth or less."""
    machine = load_machine("hitachi_ex3500")
    bucket = [k for k, link in enumerate(machine.marker_links) if link == max(machine.marker_links)]

    def mislabel(pixels):
        pixels[:, bucket] = pixels[:, bucket[::-1]]

    fits, fit, joints, n_obs = mislabelled_fits(mislabel)
    information = np.array([np.diagonal(f.information) for f in fits])  # (F, J)
    error = np.abs(np.array([f.values for f in fits]) - joints)
    assert len(bucket) == 4 and fit.left_out == 1 and fits[65].observations == n_obs - 12
    assert information[65, -1] < 1e-3 * np.median(information[55:65, -1])
    assert np.all(information[65, :-1] > 0.1 * np.median(information[55:65, :-1], axis=0))  # measured 0.19-0.45
    assert np.all(error[65, :-1] < 3 * error[55:65, :-1].max(axis=0))


def test_a_frame_no_subset_explains_is_weighed_by_its_residuals():
    """A camera's labels all shifted by one marker in one frame (31 of 93 observations wrong,
    more than the quarter that may be left out): no pose explains it and no subset left out
    does; its fit's information is divided by its cost per observation over the usual one, so
    the smoother weighs it as the outlier it is (a random digger's two such frames, taken at
    full weight, had pulled the live rows 2.5 m off). The frames around it keep theirs."""
    fits, fit, _, n_obs = mislabelled_fits(lambda pixels: pixels.__setitem__(0, np.roll(pixels[0], 1, axis=0)))
    weight = np.array([np.trace(f.information) for f in fits])
    assert all(f.valid for f in fits) and fit.left_out == 0 and fits[65].observations == n_obs
    assert weight[65] < 0.1 * np.median(weight[55:65]) and weight[66] > 0.5 * np.median(weight[55:65])


def test_after_a_frame_without_a_fit_the_pose_before_it_is_kept_over_a_far_one_as_good(monkeypatch):
    """A frame with too few observations for a fit leaves the next frame without a warm start,
    and it is fitted from the grid as a first frame is; where the grid's answer is another
    pose (a mirror that explains the pixels as well; here the grid's search stopped far from
    the truth), a fit from the pose before the gap that explains them as well or better is
    kept: the machine was there a frame ago. (A random digger's rows were 1.4-11 m off for six
    frames so, with tip SDs of 6-14 cm.)"""
    from mocap.core.camera import project
    from conftest import scene

    machine = load_machine("hitachi_ex3500")
    cameras, q, _, _ = scene(machine, 3, seed=2)
    rng = np.random.default_rng(4)
    joints = np.tile(q, (12, 1))
    joints[:, 0] += np.linspace(0.0, 0.05, 12)
    pixels = project(cameras, machine.markers(joints))
    pixels = pixels + rng.normal(0, 0.5, pixels.shape)
    pixels[:, 8] = np.nan
    pixels[0, 8, :1] = project(cameras, machine.markers(joints[8:9]))[0, 0, :1]  # one observation: no fit
    far = q + np.array([0.8, 0.3, -0.4, 0.5])[: machine.n_joints]
    mirror = project(cameras, machine.markers(far[None]))[:, :, None]  # (C, 1, 1, M, 2): the far pose's pixels

    def stopped_far(self, frame, moves):  # a grid whose answer is elsewhere and explains the pixels as well
        return self.fitters[moves].fit(np.where(np.isfinite(frame), mirror[:, 0], np.nan), far[None], None)
    fit = WarmFit(machine, cameras)
    monkeypatch.setattr(WarmFit, "_from_grid", stopped_far)
    fits = [fit(pixels[:, f]) for f in range(12)]
    assert not fits[8].valid and all(f.valid for f in fits[:8] + fits[9:])
    error = np.abs(np.array([f.values[: machine.n_joints] for f in fits[9:]]) - joints[9:])
    assert error.max() < 0.01, error  # rad: the pose before the gap's, followed on
