"""Synthetic sessions: dig plans, inverse kinematics, cameras' clocks, visibility, truth files."""

from __future__ import annotations

import numpy as np
import pytest

from mocap.cli import main
from mocap.core.ik import PlanarChain
from mocap.core.shapes import link_boxes
from mocap.core.visibility import marker_normals, segment_hits_box
from mocap.errors import InputError
from mocap.io.cameras_toml import load_calibration
from mocap.io.machine_toml import MACHINES_DIR, load_machine
from mocap.io.motion_csv import load_motion, world_from_base_of
from mocap.io.points_csv import load_points
from mocap.io.session_toml import load_session_config
from mocap.io.tracks_csv import load_tracks
from mocap.synthetic import SessionOptions, make_session
from mocap.synthetic.motion import check_limits, plan_session
from mocap.synthetic.paths import min_jerk
from mocap.synthetic.scenes import random_joints

MACHINES = ("hitachi_ex3500", "bobcat_225")


@pytest.fixture(scope="module")
def ex3500():
    return load_machine("hitachi_ex3500")


@pytest.fixture(scope="module")
def session(ex3500):
    """One dig cycle of three cameras: the checks on it are per frame, and a cycle swings the
    machine through dig, dump and return (the hold before it, the base's bounce after)."""
    return make_session(ex3500, "hitachi_ex3500", n_cameras=3, n_cycles=1, seed=11)


def house_plane(machine, joints, chain):
    """Bucket tip (F, 2) in the house's x-z plane and bucket angle (F,), by forward kinematics."""
    tip = machine.points(joints)[:, machine.point_names.index("bucket_tip")]
    swing = joints[:, chain.swing]
    x = np.cos(swing) * tip[:, 0] + np.sin(swing) * tip[:, 1]
    return np.stack([x, tip[:, 2]], axis=-1), machine.bucket_angles(joints)


@pytest.mark.parametrize("name", MACHINES)
def test_ik_inverts_forward_kinematics(name):
    machine = load_machine(name)
    chain = PlanarChain.from_machine(machine)
    joints = random_joints(machine, 200, np.random.default_rng(1))
    tip, angle = house_plane(machine, joints, chain)
    back = chain.inverse(tip - [0.0, chain.house_height], angle, joints[:, chain.swing])
    np.testing.assert_allclose(back, joints, atol=1e-9)


def check_reached(machine, chain, plan, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The plan's joints and tip at times t, checked: inside the limits, and forward
    kinematics puts the tip on the planned path at the planned bucket angle."""
    joints = plan.joints(t)
    check_limits(machine, joints)
    planned = plan.tip_plan(t)
    tip, angle = house_plane(machine, joints, chain)
    np.testing.assert_allclose(tip, planned[:, :2], atol=1e-9)
    np.testing.assert_allclose(angle, planned[:, 2], atol=1e-9)
    return joints, tip


@pytest.mark.parametrize("name, top_speed_deg", [("hitachi_ex3500", 100.0), ("bobcat_225", 150.0)])
def test_planned_digs_are_reached_within_limits(name, top_speed_deg):
    machine = load_machine(name)
    chain = PlanarChain.from_machine(machine)
    for seed in range(4):
        plan = plan_session(machine, 4, np.random.default_rng(seed), bounce=0.0)
        t = np.arange(0.0, plan.duration, 0.05)
        joints, _ = check_reached(machine, chain, plan, t)
        np.testing.assert_allclose(joints[:, chain.swing], plan.swing(t), atol=1e-12)
        # smooth: no joint turns faster than a machine of its size does
        assert np.abs(np.diff(joints, axis=0)).max() / 0.05 < np.radians(top_speed_deg)


def dig_of(plan, machine, label, fps=100.0):
    """(arc fraction, bucket angle deg, tip (T, 2)) of the first dig of class `label`, by FK."""
    chain = PlanarChain.from_machine(machine)
    cycle = next(c for c in plan.cycles if c.label == label)
    t = np.arange(cycle.dig_start, cycle.dig_end, 1.0 / fps)
    tip, angle = house_plane(machine, plan.joints(t), chain)
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(tip, axis=0), axis=1))]
    return arc / arc[-1], np.degrees(angle), tip


@pytest.mark.parametrize("seed", [0, 1])
def test_dig_classes_have_their_bucket_angle_signatures(ex3500, seed):
    plan = plan_session(ex3500, 3, np.random.default_rng(seed), redirect_probability=0.0, reactive=0.0, bounce=0.0)
    reach = float(np.linalg.norm(PlanarChain.from_machine(ex3500).offsets, axis=1).sum())
    assert sorted(c.label for c in plan.cycles) == ["Type 1", "Type 2", "Type 3"]

    s, angle, tip = dig_of(plan, ex3500, "Type 1")
    assert angle[0] < -20.0  # significantly negative
    assert 0.3 < s[np.argmax(angle >= 0)] < 0.6  # negative for up to about half the arc
    early = s < 0.2
    assert np.ptp(tip[early, 1]) < 0.02 * reach  # pushed nearly horizontally along the floor
    assert tip[0, 1] < 0.05 * reach  # at the base of the pile
    linear = np.interp(s, [0, 1], [angle[0], angle[-1]])
    assert np.abs(angle - linear).max() < 0.1 * (angle[-1] - angle[0])  # about linear in arc length

    s, angle, tip = dig_of(plan, ex3500, "Type 2")
    rise = angle[-1] - angle[0]
    assert abs(angle[0]) < 6.0 and tip[0, 1] < 0.06 * reach
    assert angle[np.searchsorted(s, 0.6)] - angle[0] < 0.25 * rise  # rises sharply near the end
    assert rise > 30.0

    s, angle, tip = dig_of(plan, ex3500, "Type 3")
    rise = angle[-1] - angle[0]
    assert abs(angle[0]) < 6.0
    assert tip[0, 1] > 0.3 * plan.pile.height  # midway up the pile
    direction = np.degrees(np.arctan2(*(tip[-1] - tip[0])[::-1]))
    assert abs(direction - np.degrees(plan.pile.slope)) < 8.0  # roughly parallel to the face
    half = angle[np.searchsorted(s, 0.5)] - angle[0]
    assert 0.2 * rise < half < 0.5 * rise  # about linear, steeper near the end


def test_deviations_are_recorded_and_change_the_dig(ex3500):
    rng_seed = 5
    smooth = plan_session(ex3500, 3, np.random.default_rng(rng_seed), redirect_probability=0.0, reactive=0.0)
    redirected = plan_session(ex3500, 3, np.random.default_rng(rng_seed), redirect_probability=1.0, reactive=0.0)
    assert all(c.redirection in ("temporary", "kept") for c in redirected.cycles)
    assert all(c.redirection == "none" for c in smooth.cycles)
    for c in redirected.cycles:
        if c.scaling == "proportional":
            assert c.scale[0] == c.scale[1]
        else:
            assert abs(c.scale[0] - c.scale[1]) > 0.05


def test_same_seed_same_truth(ex3500):
    small = dict(n_cameras=2, n_cycles=1, fps=5.0)  # any session will do: a small one, to stay quick
    first = make_session(ex3500, "hitachi_ex3500", seed=11, **small)
    again = make_session(ex3500, "hitachi_ex3500", seed=11, **small)
    np.testing.assert_array_equal(again.tracks.xy, first.tracks.xy)
    np.testing.assert_array_equal(again.motion.joints, first.motion.joints)
    other = make_session(ex3500, "hitachi_ex3500", seed=12, **small)
    assert other.motion.joints.shape != first.motion.joints.shape or not np.allclose(
        other.motion.joints, first.motion.joints
    )


def test_clocks_and_calibration_hold(session):
    reference = session.cameras[0]
    assert reference.time_offset == 0.0 and session.motion.frame[0] == 0
    np.testing.assert_allclose(session.motion.time, session.motion.frame / reference.fps)
    for camera in session.cameras:
        rows = session.tracks.of_camera(camera.name)
        np.testing.assert_allclose(rows.time, rows.frame / camera.fps + camera.time_offset, atol=1e-12)
        assert camera.times()[-1] >= session.plan.duration - 1.0 / camera.fps
        assert 20.0 <= np.linalg.norm(camera.camera.center[:2]) <= 80.0  # an EX3500 crew's distances
    still = session.motion.time < session.options.hold
    assert still.sum() >= 50
    np.testing.assert_array_equal(session.motion.joints[still], np.repeat(session.motion.joints[:1], still.sum(), 0))
    assert np.all(session.motion.extra["base_z"][still] == 0.0) and np.all(session.motion.extra["base_pitch_deg"][still] == 0.0)
    assert np.ptp(session.motion.extra["base_z"]) > 0  # the base bounces later


def test_truth_pixels_are_projections_of_visible_markers(session):
    for camera in session.cameras:
        rows = session.tracks.of_camera(camera.name)
        frames = np.unique(rows.frame)[::97]
        uv, seen, _ = session.observe(camera, frames)
        dense = rows.dense([camera.name], session.machine.marker_names, frames)[0]
        np.testing.assert_array_equal(np.isfinite(dense[..., 0]), seen)
        np.testing.assert_allclose(dense[seen], uv[seen], atol=1e-9)
        w, h = camera.camera.size
        assert np.all((rows.xy >= 0) & (rows.xy <= [w - 1, h - 1]))
    assert session.views.max() >= 2 and session.views.mean() > 0.5


def test_truth_motion_pushed_through_the_model_gives_the_truth_pixels(session):
    """The truth motion's columns alone (joints and the base's full pose) reproduce every
    true pixel: nothing of the base's bounce is left out of the motion CSV."""
    motion = session.motion
    base = world_from_base_of(motion.extra, len(motion))
    assert {"base_x", "base_y", "base_z", "base_roll_deg", "base_pitch_deg", "base_yaw_deg"} <= set(motion.extra)
    assert np.ptp(motion.extra["base_pitch_deg"]) > 0 and np.ptp(motion.extra["base_roll_deg"]) > 0
    camera = session.cameras[0]  # the reference clock: its frames are the motion's frames
    rows = session.tracks.of_camera(camera.name)
    frames = np.unique(rows.frame)[::37]
    world = session.machine.markers(motion.joints[frames], base[frames])
    uv = camera.camera.project(world)
    dense = rows.dense([camera.name], session.machine.marker_names, frames)[0]
    seen = np.isfinite(dense[..., 0])
    np.testing.assert_allclose(dense[seen], uv[seen], atol=1e-6)


def test_segment_box_test_agrees_with_sampling():
    rng = np.random.default_rng(3)
    box = np.array([[-1.0, -0.5, -0.2], [1.0, 0.5, 0.2]])
    start = rng.uniform(-2, 2, (4000, 3))
    end = rng.uniform(-2, 2, (4000, 3))
    hits = segment_hits_box(start, end, box)
    s = np.linspace(0, 1, 2001)[:, None, None]
    samples = start + s * (end - start)
    sampled = np.any(np.all((samples >= box[0]) & (samples <= box[1]), axis=-1), axis=0)
    # sampling can only miss a grazing hit shorter than one step
    assert np.all(hits[sampled])
    assert (hits & ~sampled).sum() <= 4
    assert 0.1 < hits.mean() < 0.9


def test_compiled_occlusion_is_the_slab_test_and_a_marker_on_a_neighbours_box_face_is_not_flickered():
    """`hidden_by_boxes` (compiled, first hit ends a point) hides exactly the markers whose
    line of sight the numpy slab test sends through another link's box, on random diggers,
    which paint markers where a neighbour's box meets their own link: there the marker is
    hidden only when the sight line goes into that box, so its visibility does not flip
    from frame to frame with the rounding of the pose."""
    from mocap.core.shapes import hidden_by_boxes
    from mocap.core.visibility import box_replaced
    from mocap.synthetic.machines import random_digger
    from mocap.synthetic.scenes import ring_of_cameras

    on_surface = 0
    for seed in range(6):
        machine = random_digger(np.random.default_rng(seed))
        rng = np.random.default_rng(100 + seed)
        rest = machine.markers(np.zeros((1, machine.n_joints)))[0]
        extent = np.ptp(rest, axis=0).max()
        cameras = ring_of_cameras(3, rest.mean(axis=0), (1.5 * extent, 3 * extent), rng,
                                  height=(0.1 * extent, 0.8 * extent))
        q = random_joints(machine, 60, rng)
        poses, world = machine.link_poses(q), machine.markers(q)
        boxes = link_boxes(machine)
        hides = ~box_replaced(machine)
        for camera in cameras:
            centre = np.broadcast_to(camera.center, (len(q), 3))
            hidden = hidden_by_boxes(world, np.ascontiguousarray(centre), poses, machine.marker_links.astype(np.int64),
                                     boxes, hides)
            slab = np.zeros_like(hidden)
            for link in np.flatnonzero(hides):
                inv = np.linalg.inv(poses[:, link])
                start = np.einsum("fij,fmj->fmi", inv[:, :3, :3], world) + inv[:, None, :3, 3]
                end = np.broadcast_to((inv[:, :3, :3] @ camera.center + inv[:, :3, 3])[:, None], start.shape)
                other = (machine.marker_links != link)[None]
                hit = segment_hits_box(start, end, boxes[link])
                slab |= hit & other
                # markers on this box's surface (a hair in or out with the pose's rounding): hidden by
                # it exactly when a point just along the sight line is inside it
                margin = np.minimum(start - boxes[link, 0], boxes[link, 1] - start).min(axis=-1)
                touching = (np.abs(margin) < 1e-9) & other
                on_surface += int(touching.sum())
                just_along = start + 1e-6 * (end - start)
                into = np.all((just_along > boxes[link, 0]) & (just_along < boxes[link, 1]), axis=-1)
                assert np.array_equal(hit[touching], into[touching])
            assert np.array_equal(hidden, slab)
    assert on_surface > 100  # the case is common on random diggers, not a corner of a corner


def test_hidden_markers_are_behind_other_links(session):
    machine = session.machine
    camera = session.cameras[0]
    frames = np.arange(0, camera.frames, 41)
    uv, seen, poses = session.observe(camera, frames)
    centre = camera.camera.center
    times = camera.times(frames)
    world = machine.markers(session.plan.joints(times), session.plan.world_from_base(times))
    normals = np.einsum("fmij,mj->fmi", poses[:, machine.marker_links, :3, :3], session.normals)
    facing = np.einsum("fmi,fmi->fm", normals, centre - world) / np.linalg.norm(centre - world, axis=-1) > 0.2
    s = np.linspace(0.0, 1.0, 400)
    samples = world[..., None, :] + s[:, None] * (centre - world)[..., None, :]  # (F, M, S, 3)
    behind = np.zeros(seen.shape, dtype=bool)
    for l in range(len(machine.links)):
        inv = np.linalg.inv(poses[:, l])
        local = np.einsum("fij,fmsj->fmsi", inv[:, :3, :3], samples) + inv[:, None, None, :3, 3]
        inside = np.all((local >= session.boxes[l, 0]) & (local <= session.boxes[l, 1]), axis=-1).any(axis=-1)
        behind |= inside & (machine.marker_links != l)[None]
    in_image = np.all(np.isfinite(uv), axis=-1)
    candidates = facing & in_image
    assert (candidates & behind).sum() > 0  # the scene has occlusions
    assert np.mean(seen[candidates] == ~behind[candidates]) > 0.995


def test_marker_normals_point_out_of_their_boxes(ex3500):
    boxes = link_boxes(ex3500)
    normals = marker_normals(ex3500, boxes)
    middle = boxes[ex3500.marker_links].mean(axis=1)
    assert np.all(np.einsum("mi,mi->m", ex3500.marker_positions - middle, normals) > 0)
    assert np.all(np.abs(normals).sum(axis=1) == 1)


def test_guards():
    with pytest.raises(InputError, match="bucket_tip"):
        PlanarChain.from_machine(load_machine("cube_pair"))
    chain = PlanarChain.from_machine(load_machine("bobcat_225"))
    with pytest.raises(ValueError, match="out of reach at frame 1"):
        chain.inverse(np.array([[3.5, 0.0], [40.0, 0.0]]), np.zeros(2), np.zeros(2))
    machine = load_machine("bobcat_225")
    with pytest.raises(ValueError, match="limits of joint 'boom'"):
        check_limits(machine, np.array([[0.0, np.radians(80.0), np.radians(-90.0), 0.0]]))
    with pytest.raises(ValueError, match="n_cameras must be 1..8"):
        SessionOptions(n_cameras=0)
    with pytest.raises(ValueError, match="n_cycles must be at least 1"):
        SessionOptions(n_cycles=0)
    with pytest.raises(ValueError, match="classes must be some of"):
        SessionOptions(classes=("Type 4",))
    with pytest.raises(ValueError, match="hold must be at least"):
        SessionOptions(hold=0.1)


def test_cli_writes_truth_that_reads_back(tmp_path, capsys):
    out = tmp_path / "session"
    argv = ["synth", "--machine", "bobcat_225", "--cameras", "2", "--cycles", "1", "--seed", "3",
            "--out", str(out), "--no-video", "--distortion"]
    assert main(argv) == 0
    machine = load_machine("bobcat_225")
    truth = make_session(machine, "bobcat_225", n_cameras=2, n_cycles=1, seed=3, distortion=True)
    config = load_session_config(out / "session.toml")
    assert config.machine == "bobcat_225" and [c.name for c in config.cameras] == ["cam1", "cam2"]
    assert [c.fps for c in config.cameras] == [c.fps for c in truth.cameras]
    calibration = load_calibration(out / "truth" / "cameras.toml")
    np.testing.assert_allclose(calibration.time_offsets, [c.time_offset for c in truth.cameras])
    np.testing.assert_allclose(calibration.joints(machine), truth.motion.joints[0], atol=1e-9)
    assert np.any(calibration.cameras[1].distortion != 0)
    tracks = load_tracks(out / "truth" / "tracks.csv")
    assert len(tracks) == len(truth.tracks)
    np.testing.assert_allclose(tracks.xy, truth.tracks.xy, atol=1e-4)
    motion = load_motion(out / "truth" / "motion.csv", machine)
    np.testing.assert_allclose(motion.bucket_angle, truth.motion.bucket_angle, atol=1e-6)
    points = load_points(out / "truth" / "markers.csv")
    # reference frame 0 is the calibration frame: the stored cameras reproject its markers
    first = tracks.of_camera("cam1").of_frame(0)
    xyz = points.xyz[(points.frame == 0)][machine.marker_index(first.marker)]
    np.testing.assert_allclose(calibration.cameras[0].project(xyz), first.xy, atol=2e-3)
    cycles = (out / "truth" / "cycles.csv").read_text().splitlines()
    assert cycles[0].startswith("cycle,class,scaling") and len(cycles) == 2
    assert main(argv) == 2  # the folder is not empty now
    assert "not empty" in capsys.readouterr().err


@pytest.mark.parametrize(
    "extra, message",
    [(["--size", "big"], "expected WIDTHxHEIGHT"), (["--classes", "4"], "comma list of 1, 2, 3"),
     (["--cameras", "0"], "give 1 to 8 cameras"), (["--cycles", "0"], "give 1 to 100 dig cycles"),
     (["--machine", "nope"], "no machine model named")],
)
def test_cli_rejects_bad_options(tmp_path, capsys, extra, message):
    argv = ["synth", "--machine", "bobcat_225", "--out", str(tmp_path / "s"), "--no-video", *extra]
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_small_objects_check_their_shapes(session):
    from dataclasses import replace

    from mocap.synthetic.paths import SmoothNoise

    with pytest.raises(ValueError, match="SmoothNoise needs amplitude and phase"):
        SmoothNoise(np.zeros((3, 2)), np.zeros(4), np.zeros((3, 2)))
    with pytest.raises(ValueError, match="needs fps > 0 and frames >= 1"):
        replace(session.cameras[0], fps=0.0)


def test_cli_copies_a_model_from_outside_into_the_session(tmp_path):
    from mocap.io.machine_toml import MACHINES_DIR
    from mocap.io.session import Session

    model = tmp_path / "my_excavator.toml"
    model.write_text((MACHINES_DIR / "bobcat_225.toml").read_text())
    out = tmp_path / "s"
    assert main(["synth", "--machine", str(model), "--cameras", "1", "--cycles", "1", "--out", str(out), "--no-video"]) == 0
    assert load_session_config(out / "session.toml").machine == "machine.toml"
    assert Session.open(out).machine().joint_names == load_machine("bobcat_225").joint_names


@pytest.mark.parametrize("name", MACHINES)
def test_long_sessions_of_every_seed_are_reached_and_follow_their_digs(name):
    """12 digs for 31 seeds: the face advancing dig by dig once carried late digs beyond the
    reach. Every planned state is reached inside the joint limits, forward kinematics of the
    joints puts the tip on the requested path, and each dig is the one its truth records."""
    machine = load_machine(name)
    chain = PlanarChain.from_machine(machine)
    for seed in range(31):
        plan = plan_session(machine, 12, np.random.default_rng(seed), bounce=0.0)
        t = np.arange(0.0, plan.duration, 0.2)
        _, tip = check_reached(machine, chain, plan, t)
        digs = [s for s in plan.segments if s.dig is not None]
        assert len(digs) == len(plan.cycles) == 12
        for cycle, segment in zip(plan.cycles, digs):
            assert (segment.t0, segment.t1) == (cycle.dig_start, cycle.dig_end)
            assert segment.dig.scale == cycle.scale and segment.dig.label == cycle.label
            # scaled at most 20 % below the drawn range (0.88 x 0.85 x 0.97 .. 1.08 x 1.15 x 1.03)
            assert 0.8 * 0.72 < min(cycle.scale) and max(cycle.scale) < 1.28
            inside = (t > cycle.dig_start) & (t < cycle.dig_end)
            tau = (t[inside] - cycle.dig_start) / (cycle.dig_end - cycle.dig_start)
            clean = segment.dig.tip(min_jerk(tau))  # the requested path without noise or redirection
            bound = 0.04 * np.linalg.norm(chain.offsets, axis=1).sum()  # redirection + noise: <= 3 % + 1 %
            assert np.abs(tip[inside] - clean).max() < bound


def test_a_linkage_that_cannot_dig_is_one_line_and_exit_2(tmp_path, capsys):
    text = (MACHINES_DIR / "bobcat_225.toml").read_text()
    cramped = tmp_path / "cramped.toml"
    cramped.write_text(text.replace("limits = [-35, 75]", "limits = [-2, 2]"))
    assert main(["synth", "--machine", str(cramped), "--cycles", "2", "--no-video", "--out", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "does not fit the linkage" in err
    with pytest.raises(InputError, match="dig 1 .* does not fit the linkage"):
        plan_session(load_machine(cramped), 1, np.random.default_rng(0))


def test_truth_stretch_is_the_scale_of_a_dig_of_the_general_shape():
    from dataclasses import replace
    from mocap.synthetic.paths import CLASSES as LABELS, nominal_shape, stretch
    for label in LABELS:
        general = nominal_shape(label, 10.0, np.radians(68.0), 15.5)
        for scale in ((1.0, 1.0), (1.1, 0.9), (0.9, 1.15)):
            np.testing.assert_allclose(stretch(replace(general, scale=scale), general), scale, rtol=2e-3)
