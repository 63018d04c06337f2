"""A rolling shutter in the synthetic field sessions: the pictures composed by rows, the
truth where each marker is when its own row is read, a global shutter as before."""

from __future__ import annotations

import numpy as np
import pytest

from mocap.cli import main
from mocap.io.machine_toml import load_machine
from mocap.synthetic import SessionOptions, make_session
from mocap.synthetic.effects import EffectOptions
from mocap.synthetic.looks import Look, random_look
from mocap.synthetic.render import WHITE, CameraRenderer, RenderOptions
from mocap.synthetic.shutter import instants, row_delay, row_weights

SIZE = (1280, 720)


@pytest.fixture(scope="module")
def sessions():
    machine = load_machine("hitachi_ex3500")
    kwargs = dict(n_cameras=1, n_cycles=1, seed=3, size=SIZE, bounce=0.0, hold=1.0)
    return make_session(machine, "hitachi_ex3500", readout=0.9, **kwargs), make_session(machine, "hitachi_ex3500",
                                                                                          **kwargs)


def fastest_frames(session, count: int) -> np.ndarray:
    """The `count` frames (sorted) in which the fastest visible marker moves most."""
    camera = session.cameras[0]
    uv, _, _ = session.observe(camera, np.arange(camera.frames))
    travel = np.nanmax(np.nan_to_num(np.linalg.norm(np.diff(uv, axis=0), axis=-1)), axis=1)
    return np.sort(np.argsort(-travel)[:count])


def disk_centroid(grey: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray | None:
    """The dark centroid (2,) of a disk of about `radius` px near `centre` on its white
    square (None unless the ring around the disk is all white: the disk's own square, not
    cut by an edge or another link)."""
    x, y = np.round(centre).astype(int)
    r = int(np.ceil(radius + 3))
    window = grey[y - r : y + r + 1, x - r : x + r + 1]
    if window.shape != (2 * r + 1, 2 * r + 1):
        return None
    yy, xx = np.mgrid[y - r : y + r + 1, x - r : x + r + 1]
    distance = np.hypot(xx - centre[0], yy - centre[1])
    ring = (distance > radius + 1.5) & (distance < radius + 2.5)
    if np.any(np.abs(window[ring] - WHITE[0]) > 3):
        return None
    weight = np.where(distance <= radius + 1.5, np.clip(WHITE[0] - window, 0, None), 0.0)
    return np.array([(weight * xx).sum(), (weight * yy).sum()]) / weight.sum()


def test_rolling_shutter_draws_each_marker_where_its_row_was_read(sessions):
    """At the fastest frames, the disks' centroids in the clean pictures lie on the truth
    tracks (each marker when its own row was read) to the renderer's accuracy (its fine
    grid's and the perspective's: 0.1 px, as with a global shutter), while where the markers
    were at the frame's time lies up to a pixel or more away."""
    rolling, _ = sessions
    camera = rolling.cameras[0]
    frames = fastest_frames(rolling, 4)
    renderer = CameraRenderer(rolling, 0, RenderOptions(effects=EffectOptions.none()), np.random.default_rng(0))
    at_frame, seen, poses = rolling.observe(camera, frames)
    truth = rolling.tracks
    on_link = poses[:, rolling.machine.marker_links]
    disks = np.einsum("fmij,mnj->fmni", on_link[..., :3, :3], renderer.disks) + on_link[..., None, :3, 3]
    disks = renderer._project(camera.cam_from_world(camera.times(frames)), disks)
    errors, shifts = [], []
    for k, (frame, image) in enumerate(renderer.frames(frames, clean=True)):
        grey = image.astype(float).mean(axis=2)
        rows = truth.select(truth.frame == frame)
        for name, xy in zip(rows.marker, rows.xy):
            m = rolling.machine.marker_names.index(name)
            radius = np.sqrt(np.prod(np.ptp(disks[k, m], axis=0))) / 2
            found = disk_centroid(grey, xy, radius)
            if found is not None:
                errors.append(np.linalg.norm(found - xy))
                shifts.append(np.linalg.norm(xy - at_frame[k, m]))
    errors, shifts = np.array(errors), np.array(shifts)
    assert len(errors) >= 20
    assert errors.max() <= 0.1
    moved = shifts > 0.5
    assert moved.sum() >= 3 and shifts.max() > 1.0
    assert np.all(errors[moved] < 0.1 * shifts[moved])


def test_global_shutter_is_unchanged_and_a_still_frame_too(sessions):
    """Readout 0: the truth is the markers at the frame's time; a still frame (the machine
    holding) is drawn the same with a rolling shutter, a moving one is not."""
    rolling, plain = sessions
    camera = plain.cameras[0]
    uv, seen, _ = plain.observe(camera, np.arange(camera.frames))
    f, m = plain.tracks.frame.astype(int), plain.machine.marker_index(plain.tracks.marker)
    assert np.array_equal(plain.tracks.xy, uv[f, m]) and np.all(seen[f, m])
    assert np.array_equal(rolling.tracks.frame, plain.tracks.frame)
    still = plain.tracks.frame < 10
    assert np.array_equal(rolling.tracks.xy[still], plain.tracks.xy[still])
    frames = np.array([5, fastest_frames(plain, 1)[0]])
    options = RenderOptions(effects=EffectOptions(noise=0.0, blur=0.5, exposure=0.0, dust=0.0))
    pictures = [[image for _, image in CameraRenderer(s, 0, options, np.random.default_rng(1)).frames(frames)]
                for s in (rolling, plain)]
    assert np.array_equal(pictures[0][0], pictures[1][0])
    assert np.abs(pictures[0][1].astype(int) - pictures[1][1]).max() > 100


@pytest.mark.parametrize("readout, exposure", [(0.9, 0.0), (0.5, 0.5), (0.2, 0.7)])
def test_rows_are_composed_at_their_own_instants(readout, exposure):
    """Each row's weights add up to 1 and centre on the instant the row is read; spread as
    the exposure's box (SD exposure / sqrt 12) and at most the interpolation between two
    instants (a share a of a step from one: variance a (step - a) <= step^2 / 4) more."""
    height = 90
    for count in (2, 5, 12):
        weights = row_weights(height, readout, exposure, count).astype(float)
        times = instants(readout, exposure, count)
        assert np.allclose(weights.sum(axis=0), 1.0) and np.all(weights >= 0)
        assert np.allclose(times @ weights, row_delay(np.arange(height), height, readout), atol=1e-6)
        spread = np.sqrt(((times[:, None] - times @ weights) ** 2 * weights).sum(axis=0))
        step = times[1] - times[0]
        assert np.all(spread <= np.sqrt(exposure**2 / 12 + step**2 / 4) + 1e-6)  # the box's and the interpolation's
        assert np.all(spread >= exposure / np.sqrt(12) - 1e-6)


def test_random_looks_draw_rolling_and_global_shutters():
    looks = [random_look(np.random.default_rng(seed)) for seed in range(60)]
    readouts = np.array([look.readout for look in looks])
    assert 0.15 < np.mean(readouts == 0) < 0.6 and readouts.max() <= 0.9 and readouts[readouts > 0].min() >= 0.2
    look = next(look for look in looks if look.readout)
    assert f"rolling shutter {look.readout:.2f}" in look.name and look.table()["readout"] == look.readout


def test_guards(tmp_path, capsys):
    with pytest.raises(ValueError, match="readout must be 0..0.9"):
        Look(readout=0.95)
    with pytest.raises(ValueError, match="readout must be 0..0.9"):
        SessionOptions(readout=-0.1)
    argv = ["synth", "--machine", "bobcat_225", "--out", str(tmp_path / "s"), "--rolling-shutter", "1.2"]
    assert main(argv) == 2
    assert "--rolling-shutter 1.2: give a share of the frame interval, 0..0.9" in capsys.readouterr().err
