"""The noise floor: the error of interpolating between frames (cameras whose clocks differ
by a fraction of a frame) and the pixel quantisation are part of the noise model, so exact
tracks never make a frame `unexplained`; frames that no pose explains still are."""

import numpy as np
import pytest

from mocap.core.tracks import concatenate
from mocap.io.machine_toml import load_machine
from mocap.reconstruct.kinfit import fit_joints, noise_floor
from mocap.reconstruct.timing import tracks_on_reference_clock
from mocap.synthetic.machines import random_motion
from mocap.synthetic.scenes import observe, ring_of_cameras

FPS, OFFSET = 30.0, 0.37 / 30.0  # the second camera's clock 0.37 frame behind


@pytest.fixture(scope="module")
def exact():
    """Noise-free tracks of a shovel moving at three times a machine's pace, two cameras,
    resampled onto the first camera's clock (the second's linearly interpolated)."""
    machine = load_machine("hitachi_ex3500")
    rng = np.random.default_rng(0)
    cameras = ring_of_cameras(2, np.array([5.0, 0.0, 5.0]), (30.0, 50.0), rng, fov_deg=(40.0, 55.0))
    full = random_motion(machine, 480, rng, fps=FPS)
    t = np.arange(150) / FPS
    parts = []
    for c, camera in enumerate(cameras):
        times = (t + c * OFFSET) * 3 * FPS
        joints = np.stack([np.interp(times, np.arange(len(full)), full[:, j]) for j in range(full.shape[1])], -1)
        parts.append(observe([camera], machine, joints, rng, noise_px=0.0))
    clock = tracks_on_reference_clock(concatenate(parts), [c.name for c in cameras], machine.marker_names,
                                      np.full(2, FPS), np.array([0.0, OFFSET]))
    return machine, cameras, clock.pixels


def test_exact_interpolated_tracks_leave_no_frame_unexplained(exact):
    """Before the floor: 7 of these 150 frames were `unexplained` at the 0.003 px of noise
    the fit estimates."""
    machine, cameras, pixels = exact
    fit = fit_joints(machine, cameras, pixels)
    assert fit.noise_px < 0.05  # the interpolation leaves a few hundredths of a pixel, in places more
    assert fit.valid.all() and fit.explained.all()


def test_frames_that_no_pose_explains_stay_unexplained(exact):
    machine, cameras, pixels = exact
    wrong = pixels.copy()
    swap = np.random.default_rng(1).permutation(pixels.shape[2])
    wrong[:, 70:73] = pixels[:, 70:73][:, :, swap]  # every camera's labels mixed in three frames
    fit = fit_joints(machine, cameras, wrong)
    assert not fit.explained[70:73].any() and fit.explained[:65].all() and fit.explained[78:].all()


def test_the_floor_carries_quantisation_and_the_bend():
    rng = np.random.default_rng(2)
    whole = np.round(rng.uniform(0, 500, (1, 20, 3, 2)))
    t = np.arange(20.0)
    parabola = np.stack([np.stack([0.5 * t**2, t], -1)] * 3, 1)[None] + 0.25  # bend 1 px per frame², not whole
    floor = noise_floor(parabola)
    assert floor[0, 10] == pytest.approx(np.full(3, 1 / 8))
    assert (noise_floor(whole) >= 1 / np.sqrt(12) - 1e-12).all()
