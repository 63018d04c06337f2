"""The Rerun replay: recordings read back with Rerun's own chunk API and checked against
the inputs they were made from (seeded synthetic scenes)."""

from __future__ import annotations

import logging
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from rerun.chunk import RrdReader
from scipy.interpolate import CubicSpline

from mocap.cli import main
from mocap.core.calibration import Calibration
from mocap.core.motion import Motion
from mocap.core.points import Points
from mocap.errors import InputError
from mocap.io.cameras_toml import save_calibration
from mocap.io.machine_toml import load_machine
from mocap.io.motion_csv import load_motion, save_motion
from mocap.io.points_csv import save_points
from mocap.io.session_toml import SessionCamera, SessionConfig, save_session_config
from mocap.io.tracks_csv import save_tracks
from mocap.synthetic.encode import video_writer
from mocap.synthetic.scenes import observe, random_joints, ring_of_cameras
from mocap.viewer import Cycles, Replay, Sinks, load_cycles, run_replay
from mocap.viewer import replay as replay_module
from mocap.viewer import scene
from mocap.viewer.video import load_video

FPS = 30.0
N_FRAMES = 90
OFFSET = 0.1  # cam2's clock, s: its frame n shows time n / FPS + OFFSET
FLOAT32 = 2e-6  # relative precision of the recording's float32 values


# --- scene ------------------------------------------------------------------------------
def encode_video(path: Path, n_frames: int, codec: str = "h264", size=(64, 48)) -> Path:
    with video_writer(path, size, FPS, codec) as write:
        for i in range(n_frames):
            write(np.full((size[1], size[0], 3), (7 * i) % 256, dtype=np.uint8))
    return path


def smooth_motion(machine, rng, n_frames: int) -> Motion:
    keys = random_joints(machine, 5, rng)
    time = np.arange(n_frames) / FPS
    joints = CubicSpline(np.linspace(0.0, time[-1], len(keys)), keys)(time)
    joints_sd = np.full_like(joints, np.radians(0.2))
    points_sd = rng.uniform(0.01, 0.03, (n_frames, len(machine.point_names)))
    return Motion(
        machine.joint_names,
        machine.point_names,
        np.arange(n_frames),
        time,
        joints,
        machine.points(joints),
        machine.bucket_angles(joints),
        joints_sd=joints_sd,
        points_sd=points_sd,
        extra={"filled": (np.arange(n_frames) % 10 == 0).astype(float)},
    )


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A bobcat digging for 3 s before 3 cameras; cam1 has an H.264 video, cam2 (on a clock
    0.1 s late) an H.264 video too, cam3 an MPEG-4 one the replay must refuse."""
    rng = np.random.default_rng(11)
    machine = load_machine("bobcat_225")
    motion = smooth_motion(machine, rng, N_FRAMES)
    cameras = ring_of_cameras(3, [2.0, 0.0, 1.0], (9.0, 14.0), rng)
    calibration = Calibration(
        tuple(cameras),
        ({"fps": FPS}, {"fps": FPS, "time_offset": OFFSET}, {"fps": FPS}),
        {"machine": machine.name},
    )
    tracks = observe(cameras, machine, motion.joints, rng, noise_px=0.5, miss_fraction=0.2)
    truth = machine.markers(motion.joints)  # (F, M, 3)
    f, m = np.nonzero(rng.random(truth.shape[:2]) > 0.3)
    points = Points(
        f,
        np.asarray(machine.marker_names, dtype=object)[m],
        truth[f, m] + rng.normal(0, 0.01, (len(f), 3)),
        np.full(len(f), 0.5),
        np.full(len(f), 2),
    )
    folder = tmp_path_factory.mktemp("videos")
    videos = {
        "cam1": encode_video(folder / "cam1.mp4", N_FRAMES),
        "cam2": encode_video(folder / "cam2.mp4", N_FRAMES),
        "cam3": encode_video(folder / "cam3.mp4", 10, codec="mp4v"),
    }
    cycles = Cycles(("1", "2"), np.array([0, 45]), np.array([44, N_FRAMES - 1]))
    replay = Replay(machine, calibration, motion, calibration.fps(), points, tracks, videos, cycles)
    return replay


class Recording:
    """A .rrd file read back: per entity path, its chunks' record batches."""

    def __init__(self, path: Path):
        reader = RrdReader(path)
        self.blueprints = reader.blueprints()
        self.blueprint_chunks = [c for b in self.blueprints for c in reader.stream(store=b).collect().stream()]
        self.chunks: dict[str, list] = {}
        for chunk in reader.stream().collect().stream():
            self.chunks.setdefault(chunk.entity_path, []).append(chunk)

    def marker_labels(self) -> dict[int, str]:
        """Class id -> marker name, from the annotation context logged at /world."""
        (context,) = self.static("/world", "AnnotationContext:context")
        return {c["class_id"]: c["class_description"]["info"]["label"] for c in context}

    @property
    def entities(self) -> set[str]:
        return set(self.chunks)

    def static(self, entity: str, component: str) -> list:
        """The last static value of a component (one row's list of instances)."""
        for chunk in self.chunks.get(entity, []):
            batch = chunk.to_record_batch()
            if chunk.is_static and component in batch.schema.names:
                return batch.column(component).to_pylist()[-1]
        raise KeyError(f"{entity} has no static {component}")

    def series(self, entity: str, component: str, timeline: str = "frame"):
        """(times (R,), rows: list of R instance lists) of a temporal component, time-ordered."""
        times, rows = [], []
        for chunk in self.chunks.get(entity, []):
            batch = chunk.to_record_batch()
            if chunk.is_static or component not in batch.schema.names:
                continue
            times.append(batch.column(timeline).cast(pa.int64()).to_numpy())
            rows += batch.column(component).to_pylist()
        if not times:
            raise KeyError(f"{entity} has no temporal {component}")
        times = np.concatenate(times)
        order = np.argsort(times, kind="stable")
        return times[order], [rows[i] for i in order]


@pytest.fixture(scope="module")
def recorded(world, tmp_path_factory):
    path = tmp_path_factory.mktemp("rrd") / "dig.rrd"
    summary = run_replay(world, Sinks(save=path))
    return summary, Recording(path)


# --- the recording against its inputs -----------------------------------------------------
def test_recording_has_the_entity_tree_timelines_and_blueprint(recorded):
    summary, rec = recorded
    expected = {f"/world/machine/{link}" for link in ("undercarriage", "house", "boom", "arm", "bucket")}
    expected |= {f"/world/cameras/{cam}" for cam in ("cam1", "cam2", "cam3")}
    expected |= {"/world/markers/model", "/world/markers/observed", "/world/bucket_tip", "/world/trail/1"}
    expected |= {"/world/trail/2", "/plots/bucket/bucket_angle", "/plots/speed/bucket_tip", "/plots/joints/boom"}
    assert expected <= rec.entities
    for chunk in rec.chunks["/world/machine/boom"]:
        if not chunk.is_static:
            assert set(chunk.timeline_names) == {"frame", "time"}
    assert len(rec.blueprints) == 1
    assert summary.frames == N_FRAMES and summary.trails == 2


def test_default_blueprint_shows_the_scene_each_camera_and_the_plots(world, recorded):
    _, rec = recorded
    origins, overrides, selection = [], {}, None
    for chunk in rec.blueprint_chunks:
        batch = chunk.to_record_batch()
        if "TimePanelBlueprint:time_selection" in batch.schema.names:
            selection = batch.column("TimePanelBlueprint:time_selection").to_pylist()[-1][0]
            fps = batch.column("TimePanelBlueprint:fps").to_pylist()[-1][0]
        if "ViewBlueprint:space_origin" in batch.schema.names:
            origins += [o[0] for o in batch.column("ViewBlueprint:space_origin").to_pylist()]
        if "VisibleTimeRanges:ranges" in batch.schema.names:
            overrides[chunk.entity_path.split("/overrides")[1]] = batch.column("VisibleTimeRanges:ranges").to_pylist()[-1]
    assert sorted(origins) == sorted(
        ["world", "world/cameras/cam1", "world/cameras/cam2", "world/cameras/cam3", "plots", "plots", "plots"]
    )  # three panels of plots: joints, the bucket, the measurement's quality (no phases without cycles' phases)
    assert selection == {"min": world.cycles.start[0], "max": selection["max"]}  # the first dig, looped
    assert fps == FPS  # played at the reference camera's rate (Rerun's default is 30)
    assert set(overrides) == {"/world/trail/1/visualizers", "/world/trail/2/visualizers"}
    ranges = {r["timeline"]: r["range"] for r in overrides["/world/trail/2/visualizers"]}
    assert set(ranges) == {"frame", "time"}
    assert ranges["frame"]["start"] == world.cycles.start[1]  # from the cycle's start ...
    assert ranges["time"]["start"] == round(world.cycles.start[1] / FPS * 1e9)  # (ns)
    assert ranges["frame"]["end"] == ranges["time"]["end"] == 0  # ... up to the time cursor


def test_world_is_z_up_right_handed(recorded):
    import rerun as rr

    _, rec = recorded
    expected = rr.components.ViewCoordinates(rr.ViewCoordinates.RIGHT_HAND_Z_UP).as_arrow_array().to_pylist()
    assert rec.static("/world", "ViewCoordinates:xyz") == expected


def test_link_transforms_equal_the_motion(world, recorded):
    _, rec = recorded
    poses = world.machine.link_poses(world.motion.joints)  # (F, L, 4, 4)
    for i, link in enumerate(world.machine.link_names):
        frames, translation = rec.series(f"/world/machine/{link}", "Transform3D:translation")
        _, quaternion = rec.series(f"/world/machine/{link}", "Transform3D:quaternion")
        np.testing.assert_array_equal(frames, world.motion.frame)
        translation = np.array(translation)[:, 0]
        np.testing.assert_allclose(translation, poses[:, i, :3, 3], atol=FLOAT32 * 10)
        from scipy.spatial.transform import Rotation

        rotation = Rotation.from_quat(np.array(quaternion)[:, 0]).as_matrix()  # x, y, z, w
        np.testing.assert_allclose(rotation, poses[:, i, :3, :3], atol=1e-5)
        half = (np.array(rec.static(f"/world/machine/{link}", "Boxes3D:half_sizes"))[0])
        assert np.all(half > 0)


def test_markers_model_and_observed(world, recorded):
    _, rec = recorded
    frames, model = rec.series("/world/markers/model", "Points3D:positions")
    np.testing.assert_array_equal(frames, world.motion.frame)
    np.testing.assert_allclose(np.array(model), world.machine.markers(world.motion.joints), atol=1e-5)
    ids = rec.static("/world/markers/model", "Points3D:class_ids")
    labels = rec.marker_labels()
    assert [labels[i] for i in ids] == list(world.machine.marker_names)

    frames, observed = rec.series("/world/markers/observed", "Points3D:positions")
    _, observed_ids = rec.series("/world/markers/observed", "Points3D:class_ids")
    points = world.points
    for frame in (0, 37, N_FRAMES - 1):
        row = int(np.flatnonzero(frames == frame)[0])
        mine = points.frame == frame
        got = {labels[c]: p for c, p in zip(observed_ids[row], observed[row])}
        want = dict(zip(points.marker[mine], points.xyz[mine]))
        assert set(got) == set(want)
        for name in want:
            np.testing.assert_allclose(got[name], want[name], atol=1e-5)


def test_tip_and_trails_per_cycle(world, recorded):
    _, rec = recorded
    tip = world.motion.point("bucket_tip")
    frames, positions = rec.series("/world/bucket_tip", "Points3D:positions")
    np.testing.assert_allclose(np.array(positions)[:, 0], tip, atol=1e-5)
    for name, start, end in zip(world.cycles.name, world.cycles.start, world.cycles.end):
        frames, strips = rec.series(f"/world/trail/{name}", "LineStrips3D:strips")
        np.testing.assert_array_equal(frames, np.arange(start + 1, end + 1))  # a segment ends at each frame
        segments = np.array([row[0] for row in strips])  # (S, 2, 3)
        np.testing.assert_allclose(segments[:, 1], tip[frames], atol=1e-5)
        np.testing.assert_allclose(segments[:, 0], tip[frames - 1], atol=1e-5)


def test_cameras_sit_where_the_calibration_puts_them(world, recorded):
    _, rec = recorded
    for camera in world.calibration.cameras:
        path = f"/world/cameras/{camera.name}"
        translation = np.array(rec.static(path, "Transform3D:translation"))[0]
        matrix = np.array(rec.static(path, "Transform3D:mat3x3"))[0].reshape(3, 3).T  # stored column-major
        np.testing.assert_allclose(translation, camera.center, rtol=FLOAT32 * 10, atol=1e-5)
        np.testing.assert_allclose(matrix, camera.cam_from_world.rotation.T, atol=1e-6)  # world_from_cam
        k = np.array(rec.static(path, "Pinhole:image_from_camera"))[0].reshape(3, 3).T
        shifted = camera.matrix.copy()
        shifted[:2, 2] += 0.5  # OpenCV's pixel centre (0, 0) is Rerun's (0.5, 0.5)
        np.testing.assert_allclose(k, shifted, rtol=FLOAT32 * 10)
        np.testing.assert_allclose(rec.static(path, "Pinhole:resolution")[0], camera.size)


def test_videos_are_the_files_assets_with_a_frame_per_motion_frame(world, recorded):
    summary, rec = recorded
    assert summary.videos == ("cam1", "cam2")
    for name, offset in (("cam1", 0.0), ("cam2", OFFSET)):
        path = f"/world/cameras/{name}/video"
        blob = rec.static(path, "AssetVideo:blob")[0]
        assert bytes(blob) == world.videos[name].read_bytes()  # the file itself, not re-encoded
        frames, stamps = rec.series(path, "VideoFrameReference:timestamp")
        late = round(offset * FPS)  # cam2's video starts 3 reference frames late ...
        np.testing.assert_array_equal(frames, np.arange(N_FRAMES))
        expected = load_video(world.videos[name], name).timestamps_ns[np.maximum(frames - late, 0)]
        np.testing.assert_array_equal(np.array(stamps)[:, 0], expected)  # ... showing its first frame till then
    note_frames, labels = rec.series("/world/cameras/cam2/note", "Points2D:labels")
    assert list(note_frames) == [0] and labels[0][0] == f"starts {OFFSET:.2f} s later: first frame"
    assert "/world/cameras/cam1/note" not in rec.entities
    assert "/world/cameras/cam3/video" not in rec.entities


def test_each_video_shows_its_first_frame_as_an_image_under_the_video(world, recorded):
    import cv2

    _, rec = recorded
    for name in ("cam1", "cam2"):  # the test videos' frame i is grey level 7 i: the first is black
        path = f"/world/cameras/{name}/first_frame"
        assert rec.static(path, "EncodedImage:media_type") == ["image/jpeg"]
        image = cv2.imdecode(np.frombuffer(bytes(rec.static(path, "EncodedImage:blob")[0]), np.uint8), cv2.IMREAD_COLOR)
        assert image.shape == (48, 64, 3) and image.max() <= 3  # H.264 and JPEG round the grey level a little
        assert rec.static(path, "EncodedImage:draw_order")[0] < -15.0  # under the video's frames (Rerun's -15)
    assert "/world/cameras/cam3/first_frame" not in rec.entities  # no playable video, no image


def test_non_h264_video_is_skipped_with_a_warning(world, caplog):
    with caplog.at_level(logging.WARNING, logger="mocap.viewer.video"):
        assert load_video(world.videos["cam3"], "cam3") is None
    assert "codec mpeg4" in caplog.text and "H.264" in caplog.text


def test_tracks_are_drawn_on_their_camera_on_the_reference_clock(world, recorded):
    _, rec = recorded
    labels = rec.marker_labels()
    for name, shift in (("cam1", 0), ("cam2", round(OFFSET * FPS))):
        frames, xy = rec.series(f"/world/cameras/{name}/tracks", "Points2D:positions")
        _, ids = rec.series(f"/world/cameras/{name}/tracks", "Points2D:class_ids")
        mine = world.tracks.of_camera(name)
        np.testing.assert_array_equal(frames, np.unique(mine.frame) + shift)
        row = len(frames) // 2
        at = mine.of_frame(frames[row] - shift)
        got = {labels[c]: p for c, p in zip(ids[row], xy[row])}
        for marker, pixel in zip(at.marker, at.xy):
            np.testing.assert_allclose(got[marker], pixel + 0.5, atol=1e-3)


def test_plots_carry_the_motion_columns(world, recorded):
    _, rec = recorded
    motion = world.motion
    frames, boom = rec.series("/plots/joints/boom", "Scalars:scalars")
    j = motion.joint_names.index("boom")
    np.testing.assert_allclose(np.array(boom)[:, 0], np.degrees(motion.joints[:, j]), atol=1e-9)
    times, _ = rec.series("/plots/joints/boom", "Scalars:scalars", timeline="time")
    np.testing.assert_allclose(times * 1e-9, motion.time, atol=1e-9)
    _, angle = rec.series("/plots/bucket/bucket_angle", "Scalars:scalars")
    np.testing.assert_allclose(np.array(angle)[:, 0], np.degrees(motion.bucket_angle), atol=1e-9)
    _, speed = rec.series("/plots/speed/bucket_tip", "Scalars:scalars")
    np.testing.assert_allclose(np.array(speed)[:, 0], scene.tip_speed(motion, "bucket_tip"))
    _, sd = rec.series("/plots/uncertainty_m/bucket_tip_sd", "Scalars:scalars")
    np.testing.assert_allclose(np.array(sd)[:, 0], motion.points_sd[:, 0])
    _, sd = rec.series("/plots/uncertainty/boom_sd", "Scalars:scalars")
    np.testing.assert_allclose(np.array(sd)[:, 0], 0.2)
    _, filled = rec.series("/plots/extra_filled/filled", "Scalars:scalars")
    np.testing.assert_array_equal(np.array(filled)[:, 0], motion.extra["filled"])


def test_failed_recording_leaves_no_file(world, tmp_path, monkeypatch):
    def broken(rec, replay):
        raise RuntimeError("disk gone")

    monkeypatch.setattr(replay_module, "record_replay", broken)
    with pytest.raises(RuntimeError, match="disk gone"):
        run_replay(world, Sinks(save=tmp_path / "out.rrd"))
    assert list(tmp_path.iterdir()) == []


def test_no_viewer_at_the_url_is_an_input_error_and_leaves_no_file(world, tmp_path):
    with pytest.raises(InputError, match="is a Rerun viewer running there"):
        run_replay(world, Sinks(save=tmp_path / "out.rrd", connect="rerun+http://127.0.0.1:9/proxy"))
    assert list(tmp_path.iterdir()) == []


def test_run_replay_needs_a_sink(world):
    with pytest.raises(ValueError, match="no sink"):
        run_replay(world, Sinks())


# --- the pure parts ---------------------------------------------------------------------
def test_tip_speed_of_uniform_motion_and_from_a_column():
    time = np.arange(20) / 10.0
    points = np.zeros((20, 1, 3))
    points[:, 0, 0] = 3.0 * time  # 3 m/s along x
    points[:, 0, 2] = 4.0 * time  # and 4 m/s up: 5 m/s
    motion = Motion((), ("bucket_tip",), np.arange(20), time, np.zeros((20, 0)), points, np.zeros(20))
    np.testing.assert_allclose(scene.tip_speed(motion, "bucket_tip"), 5.0)
    given = Motion((), ("bucket_tip",), np.arange(20), time, np.zeros((20, 0)), points, np.zeros(20),
                   extra={"bucket_tip_speed": np.full(20, 1.5)})
    np.testing.assert_array_equal(scene.tip_speed(given, "bucket_tip"), 1.5)


def test_trails_leave_out_segments_at_unknown_tips():
    points = np.arange(30, dtype=float).reshape(10, 1, 3)
    points[4] = np.nan
    motion = Motion((), ("tip",), np.arange(10) + 100, np.arange(10) / 30, np.zeros((10, 0)), points, np.zeros(10))
    trails = scene.trails(motion, "tip", np.array([100, 106, 500]), np.array([105, 109, 600]), ["a", "b", "c"])
    assert [t.name for t in trails] == ["a", "b"]  # cycle c has no frames
    np.testing.assert_array_equal(trails[0].frame, [101, 102, 103])  # 104 and 105 touch frame 104
    np.testing.assert_array_equal(trails[1].frame, [107, 108, 109])
    assert trails[1].first_frame == 106


def test_link_poses_follow_a_moving_base():
    machine = load_machine("bobcat_225")
    rng = np.random.default_rng(5)
    motion = smooth_motion(machine, rng, 12)
    lifted = Motion(
        motion.joint_names, motion.point_names, motion.frame, motion.time, motion.joints, motion.points,
        motion.bucket_angle, extra={"base_z": np.linspace(0.0, 0.05, 12)},
    )
    base = np.tile(np.eye(4), (12, 1, 1))
    base[:, 2, 3] = np.linspace(0.0, 0.05, 12)
    series = scene.link_series(machine, lifted)
    np.testing.assert_allclose(series.translation, machine.link_poses(motion.joints, base)[:, :, :3, 3])
    markers = scene.model_markers(machine, series)
    np.testing.assert_allclose(markers, machine.markers(motion.joints, base))
    assert scene.world_from_base(motion) is None


def test_clock_mapping_between_cameras():
    np.testing.assert_array_equal(scene.reference_frames(scene.camera_time([0, 30, 60], 30.0, 0.5), 30.0, 0.0), [15, 45, 75])
    motion = Motion((), (), np.arange(10), np.arange(10) / 10.0, np.zeros((10, 0)), np.zeros((10, 0, 3)), np.zeros(10))
    rows, frames = scene.video_frame_rows(motion, 5, 20.0, 0.2)  # the video starts at 0.2 s, 5 frames at 20 fps
    np.testing.assert_array_equal(rows, [2, 3, 4])
    np.testing.assert_array_equal(frames, [0, 2, 4])


def test_load_cycles(tmp_path):
    path = tmp_path / "cycles.csv"
    path.write_text("cycle,start_frame,end_frame,class\n1,0,40,Type 1\n2,41,90,Type 3\n")
    cycles = load_cycles(path)
    assert cycles.name == ("1", "2")
    np.testing.assert_array_equal(cycles.start, [0, 41])
    np.testing.assert_array_equal(cycles.end, [40, 90])


@pytest.mark.parametrize(
    "text, message",
    [
        ("cycle,start_frame\n1,0\n", "header lacks end_frame"),
        ("start_frame,end_frame\n10,5\n", "line 2: end_frame 5 is before start_frame 10"),
        ("start_frame,end_frame\n1.5,5\n", "line 2: start_frame and end_frame must be integers"),
        ("start_frame,end_frame\n1,5,7\n", "line 2: 3 fields, the header has 2"),
    ],
)
def test_load_cycles_rejects_bad_files(tmp_path, text, message):
    path = tmp_path / "cycles.csv"
    path.write_text(text)
    with pytest.raises(InputError, match=message):
        load_cycles(path)


def test_load_cycles_missing_file(tmp_path):
    with pytest.raises(InputError, match="file not found"):
        load_cycles(tmp_path / "nope.csv")


# --- command line -----------------------------------------------------------------------
@pytest.fixture(scope="module")
def session_dir(world, tmp_path_factory):
    root = tmp_path_factory.mktemp("session")
    cameras = tuple(SessionCamera(c.name, f"videos/{c.name}.mp4", FPS) for c in world.calibration.cameras)
    save_session_config(SessionConfig("bobcat_225", cameras), root / "session.toml")
    save_calibration(world.calibration, root / "calibration" / "cameras.toml")
    save_motion(world.motion, world.machine, root / "results" / "motion.csv")
    save_points(world.points, root / "results" / "points.csv")
    for camera in world.calibration.names:
        save_tracks(world.tracks.of_camera(camera), root / "tracks" / f"{camera}.csv")
    (root / "videos").mkdir()
    (root / "videos" / "cam1.mp4").write_bytes(world.videos["cam1"].read_bytes())
    (root / "results" / "cycles.csv").write_text("cycle,start_frame,end_frame\n1,0,44\n2,45,89\n")
    return root


def test_cli_session_writes_results_session_rrd(session_dir, capsys):
    assert main(["view", str(session_dir)]) == 0
    rec = Recording(session_dir / "results" / "session.rrd")
    assert {"/world/cameras/cam1/video", "/world/trail/1", "/world/trail/2", "/world/markers/observed"} <= rec.entities
    assert "/world/cameras/cam2/video" not in rec.entities  # the session has no video for cam2
    assert "/world/cameras/cam3/tracks" in rec.entities
    assert "replay of 90 frames, 3 cameras, video for cam1, 2 trail(s)" in capsys.readouterr().out


def test_cli_explicit_form(session_dir, world, tmp_path):
    out = tmp_path / "dig.rrd"
    status = main(
        [
            "view",
            "--machine", "bobcat_225",
            "--calibration", str(session_dir / "calibration" / "cameras.toml"),
            "--motion", str(session_dir / "results" / "motion.csv"),
            "--tracks", str(session_dir / "tracks" / "cam2.csv"),
            "--video", f"cam2={world.videos['cam2']}",
            "--save", str(out),
        ]
    )
    assert status == 0
    rec = Recording(out)
    assert "/world/cameras/cam2/video" in rec.entities and "/world/cameras/cam2/tracks" in rec.entities
    assert "/world/cameras/cam1/tracks" not in rec.entities and "/world/markers/observed" not in rec.entities
    frames, _ = rec.series("/world/trail/all", "LineStrips3D:strips")
    np.testing.assert_array_equal(frames, np.arange(1, N_FRAMES))


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--save", "{tmp}/out.txt"], "a Rerun recording is a .rrd file"),
        (["--video", "cam1", "--save", "{tmp}/o.rrd"], "expected NAME=PATH"),
        (["--video", "camX=a.mp4", "--save", "{tmp}/o.rrd"], "no camera camX in the calibration"),
        ([], "nowhere to send the replay"),
        (["--cycles", "{tmp}/missing.csv", "--save", "{tmp}/o.rrd"], "missing.csv: file not found"),
    ],
)
def test_cli_bad_input_is_one_line_and_exit_2(session_dir, tmp_path, capsys, extra, message):
    base = [
        "view",
        "--machine", "bobcat_225",
        "--calibration", str(session_dir / "calibration" / "cameras.toml"),
        "--motion", str(session_dir / "results" / "motion.csv"),
    ]
    assert main(base + [e.format(tmp=tmp_path) for e in extra]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and err.startswith("mocap view: error:")
    assert not (tmp_path / "o.rrd").exists()


@pytest.mark.parametrize(
    "extras, message",
    [
        ({"fps": 0.0}, "[cam_01]: 'fps' must be a positive number of frames per second (at most 10000), got 0.0"),
        ({"fps": "thirty"}, "[cam_01]: 'fps' must be a positive number of frames per second (at most 10000), got 'thirty'"),
        ({"fps": 30.0, "time_offset": "late"}, "[cam_01]: 'time_offset' must be a number of seconds"),
    ],
)
def test_cli_bad_camera_clock_is_one_line_and_exit_2(world, session_dir, tmp_path, capsys, extras, message):
    calibration = tmp_path / "cameras.toml"
    save_calibration(Calibration(world.calibration.cameras, ({}, extras, {}), world.calibration.metadata), calibration)
    argv = ["view", str(session_dir), "--calibration", str(calibration), "--save", str(tmp_path / "o.rrd")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and str(calibration) in err and err.count("\n") == 1
    assert not (tmp_path / "o.rrd").exists()


def test_cli_wrong_machine_in_a_subprocess(session_dir, tmp_path):
    argv = [
        "view", "--machine", "hitachi_ex3500", "--calibration", str(session_dir / "calibration" / "cameras.toml"),
        "--motion", str(session_dir / "results" / "motion.csv"), "--save", str(tmp_path / "o.rrd"),
    ]
    done = subprocess.run([sys.executable, "-m", "mocap.cli", *argv], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr  # a fresh interpreter: one line, no traceback
    assert "calibrated for machine 'Bobcat 225" in done.stderr and done.stderr.count("\n") == 1
    assert "Traceback" not in done.stderr and not (tmp_path / "o.rrd").exists()


@pytest.mark.parametrize(
    "argv, message",
    [
        (["view", "{tmp}/no_session"], "is this a session folder?"),
        (["view", "--save", "{tmp}/o.rrd"], "name a session folder or pass --machine"),
    ],
)
def test_cli_without_a_session_or_inputs(tmp_path, capsys, argv, message):
    assert main([a.format(tmp=tmp_path) for a in argv]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_cli_replays_a_synthetic_session(tmp_path, capsys):
    """`mocap synth` (truth only) then `mocap view` on its truth: the trail follows the
    synthetic cycles file and the base link the truth's bouncing base."""
    root = tmp_path / "synthetic"
    synth = ["synth", "--machine", "bobcat_225", "--cycles", "1", "--seed", "3", "--out", str(root), "--no-video"]
    assert main(synth) == 0
    truth = root / "truth"
    argv = ["view", str(root), "--calibration", str(truth / "cameras.toml"), "--motion", str(truth / "motion.csv")]
    assert main(argv + ["--cycles", str(truth / "cycles.csv")]) == 0
    assert "1 trail(s)" in capsys.readouterr().out
    rec = Recording(root / "results" / "session.rrd")
    cycles = load_cycles(truth / "cycles.csv")
    frames, _ = rec.series(f"/world/trail/{cycles.name[0]}", "LineStrips3D:strips")
    np.testing.assert_array_equal(frames, np.arange(cycles.start[0] + 1, cycles.end[0] + 1))
    motion = load_motion(truth / "motion.csv", load_machine("bobcat_225"))
    _, translation = rec.series("/world/machine/undercarriage", "Transform3D:translation")
    base_z = motion.extra["base_z"]
    assert np.ptp(base_z) > 0.001  # the base bounces ...
    np.testing.assert_allclose(np.array(translation)[:, 0, 2], base_z, atol=1e-6)  # ... and the replay follows


def test_trails_coloured_by_class_phases_plotted_machine_framed_names_on_hover(world, tmp_path):
    cycles = Cycles(("1", "2"), np.array([0, 45]), np.array([44, N_FRAMES - 1]), ("Type 1", "other"),
                    np.array([[0, 20, 30, 38], [45, 60, -1, -1]]))
    replay = Replay(world.machine, world.calibration, world.motion, world.fps, tracks=world.tracks, cycles=cycles)
    run_replay(replay, Sinks(save=tmp_path / "classes.rrd"))
    rec = Recording(tmp_path / "classes.rrd")
    packed = {name: (r << 24) | (g << 16) | (b << 8) | 255 for name, (r, g, b) in
              (("Type 1", (31, 119, 180)), ("other", (150, 150, 150)))}
    assert rec.static("/world/trail/1", "LineStrips3D:colors") == [packed["Type 1"]]
    assert rec.static("/world/trail/2", "LineStrips3D:colors") == [packed["other"]]
    frames, rows = rec.series("/plots/phase", "Scalars:scalars")
    expected = np.concatenate([np.full(20, 1), np.full(10, 2), np.full(8, 3), np.full(7, 4), np.full(15, 1),
                               np.full(N_FRAMES - 60, 2)])
    np.testing.assert_array_equal(frames, np.arange(N_FRAMES))
    np.testing.assert_array_equal(np.array(rows).ravel(), expected)
    assert rec.static("/world/cameras/cam1/tracks", "Points2D:show_labels") == [False]
    assert rec.static("/world/markers/model", "Points3D:show_labels") == [False]
    eye = {}
    for chunk in rec.blueprint_chunks:
        batch = chunk.to_record_batch()
        for name in ("EyeControls3D:position", "EyeControls3D:look_target"):
            if name in batch.schema.names:
                eye[name] = np.array(batch.column(name).to_pylist()[-1]).ravel()
    tip = world.motion.point("bucket_tip")
    low, high = np.minimum(tip.min(axis=0), 0), np.maximum(tip.max(axis=0), 0)
    assert np.all(eye["EyeControls3D:look_target"] >= low - 1e-6) and np.all(eye["EyeControls3D:look_target"] <= high + 1e-6)
    distance = np.linalg.norm(eye["EyeControls3D:position"] - eye["EyeControls3D:look_target"])
    assert distance < 2.0 * np.linalg.norm(high - low) + 1.0  # the machine's working range, not the cameras'
    assert eye["EyeControls3D:position"][1] < eye["EyeControls3D:look_target"][1]  # from the side


def test_open_without_a_display_says_to_serve(tmp_path, monkeypatch, capsys):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    assert main(["view", str(tmp_path), "--open"]) == 2
    err = capsys.readouterr().err
    assert "no display" in err and "--serve" in err and len(err.splitlines()) == 1
