"""The lens model a frame's pixels need, chosen by the data: the calibration is solved
without distortion, then with k1, then with k1 and k2, while the Bayesian information
criterion of its pixel residuals falls (each added coefficient must buy more than log n of
the pixels' cost); the model with the lowest criterion is kept if the frame carries it
(`carried`: the freed coefficients far from zero together, and each beyond its own SD, by
the calibration's covariance). A few markers in a small part of the image fit a
lens coefficient as well as any, but do not fix it: its SD there is as large as itself,
and the image away from the markers would be tens of pixels off. Else the next simpler
model is tried in the same way, down to no distortion."""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from mocap.calibration.problem import Observations
from mocap.calibration.solve import CalibrationOptions, CalibrationResult, calibrate
from mocap.core.camera import Camera
from mocap.core.guess import Guess
from mocap.core.machine import Machine
from mocap.errors import InputError
from mocap.reconstruct.chi2 import upper_quantile

log = logging.getLogger(__name__)

LENS_MODELS = ("none", "k1", "k1k2")
JOINT_TAIL = 1e-3  # the freed coefficients together this far in the tail of no lens at all ...
CAMERA_SDS = 1.0  # ... and each at least this many of its SDs from zero, or the model is not carried


def carried(result: CalibrationResult, model: str) -> bool:
    """Whether the calibration's frame carries the lens coefficients of `model` that it
    fitted: together beyond the JOINT_TAIL quantile of their chi-square under no
    distortion (their covariance), and each at least CAMERA_SDS SDs from zero (one camera
    seeing a few markers in a corner of its image fits any value). Coefficients held
    (known intrinsics) do not count."""
    terms = {"k1": ("k1",), "k1k2": ("k1", "k2")}.get(model, ())
    index = np.array([k for k, name in enumerate(result.parameter_names) if name.rsplit(".", 1)[-1] in terms], int)
    if not len(index):
        return True
    variance = np.diag(result.covariance)[index]
    index = index[variance > 0]
    if not len(index):
        return True
    value, block = result.parameters[index], result.covariance[np.ix_(index, index)]
    if np.any(np.abs(value) < CAMERA_SDS * np.sqrt(np.diag(block))):
        return False
    joint = float(value @ np.linalg.solve(block, value))
    return joint > float(upper_quantile(np.array([len(index)]), JOINT_TAIL)[0])


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
    fitted: dict[str, CalibrationResult] = {}
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
        fitted[model] = result
        if best is not None and criterion[model] >= criterion[best[0]]:
            break
        best = (model, result)
    if best is None:
        raise first_error
    while best[0] != "none" and not carried(best[1], best[0]):
        simpler = LENS_MODELS[LENS_MODELS.index(best[0]) - 1]
        log.info("lens model %s not carried by the frame: %s tried", best[0], simpler)
        if simpler not in fitted:
            raise first_error
        best = (simpler, fitted[simpler])
    log.info("lens model chosen by the data: %s (BIC %s)", best[0], criterion)
    return best[1], criterion
