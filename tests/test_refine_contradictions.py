"""Refine estimates the tracks' noise and refines; it refuses only a contradiction it can
name: a wrong sync (a clock shift explains a camera's residuals) or wrong labels (one
camera's tracks far from where the others put the markers). Real data the project did not
make (OpenCV's sample stereo pairs) with a lens model that leaves 1.5-2 px: written, and
better than the one-frame calibration it started from."""

from pathlib import Path

import numpy as np
import pytest

from mocap import cli
from mocap.errors import ConvergenceError
from mocap.io.cameras_toml import load_calibration
from mocap.io.machine_toml import load_machine
from mocap.io.tracks_csv import load_tracks
from mocap.reconstruct.refine import RefineOptions, refine
from mocap.reconstruct.triangulate import TriangulateOptions, triangulate
from mocap.synthetic.scenes import observe, ring_of_cameras
from test_refine import perturbed

DATA = Path(__file__).parent / "data" / "opencv_stereo"
FPS = 30.0
NOISE = 0.5
START = np.radians([0.0, 40.0, -70.0, 30.0])


def smooth_joints(t: np.ndarray) -> np.ndarray:
    """(F, J) a smooth dig-like motion of the shovel over time t (F,) s."""
    t = np.asarray(t)[:, None]
    return START + np.radians([40, 15, 25, 35]) * np.sin(
        2 * np.pi * t * np.array([0.30, 0.66, 0.78, 1.02]) + np.array([0.0, 1.0, 2.0, 3.0]))


@pytest.fixture(scope="module")
def video():
    """3 cameras watching 60 frames of smooth motion; `shifted(dt)` their pixels with camera
    1's clock dt frames off."""
    machine = load_machine("hitachi_ex3500")
    rng = np.random.default_rng(11)
    cameras = ring_of_cameras(3, np.array([5.0, 0.0, 5.0]), (30.0, 60.0), rng, fov_deg=(40.0, 60.0))
    names, frames = [c.name for c in cameras], np.arange(60)
    start = perturbed(cameras, rng)

    def shifted(dt: float) -> np.ndarray:
        pixels = []
        for c, camera in enumerate(cameras):
            t = (frames + (dt if c == 1 else 0.0)) / FPS
            tracks = observe([camera], machine, smooth_joints(t), np.random.default_rng(c), noise_px=NOISE)
            pixels.append(tracks.dense([names[c]], machine.marker_names, frames)[0])
        return np.stack(pixels)

    return machine, cameras, start, shifted


def test_a_wrong_sync_is_named_and_refused(video):
    machine, _, start, shifted = video
    with pytest.raises(ConvergenceError, match=r"clocks disagree by up to 3\.0 frames \(cam2 \+3\.0, .*wrong sync"):
        refine(machine, start, shifted(3.0), RefineOptions(frames=15))


def test_cameras_not_genlocked_are_refined_and_the_noise_reported(video):
    """A third of a frame between the clocks (webcams not genlocked): no contradiction; the
    offset solved for (the tracks' own image velocity), the noise estimated as it is, the
    cameras refined. 0.5 px on ~25 markers x 15 frames moving ~1.5 px/frame: the offset to
    ~0.02 frame."""
    machine, cameras, start, shifted = video
    result = refine(machine, start, shifted(0.3), RefineOptions(frames=15))
    assert result.clock_frames[1] == pytest.approx(0.3, abs=0.06) and abs(result.clock_frames[2]) < 0.06
    assert result.noise_px == pytest.approx(NOISE, rel=0.2)
    assert max(result.median_px) < 1.5 * NOISE * np.sqrt(2)
    for refined, true, initial in zip(result.cameras, cameras, start):
        assert np.linalg.norm(refined.center - true.center) < np.linalg.norm(initial.center - true.center)


def test_tracks_the_model_contradicts_as_a_whole_are_refused(video):
    """Every camera's tracks labelled alike but as other markers of the model (no camera
    stands out, no clock explains it): the tracks lie far from any refined model, where their
    own frame-to-frame noise is ~0.5 px; named with both figures, nothing returned."""
    machine, _, start, shifted = video
    pixels = shifted(0.0)
    swapped = pixels[:, :, np.random.default_rng(0).permutation(pixels.shape[2])]
    with pytest.raises(ConvergenceError, match=r"the tracks lie \d+\.\d px \(median\) from the refined model where "
                                               r"their own noise is 0\.[4-6]\d px: a wrong machine model"):
        refine(machine, start, swapped, RefineOptions(frames=15))


def adjacent_rmse(cameras, pixels) -> float:
    """RMS error, in squares, of adjacent corners' distance (the 9x6 board's truth)."""
    xyz = triangulate(list(cameras), pixels, TriangulateOptions(max_error_px=1e6)).xyz
    grid = xyz.reshape(len(xyz), 6, 9, 3)
    steps = np.r_[np.linalg.norm(np.diff(grid, axis=2), axis=-1).ravel(), np.linalg.norm(np.diff(grid, axis=1), axis=-1).ravel()]
    return float(np.sqrt(np.nanmean((steps - 1.0) ** 2)))


def test_real_tracks_far_from_a_plain_lens_are_refined_not_refused(tmp_path, capsys):
    """OpenCV's sample pairs with no lens distortion allowed: the tracks stay 1.5-2 px from
    the refined cameras (the barrel distortion left out), which the former 1 px gate
    refused; now refine writes the result, says how far the tracks lie, and the board comes
    out better than from the one-frame calibration."""
    board, corners = str(DATA / "board.toml"), str(DATA / "corners.csv")
    one, refined = tmp_path / "one.toml", tmp_path / "refined.toml"
    assert cli.main(["calibrate", board, corners, "--size", "640x480", "--distortion", "none", "--out", str(one)]) == 0
    capsys.readouterr()
    assert cli.main(["refine", board, str(one), corners, "--base-motion", "--distortion", "none", "--out", str(refined)]) == 0
    report = capsys.readouterr().out
    assert "px (median) from the refined cameras, noise estimated" in report
    tracks = load_tracks(DATA / "corners.csv")
    pixels = tracks.dense(["left", "right"], load_machine(DATA / "board.toml").marker_names, tracks.frames)
    before, after = (adjacent_rmse(load_calibration(path).cameras, pixels) for path in (one, refined))
    assert after < 0.5 * before
    # an explicit gate is still kept
    assert cli.main(["refine", board, str(one), corners, "--base-motion", "--distortion", "none", "--max-median", "1",
                     "--out", str(tmp_path / "gated.toml")]) == 2
    assert "more than --max-median 1 px" in capsys.readouterr().err
