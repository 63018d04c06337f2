"""Frames that two far-apart solutions explain equally well.

A joint whose link shows one marker to one camera can often be turned to a second value
(a mirror solution) that puts every marker on the same pixels within the noise: the data
cannot tell the two apart, however good the fit. No optimiser fixes that, and the
standard deviation of the fit (a local curvature) does not show it. Such frames are found
by fitting sampled frames again with each joint started across its range and looking for
a solution as good as the fit's (a chi-square difference below `CHI2_SAME`) lying many
standard deviations away; the stage says so in its report and the benchmark counts them.

Shapes: C cameras, F frames, M markers, J joints.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from mocap.camera import Camera
from mocap.machine import Machine
from mocap.reconstruct.kinfit import FitOptions, JointFit, fit_joints

CHI2_SAME = 4.0  # a chi-square difference below this: the pixels do not prefer either solution (95 %, 1 dof)
FAR_SDS = 5.0  # the second solution lies at least this many of the fit's SDs away (Mahalanobis)
LEVELS = 4  # starts per joint across its range


@dataclass(frozen=True)
class Ambiguity:
    """checked (F,) frames fitted again; ambiguous (F,) those with a second solution as good
    as the fit's and far from it; alternative (F, J) that solution (NaN elsewhere)."""

    checked: np.ndarray
    ambiguous: np.ndarray
    alternative: np.ndarray

    @property
    def share(self) -> float:
        """The share of the checked frames that are ambiguous."""
        return float(self.ambiguous.sum() / max(self.checked.sum(), 1))


def second_solutions(machine: Machine, cameras: list[Camera], pixels: np.ndarray, fit: JointFit,
                     options: FitOptions | None = None, stride: int = 8, most: int = 256) -> Ambiguity:
    """Every `stride`-th valid frame of `fit` (from pixels (C, F, M, 2)), at most `most` of
    them spread over the session, fitted again from each joint set to `LEVELS` values across
    its range, the others kept. (Whether a second solution exists depends on what the
    cameras see of the links, not on the hour: a long session needs no more frames checked.)"""
    options = options or FitOptions()
    n_frames, n_joints = fit.joints.shape
    valid = np.nonzero(fit.valid)[0]
    frames = valid[:: max(stride, -(-len(valid) // most))]
    checked = np.zeros(n_frames, dtype=bool)
    checked[frames] = True
    ambiguous = np.zeros(n_frames, dtype=bool)
    alternative = np.full((n_frames, n_joints), np.nan)
    if not len(frames) or n_joints == 0 or fit.base is not None:
        return Ambiguity(checked, ambiguous, alternative)
    again = replace(options, noise_px=fit.noise_px, repair_passes=0)
    own_chi2 = _chi2(fit, fit.noise_px)[frames]
    best = np.full(len(frames), np.inf)
    limits = machine.joint_limits
    lower = np.where(np.isfinite(limits[:, 0]), limits[:, 0], -1.0)
    upper = np.where(np.isfinite(limits[:, 1]), limits[:, 1], 1.0)
    for j in range(n_joints):
        for level in (np.arange(LEVELS) + 0.5) / LEVELS:
            start = fit.joints[frames].copy()
            start[:, j] = lower[j] + level * (upper[j] - lower[j])
            other = _quietly(fit_joints, machine, cameras, pixels[:, frames], start, again)
            gap = other.joints - fit.joints[frames]
            distance = np.einsum("fp,fpq,fq->f", gap, fit.information[frames], gap)
            same = (_chi2(other, fit.noise_px) < own_chi2 + CHI2_SAME) & (distance > FAR_SDS**2)
            closer = same & (distance < best)  # the nearest far solution: the one the data least exclude
            best = np.where(closer, distance, best)
            alternative[frames[closer]] = other.joints[closer]
    ambiguous[frames] = np.isfinite(best)
    return Ambiguity(checked, ambiguous, alternative)


def _quietly(function, *args):
    """function(*args) with the fit's own warnings (frames a wrong start leaves unexplained) held back."""
    logger = logging.getLogger(fit_joints.__module__)
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        return function(*args)
    finally:
        logger.setLevel(level)


def _chi2(fit: JointFit, noise_px: float) -> np.ndarray:
    """(F,) the robustly weighted sum of squared residuals in units of the noise."""
    squared = np.sum(fit.residuals**2, axis=-1) * fit.weights  # (C, F, M)
    return np.nansum(squared, axis=(0, 2)) / noise_px**2
