"""The lens model a frame's pixels need, chosen by the data: the calibration is solved
without distortion, then with k1, then with k1 and k2, while the Bayesian information
criterion of its pixel residuals falls (each added coefficient must buy more than log n of
the pixels' cost); the model with the lowest criterion is kept."""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from mocap.calibration.problem import Observations
from mocap.calibration.solve import CalibrationOptions, CalibrationResult, Guess, calibrate
from mocap.camera import Camera
from mocap.errors import InputError
from mocap.machine import Machine

log = logging.getLogger(__name__)

LENS_MODELS = ("none", "k1", "k1k2")


def information_criterion(result: CalibrationResult, scale_px: float) -> float:
    """BIC of a calibration: n log(cost / n) + p log(n) over every pixel coordinate
    (outliers too), the cost Huber's at `scale_px` so that an outlier counts linearly."""
    e = np.abs(np.concatenate([r.residual for r in result.residuals]))
    n = max(len(e), 1)
    cost = np.where(e <= scale_px, e * e, 2 * scale_px * e - scale_px**2).sum()
    return float(n * np.log(max(cost, 1e-300) / n) + len(result.parameters) * np.log(n))


def calibrate_choosing_lens(machine: Machine, observations: Observations, templates: list[Camera],
                            options: CalibrationOptions, guess: Guess | None = None
                            ) -> tuple[CalibrationResult, dict[str, float]]:
    """The calibration with the lens model the data choose, and {model: BIC} of those tried
    (inf where that model did not converge). Raises the first model's error when none converges."""
    criterion: dict[str, float] = {}
    best: tuple[str, CalibrationResult] | None = None
    first_error = None
    for model in LENS_MODELS:
        try:
            result = calibrate(machine, observations, templates, replace(options, distortion=model), guess)
        except InputError as exc:  # too few pixels for its coefficients, or no convergence
            criterion[model] = float("inf")
            first_error = first_error or exc
            if best is not None:
                break
            continue
        criterion[model] = information_criterion(result, options.f_scale_px)
        if best is not None and criterion[model] >= criterion[best[0]]:
            break
        best = (model, result)
    if best is None:
        raise first_error
    log.info("lens model chosen by the data: %s (BIC %s)", best[0], criterion)
    return best[1], criterion
