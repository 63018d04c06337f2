"""Triangulation, the reference clock, and `mocap triangulate` end to end."""

from dataclasses import replace

import numpy as np
import pytest

from mocap import cli
from mocap.core.calibration import Calibration
from mocap.core.camera import Camera
from mocap.core.geometry import Rigid, rotvec_to_matrix
from mocap.core.tracks import Tracks
from mocap.io.cameras_toml import save_calibration
from mocap.io.machine_toml import load_machine
from mocap.io.points_csv import load_points
from mocap.io.tracks_csv import save_tracks
from mocap.reconstruct.outliers import track_outliers
from mocap.reconstruct.timing import resample, tracks_on_reference_clock
from mocap.reconstruct.triangulate import (
    TriangulateOptions, _solve, _solve_numpy, triangulate, triangulate_tracks, undistort,
)
from mocap.synthetic.machines import random_motion
from mocap.synthetic.scenes import observe, random_joints, ring_of_cameras

NOISE = 0.5


@pytest.fixture(scope="module")
def machine():
    return load_machine("hitachi_ex3500")


def rig(n_cameras, seed, distorted=True):
    rng = np.random.default_rng(seed)
    cameras = ring_of_cameras(n_cameras, np.array([5.0, 0.0, 5.0]), (30.0, 60.0), rng, fov_deg=(40.0, 60.0))
    if distorted:
        cameras = [replace(c, distortion=np.array([-0.08, 0.01, 0.0005, -0.0003, 0.0])) for c in cameras]
    return cameras, rng


def cramer_rao_mahalanobis(cameras, world, used, error):
    """error^T (J^T J / sigma^2) error per point, J the projection Jacobian at the truth."""
    from mocap.core.camera import project_cam

    info = np.zeros(world.shape[:-1] + (3, 3))
    for c, camera in enumerate(cameras):
        rot = camera.cam_from_world.rotation
        _, d_uv = project_cam(world @ rot.T + camera.cam_from_world.translation, camera.matrix, camera.distortion, True)
        jac = d_uv @ rot
        info += np.where(used[c][..., None, None], np.swapaxes(jac, -1, -2) @ jac, 0.0)
    return np.einsum("...i,...ij,...j->...", error, info / NOISE**2, error)


def test_exact_without_noise(machine):
    cameras, rng = rig(3, seed=1)
    world = machine.markers(random_joints(machine, 50, rng))
    pixels = np.stack([c.project(world) for c in cameras])
    result = triangulate(cameras, pixels)
    assert result.xyz.shape == world.shape and (result.views == 3).all()
    np.testing.assert_allclose(result.xyz, world, atol=1e-6)
    assert result.error_px.max() < 1e-6


def test_accuracy_matches_the_cramer_rao_bound(machine):
    cameras, rng = rig(4, seed=2)
    world = machine.markers(random_joints(machine, 200, rng))
    pixels = np.stack([c.project(world) for c in cameras]) + rng.normal(0, NOISE, (4,) + world.shape[:-1] + (2,))
    pixels[0, :100] = np.nan  # half the points in 3 views
    result = triangulate(cameras, pixels)
    d2 = cramer_rao_mahalanobis(cameras, world, result.used, result.xyz - world)
    assert np.mean(d2) == pytest.approx(3.0, rel=0.1)  # chi-square with 3 dof
    assert np.median(result.error_px) == pytest.approx(NOISE, rel=0.3)


def test_drops_a_wrong_view(machine):
    cameras, rng = rig(4, seed=3)
    joints = random_joints(machine, 300, rng)
    world = machine.markers(joints)
    tracks = observe(cameras, machine, joints, rng, noise_px=NOISE, outliers=500, outlier_px=(20.0, 60.0))
    pixels = tracks.dense([c.name for c in cameras], machine.marker_names, np.arange(300))
    clean = np.stack([c.project(world) for c in cameras])
    wrong = np.linalg.norm(pixels - clean, axis=-1) > 10.0
    result = triangulate(cameras, pixels, TriangulateOptions(max_error_px=4.0))
    one_wrong = (wrong.sum(0) == 1) & (np.isfinite(pixels[..., 0]).sum(0) == 4)
    assert one_wrong.sum() > 300
    assert (result.used & wrong)[:, one_wrong].sum() == 0  # every wrong view was dropped
    assert (result.views[one_wrong] == 3).all()
    d2 = cramer_rao_mahalanobis(cameras, world, result.used, result.xyz - world)
    assert np.mean(d2[one_wrong]) < 3.6


def wide_rig(seed):
    """Three cameras 50-100 degrees apart (two opposite cameras alone would leave a
    point's depth, and so a track's prediction, too vague to tell a wild view)."""
    rng = np.random.default_rng(seed)
    return ring_of_cameras(3, np.array([5.0, 0.0, 5.0]), (30.0, 60.0), rng, fov_deg=(40.0, 60.0), spread_deg=100.0), rng


def wild_along_epipolar_lines(cameras, world, pixels, frames, rng):
    """Put a wild pixel into one camera at each of `frames`, a random marker's, along the
    epipolar line of another camera's (noise-free) pixel, the wild camera's track with a
    gap around it; every other frame's third view hidden. Returns (wild (C, F, M), marker
    of each frame, whether only two views see it)."""
    n_cams = len(cameras)
    marks = rng.integers(0, world.shape[1], len(frames))
    wild_cam = rng.integers(0, n_cams, len(frames))
    other = (wild_cam + rng.integers(1, n_cams, len(frames))) % n_cams
    two_views = np.arange(len(frames)) % 2 == 0
    for f, m, a, b, two in zip(frames, marks, wild_cam, other, two_views):
        ray = world[f, m] - cameras[b].center
        moved = world[f, m] + rng.choice([-1, 1]) * rng.uniform(1.0, 3.0) * ray / np.linalg.norm(ray)
        pixels[a, f, m] = cameras[a].project(moved[None])[0]
        pixels[b, f, m] = cameras[b].project(world[f, m][None])[0]  # the two agree exactly
        pixels[a, [f - 1, f + 1, f - 3, f + 3], m] = np.nan  # the wild camera's track has a gap around it
        if two:
            pixels[3 - a - b, f, m] = np.nan
    wild = np.zeros(pixels.shape[:3], bool)
    wild[wild_cam, frames, marks] = True
    return wild, marks, two_views


def test_a_wild_view_that_one_frame_cannot_tell_is_dropped_by_the_track(machine):
    """A wild pixel along the epipolar line of another view: with that view alone the two
    agree exactly, with a third leave-one-out may drop the good third. The camera's own
    track has a gap around it (no 2-D judgement); the marker's 3-D track tells."""
    cameras, rng = wide_rig(8)
    n_frames = 90
    world = machine.markers(random_motion(machine, n_frames, rng))
    pixels = np.stack([c.project(world) for c in cameras]) + rng.normal(0, NOISE, (3,) + world.shape[:-1] + (2,))
    frames = rng.choice(np.arange(4, n_frames - 4, 3), 24, replace=False)
    wild, marks, two_views = wild_along_epipolar_lines(cameras, world, pixels, frames, rng)
    assert not any(track_outliers(pixels[c])[wild[c]].any() for c in range(3))  # its 2-D track cannot tell

    alone = triangulate(cameras, pixels)
    assert (alone.used & wild).any(0)[frames[two_views], marks[two_views]].all()  # per frame: kept
    result = triangulate_tracks(cameras, pixels)
    assert not (result.used & wild).any()
    assert not (alone.used & ~result.used & ~wild).any()  # no good view dropped
    assert np.isnan(result.xyz[frames[two_views], marks[two_views]]).all()  # one good view left: no point
    three = frames[~two_views], marks[~two_views]
    assert (result.views[three] == 2).all()
    assert (alone.used & wild).any(0)[three].sum() >= 3  # leave-one-out dropped a good view there
    assert result.contradicted.sum() == (alone.used & wild).sum()
    solved = np.isfinite(result.xyz[..., 0])
    d2 = cramer_rao_mahalanobis(cameras, world, result.used, np.nan_to_num(result.xyz - world))[solved]
    assert np.mean(d2) < 3.5  # chi-square with 3 dof: at the bound


def test_cli_triangulates_in_chunks_as_in_one(tmp_path, machine, monkeypatch, capsys):
    """`mocap triangulate` asks the tracks chunk by chunk; each chunk brings the frames its
    edges' predictions need, so that the points are those of one call over all frames."""
    from mocap.reconstruct import stage

    cameras, rng = wide_rig(9)
    world = machine.markers(random_motion(machine, 40, rng))
    pixels = np.stack([c.project(world) for c in cameras]) + rng.normal(0, NOISE, (3,) + world.shape[:-1] + (2,))
    wild, _, _ = wild_along_epipolar_lines(cameras, world, pixels, np.array([6, 7, 13, 14, 20, 27, 28, 34]), rng)
    c, f, m = np.nonzero(np.isfinite(pixels[..., 0]))
    names = np.array([cam.name for cam in cameras])
    tracks = Tracks.from_rows(names[c], f, np.array(machine.marker_names)[m], pixels[c, f, m])
    save_calibration(Calibration(tuple(cameras), tuple({"fps": 30.0, "time_offset": 0.0} for _ in cameras)),
                     tmp_path / "cameras.toml")
    save_tracks(tracks, tmp_path / "tracks.csv")
    monkeypatch.setattr(stage, "_CHUNK_FRAMES", 7)  # wild pixels at the chunks' first and last frames
    out = tmp_path / "points.csv"
    assert cli.main(["triangulate", str(tmp_path / "cameras.toml"), str(tmp_path / "tracks.csv"), "--out", str(out)]) == 0
    points = load_points(out)
    clock = tracks_on_reference_clock(tracks, names, machine.marker_names, np.full(3, 30.0), np.zeros(3))
    whole = triangulate_tracks(cameras, clock.pixels)
    f, m = np.nonzero(np.isfinite(whole.xyz[..., 0]))
    assert len(points) == len(f) and whole.contradicted.sum() == wild.sum()
    np.testing.assert_allclose(points.xyz, whole.xyz[f, m], atol=1e-4)  # the chunks' noise estimates differ a little
    assert f"; {wild.sum()} view(s) dropped that the markers' 3-D tracks contradict" in capsys.readouterr().out


@pytest.mark.parametrize("distorted", [True, False])
def test_compiled_solve_equals_its_numpy_statement(machine, distorted):
    cameras, rng = rig(4, seed=6, distorted=distorted)
    world = machine.markers(random_joints(machine, 40, rng)).reshape(-1, 3)
    world[:5] = cameras[1].center + (cameras[1].center - world[:5])  # behind camera 1
    pixels = np.stack([c.project(world) for c in cameras]) + rng.normal(0, NOISE, (4, len(world), 2))
    pixels[:, :5][1] = rng.uniform(0, 500, (5, 2))  # camera 1 claims to see them anyway
    pixels[rng.random(pixels.shape[:2]) < 0.2] = np.nan
    used = np.isfinite(pixels).all(-1) & (rng.random(pixels.shape[:2]) < 0.9)
    keep = used.sum(0) >= 2  # as triangulate solves (one view leaves the point undetermined)
    pixels, used, world = pixels[:, keep], used[:, keep], world[keep]
    normalised = undistort(cameras, pixels)
    start = world + rng.normal(0, 0.05, world.shape)
    for iterations, begin in [(0, None), (2, None), (3, start)]:
        compiled = _solve(cameras, pixels, normalised, used, iterations, start=begin)
        statement = _solve_numpy(cameras, pixels, normalised, used, iterations, start=begin)
        for a, b in zip(compiled, statement):
            assert np.array_equal(np.isnan(a), np.isnan(b))
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9)
    assert np.isnan(statement[2][:5]).any()  # the points behind a camera were covered


def test_unseen_points_are_nan():
    cameras, _ = rig(2, seed=4)
    pixels = np.stack([c.project(np.array([[[1.0, 2.0, 3.0], [4.0, 1.0, 2.0]]])) for c in cameras])
    pixels[1, 0, 1] = np.nan
    result = triangulate(cameras, pixels)
    assert np.isfinite(result.xyz[0, 0]).all() and np.isnan(result.xyz[0, 1]).all()
    assert result.views.tolist() == [[2, 1]]


def test_guards():
    cameras, _ = rig(2, seed=5)
    with pytest.raises(ValueError, match="pixels must have shape"):
        triangulate(cameras, np.zeros((3, 4, 2)))
    with pytest.raises(ValueError, match="min_views >= 2"):
        TriangulateOptions(min_views=1)
    with pytest.raises(ValueError, match="fps must be positive"):
        resample([np.zeros((2, 1, 2))], np.array([0]), np.array([0.0]), np.array([0.0]))


def test_resampling_interpolates_and_never_extrapolates():
    # a marker moving linearly in camera 1 (25 fps, 0.1 s late); the reference runs at 30 fps
    frames_1 = np.arange(0, 50)
    time_1 = frames_1 / 25.0 + 0.1
    track_1 = np.stack([10 * time_1, -3 * time_1], -1)[:, None, :]
    track_1[20:23] = np.nan  # a gap
    reference = np.full((60, 1, 2), 1.0)
    out = resample([reference, track_1], np.array([0, 0]), np.array([30.0, 25.0]), np.array([0.0, 0.1]))
    t = out.time
    inside = (t >= time_1[0]) & (t <= time_1[-1])
    gap = (t > time_1[19]) & (t < time_1[23])
    expected = np.stack([10 * t, -3 * t], -1)
    ok = inside & ~gap
    np.testing.assert_allclose(out.pixels[1, ok, 0], expected[ok], atol=1e-9)
    assert np.isnan(out.pixels[1, ~inside | gap]).all()
    assert out.frame[0] == 0 and out.frame[-1] == 61  # camera 1 runs until 49 / 25 + 0.1 = 2.06 s


def test_tracks_on_the_reference_clock_take_exact_frames():
    tracks = Tracks.from_rows(["a", "a", "b"], [0, 1, 1], ["m", "m", "m"], [[1, 2], [3, 4], [5, 6]])
    out = tracks_on_reference_clock(tracks, ["a", "b"], ["m"], np.array([30.0, 30.0]), np.zeros(2))
    assert out.frame.tolist() == [0, 1]
    assert out.pixels[1, 1, 0].tolist() == [5.0, 6.0] and np.isnan(out.pixels[1, 0]).all()


def test_cli_triangulate(tmp_path, machine, capsys):
    cameras, rng = rig(3, seed=6)
    joints = random_joints(machine, 20, rng)
    tracks = observe(cameras, machine, joints, rng, noise_px=NOISE)
    calibration = Calibration(tuple(cameras), tuple({"fps": 30.0, "time_offset": 0.0} for _ in cameras))
    save_calibration(calibration, tmp_path / "cameras.toml")
    for camera in cameras:
        save_tracks(tracks.of_camera(camera.name), tmp_path / f"{camera.name}.csv")
    paths = [str(tmp_path / f"{c.name}.csv") for c in cameras]
    out = tmp_path / "points.csv"
    assert cli.main(["triangulate", str(tmp_path / "cameras.toml"), *paths, "--out", str(out)]) == 0
    points = load_points(out)
    world = machine.markers(joints)
    truth = world[points.frame, machine.marker_index(points.marker)]
    seen_twice = (np.isfinite(tracks.dense([c.name for c in cameras], machine.marker_names, np.arange(20))[..., 0]).sum(0) >= 2)
    assert len(points) == seen_twice.sum() > 0.9 * seen_twice.size
    assert np.sqrt(np.mean(np.sum((points.xyz - truth) ** 2, -1))) < 0.05
    assert "points in 20 frames" in capsys.readouterr().out

    save_tracks(Tracks.from_rows(["nope"], [0], ["U1"], [[1.0, 2.0]]), tmp_path / "bad.csv")
    code = cli.main(["triangulate", str(tmp_path / "cameras.toml"), str(tmp_path / "bad.csv"), "--out", str(out)])
    assert code == 2
    assert "lacks" in capsys.readouterr().err and load_points(out).frame.size == len(points)
    code = cli.main(["triangulate", str(tmp_path / "cameras.toml"), paths[0], "--out", str(tmp_path / "one.csv")])
    assert code == 2 and "no marker is seen by two cameras" in capsys.readouterr().err
    assert not (tmp_path / "one.csv").exists()


def test_cli_refuses_views_that_disagree(tmp_path, machine, capsys):
    """A calibration whose second camera is turned by 3 degrees about two axes: its views and the first
    camera's disagree far beyond any pixel noise, and triangulate says so."""
    cameras, rng = rig(2, seed=9)
    joints = random_joints(machine, 10, rng)
    tracks = observe(cameras, machine, joints, rng, noise_px=NOISE)
    turned = Rigid(rotvec_to_matrix(np.radians([3.0, 0.0, 3.0])) @ cameras[1].cam_from_world.rotation,
                   cameras[1].cam_from_world.translation)
    wrong = [cameras[0], Camera(cameras[1].name, cameras[1].size, cameras[1].matrix, cameras[1].distortion, turned)]
    save_calibration(Calibration(tuple(wrong), tuple({"fps": 30.0} for _ in wrong)), tmp_path / "cameras.toml")
    save_tracks(tracks, tmp_path / "tracks.csv")
    out = tmp_path / "points.csv"
    assert cli.main(["triangulate", str(tmp_path / "cameras.toml"), str(tmp_path / "tracks.csv"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "disagree" in err and len(err.strip().splitlines()) == 1 and not out.exists()


def _biased_and_turned(machine, seed):
    """3 cameras watching a moving machine: the tracks with 0.5 px of noise; the same with
    3 px of noise and each camera's view of each marker off by its own fixed 10 px (points
    that are not one physical point in every view, as a body's keypoints are: they jitter
    as well); the calibration, and one with a camera turned by 4 degrees."""
    cameras, rng = rig(3, seed=seed)
    joints = random_motion(machine, 60, rng)
    tracks = observe(cameras, machine, joints, rng, noise_px=NOISE)
    jittery = observe(cameras, machine, joints, rng, noise_px=3.0)
    bias = {(c.name, m): rng.normal(0.0, 10.0, 2) for c in cameras for m in machine.marker_names}
    biased = Tracks(jittery.camera, jittery.frame, jittery.marker,
                    jittery.xy + np.array([bias[c, m] for c, m in zip(jittery.camera, jittery.marker)]),
                    jittery.time, jittery.score)
    turned = Rigid(rotvec_to_matrix(np.radians([4.0, 0.0, 4.0])) @ cameras[1].cam_from_world.rotation,
                   cameras[1].cam_from_world.translation)
    wrong = list(cameras)
    wrong[1] = replace(cameras[1], cam_from_world=turned)
    extras = tuple({"fps": 30.0, "time_offset": 0.0} for _ in cameras)
    return tracks, biased, Calibration(tuple(cameras), extras), Calibration(tuple(wrong), extras)


def test_views_that_disagree_in_no_camera_s_way_are_written_a_turned_camera_refused(machine):
    """The views' disagreement is judged by the data, not by a fixed pixel limit: markers
    that jitter by 3 px and that each view places 10 px off in its own way (beyond the 5 px
    prior) are triangulated, their disagreement named in the report; a camera turned by
    4 degrees, whose disagreement moving it explains, is refused with its name, and so are
    cameras swapped; 0.5 px tracks whose views disagree 10 times beyond their own noise where no
    camera's move explains it (one camera's labels shuffled) are refused as well; an explicit
    limit is the user's, in place of these checks."""
    from mocap.errors import InputError
    from mocap.reconstruct.stage import MAX_NOISE_PX
    from mocap.reconstruct.stage import triangulate as triangulate_stage

    tracks, biased, right, wrong = _biased_and_turned(machine, seed=3)
    result = triangulate_stage(right, biased)
    assert result.noise_px > 2 * MAX_NOISE_PX and "the views disagree by" in result.report(None)
    assert len(result.points) > 0.9 * 60 * len(machine.marker_names)
    with pytest.raises(InputError, match=r"moving camera cam2 \(\d+ %\)"):
        triangulate_stage(wrong, tracks)
    assert triangulate_stage(right, tracks).noise_px < 2 * NOISE  # the same tracks, the right cameras
    swapped = list(right.cameras)
    swapped[0], swapped[2] = (replace(swapped[0], cam_from_world=swapped[2].cam_from_world),
                              replace(swapped[2], cam_from_world=swapped[0].cam_from_world))
    with pytest.raises(InputError, match="not match the tracks"):
        triangulate_stage(replace(right, cameras=tuple(swapped)), tracks)
    names = list(machine.marker_names)
    relabel = dict(zip(names, np.random.default_rng(0).permutation(names)))  # cam2's labels shuffled
    marker = np.array([relabel[m] if c == "cam2" else m for c, m in zip(tracks.camera, tracks.marker)], dtype=object)
    with pytest.raises(InputError, match=r"\d+ times the noise the tracks show by themselves"):
        triangulate_stage(right, Tracks(tracks.camera, tracks.frame, marker, tracks.xy, tracks.time, tracks.score))
    with pytest.raises(InputError, match="beyond --max-noise-px 1"):
        triangulate_stage(right, biased, max_noise_px=1.0)
