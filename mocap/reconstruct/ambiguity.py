"""Frames that two far-apart solutions explain equally well.

A joint whose link shows one marker to one camera can often be turned to a second value
(a mirror solution) that puts every marker on the same pixels within the noise: the data
cannot tell the two apart, however good the fit. No optimiser fixes that, and the
standard deviation of the fit (a local curvature) does not show it. Such frames are found
by fitting every frame (up to `most` of them spread over a long session) again with each
joint started across its range and looking for a solution as good as the fit's (a
chi-square difference below `PREFERRED_CHI2`) lying `FAR_SDS` standard deviations away (the
fit's own thresholds, by which it mends a stretch on a mirror solution); the stage
says so in its report and the benchmark counts them. All the restarts are solved in one
compiled call, and a restart that comes back to the fit's own solution stops there.

Shapes: C cameras, F frames, M markers, J joints, S starts per frame.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from mocap.core.camera import Camera
from mocap.core.machine import Machine
from mocap.reconstruct.kinfit import FAR_SDS, PREFERRED_CHI2, FitOptions, JointFit, refit
from mocap.reconstruct.kinmodel import FrameState

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
                     options: FitOptions | None = None, stride: int = 1, most: int = 256) -> Ambiguity:
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
    limits = machine.joint_limits
    lower = np.where(np.isfinite(limits[:, 0]), limits[:, 0], -1.0)
    upper = np.where(np.isfinite(limits[:, 1]), limits[:, 1], 1.0)
    starts = []
    for j in range(n_joints):
        for level in (np.arange(LEVELS) + 0.5) / LEVELS:
            start = fit.joints[frames].copy()
            start[:, j] = lower[j] + level * (upper[j] - lower[j])
            starts.append(start)
    n_starts = len(starts)
    repeated = np.tile(frames, n_starts)
    own = FrameState(fit.joints[repeated], None, None, np.zeros(len(repeated)),
                     fit.information[repeated] * fit.noise_px**2)
    other = refit(machine, cameras, pixels[:, repeated], np.concatenate(starts),
                  replace(options, noise_px=fit.noise_px), own)
    other_chi2 = np.where(np.isfinite(other.cost), _chi2(other.residual, other.weight, fit.noise_px), np.inf)
    own_chi2 = np.tile(_chi2_of_fit(fit)[frames], n_starts)
    gap = other.joints - fit.joints[repeated]
    distance = np.einsum("fp,fpq,fq->f", gap, fit.information[repeated], gap)
    same = (other_chi2 < own_chi2 + PREFERRED_CHI2) & (distance > FAR_SDS**2)
    # of each frame's far solutions, the nearest: the one the data least exclude
    distance = np.where(same, distance, np.inf).reshape(n_starts, len(frames))
    nearest = np.argmin(distance, axis=0)
    found = np.isfinite(distance[nearest, np.arange(len(frames))])
    ambiguous[frames] = found
    alternative[frames[found]] = other.joints.reshape(n_starts, len(frames), n_joints)[nearest, np.arange(len(frames))][found]
    return Ambiguity(checked, ambiguous, alternative)


def _chi2(residual: np.ndarray, weight: np.ndarray, noise_px: float) -> np.ndarray:
    """(F,) the robustly weighted sum of squared residuals (F, N) in units of the noise."""
    return (residual.astype(float) ** 2 * weight).sum(1) / noise_px**2


def _chi2_of_fit(fit: JointFit) -> np.ndarray:
    """(F,) `_chi2` of a JointFit's residuals (C, F, M, 2) and weights (C, F, M)."""
    squared = np.sum(fit.residuals**2, axis=-1) * fit.weights  # (C, F, M)
    return np.nansum(squared, axis=(0, 2)) / fit.noise_px**2
