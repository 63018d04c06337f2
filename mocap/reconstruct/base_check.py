"""Does the base move? A fit of a fixed base whose residuals a moving base explains.

A machine's base bounces while it digs and settles when it walks; the cameras may have been
knocked since the calibration. A fit that holds the base where the calibration saw it then
leaves residuals above the pixel noise in every frame, and its joints take up what they can
of the base's motion. The check fits a sample of frames both ways — the base fixed, and a
6-DoF base pose per frame — and compares the pixel noise each leaves (each corrected for its
own parameters) by the Bayesian information criterion: the moving base must explain more
than its six parameters a frame are worth. It only reports; `mocap fit --base-motion` acts.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from mocap.core.camera import Camera
from mocap.core.machine import Machine, Tolerance
from mocap.reconstruct.kinfit import FitOptions, JointFit, fit_joints

SAMPLE_FRAMES = 100  # frames the check fits both ways, spread over the session


@dataclass(frozen=True)
class BaseCheck:
    """frames the sample's frames fitted both ways; fixed_noise_px, moving_noise_px the pixel
    noise each leaves; observations the 2-D observations of the sample; moves whether the
    information criterion prefers the moving base."""

    frames: int
    fixed_noise_px: float
    moving_noise_px: float
    observations: int

    @property
    def evidence(self) -> float:
        """The information criterion's gain for a moving base over its penalty (BIC with each
        model's Gaussian log-likelihood at its own noise, n log sigma^2 + k log n): above 1
        the moving base is preferred."""
        scalars = 2 * self.observations
        gain = scalars * 2.0 * np.log(self.fixed_noise_px / self.moving_noise_px)
        return float(gain / (6 * self.frames * np.log(scalars)))

    @property
    def moves(self) -> bool:
        return self.evidence > 1.0


def check_base_motion(machine: Machine, cameras: list[Camera], pixels: np.ndarray, fit: JointFit,
                      options: FitOptions, sample: int = SAMPLE_FRAMES) -> BaseCheck | None:
    """Fit up to `sample` of the fit's explained frames (pixels (C, F, M, 2)) with a fixed
    and with a moving base, from the fit's joints, the markers weighed as they are; None
    when too few frames or the fit already moves the base."""
    usable = np.nonzero(fit.valid & fit.explained)[0]
    if options.base_motion or len(usable) < 2 or machine.n_joints == 0:
        return None
    frames = usable[np.unique(np.linspace(0, len(usable) - 1, min(sample, len(usable))).round().astype(int))]
    return compare_bases(machine, cameras, pixels[:, frames], fit.joints[frames], options)


def compare_bases(machine: Machine, cameras: list[Camera], pixels: np.ndarray, start: np.ndarray,
                  options: FitOptions) -> BaseCheck | None:
    """The frames pixels (C, F, M, 2) fitted with a fixed and with a moving base from the
    joints `start` (F, J), compared by the information criterion; None when a base pose per
    frame would leave no redundancy."""
    plain = replace(options, tolerance=Tolerance(), base_motion=False, noise_px=None, repair_passes=0)
    fixed = fit_joints(machine, cameras, pixels, start, plain)
    moving = fit_joints(machine, cameras, pixels, start, replace(plain, base_motion=True))
    observations = int(fixed.n_observations.sum())
    frames = pixels.shape[1]
    if 2 * observations <= (machine.n_joints + 6) * frames:
        return None  # a base pose per frame would leave no redundancy
    return BaseCheck(frames, fixed.noise_px, moving.noise_px, observations)
