"""The smoother, gap filling, uncertainty of named points, and `mocap fit` end to end."""

import re
from dataclasses import replace

import numpy as np
import pytest

from mocap import cli
from mocap.core.calibration import Calibration
from mocap.core.tracks import Tracks
from mocap.io.cameras_toml import save_calibration
from mocap.io.machine_toml import load_machine, save_machine
from mocap.io.motion_csv import load_motion
from mocap.io.tracks_csv import load_tracks, save_tracks
from mocap.reconstruct.motion import reconstruct_motion
from mocap.reconstruct.smooth import SmoothOptions, scatter_scale, smooth
from mocap.reconstruct.uncertainty import point_quantities
from mocap.synthetic.scenes import observe, ring_of_cameras

NOISE = 0.5
FPS = 30.0


@pytest.fixture(scope="module")
def machine():
    return load_machine("hitachi_ex3500")


def dig_like(machine, seconds, rng):
    """Smooth joint trajectories (F, J): a few slow sinusoids inside the limits."""
    time = np.arange(int(seconds * FPS)) / FPS
    limits = machine.joint_limits.copy()
    limits[0] = np.radians([-60, 60])
    centre, half = limits.mean(1), 0.35 * (limits[:, 1] - limits[:, 0])
    phase = rng.uniform(0, 2 * np.pi, (3, machine.n_joints))
    period = rng.uniform(8.0, 20.0, (3, machine.n_joints))
    wave = sum(np.sin(2 * np.pi * time[:, None] / period[k] + phase[k]) for k in range(3)) / 3
    return time, centre + half * wave


def test_smoother_reduces_noise_with_honest_intervals():
    rng = np.random.default_rng(1)
    time = np.arange(900) / FPS
    truth = np.c_[np.sin(time / 3.0), 0.5 * np.cos(time / 2.0)]
    sd = np.array([0.02, 0.01])
    measured = truth + rng.normal(0, sd, truth.shape)
    information = np.tile(np.diag(1 / sd**2), (len(time), 1, 1))
    out = smooth(time, measured, information, np.ones(len(time), bool))
    error = out.values - truth
    assert (np.sqrt(np.mean(error**2, 0)) < 0.6 * sd).all()
    z = error / np.sqrt(np.diagonal(out.covariance, axis1=1, axis2=2))
    assert 0.9 < np.mean(np.abs(z) < 1.96) < 0.995
    assert not out.filled.any()
    velocity_error = out.velocities[:, 0] - np.cos(time / 3.0) / 3.0
    assert np.sqrt(np.mean(velocity_error**2)) < 0.02
    assert np.mean(np.abs(velocity_error) < 1.96 * np.sqrt(out.velocity_covariance[:, 0, 0])) > 0.85


def test_gaps_are_filled_and_long_gaps_left_empty():
    rng = np.random.default_rng(2)
    time = np.arange(600) / FPS
    truth = np.sin(time / 2.0)[:, None]
    measured = truth + rng.normal(0, 0.01, truth.shape)
    valid = np.ones(600, bool)
    valid[100:130] = False  # 1 s
    valid[300:420] = False  # 4 s
    information = np.tile(np.eye(1) / 0.01**2, (600, 1, 1))
    out = smooth(time, np.where(valid[:, None], measured, np.nan), information, valid, options=SmoothOptions(max_gap_s=2.0))
    assert out.filled[100:130].all() and not out.filled[:100].any()
    assert np.isnan(out.values[300:420]).all() and not out.filled[300:420].any()
    gap_error = np.abs(out.values[100:130, 0] - truth[100:130, 0])
    assert (gap_error < 3 * np.sqrt(out.covariance[100:130, 0, 0])).all()


def test_singular_information_leaves_one_parameter_to_the_model():
    time = np.arange(200) / FPS
    truth = np.c_[time, 1.0 + 0.5 * time]
    information = np.tile(np.eye(2) * 1e4, (200, 1, 1))
    information[80:110, 1, :] = information[80:110, :, 1] = 0.0  # parameter 1 unobserved
    measured = truth.copy()
    measured[80:110, 1] = 123.0  # whatever the fit left there
    out = smooth(time, measured, information, np.ones(200, bool), options=SmoothOptions(process_noise=1e-3))
    np.testing.assert_allclose(out.values[:, 1], truth[:, 1], atol=1e-3)
    assert out.filled[80:110].all() and not out.filled[:80].any()


def test_fits_whose_errors_correlate_from_frame_to_frame_widen_the_smoothed_sds():
    """Fits whose errors are shared by neighbouring frames (lag-1 correlation 0.5, none beyond:
    two reference frames interpolated from one camera frame) but whose information says they
    are independent: the smoother averages them as if independent and its SDs cover the
    truth's 95 % band in 84 % of the frames; `scatter_scale` measures the correlation, and
    the smoothed SDs times its scale cover it as a 95 % band should."""
    rng = np.random.default_rng(8)
    time = np.arange(1200) / FPS
    truth = np.c_[np.sin(time / 3.0), 0.5 * np.cos(time / 2.0)]
    sd = 0.02
    shared = rng.normal(0, sd, (len(time) + 1, 2))
    measured = truth + (shared[1:] + shared[:-1]) / np.sqrt(2)
    information = np.tile(np.eye(2) / sd**2, (len(time), 1, 1))
    out = smooth(time, measured, information, np.ones(len(time), bool))
    scale, factor, rho = scatter_scale(measured, information, np.ones(len(time), bool), out)
    assert 0.35 < rho < 0.55 and factor < 1.2
    z = np.abs(out.values - truth) / np.sqrt(np.diagonal(out.covariance, axis1=1, axis2=2))
    assert np.mean(z < 1.96) < 0.9  # the smoother alone: overconfident
    assert 0.93 < np.mean(z / np.sqrt(scale) < 1.96) < 0.995


def test_partly_observed_frames_on_a_far_branch_are_left_out_and_the_right_ones_kept():
    """Two stretches whose fits leave parameter 1 unobserved: in the first the fit's parameter 0
    is right and narrows the smoother there below the model's own SD; in the second (a random
    digger's fits with its moving markers lost: a far branch that explains their few pixels
    as well, the same for 20 frames, with the SD of a good fit) it is 0.8 off and is left out:
    the smoother fills those frames from the frames that observe both, within 3 of its SDs,
    where used it followed the branch 0.8 off at 0.01 SD (e/SD 80)."""
    rng = np.random.default_rng(6)
    time = np.arange(300) / FPS
    truth = np.c_[np.sin(time), 0.5 * np.cos(time / 2.0)]
    sd = np.array([0.01, 0.01])
    measured = truth + rng.normal(0, sd, truth.shape)
    information = np.tile(np.diag(1 / sd**2), (300, 1, 1))
    partly = np.r_[60:80, 200:220]
    information[partly, 1, :] = information[partly, :, 1] = 0.0  # parameter 1 unobserved
    measured[partly, 1] = 3.0  # whatever the fit left there
    measured[200:220, 0] = truth[200:220, 0] + 0.8  # a far branch
    out = smooth(time, measured, information, np.ones(300, bool), options=SmoothOptions(process_noise=0.05))
    error, spread = np.abs(out.values - truth), np.sqrt(np.diagonal(out.covariance, axis1=1, axis2=2))
    assert out.filled[200:220].all() and (error[200:220] < 3 * spread[200:220]).all()
    assert error[200:220, 0].max() < 0.1
    # the right partial frames still count: parameter 0 there as sharp as in the frames around
    assert not out.filled[:60].any() and np.median(spread[60:80, 0]) < 1.5 * np.median(spread[20:60, 0])
    assert (error[60:80] < 3 * spread[60:80]).all()


# a random digger's frame of two markers (its fit's information on four joints, rank 2): a
# fixed ridge of 1e-12 was lost in the rounding of these entries and `mocap fit` stopped on
# a singular matrix
RANK_TWO = [[491982.9540009241, 194294.22142259034, -62008.74167934935, 62595.10443755668],
            [194294.22142259034, 827222.1050437938, -373435.92126978625, 97326.76000215138],
            [-62008.74167934935, -373435.92126978625, 170061.57285024223, -41648.4783411756],
            [62595.10443755668, 97326.76000215138, -41648.4783411756, 14988.357767726304]]


def test_a_frame_that_leaves_two_directions_unobserved_is_filled_not_fatal():
    """A well-observed run of four parameters with one frame whose information is rank 2
    at the scale of 1e5: the smoother runs, marks that frame filled, and the frames around it
    keep their values to the noise."""
    rng = np.random.default_rng(4)
    time = np.arange(90) / FPS
    truth = np.c_[np.sin(time), np.cos(time), 0.5 * time, 0.2 * np.sin(2 * time)]
    information = np.tile(np.eye(4) / 0.001**2, (90, 1, 1))
    information[45] = RANK_TWO
    measured = truth + rng.normal(0, 0.001, truth.shape)
    out = smooth(time, measured, information, np.ones(90, bool))
    assert out.filled[45] and not out.filled[:45].any() and not out.filled[46:].any()
    assert np.abs(out.values - truth).max() < 0.01  # the filled frame from its neighbours


def test_guards():
    with pytest.raises(ValueError, match="time must increase"):
        smooth(np.zeros(3), np.zeros((3, 1)), np.ones((3, 1, 1)), np.ones(3, bool))
    with pytest.raises(ValueError, match="smooth needs"):
        smooth(np.arange(3.0), np.zeros((3, 2)), np.ones((3, 1, 1)), np.ones(3, bool))
    with pytest.raises(ValueError, match="gate_probability"):
        SmoothOptions(gate_probability=0.0)
    with pytest.raises(ValueError, match="values must be"):
        point_quantities(load_machine("hitachi_ex3500"), np.zeros((2, 3)), np.zeros((2, 3, 3)))


def _occluded_dig(machine, seed):
    rng = np.random.default_rng(seed)
    cameras = ring_of_cameras(3, np.array([5.0, 0.0, 5.0]), (30.0, 60.0), rng, fov_deg=(40.0, 60.0))
    time, joints = dig_like(machine, 20.0, rng)
    tracks = observe(cameras, machine, joints, rng, noise_px=NOISE)
    pixels = tracks.dense([c.name for c in cameras], machine.marker_names, np.arange(len(time)))
    bucket = [i for i, n in enumerate(machine.marker_names) if n.startswith("K")]
    pixels[:, HIDDEN][:, :, bucket] = np.nan
    return time, joints, reconstruct_motion(machine, cameras, np.arange(len(time)), time, pixels).motion


HIDDEN = slice(300, 330)  # one second


def test_bucket_occlusion_filled_with_honest_uncertainty(machine):
    """The gap is filled within 10 cm and its SD covers the error; over three sessions the 95 %
    intervals of the joints and the bucket angle cover 90-98 % of the truth (the smoothed
    errors are correlated in time, so one 20 s session alone is too few samples)."""
    z_joints, z_angles = [], []
    for seed in (3, 4, 5):
        time, joints, motion = _occluded_dig(machine, seed)
        tip_true = machine.points(joints)[:, 0]
        error = np.linalg.norm(motion.points[:, 0] - tip_true, axis=-1)
        assert motion.extra["filled"][HIDDEN].all() and motion.extra["filled"].sum() == 30
        assert error[HIDDEN].max() < 0.10
        assert (error[HIDDEN] < 2.0 * motion.points_sd[HIDDEN, 0]).all()  # the 3-D SD covers the gap
        z_joints.append((motion.joints - joints) / motion.joints_sd)
        z_angles.append((motion.bucket_angle - machine.bucket_angles(joints)) / motion.bucket_angle_sd)
        speed_true = np.linalg.norm(np.gradient(tip_true, time, axis=0), axis=-1)
        assert np.median(np.abs(motion.extra["bucket_tip_speed"] - speed_true)) < 0.02 * np.median(speed_true)
    assert 0.9 < np.mean(np.abs(np.concatenate(z_joints)) < 1.96) < 0.98
    assert 0.9 < np.mean(np.abs(np.concatenate(z_angles)) < 1.96) < 0.98


def test_cli_fit(tmp_path, machine, capsys):
    rng = np.random.default_rng(4)
    cameras = ring_of_cameras(2, np.array([5.0, 0.0, 5.0]), (30.0, 60.0), rng, fov_deg=(40.0, 60.0))
    time, joints = dig_like(machine, 4.0, rng)
    tracks = observe(cameras, machine, joints, rng, noise_px=NOISE)
    save_calibration(Calibration(tuple(cameras), tuple({"fps": FPS} for _ in cameras)), tmp_path / "cameras.toml")
    for camera in cameras:
        save_tracks(tracks.of_camera(camera.name), tmp_path / f"{camera.name}.csv")
    paths = [str(tmp_path / f"{c.name}.csv") for c in cameras]
    out = tmp_path / "motion.csv"
    args = ["fit", "hitachi_ex3500", str(tmp_path / "cameras.toml"), *paths, "--out", str(out)]
    assert cli.main(args) == 0
    motion = load_motion(out, machine)
    assert len(motion) == len(time) and "filled" in motion.extra and "bucket_tip_speed" in motion.extra
    tip_error = np.linalg.norm(motion.point("bucket_tip") - machine.points(joints)[:, 0], axis=-1)
    assert np.sqrt(np.mean(tip_error**2)) < 3 * np.sqrt(np.mean(motion.points_sd[:, 0] ** 2))
    assert np.degrees(np.abs(motion.joints - joints)).max() < 1.0
    assert "frames written" in capsys.readouterr().out

    assert cli.main(args + ["--no-smooth", "--base-motion"]) == 0
    assert "filled" not in load_motion(out, machine).extra
    assert cli.main(["fit", "cube_pair", str(tmp_path / "cameras.toml"), *paths, "--out", str(out)]) == 2
    assert "not in the machine model" in capsys.readouterr().err
    assert cli.main(args + ["--loss-scale", "0"]) == 2
    assert "scale_px must be positive" in capsys.readouterr().err


def test_fit_with_base_motion_writes_and_recovers_the_bouncing_base(tmp_path):
    """A synthetic session whose base bounces (6-DoF): `mocap fit --base-motion` on its
    noisy true tracks with the true cameras writes the base pose with SDs, and the pose
    lies within a few SDs of the truth's, whose columns are the same."""
    root = tmp_path / "s"
    assert cli.main(["synth", "--machine", "bobcat_225", "--cycles", "1", "--seed", "5", "--bounce", "3",
                     "--out", str(root), "--no-video"]) == 0
    machine = load_machine("bobcat_225")
    truth = load_tracks([root / "truth" / "tracks.csv"])
    rng = np.random.default_rng(5)
    noisy = Tracks.from_rows(truth.camera, truth.frame, truth.marker, truth.xy + rng.normal(0, NOISE, truth.xy.shape), truth.time)
    save_tracks(noisy, tmp_path / "tracks.csv")
    out = tmp_path / "motion.csv"
    assert cli.main(["fit", "bobcat_225", str(root / "truth" / "cameras.toml"), str(tmp_path / "tracks.csv"),
                     "--out", str(out), "--base-motion", "--no-smooth"]) == 0
    fitted, expected = load_motion(out, machine), load_motion(root / "truth" / "motion.csv", machine)
    frames = np.searchsorted(expected.frame, fitted.frame)
    for name in ("base_x", "base_y", "base_z", "base_roll_deg", "base_pitch_deg", "base_yaw_deg"):
        sd = fitted.extra[name.replace("_deg", "_sd_deg") if name.endswith("_deg") else f"{name}_sd"]
        z = (fitted.extra[name] - expected.extra[name][frames]) / sd
        ok = np.isfinite(z)
        assert ok.mean() > 0.9 and np.sqrt(np.mean(z[ok] ** 2)) < 2.0, name
    assert np.ptp(expected.extra["base_pitch_deg"]) > 5 * np.median(fitted.extra["base_pitch_sd_deg"])


@pytest.mark.parametrize("bounce", [0.0, 1.0])
def test_fit_says_when_the_base_moves(tmp_path, capsys, bounce):
    """`mocap fit` fits the base per frame when a base pose per frame explains the fixed
    base's residuals (the synthetic base bounces), and says so, naming the noise each
    leaves: the moving base leaves the tracks' own noise, the fixed one more; the base's
    pitch comes out as the truth's. A still base stays fixed, as does one `--fixed-base` holds."""
    root = tmp_path / "s"
    assert cli.main(["synth", "--machine", "hitachi_ex3500", "--cycles", "1", "--seed", "7", "--bounce", str(bounce),
                     "--out", str(root), "--no-video"]) == 0
    truth = load_tracks([root / "truth" / "tracks.csv"])
    rng = np.random.default_rng(7)
    noisy = Tracks.from_rows(truth.camera, truth.frame, truth.marker, truth.xy + rng.normal(0, NOISE, truth.xy.shape), truth.time)
    save_tracks(noisy, tmp_path / "tracks.csv")
    capsys.readouterr()
    assert cli.main(["fit", "hitachi_ex3500", str(root / "truth" / "cameras.toml"), str(tmp_path / "tracks.csv"),
                     "--out", str(tmp_path / "motion.csv"), "--no-smooth"]) == 0
    said = re.search(r"the base moves: a base pose per frame leaves ([\d.]+) px of noise where the fixed "
                     r"base leaves ([\d.]+) px", capsys.readouterr().out)
    motion = load_motion(tmp_path / "motion.csv", load_machine("hitachi_ex3500"))
    if not bounce:
        assert said is None and "base_pitch_deg" not in motion.extra
        return
    assert said is not None
    moving, fixed = map(float, said.groups())
    assert moving < 1.1 * NOISE and fixed > 1.3 * moving  # resampling to the reference clock averages some noise away
    truth = load_motion(root / "truth" / "motion.csv", load_machine("hitachi_ex3500"))
    frames = np.searchsorted(truth.frame, motion.frame)
    z = (motion.extra["base_pitch_deg"] - truth.extra["base_pitch_deg"][frames]) / motion.extra["base_pitch_sd_deg"]
    assert np.sqrt(np.nanmean(z**2)) < 2.0  # the base fitted per frame, as the truth's
    assert np.ptp(truth.extra["base_pitch_deg"]) > 5 * np.nanmedian(motion.extra["base_pitch_sd_deg"])
    capsys.readouterr()
    assert cli.main(["fit", "hitachi_ex3500", str(root / "truth" / "cameras.toml"), str(tmp_path / "tracks.csv"),
                     "--out", str(tmp_path / "motion.csv"), "--no-smooth", "--fixed-base"]) == 0
    assert "base moves" not in capsys.readouterr().out
    assert "base_pitch_deg" not in load_motion(tmp_path / "motion.csv", load_machine("hitachi_ex3500")).extra


def test_fit_refuses_a_model_the_tracks_contradict(tmp_path, capsys):
    """A wrong machine model that shares the marker names (its markers moved around): the
    tracks lie far from any pose of it, and fit says so instead of writing a confident
    motion; the right model on the same tracks passes the same gate."""
    machine = load_machine("hitachi_ex3500")
    rng = np.random.default_rng(8)
    cameras = ring_of_cameras(2, np.array([5.0, 0.0, 5.0]), (30.0, 60.0), rng, fov_deg=(40.0, 60.0))
    time, joints = dig_like(machine, 2.0, rng)
    save_tracks(observe(cameras, machine, joints, rng, noise_px=NOISE), tmp_path / "tracks.csv")
    save_calibration(Calibration(tuple(cameras), tuple({"fps": FPS} for _ in cameras)), tmp_path / "cameras.toml")
    wrong = replace(machine, marker_positions=machine.marker_positions[rng.permutation(len(machine.marker_names))])
    save_machine(wrong, tmp_path / "wrong.toml")
    out = tmp_path / "motion.csv"
    args = [str(tmp_path / "cameras.toml"), str(tmp_path / "tracks.csv"), "--out", str(out)]
    assert cli.main(["fit", str(tmp_path / "wrong.toml"), *args]) == 2
    err = capsys.readouterr().err
    assert "do not match the tracks" in err and len(err.strip().splitlines()) == 1 and not out.exists()
    assert cli.main(["fit", "hitachi_ex3500", *args]) == 0 and out.exists()
    assert cli.main(["fit", "hitachi_ex3500", *args, "--max-noise-px", "0"]) == 2
