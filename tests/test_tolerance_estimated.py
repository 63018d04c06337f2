"""A tolerance the machine file does not state is estimated from the calibration's
residuals: field scenes (every marker coordinate off by up to ±5 %, 0.8 px noise) whose
exact model put a camera many times its Cramér–Rao bound away are calibrated within the
tolerance their residuals show, reported; a stated tolerance, an exact one too, wins, and
a clean scene's residuals show none."""

import numpy as np
import pytest

from mocap.calibration import CalibrationOptions, calibrate, template_camera
from mocap.calibration.noise import model_error_fraction
from mocap.calibration.report import format_report
from mocap.core.machine import Tolerance
from mocap.synthetic.machines import SceneOptions, random_scene

from test_field_calibration import FIELD, _bound, _field_scene

ALONG_SIGHT_99 = 2.58  # a camera's error lies along its line of sight: |N(0, 1)| at 99 %


def _ratios(result, scene) -> np.ndarray:
    error = np.array([np.linalg.norm(a.center - b.center) for a, b in zip(result.cameras, scene.cameras)])
    return error / _bound(scene)


@pytest.mark.parametrize("seed", [1000010, 1000011])  # the exact model: 7.6 and 6.6 times the bound
def test_a_tolerance_not_stated_is_estimated_and_used(seed):
    scene, templates, _ = _field_scene(seed)
    result = calibrate(scene.model, scene.observations(), templates, CalibrationOptions())
    assert result.estimated_tolerance is not None and 0.02 < result.estimated_tolerance < 0.2
    assert np.all(_ratios(result, scene) < ALONG_SIGHT_99), _ratios(result, scene)
    assert "within an estimated tolerance of" in format_report(result, 0)
    exact = calibrate(scene.model, scene.observations(), templates, CalibrationOptions(tolerance=Tolerance()))
    assert exact.estimated_tolerance is None and np.max(_ratios(exact, scene)) > ALONG_SIGHT_99


SCENE_SPREAD = 0.012  # the estimate's SD from scene to scene (one frame each), the truth being 0.05


def test_the_estimated_tolerance_is_the_stated_fraction_on_average():
    """Field scenes whose coordinates are off by up to ±5 %: the estimates from their exact
    models' residuals (each standardised by the share of its variance the fit leaves) average
    5 %, within twice their spread over the mean of four; reading the projected scale as an
    SD, or the residuals as the whole model error, puts the average at 7 %."""
    estimates = []
    for seed in (1000008, 1000010, 1000011, 1000014):
        scene, templates, _ = _field_scene(seed)
        result = calibrate(scene.model, scene.observations(), templates, CalibrationOptions())
        estimates.append(result.estimated_tolerance)
    assert None not in estimates, estimates
    assert abs(np.mean(estimates) - FIELD.tolerance) < 2 * SCENE_SPREAD / np.sqrt(len(estimates)), estimates


def test_a_stated_tolerance_wins():
    scene, templates, options = _field_scene(1000011)
    assert calibrate(scene.model, scene.observations(), templates, options).estimated_tolerance is None


def test_a_clean_scene_shows_no_model_error():
    scene = random_scene(np.random.default_rng(4), SceneOptions(), n_frames=2)
    templates = [template_camera(c.name, c.size) for c in scene.cameras]
    assert calibrate(scene.model, scene.observations(), templates, CalibrationOptions()).estimated_tolerance is None


def test_outliers_named_on_many_markers_show_the_model_error():
    """An exact model's fit that named outliers on several markers (the model error's
    largest residuals) leaves the rest only 1.3 times the stated noise: the model error is
    still shown and its tolerance estimated (80 residuals: over such draws the estimate's SD
    is 0.0032 and it lies 0.002 low, the stated noise being above the true; the bound is
    that bias and 3 SDs); with no outliers named, residuals at 1.3 times the noise show none."""
    rng = np.random.default_rng(0)
    marker = np.repeat(np.arange(20), 4)
    scale = rng.uniform(20.0, 80.0, len(marker))  # px a fraction of 1 moves each observation
    left = np.full(len(marker), 0.8)  # the share of each residual's variance the fit leaves
    residual = rng.normal(size=(len(marker), 2)) * np.sqrt((0.8**2 + (0.05 * scale) ** 2) * left)[:, None]
    squared = np.sum(residual**2, axis=1)
    named = np.zeros(len(marker), dtype=bool)
    named[[0, 4, 8, 12]] = True  # four markers' largest residuals named outliers
    estimate = model_error_fraction(squared, scale, marker, 1.0, 1.3, left, named)
    assert estimate is not None and abs(estimate - 0.05) < 0.002 + 3 * 0.0032, estimate
    assert model_error_fraction(squared, scale, marker, 1.0, 1.3, left) is None
