"""A one-frame calibration frees a lens coefficient only where the frame carries it: each
freed coefficient beyond its own SD, all of them together far from zero (the calibration's
covariance). A few markers in a small part of the image (12 board corners) fit k1 as well
as any value, which the criterion of the fitted pixels alone took for a lens, and the
cameras came out hundreds of pixels off away from the markers. Real lenses (OpenCV's
sample pairs, k1 about -0.3) stay freed."""

from pathlib import Path

import numpy as np
import pytest

from mocap.calibration import CalibrationOptions, Observations
from mocap.calibration.lens_choice import calibrate_choosing_lens, carried
from mocap.calibration.solve import template_camera
from mocap.errors import InputError
from mocap.io.machine_toml import load_machine
from mocap.io.tracks_csv import load_tracks
from mocap.synthetic.lens_scene import board_scene

BLOCK = [row * 9 + column for row in range(3) for column in range(4)]  # 12 corners, a corner of the board
DATA = Path(__file__).parent / "data" / "opencv_stereo"


def corner_block(pixels):
    c, m = np.nonzero(np.isfinite(pixels[:, 0, :, 0]))
    keep = np.isin(m, BLOCK)
    return Observations(c[keep], m[keep], pixels[c[keep], 0, m[keep]])


def test_twelve_corners_do_not_carry_a_lens_the_pinhole_cannot():
    """Mild distortion (k1 = -0.02), 12 corners per camera: k1 has the lowest BIC, with k1
    up to 2 and the image corners 100-10,000 px off; now the frame's own doubt is reported."""
    scene = board_scene(np.random.default_rng(0), n_frames=1, noise_px=0.5, k1=-0.02)
    templates = [template_camera(x.name, x.size) for x in scene.cameras]
    with pytest.raises(InputError, match="focal length and distance of camera"):
        calibrate_choosing_lens(scene.board, corner_block(scene.pixels), templates, CalibrationOptions())


def test_real_lenses_are_carried_by_twelve_corners():
    board = load_machine(DATA / "board.toml")
    tracks = load_tracks(DATA / "corners.csv")
    pixels = tracks.dense(["left", "right"], board.marker_names, tracks.frames)
    templates = [template_camera(n, (640, 480)) for n in ("left", "right")]
    result, criterion = calibrate_choosing_lens(board, corner_block(pixels), templates, CalibrationOptions())
    assert min(criterion, key=criterion.get) == "k1" and carried(result, "k1")
    assert all(-0.5 < camera.distortion[0] < -0.1 for camera in result.cameras)  # OpenCV's own: about -0.3
