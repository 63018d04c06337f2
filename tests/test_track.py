"""Labelled tracking on drawn sequences: a calibrated camera, the machine moving inside its
joint limits, markers drawn as projected disks, clutter, dust and a passing occluder."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from mocap.cli import main
from mocap.core.calibration import Calibration, joints_to_table
from mocap.core.camera import project_cam
from mocap.core.tracks import Tracks
from mocap.core.visibility import visible_markers
from mocap.io.cameras_toml import save_calibration
from mocap.io.machine_toml import load_machine
from mocap.io.tracks_csv import load_tracks, save_tracks
from mocap.io.video import Video
from mocap.synthetic.scenes import look_at_camera
from mocap.tracking import CameraModel, TrackOptions, track_frames
from mocap.tracking.detect import detect_disks
from mocap.tracking.labels import labels_from_pixels
from mocap.tracking.tracker import assign
from test_detect import background, draw_clutter, draw_markers, finish

MARKER_RADIUS = 0.07  # m, on the Bobcat


def joint_path(machine, n_frames: int, rng: np.random.Generator, speed: float = 1.0) -> np.ndarray:
    """(F, J) smooth joint values inside the limits (the middle half of each range, swing ±30°)."""
    limits = np.degrees(machine.joint_limits)
    limits[0] = [-30, 30]
    middle, half = limits.mean(axis=1), 0.25 * np.ptp(limits, axis=1)
    t = np.arange(n_frames)[:, None] / 30.0
    freq = rng.uniform(0.2, 0.5, machine.n_joints) * speed
    phase = rng.uniform(0, 2 * np.pi, machine.n_joints)
    return np.radians(middle + half * np.sin(2 * np.pi * freq * t + phase))


def make_scene(n_frames=40, size=(800, 450), clutter=25, occluder=None, seed=0, speed=1.0):
    """Frames [(index, grey)], truth pixels (F, M, 2), truth visibility (F, M), the model and joints."""
    rng = np.random.default_rng(seed)
    machine = load_machine("bobcat_225")
    camera = look_at_camera("cam1", size, 0.95 * size[0], [5.5, -6.5, 2.8], [1.6, 0.0, 0.9])
    model = CameraModel(machine, camera)
    joints = joint_path(machine, n_frames, rng, speed)
    base = background(size, rng)
    frames, uvs, seen = [], [], []
    for f in range(n_frames):
        image = base.copy()
        draw_clutter(image, rng, clutter // 2)  # behind the machine
        visible = model.visible(joints[f : f + 1])[0]
        poses = machine.link_poses(joints[f : f + 1])[0]
        world = machine.markers(joints[f : f + 1])[0]
        normals = np.einsum("mij,mj->mi", poses[machine.marker_links, :3, :3], model.normals)
        uv = camera.project(world)
        draw_markers(image, camera, world[visible], normals[visible], MARKER_RADIUS)
        draw_clutter(image, rng, clutter - clutter // 2, radius=(1.0, 3.0))  # dust in front
        if occluder is not None and occluder[0] <= f < occluder[1]:
            x0 = int(0.2 * size[0] + (f - occluder[0]) * 12)
            image[:, x0 : x0 + 90] = 90.0
            visible &= ~((uv[:, 0] > x0 - 12) & (uv[:, 0] < x0 + 102))  # disk (partly) covered
        frames.append((f, finish(image, rng, blur=0.9, noise=2.5)))
        uvs.append(uv)
        seen.append(visible)
    return frames, np.array(uvs), np.array(seen), model, joints


def score(tracks: Tracks, model: CameraModel, truth_uv: np.ndarray, truth_seen: np.ndarray):
    """(labelled fraction of visible markers, wrong labels (2 px or more from the labelled
    marker's true place), centre errors (K,) px of the right ones)."""
    index = model.machine.marker_index(tracks.marker)
    error = np.linalg.norm(tracks.xy - truth_uv[tracks.frame, index], axis=1)
    right = error < 2.0
    return (right & truth_seen[tracks.frame, index]).sum() / truth_seen.sum(), int((~right).sum()), error[right]


def test_tracking_labels_visible_markers_among_clutter_and_dust():
    frames, uv, seen, model, joints = make_scene()
    start = joints[0] + np.radians([6, -5, 5, 8])
    tracks, summary = track_frames(model, frames, start, fps=30.0)
    labelled, wrong, error = score(tracks, model, uv, seen)
    assert summary.frames == len(frames) and summary.fitted == len(frames)
    assert labelled >= 0.97  # markers under a dust speck may be missed
    assert wrong == 0
    # noise 2.5 grey levels, contrast ~215, markers of 5-9 px radius
    assert np.median(error) < 0.05 and np.percentile(error, 95) < 0.15
    assert np.allclose(tracks.time, tracks.frame / 30.0)


def test_markers_come_back_after_an_occluder_passes():
    frames, uv, seen, model, joints = make_scene(n_frames=36, clutter=10, occluder=(8, 26), seed=1)
    tracks, _ = track_frames(model, frames, joints[0], fps=30.0)
    labelled, wrong, _ = score(tracks, model, uv, seen)
    assert wrong == 0 and labelled >= 0.97
    names = np.asarray(model.machine.marker_names)
    hidden_then_back = names[np.any(~seen[8:26] & seen[7], axis=0) & seen[27]]
    assert len(hidden_then_back) >= 3
    assert set(hidden_then_back) <= set(tracks.select(tracks.frame == 27).marker)


def test_tracking_holds_through_camera_shake():
    """The camera shaken by the wind: every frame shifted by up to 4 px (a smooth random
    walk), which the joints cannot explain; the shift is taken out before the fit."""
    frames, uv, seen, model, joints = make_scene(n_frames=30, clutter=10, seed=6)
    rng = np.random.default_rng(6)
    shift = np.clip(np.cumsum(rng.normal(0, 1.5, (len(frames), 2)), axis=0), -4, 4)
    for f, (index, gray) in enumerate(frames):
        warp = np.float32([[1, 0, shift[f, 0]], [0, 1, shift[f, 1]]])
        frames[f] = (index, cv2.warpAffine(gray, warp, gray.shape[::-1], flags=cv2.INTER_CUBIC,
                                           borderMode=cv2.BORDER_REPLICATE))
    uv = uv + shift[:, None]
    tracks, summary = track_frames(model, frames, joints[0], fps=30.0)
    labelled, wrong, error = score(tracks, model, uv, seen)
    assert summary.fitted == len(frames)
    assert wrong == 0 and labelled >= 0.97
    assert np.median(error) < 0.1  # the warp's cubic interpolation blurs a little


def test_markers_of_turning_links_are_kept_through_a_jolt():
    """The camera jolted 4 px every third frame and back the next: the first fit from the
    prediction takes part of the jolt for a turn of the links (the base's markers, fixed in
    the world, moved), and against it the markers of those links were disowned (before: 11 %
    of the markers unlabelled, all in the jolted frames); the joints are fitted again from the
    prediction once the shift is out."""
    frames, uv, seen, model, joints = make_scene(n_frames=16, clutter=10, seed=6)
    shift = np.zeros((len(frames), 2))
    shift[4::3] = [-4.0, -3.2]
    for f, (index, gray) in enumerate(frames):
        warp = np.float32([[1, 0, shift[f, 0]], [0, 1, shift[f, 1]]])
        frames[f] = (index, cv2.warpAffine(gray, warp, gray.shape[::-1], flags=cv2.INTER_CUBIC,
                                           borderMode=cv2.BORDER_REPLICATE))
    tracks, summary = track_frames(model, frames, joints[0], fps=30.0)
    labelled, wrong, error = score(tracks, model, uv + shift[:, None], seen)
    assert summary.fitted == len(frames)
    assert wrong == 0 and labelled >= 0.99
    assert np.median(error) < 0.1  # the warp's cubic interpolation blurs a little


def test_labels_from_rough_user_pixels():
    frames, uv, seen, model, joints = make_scene(n_frames=1, seed=2)
    rng = np.random.default_rng(5)
    given = np.where(seen[0][:, None], uv[0] + rng.uniform(-3, 3, uv[0].shape), np.nan)
    given[np.nonzero(seen[0])[0][::2]] = np.nan  # the user digitised every other marker
    found = detect_disks(frames[0][1])
    result = labels_from_pixels(model, found, given, model.machine.clip_to_limits(joints[0] + 0.2))
    names = np.asarray(model.machine.marker_names)
    assert set(names[result.markers]) == set(names[seen[0]])
    assert np.max(np.linalg.norm(result.detections.xy - uv[0, result.markers], axis=1)) < 0.15


def test_fit_recovers_joints_from_noisy_pixels():
    rng = np.random.default_rng(3)
    _, _, _, model, joints = make_scene(n_frames=5, clutter=0, seed=3)
    noise = 0.3
    pixels = model.pixels(joints) + rng.normal(0, noise, (5, len(model.machine.marker_names), 2))
    fitted, residual, _ = model.fit(pixels, joints + np.radians(4), iterations=10)
    # the joints' standard deviations from the pixel noise: noise * sqrt(diag((J^T J)^-1))
    _, jac = numpy_residuals(model, joints, np.zeros_like(pixels))
    information = np.einsum("fmaj,fmak->fjk", jac, jac)
    sd = noise * np.sqrt(np.diagonal(np.linalg.inv(information), axis1=1, axis2=2))
    assert np.all(np.abs(fitted - joints) < 4 * sd)
    assert np.sqrt(np.nanmean(residual**2)) < 2 * noise


def numpy_residuals(model: CameraModel, joints: np.ndarray, target: np.ndarray):
    """Residuals (F, M, 2) and their Jacobian (F, M, 2, J) by the vectorised numpy of the
    machine's and the camera's own functions (the reference for the compiled fit)."""
    markers, dmarkers = model.machine.markers_with_jacobian(joints)
    camera = model.camera
    uv, duv = project_cam(camera.cam_from_world.apply(markers), camera.matrix, camera.distortion, with_jacobian=True)
    return uv - target, (duv @ camera.cam_from_world.rotation) @ dmarkers


def numpy_fit(model: CameraModel, pixels, start, iterations=6, scale_px=2.0, prior_weight=1e-2):
    """`CameraModel.fit`'s robust Gauss-Newton in vectorised numpy."""
    start = np.broadcast_to(start, (len(pixels), model.machine.n_joints))
    observed = np.all(np.isfinite(pixels), axis=-1)
    target = np.where(observed[..., None], pixels, 0.0)
    joints = start.copy()
    for _ in range(iterations):
        residual, jac = numpy_residuals(model, joints, target)
        norm = np.linalg.norm(residual, axis=-1)
        weight = np.where(observed & np.isfinite(norm), np.minimum(1.0, scale_px / np.maximum(norm, 1e-12)), 0.0)
        residual = np.where(weight[..., None] > 0, residual, 0.0)
        jac = np.where(weight[..., None, None] > 0, jac, 0.0)
        normal = np.einsum("fm,fmaj,fmak->fjk", weight, jac, jac) + prior_weight * np.eye(model.machine.n_joints)
        gradient = np.einsum("fm,fmaj,fma->fj", weight, jac, residual) + prior_weight * (joints - start)
        joints = model.machine.clip_to_limits(joints - np.linalg.solve(normal, gradient[..., None])[..., 0])
    uv = model.camera.project(model.machine.markers(joints))
    return joints, np.where(observed, np.linalg.norm(uv - target, axis=-1), np.nan), uv


@pytest.mark.parametrize("distortion", [np.zeros(5), np.array([-0.12, 0.05, 0.002, -0.001, 0.01])])
def test_compiled_fit_is_the_numpy_fit(distortion):
    """The compiled fit and pixels give what numpy's vectorised kinematics, lens and normal
    equations give: markers missing, an outlier, a start far off, a distorting lens, and
    some markers behind the camera."""
    rng = np.random.default_rng(8)
    _, _, _, model, joints = make_scene(n_frames=6, clutter=0, seed=8)
    model = CameraModel(model.machine, replace(model.camera, distortion=distortion))
    truth = model.camera.project(model.machine.markers(joints))
    np.testing.assert_allclose(model.pixels(joints), truth, rtol=0, atol=1e-9)
    pixels = truth + rng.normal(0, 0.5, truth.shape)
    pixels[rng.random(pixels.shape[:2]) < 0.3] = np.nan
    pixels[1, 2] += 40.0  # an outlier the Huber weight takes down
    start = model.machine.clip_to_limits(joints + rng.normal(0, np.radians(8), joints.shape))
    # (behind the camera, the pinhole: a lens's polynomial far outside the picture is no lens)
    behind = replace(model.camera, distortion=np.zeros(5), cam_from_world=replace(
        model.camera.cam_from_world, translation=model.camera.cam_from_world.translation + [0, 0, -6.0]))
    for tested in (model, CameraModel(model.machine, behind)):
        if tested is not model:
            z = tested.camera.cam_from_world.apply(model.machine.markers(joints))[..., 2]
            assert np.any(z < 0) and np.any(z > 0)  # some markers behind the camera
            assert np.array_equal(np.isnan(tested.pixels(joints)[..., 0]), z <= 0)
        for iterations in (1, 8):
            got, want = tested.fit(pixels, start, iterations=iterations), numpy_fit(tested, pixels, start, iterations)
            for a, b in zip(got, want):
                np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9)


def numpy_view(model: CameraModel, joints: np.ndarray):
    """`CameraModel.view` by `mocap.core.visibility`'s vectorised numpy: pixels, seen, px per metre."""
    poses = model.machine.link_poses(joints)
    camera = model.camera
    cam_from_world = np.broadcast_to(camera.cam_from_world.matrix, (len(joints), 4, 4))
    uv, seen = visible_markers(model.machine, model.boxes, model.normals, poses, cam_from_world, camera.matrix,
                               camera.distortion, camera.size)
    on_link = poses[:, model.machine.marker_links]
    points_cam = camera.cam_from_world.apply(model.machine.markers(joints))
    if not model.solid:
        seen = (points_cam[..., 2] > 0) & np.all((uv >= -0.5) & (uv <= np.array(camera.size) - 0.5), axis=-1)
    normal_cam = np.einsum("ij,fmjk,mk->fmi", camera.cam_from_world.rotation, on_link[..., :3, :3], model.normals)
    facing = np.abs(np.einsum("fmi,fmi->fm", normal_cam, points_cam)) / np.linalg.norm(points_cam, axis=-1)
    facing = facing if model.solid else np.ones_like(facing)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(points_cam[..., 2] > 0, camera.focal / points_cam[..., 2], np.nan) * np.sqrt(facing)
    return uv, seen, scale


@pytest.mark.parametrize("solid", [True, False])
def test_compiled_view_is_the_numpy_view(solid):
    """The compiled view gives `mocap.core.visibility`'s pixels and hidden markers, and the same
    scale, over a machine's motion (markers turning away, hidden by links, leaving the
    picture), through a distorting lens."""
    rng = np.random.default_rng(9)
    _, _, _, model, _ = make_scene(n_frames=1, clutter=0, seed=9)
    camera = replace(model.camera, distortion=np.array([-0.12, 0.05, 0.002, -0.001, 0.01]))
    model = CameraModel(model.machine, camera, solid=solid)
    limits = model.machine.joint_limits.copy()
    limits[0] = [-np.pi, np.pi]
    joints = rng.uniform(limits[:, 0], limits[:, 1], (300, model.machine.n_joints))
    got, want = model.view(joints), numpy_view(model, joints)
    np.testing.assert_allclose(got.uv, want[0], rtol=0, atol=1e-9)
    assert np.array_equal(got.visible, want[1])
    np.testing.assert_allclose(got.scale, want[2], rtol=1e-12)
    if solid:  # some hidden by links and some turned away, not only outside the picture
        inside = np.all((want[0] >= 0) & (want[0] <= np.array(camera.size) - 1), axis=-1)
        assert 0.1 < np.mean(want[1][inside]) < 0.9


def test_centre_offsets_are_the_perspective_shift_of_each_disk():
    """The model's offset from each marker's image ellipse centre to the image of its disk's
    centre: the ellipse fitted to the projected rim, shifted by it, lands on the projected
    centre exactly."""
    from test_detect import _fit_conic, disk_frame

    _, _, _, model, joints = make_scene(n_frames=1, clutter=0, seed=4)
    machine, camera = model.machine, model.camera
    offsets = model.centre_offsets(joints[:1], MARKER_RADIUS)[0]
    poses = machine.link_poses(joints[:1])[0]
    world = machine.markers(joints[:1])[0]
    normals = np.einsum("mij,mj->mi", poses[machine.marker_links, :3, :3], model.normals)
    t = np.linspace(0, 2 * np.pi, 100, endpoint=False)
    shifts = []
    for m in np.flatnonzero(model.visible(joints[:1])[0]):
        e1, e2 = disk_frame(camera, world[m], normals[m], MARKER_RADIUS)
        outline = camera.project(world[m] + MARKER_RADIUS * (np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2))
        centre = _fit_conic(outline)[0]
        np.testing.assert_allclose(centre + offsets[m], camera.project(world[m]), atol=1e-6)
        shifts.append(np.linalg.norm(offsets[m]))
    assert max(shifts) > 0.01  # there is a shift to correct at this range


def test_assignment_is_optimal_and_gated():
    predicted = np.array([[0.0, 0.0], [3.0, 0.0], [100.0, 100.0]])
    detected = np.array([[2.0, 0.0], [5.0, 0.0], [300.0, 300.0]])
    markers, index = assign(predicted, detected, np.full(3, 4.0), np.ones(3, bool))
    # greedy would give marker 1 the detection at 2 and leave marker 0 alone
    assert dict(zip(markers.tolist(), index.tolist())) == {0: 0, 1: 1}
    markers, _ = assign(predicted, detected, np.full(3, 4.0), np.array([True, False, True]))
    assert markers.tolist() == [0]


def test_an_undetected_marker_does_not_pass_its_neighbours_on():
    """Markers in a row 60 px apart, the first not detected, a blob 60 px past the last:
    matching every marker would shift all three along (3 x 60²); leaving the first out
    costs one pair at its gate (100²), and the other two keep their own disks."""
    predicted = np.array([[0.0, 0.0], [60.0, 0.0], [120.0, 0.0]])
    detected = np.array([[60.0, 0.0], [120.0, 0.0], [180.0, 0.0]])
    markers, index = assign(predicted, detected, np.full(3, 100.0), np.ones(3, bool))
    assert dict(zip(markers.tolist(), index.tolist())) == {1: 0, 2: 1}
    # within a wider gate the shift is cheaper than a miss (3 x 60² < 110²) and is taken
    markers, index = assign(predicted, detected, np.full(3, 110.0), np.ones(3, bool))
    assert dict(zip(markers.tolist(), index.tolist())) == {0: 0, 1: 1, 2: 2}


def test_options_guards():
    with pytest.raises(ValueError, match="positive"):
        TrackOptions(gate_px=0)
    with pytest.raises(ValueError, match=">= 1"):
        TrackOptions(min_markers=0)


# --- the command line ------------------------------------------------------------------


def write_video(path: Path, frames, fps: float = 30.0, codec: str = "mp4v") -> None:
    h, w = frames[0][1].shape
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*codec), fps, (w, h))
    for _, gray in frames:
        writer.write(cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR))
    writer.release()


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    root = tmp_path_factory.mktemp("track")
    frames, uv, seen, model, joints = make_scene(n_frames=24, clutter=10, seed=4)
    write_video(root / "cam1.mp4", frames)
    calibration = Calibration(
        (model.camera,), ({"fps": 30.0},),
        {"machine": "bobcat_225", "frame": 0, "joints": joints_to_table(joints[0] + np.radians(3), model.machine)},
    )
    save_calibration(calibration, root / "cameras.toml")
    write_video(root / "cam1.avi", frames, codec="MJPG")
    return root, uv, seen, model


def _args(root: Path, *extra) -> list[str]:
    return ["track", str(root / "cam1.mp4"), "--machine", "bobcat_225", "--calibration",
            str(root / "cameras.toml"), "--camera", "cam1", *extra]


def test_cli_proposes_labels_then_tracks_from_them(session, capsys):
    root, uv, seen, model = session
    assert main(_args(root, "--propose-labels", str(root / "labels.csv"))) == 0
    assert "proposed labels of frame 0" in capsys.readouterr().out
    labels = load_tracks(root / "labels.csv")
    assert set(labels.frame) == {0} and set(labels.marker) == set(np.asarray(model.machine.marker_names)[seen[0]])
    assert main(_args(root, "--labels", str(root / "labels.csv"), "--out", str(root / "tracks.csv"))) == 0
    tracks = load_tracks(root / "tracks.csv")
    labelled, wrong, error = score(tracks, model, uv, seen)
    # the mp4v encoding blurs and rings: centres to a tenth of a pixel
    assert wrong == 0 and labelled >= 0.97 and np.median(error) < 0.15
    assert set(tracks.camera) == {"cam1"} and np.all(np.isfinite(tracks.score))


def test_cli_keeps_tracks_before_a_truncated_video(session, capsys):
    root, uv, seen, model = session
    data = (root / "cam1.avi").read_bytes()  # an AVI stays readable when cut short
    broken = root / "broken.avi"
    broken.write_bytes(data[: int(len(data) * 0.6)])
    info = Video(broken).info
    assert info.frame_count == len(uv)  # the header still says 24 frames
    args = _args(root, "--out", str(root / "broken.csv"))
    args[1] = str(broken)
    assert main(args) == 3  # partial: its own exit status
    out = capsys.readouterr()
    assert "the video broke at frame" in out.err
    tracks = load_tracks(root / "broken.csv")
    assert 0 < tracks.frame.max() < len(uv) - 1


def test_cli_errors_are_one_line(session, capsys, tmp_path):
    root, uv, seen, model = session
    assert main(_args(root, "--out", str(tmp_path / "t.csv"))[:7] + ["nope", "--out", str(tmp_path / "t.csv")]) == 2
    assert "no camera named 'nope'" in capsys.readouterr().err
    assert main(_args(root)) == 2
    assert "give --out" in capsys.readouterr().err
    labels = Tracks.from_rows(["cam1"], [5], ["U1"], [[10.0, 10.0]])
    save_tracks(labels, tmp_path / "late.csv")
    assert main(_args(root, "--labels", str(tmp_path / "late.csv"), "--out", str(tmp_path / "t.csv"))) == 2
    assert "pass --start" in capsys.readouterr().err
    save_tracks(Tracks.from_rows(["cam1"], [0], ["Z9"], [[10.0, 10.0]]), tmp_path / "bad.csv")
    assert main(_args(root, "--labels", str(tmp_path / "bad.csv"), "--out", str(tmp_path / "t.csv"))) == 2
    assert "not in the machine model: Z9" in capsys.readouterr().err
    small = tmp_path / "small.mp4"
    write_video(small, [(0, np.zeros((100, 120), np.uint8))] * 3)
    args = _args(root, "--out", str(tmp_path / "t.csv"))
    args[1] = str(small)
    assert main(args) == 2
    assert "calibrated at" in capsys.readouterr().err
    args[1] = str(tmp_path / "missing.mp4")
    assert main(args) == 2
    assert "video file not found" in capsys.readouterr().err
    assert not (tmp_path / "t.csv").exists()


def test_rendered_session_is_tracked_against_its_truth():
    from mocap.synthetic.render import CameraRenderer, RenderOptions
    from mocap.synthetic.session import make_session

    machine = load_machine("hitachi_ex3500")
    session = make_session(machine, "hitachi_ex3500", n_cameras=1, n_cycles=1, size=(960, 540), seed=3)
    renderer = CameraRenderer(session, 0, RenderOptions(), np.random.default_rng(0))
    frames = [(f, cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)) for f, image in renderer.frames(np.arange(70, 130))]
    camera = session.cameras[0].camera
    model = CameraModel(machine, camera)
    start = session.calibration.joints(machine)  # the joints at the calibration frame 0
    tracks, summary = track_frames(model, frames, start, fps=session.cameras[0].fps)
    truth = session.tracks.select((session.tracks.frame >= 70) & (session.tracks.frame < 130))
    true_xy = {(int(f), m): xy for f, m, xy in zip(truth.frame, truth.marker, truth.xy)}
    error = np.array([np.linalg.norm(xy - true_xy.get((int(f), m), np.inf)) for f, m, xy in zip(tracks.frame, tracks.marker, tracks.xy)])
    assert summary.fitted == len(frames)
    assert np.all(error < 2.0)  # no wrong labels
    # every marker is labelled but those seen at a grazing angle: a 0.3 m disk whose image is
    # under 3.5 px across its narrow axis (at half size) leaves too thin a white ring for the
    # detector's contrast and ring tests, and is missed
    joints = session.motion.joints[truth.frame]  # one camera: its frames are the reference's
    poses = machine.link_poses(joints)[:, machine.marker_links][np.arange(len(truth)), machine.marker_index(truth.marker)]
    world = np.einsum("nij,nj->ni", poses[:, :3, :3], machine.marker_positions[machine.marker_index(truth.marker)]) + poses[:, :3, 3]
    normal = np.einsum("nij,nj->ni", poses[:, :3, :3], model.normals[machine.marker_index(truth.marker)])
    to_camera = camera.center - world
    facing = np.einsum("ni,ni->n", normal, to_camera) / np.linalg.norm(to_camera, axis=1)
    labelled = set(zip(tracks.frame.tolist(), tracks.marker.tolist()))
    found = np.array([(int(f), m) in labelled for f, m in zip(truth.frame, truth.marker)])
    depth = camera.cam_from_world.apply(world)[:, 2]
    narrow_px = camera.focal * 0.3 * facing / depth
    assert np.mean(found[narrow_px >= 3.5]) >= 0.98
    # half-size pictures (not encoded) with motion blur, dust and noise 2.5 grey levels
    assert np.median(error) < 0.12 and np.percentile(error, 95) < 0.4


def test_markers_come_back_only_when_they_over_determine_their_unseen_joints():
    _, _, _, model, _ = make_scene(n_frames=1, clutter=0, seed=7)
    index = {name: i for i, name in enumerate(model.machine.marker_names)}
    base = [index[n] for n in ("U1", "U2", "U3", "H1", "H2")]  # they show the swing only
    k1, k2, a1, a2 = index["K1"], index["K2"], index["A1"], index["A2"]
    arm_held = base + [index["B1"], a2]  # boom and arm shown as well
    assert model.supported([k1], arm_held).tolist() == [False]  # the bucket joint unseen: one is not enough
    assert model.supported([k1, k2], arm_held).tolist() == [True, True]  # 4 coordinates, 1 joint
    assert model.supported([k1, k2], base).tolist() == [False, False]  # 4 coordinates, 3 joints: too loose
    assert model.supported([a1, a2, k1], base).tolist() == [True, True, True]  # 6 coordinates, 3 joints
    assert model.supported([k1], arm_held + [k2]).tolist() == [True]  # K2 held shows the bucket joint
    assert model.supported([index["U4"], a1], base).tolist() == [True, False]


def draw_tags(image, camera, centres, normals, ids, side: float, dictionary: str = "DICT_4X4_50") -> np.ndarray:
    """ArUco tags of `side` m (with a white margin) at `centres` (N, 3) facing `normals` (N,
    3) drawn into `image` by their plane's homography; returns the true centres (N, 2)."""
    from test_detect import disk_frame

    from mocap.tracking.detect import tag_dictionary

    tile_px = 60
    for centre, normal, tag_id in zip(centres, normals, ids):
        tile = cv2.aruco.generateImageMarker(tag_dictionary(dictionary), int(tag_id), tile_px).astype(np.float32)
        tile = cv2.copyMakeBorder(tile, 15, 15, 15, 15, cv2.BORDER_CONSTANT, value=235.0)
        tile = np.clip(tile, 20.0, 235.0)
        e1, e2 = disk_frame(camera, centre, normal, 1.0)
        half = 0.5 * side * tile.shape[0] / tile_px  # the margin around the tag
        corners = camera.project(centre + half * np.array([-e1 - e2, e1 - e2, e1 + e2, -e1 + e2]))
        right, down = corners[1] - corners[0], corners[3] - corners[0]
        if right[0] * down[1] - right[1] * down[0] < 0:  # seen from this side, printed the right way round
            corners = corners[[1, 0, 3, 2]]
        n = tile.shape[0]
        source = np.array([[0, 0], [n, 0], [n, n], [0, n]], np.float32) - 0.5
        homography = cv2.getPerspectiveTransform(source, corners.astype(np.float32))
        size = (image.shape[1], image.shape[0])
        warped = cv2.warpPerspective(tile, homography, size, flags=cv2.INTER_AREA)
        mask = cv2.warpPerspective(np.ones_like(tile), homography, size, flags=cv2.INTER_AREA)
        image[:] = image * (1 - mask) + warped
    return camera.project(np.asarray(centres, float))


def tag_scene(n_frames: int = 12, seed: int = 6):
    """The Bobcat with ArUco tags on its house, arm and bucket, disks elsewhere, drawn over
    `n_frames`: frames, true pixels (F, M, 2), visibility (F, M), the model, joints, tags (M,)."""
    rng = np.random.default_rng(seed)
    bobcat = load_machine("bobcat_225")
    tagged = np.isin(bobcat.marker_links, [bobcat.link_names.index(n) for n in ("house", "arm", "bucket")])
    tags = np.where(tagged, np.cumsum(tagged) - 1, -1)
    machine = replace(bobcat, marker_tags=tags, tag_dictionary="DICT_4X4_50")
    camera = look_at_camera("cam1", (800, 450), 0.95 * 800, [5.5, -6.5, 2.8], [1.6, 0.0, 0.9])
    model = CameraModel(machine, camera)
    joints = joint_path(machine, n_frames, rng)
    frames, truth_uv, truth_seen = [], [], []
    for f in range(len(joints)):
        image = background(camera.size, rng)
        visible = model.visible(joints[f : f + 1])[0]
        poses = machine.link_poses(joints[f : f + 1])[0]
        world = machine.markers(joints[f : f + 1])[0]
        normals = np.einsum("mij,mj->mi", poses[machine.marker_links, :3, :3], model.normals)
        disks, on_tags = visible & (tags < 0), visible & (tags >= 0)
        draw_markers(image, camera, world[disks], normals[disks], MARKER_RADIUS)
        draw_tags(image, camera, world[on_tags], normals[on_tags], tags[on_tags], 4 * MARKER_RADIUS)
        frames.append((f, finish(image, rng, blur=0.7, noise=2.0)))
        truth_uv.append(camera.project(world))
        truth_seen.append(visible)
    return frames, np.array(truth_uv), np.array(truth_seen), model, joints, tags


def test_tags_name_their_markers_and_label_the_first_frame():
    """The house, arm and bucket carry ArUco tags instead of disks: they are found by their
    ids in every frame, with centres to a fraction of a pixel, and they label the first
    frame from joint values far off, without digitised labels or a model search; the disks
    on the undercarriage and the boom are tracked."""
    frames, truth_uv, truth_seen, model, joints, tags = tag_scene()
    machine = model.machine
    far = machine.clip_to_limits(joints[0] + np.radians([35, -20, 25, 30]))  # the tags fix the joints
    tracks, summary = track_frames(model, frames, far, fps=30.0)
    index = machine.marker_index(tracks.marker)
    error = np.linalg.norm(tracks.xy - truth_uv[tracks.frame, index], axis=1)
    tagged_rows = tags[index] >= 0
    assert np.all(error < 2.0)  # no wrong labels
    # corners refined on the contours of tags of about 25 px, some seen at a slant
    assert np.median(error[tagged_rows]) < 0.2 and np.max(error[tagged_rows]) < 0.8
    assert np.all(tracks.score[tagged_rows] == 1.0)
    seen_tags = truth_seen & (tags >= 0)[None]
    assert np.sum(tagged_rows) == seen_tags.sum()  # every visible tag, every frame
    assert summary.fitted == len(frames)
    seen_disks = truth_seen & (tags < 0)[None]
    assert np.sum(~tagged_rows) >= 0.95 * seen_disks.sum()


def test_cli_tracks_a_machine_with_tags(tmp_path, capsys):
    """`mocap track` with a model whose markers carry tag ids: no labels file needed."""
    from mocap.io.machine_toml import save_machine

    frames, truth_uv, truth_seen, model, joints, tags = tag_scene(n_frames=8, seed=8)
    write_video(tmp_path / "cam1.mp4", frames)
    save_machine(model.machine, tmp_path / "tagged.toml")
    far = model.machine.clip_to_limits(joints[0] + np.radians([30, -15, 20, 25]))
    save_calibration(Calibration((model.camera,), ({"fps": 30.0},), {
        "machine": "tagged", "frame": 0, "joints": joints_to_table(far, model.machine)}), tmp_path / "cameras.toml")
    args = ["track", str(tmp_path / "cam1.mp4"), "--machine", str(tmp_path / "tagged.toml"), "--calibration",
            str(tmp_path / "cameras.toml"), "--camera", "cam1", "--out", str(tmp_path / "tracks.csv")]
    assert main(args) == 0
    assert "8 frames, 8 with a model fit" in capsys.readouterr().out
    tracks = load_tracks(tmp_path / "tracks.csv")
    index = model.machine.marker_index(tracks.marker)
    error = np.linalg.norm(tracks.xy - truth_uv[tracks.frame, index], axis=1)
    assert np.all(error < 2.0)  # no wrong labels (the mp4v encoding blurs the tags' corners)
    on_tags = tags[index] >= 0
    assert np.sum(on_tags) >= 0.9 * (truth_seen & (tags >= 0)[None]).sum() and np.median(error[on_tags]) < 0.3


def test_machine_found_again_within_a_second_after_it_was_hidden():
    """The whole machine hidden for 60 frames (a truck passing close to the camera) while it
    moves on: labelled again, rightly, at most 30 frames after it shows again."""
    frames, uv, seen, model, joints = make_scene(n_frames=110, clutter=10, seed=9, speed=0.6)
    hidden = range(20, 80)
    for f in hidden:
        frames[f] = (f, np.full_like(frames[f][1], 90))
    seen[hidden.start:hidden.stop] = False
    tracks, summary = track_frames(model, frames, joints[0], fps=30.0)
    labelled, wrong, _ = score(tracks, model, uv, seen)
    assert wrong == 0
    per_frame = np.bincount(tracks.frame, minlength=len(frames))
    back = hidden.stop + np.flatnonzero(per_frame[hidden.stop:] >= 5)[0]
    assert back - hidden.stop <= 30
    assert np.all(per_frame[hidden.stop + 30:] >= 0.9 * seen[hidden.stop + 30:].sum(axis=1))


def test_markers_in_view_but_never_found_are_named():
    frames, uv, seen, model, joints = make_scene(n_frames=16, clutter=5, seed=10)
    names = model.machine.marker_names
    gone = int(np.flatnonzero(seen.all(axis=0))[0])  # a marker in view throughout, its paint scraped off
    for f, gray in frames:
        cv2.circle(gray, tuple(int(v) for v in np.round(uv[f, gone])), 16, 120, -1)
    tracks, summary = track_frames(model, frames, joints[0], fps=30.0)
    assert summary.unplaced == (names[gone],)
    assert names[gone] not in set(tracks.marker)


def test_luma_stretch_is_the_exact_formula():
    """Every limited-range level, at a frame's width and at odd widths (the vector and the
    scalar paths), maps to round((v - 16) * 255 / 219), saturated."""
    from mocap.io.video import full_range

    exact = np.clip(np.round((np.arange(256) - 16) * 255 / 219), 0, 255).astype(np.uint8)
    rng = np.random.default_rng(0)
    for width in (1920, 1917, 7, 1):
        luma = rng.integers(0, 256, (9, width + 3), dtype=np.uint8)[:, :width]
        luma[0, : min(width, 256)] = np.arange(min(width, 256))
        assert np.array_equal(full_range(luma), exact[luma])
