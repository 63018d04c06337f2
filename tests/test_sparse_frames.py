"""Frames that are not a dense video: every k-th frame of a session, the machine moving
far between them. The track checks read the frame spacing from the data (how far the
tracks bend between frames) and do not take the motion for wild pixels: every good view
kept, coverage that of two cameras; on the dense video they still judge."""

import numpy as np
import pytest

from mocap.io.machine_toml import load_machine
from mocap.reconstruct.outliers import dense_tracks, track_bends
from mocap.reconstruct.timing import tracks_on_reference_clock
from mocap.reconstruct.triangulate import triangulate_tracks
from mocap.synthetic.machines import random_motion
from mocap.synthetic.scenes import observe, ring_of_cameras

NOISE = 0.5


def session(step: int, seed: int, n_frames: int = 40):
    """3 cameras, every `step`-th frame of a 30 fps session renumbered 0, 1, 2, ..."""
    machine = load_machine("hitachi_ex3500")
    rng = np.random.default_rng(seed)
    cameras = ring_of_cameras(3, np.array([5.0, 0.0, 5.0]), (30.0, 60.0), rng, fov_deg=(40.0, 60.0))
    joints = random_motion(machine, n_frames * step, rng)[::step]
    tracks = observe(cameras, machine, joints, rng, noise_px=NOISE, miss_fraction=0.1)
    return machine, cameras, tracks


@pytest.mark.parametrize("step, seed", [(5, 2), (10, 0), (20, 1), (40, 0)])
def test_sparse_frames_keep_every_good_view(step, seed):
    """Each of these sessions lost 3-28 good views to the 3-D track check and up to 9
    pixels to the 2-D one when the frames were taken for a dense video."""
    machine, cameras, tracks = session(step, seed)
    names = [c.name for c in cameras]
    clock = tracks_on_reference_clock(tracks, names, machine.marker_names, np.full(3, 30.0), np.zeros(3))
    # a track's ends are judged from two extrapolations alone: pure noise passes their limit
    # about once in a thousand pixels (~3,300 here), as on the dense video
    assert clock.dropped <= 2
    result = triangulate_tracks(cameras, clock.pixels)
    assert result.contradicted.sum() == 0
    seen = tracks.dense(names, machine.marker_names, np.arange(clock.pixels.shape[1]))
    two = np.isfinite(seen[..., 0]).sum(0) >= 2
    assert np.isfinite(result.xyz[..., 0]).sum() >= 0.95 * two.sum()


def test_the_bend_is_read_from_the_data():
    """Noise alone bends a track by about nothing; the same motion sampled 20 times more
    sparsely bends it by ~400 times as much (acceleration per frame squared)."""
    machine, cameras, tracks = session(1, 3, n_frames=400)
    names = [c.name for c in cameras]
    dense = tracks.dense(names, machine.marker_names, np.arange(400))[0]
    bend, noise = track_bends(dense)
    sparse_bend, _ = track_bends(dense[::20])
    assert np.nanmedian(bend) < 0.25 * np.nanmedian(noise) and dense_tracks(dense, 0.5).all()
    assert np.nanmedian(noise) == pytest.approx(NOISE * np.sqrt(1.5) * 2.15, rel=0.25)  # 90th pct of |d| for SD 0.5
    flat = np.random.default_rng(0).normal(0, NOISE, (200, 3, 2))
    assert dense_tracks(flat, 0.5).all()
    exact = random_motion(machine, 400, np.random.default_rng(1))[::20]
    world = machine.markers(exact)
    pixels = cameras[0].project(world)
    bent, _ = track_bends(pixels)
    assert np.nanmedian(bent) > 0.5 and not dense_tracks(pixels, 0.5).all()
    assert np.nanmedian(sparse_bend) > 10 * np.nanmedian(bend)
