"""Rendered synthetic videos: marker centres, occlusion as drawn, effects, video files, CLI."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mocap.cli import main
from mocap.core.visibility import segment_hits_box
from mocap.io.machine_toml import load_machine
from mocap.io.session_toml import load_session_config
from mocap.io.tracks_csv import load_tracks
from mocap.synthetic import make_session
from mocap.synthetic.effects import CameraEffects, EffectOptions
from mocap.synthetic.encode import frame_rate, video_writer
from mocap.synthetic.render import BLACK, WHITE, CameraRenderer, RenderOptions
from mocap.synthetic.videos import render_videos


@pytest.fixture(scope="module")
def scene():
    machine = load_machine("hitachi_ex3500")
    session = make_session(machine, "hitachi_ex3500", n_cameras=2, n_cycles=1, seed=5, size=(1280, 720), bounce=0.5)
    renderers = [CameraRenderer(session, i, RenderOptions(effects=EffectOptions.none()), np.random.default_rng(i))
                 for i in range(2)]
    return session, renderers


def outline_centroid(points: np.ndarray) -> np.ndarray:
    """Area centroid (2,) of a closed polygon (N, 2)."""
    x, y = points[:, 0], points[:, 1]
    x2, y2 = np.roll(x, -1), np.roll(y, -1)
    cross = x * y2 - x2 * y
    return np.array([((x + x2) * cross).sum(), ((y + y2) * cross).sum()]) / (3.0 * cross.sum())


def projected(renderer, frames):
    """Per frame: marker pixels (F, M, 2), visibility (F, M), disk outlines (F, M, N, 2),
    squares (F, M, 4, 2), and whether every outline point is clear of other links (F, M)."""
    session, machine = renderer.session, renderer.session.machine
    camera = renderer.field
    uv, seen, poses = session.observe(camera, frames)
    cams = camera.cam_from_world(camera.times(frames))
    on_link = poses[:, machine.marker_links]
    disks = np.einsum("fmij,mnj->fmni", on_link[..., :3, :3], renderer.disks) + on_link[..., None, :3, 3]
    squares = np.einsum("fmij,mnj->fmni", on_link[..., :3, :3], renderer.squares) + on_link[..., None, :3, 3]
    outline = np.concatenate([disks, squares], axis=2)  # (F, M, N + 4, 3)
    centre = camera.camera.center
    clear = np.ones(seen.shape, dtype=bool)
    for l in range(len(machine.links)):
        inv = np.linalg.inv(poses[:, l])
        start = np.einsum("fij,fmnj->fmni", inv[:, :3, :3], outline) + inv[:, None, None, :3, 3]
        end = np.broadcast_to((inv[:, :3, :3] @ centre + inv[:, :3, 3])[:, None, None], start.shape)
        hit = segment_hits_box(start, end, session.boxes[l]).any(axis=-1)
        clear &= ~(hit & (machine.marker_links != l)[None])
    return uv, seen, renderer._project(cams, disks), renderer._project(cams, squares), clear


def isolated(squares: np.ndarray, seen: np.ndarray, m: int, size) -> bool:
    """Marker m's square lies inside the image and overlaps no other visible marker's square."""
    low, high = squares[m].min(axis=0), squares[m].max(axis=0)
    if np.any(low < 2) or np.any(high > np.array(size) - 3):
        return False
    for k in np.flatnonzero(seen):
        if k != m and np.all(squares[k].max(axis=0) >= low) and np.all(squares[k].min(axis=0) <= high):
            return False
    return True


def test_rendered_marker_centres_match_the_projected_disks(scene):
    session, renderers = scene
    errors, to_truth, sizes = [], [], []
    for renderer in renderers:
        frames = np.array([0, 250, 420])
        uv, seen, disks, squares, clear = projected(renderer, frames)
        for k, (_, image) in enumerate(renderer.frames(frames, clean=True)):
            grey = image.astype(float).mean(axis=2)
            for m in np.flatnonzero(seen[k] & clear[k]):
                if not isolated(squares[k], seen[k], m, renderer.field.camera.size):
                    continue
                mask = np.zeros(grey.shape, np.uint8)
                cv2.fillPoly(mask, [np.round(squares[k, m] * 256).astype(np.int32)], 1, shift=8)
                mask = cv2.erode(mask, np.ones((3, 3), np.uint8)).astype(bool)
                x0, y0 = np.floor(disks[k, m].min(0)).astype(int) - 1
                x1, y1 = np.ceil(disks[k, m].max(0)).astype(int) + 2
                mask[:y0], mask[y1:], mask[:, :x0], mask[:, x1:] = False, False, False, False  # the disk's box
                weight = np.where(mask, np.clip(WHITE[0] - grey, 0, None), 0.0)
                yy, xx = np.mgrid[: grey.shape[0], : grey.shape[1]]
                found = np.array([(weight * xx).sum(), (weight * yy).sum()]) / weight.sum()
                errors.append(found - outline_centroid(disks[k, m]))
                to_truth.append(found - uv[k, m])
                sizes.append(np.ptp(disks[k, m], axis=0).min())
    errors, to_truth = np.array(errors), np.array(to_truth)
    assert len(errors) >= 20 and np.median(sizes) > 5.0
    assert np.abs(errors).max() <= 0.05
    # the truth's projected 3-D centre differs from the disk's image centroid by perspective only
    assert np.abs(to_truth).max() <= 0.1


def test_occlusion_flags_agree_with_the_pictures(scene):
    session, renderers = scene
    shown = hidden_drawn = hidden = 0
    for renderer in renderers:
        frames = np.arange(0, renderer.field.frames, 90)
        uv, seen, disks, squares, clear = projected(renderer, frames)
        for k, (_, image) in enumerate(renderer.frames(frames, clean=True)):
            w, h = renderer.field.camera.size
            for m in range(uv.shape[1]):
                x, y = np.round(uv[k, m]).astype(int) if np.all(np.isfinite(uv[k, m])) else (-1, -1)
                if not (0 <= x < w and 0 <= y < h):
                    continue
                pixel_black = np.all(image[y, x] == BLACK)
                if seen[k, m] and clear[k, m] and isolated(squares[k], seen[k], m, (w, h)):
                    shown += 1
                    assert pixel_black, f"visible marker {m} not drawn in frame {frames[k]}"
                elif not seen[k, m]:
                    under_other = any(
                        cv2.pointPolygonTest(squares[k, j].astype(np.float32), (float(x), float(y)), False) >= 0
                        for j in np.flatnonzero(seen[k])
                    )
                    if not under_other:
                        hidden += 1
                        hidden_drawn += pixel_black
    assert shown >= 50 and hidden >= 50
    assert hidden_drawn == 0


def test_effects_noise_exposure_dust():
    rng = np.random.default_rng(0)
    flat = np.full((120, 160, 3), 120, np.uint8)
    noisy = CameraEffects((160, 120), EffectOptions(noise=4.0, blur=0.0, exposure=0.0, dust=0.0), rng)
    out = noisy.apply(flat.copy(), 0.0, None, 0.0, 0.0)
    assert 3.6 < (out.astype(float) - 120).std() < 4.4 and abs(out.mean() - 120) < 0.2

    exposure = CameraEffects((160, 120), EffectOptions(noise=0.0, blur=0.0, exposure=0.1, dust=0.0), rng)
    means = [exposure.apply(flat.copy(), t, None, 0.0, 0.0).mean() for t in np.arange(0, 60, 2.0)]
    assert 2.0 < np.std(means) < 30.0

    dust = CameraEffects((160, 120), EffectOptions(noise=0.0, blur=0.0, exposure=0.0, dust=0.8), rng)
    dark = np.zeros_like(flat)
    clear = dust.apply(dark.copy(), 0.0, np.array([80.0, 60.0]), 30.0, 0.0)
    thick = dust.apply(dark.copy(), 0.0, np.array([80.0, 60.0]), 30.0, 1.0)
    assert np.all(clear == 0) and thick[60, 80].mean() > 40 and np.all(thick[:, :45] == 0)


def test_guards(tmp_path):
    with pytest.raises(ValueError, match="effect 'blur' out of range"):
        EffectOptions(blur=0.95)
    with pytest.raises(ValueError, match="codec must be one of"):
        RenderOptions(codec="gif")
    with pytest.raises(ValueError, match="supersample must be 1..8"):
        RenderOptions(supersample=0)
    with pytest.raises(ValueError, match="codec must be one of"):
        with video_writer(tmp_path / "x.mp4", (64, 64), 30.0, codec="gif"):
            pass
    assert not list(tmp_path.iterdir())
    assert frame_rate(29.97) == frame_rate(30000 / 1001) and float(frame_rate(25.0)) == 25.0


@pytest.mark.parametrize("codec", ["h264", "mp4v"])
def test_videos_hold_the_rendered_frames_in_order(tmp_path, codec):
    machine = load_machine("bobcat_225")
    session = make_session(machine, "bobcat_225", n_cameras=1, n_cycles=1, seed=2, size=(320, 180))
    options = RenderOptions(codec=codec, effects=EffectOptions.none())
    (path,) = render_videos(session, tmp_path, options)
    capture = cv2.VideoCapture(str(path))
    camera = session.cameras[0]
    assert int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) == camera.frames
    assert abs(capture.get(cv2.CAP_PROP_FPS) - camera.fps) < 1e-3
    assert (capture.get(cv2.CAP_PROP_FRAME_WIDTH), capture.get(cv2.CAP_PROP_FRAME_HEIGHT)) == (320, 180)
    renderer = CameraRenderer(session, 0, options, np.random.default_rng([session.options.seed, 1]))
    picks = [session.plan.cycles[0].dig_start, session.plan.cycles[0].dig_end]
    wanted = [int(round(t * camera.fps)) for t in picks]
    clean = dict(renderer.frames(np.array(sorted({f + d for f in wanted for d in (0, 3)})), clean=True))
    for frame in wanted:
        capture.set(cv2.CAP_PROP_POS_FRAMES, frame)
        ok, image = capture.read()
        assert ok
        same = np.abs(image.astype(float) - clean[frame]).mean()
        later = np.abs(image.astype(float) - clean[frame + 3]).mean()
        assert same < 4.0 and same < later


def test_cli_renders_a_low_resolution_session(tmp_path):
    out = tmp_path / "s"
    argv = ["synth", "--machine", "bobcat_225", "--cameras", "2", "--cycles", "1", "--seed", "4",
            "--scale", "0.2", "--fps", "5", "--codec", "mp4v", "--out", str(out)]
    assert main(argv) == 0
    config = load_session_config(out / "session.toml")
    tracks = load_tracks(out / "truth" / "tracks.csv")
    for camera in config.cameras:
        capture = cv2.VideoCapture(str(out / camera.video))
        assert capture.get(cv2.CAP_PROP_FRAME_WIDTH) == 384 and capture.get(cv2.CAP_PROP_FRAME_HEIGHT) == 216
        frames = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        rows = tracks.of_camera(camera.name)
        assert rows.frame.max() < frames and rows.frame.max() > frames - 5
        assert np.all(rows.xy <= [383, 215])


def test_cli_rejects_bad_effects(tmp_path, capsys):
    argv = ["synth", "--machine", "bobcat_225", "--out", str(tmp_path / "s"), "--dust", "2"]
    assert main(argv) == 2
    assert "blur and dust 0..0.9" in capsys.readouterr().err


def test_same_seed_same_pictures():
    machine = load_machine("bobcat_225")
    session = make_session(machine, "bobcat_225", n_cameras=1, n_cycles=1, seed=8, size=(256, 144))
    frames = np.array([10, 200, 201])
    first = [image for _, image in CameraRenderer(session, 0, RenderOptions(), np.random.default_rng(3)).frames(frames)]
    again = [image for _, image in CameraRenderer(session, 0, RenderOptions(), np.random.default_rng(3)).frames(frames)]
    other = [image for _, image in CameraRenderer(session, 0, RenderOptions(), np.random.default_rng(4)).frames(frames)]
    assert all(np.array_equal(a, b) for a, b in zip(first, again))
    assert not np.array_equal(first[1], other[1])


def test_motion_blur_keeps_moving_markers_centred_on_the_truth():
    """Smeared over an exposure centred on the frame's time, a moving marker's dark
    centroid stays at its true position then."""
    machine = load_machine("hitachi_ex3500")
    session = make_session(machine, "hitachi_ex3500", n_cameras=1, n_cycles=1, seed=3, size=(960, 540), bounce=0.0)
    camera = session.cameras[0]
    cycle = session.plan.cycles[0]
    swinging = int(round((cycle.dig_end + 0.4 * (cycle.end - cycle.dig_end)) * camera.fps))
    frames = np.arange(swinging - 1, swinging + 1)
    effects = EffectOptions(noise=0.0, blur=0.5, exposure=0.0, dust=0.0)
    renderer = CameraRenderer(session, 0, RenderOptions(effects=effects), np.random.default_rng(0))
    (_, image), = [item for item in renderer.frames(frames)][1:]
    uv, seen, _ = session.observe(camera, frames[1:])
    before, _, _ = session.observe(camera, frames[:1])
    grey = image.astype(float).mean(axis=2)
    errors, moves = [], []
    for m in np.flatnonzero(seen[0]):
        step = np.linalg.norm(uv[0, m] - before[0, m])
        x, y = np.round(uv[0, m]).astype(int)
        r = 4
        window = grey[y - r : y + r + 1, x - r : x + r + 1]
        if step < 1.0 or window.shape != (2 * r + 1, 2 * r + 1) or window.min() > 100:
            continue
        weight = np.clip(120.0 - window, 0, None)
        yy, xx = np.mgrid[y - r : y + r + 1, x - r : x + r + 1]
        found = np.array([(weight * xx).sum(), (weight * yy).sum()]) / weight.sum()
        errors.append(np.linalg.norm(found - uv[0, m]))
        moves.append(step)
    assert len(errors) >= 3
    assert np.median(errors) < 0.25 * np.median(moves)
