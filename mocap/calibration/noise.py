"""The pixel noise a calibration's residuals show, and which residuals are beyond it.

With the markers' offsets fitted within their tolerance, a fit has more unknowns than a
plain one and its residuals are smaller than the noise: the offsets absorb part of every
pixel's error (with one camera nearly all of it). The noise is therefore estimated from
the residuals divided by sqrt(1 - leverage), the share of each residual's variance that the
fit leaves (the standardised residuals of linear regression), and where the fit leaves
the data little redundancy the estimate leans on a stated noise. The same standardised
residuals judge the outliers: a wild pixel on a marker that only one camera sees is mostly
absorbed by that marker's offset, but its small residual then has a small variance too.

Shapes: N observations, R = 2N pixel rows (+ 3M prior rows), P free parameters.
"""

from __future__ import annotations

import numpy as np

from mocap.calibration.identify import inverse_information

RAYLEIGH_MEDIAN = np.sqrt(2 * np.log(2))  # median of a 2-D residual's length over the per-axis sigma
PRIOR_ROWS = 4.0  # the stated noise counts as this many residual rows of the data's own
INFORMATIVE = 0.1  # a residual whose leverage leaves less of its variance tells nothing of the noise


def leverages(jacobian: np.ndarray) -> np.ndarray:
    """(R,) the hat matrix' diagonal of a whitened Jacobian (R, P): how much of each row's
    residual the fit can absorb (0 none, 1 all)."""
    covariance = inverse_information(jacobian.T @ jacobian)
    return np.clip(np.einsum("ij,jk,ik->i", jacobian, covariance, jacobian), 0.0, 1.0)


def standardised_errors(fun: np.ndarray, jacobian: np.ndarray, n_pixel_rows: int) -> tuple[np.ndarray, np.ndarray]:
    """(N,) each observation's residual length (px) over sqrt(1 - its leverage), and (N,)
    the share 1 - leverage of its variance that the fit leaves."""
    left = 1.0 - leverages(jacobian)[:n_pixel_rows].reshape(-1, 2).mean(axis=1)
    errors = np.linalg.norm(fun[:n_pixel_rows].reshape(-1, 2), axis=1)
    return errors / np.sqrt(np.maximum(left, 1e-6)), left


def pixel_noise(fun: np.ndarray, jacobian: np.ndarray, n_pixel_rows: int, stated_px: float) -> float:
    """Per-axis pixel noise (px) from a fit's residuals `fun` (R,) and whitened Jacobian:
    the median standardised residual of the observations the fit leaves free enough
    (robust to wild pixels), weighed by the rows of redundancy 2N - trace(hat) against
    `stated_px` counted as PRIOR_ROWS rows."""
    errors, left = standardised_errors(fun, jacobian, n_pixel_rows)
    informative = left > INFORMATIVE
    redundancy = 2.0 * float(np.sum(left))
    if not informative.any() or redundancy <= 0:
        return stated_px
    measured = float(np.median(errors[informative])) / RAYLEIGH_MEDIAN
    variance = (PRIOR_ROWS * stated_px**2 + redundancy * measured**2) / (PRIOR_ROWS + redundancy)
    return float(np.sqrt(variance))


def robust_sigma(errors: np.ndarray) -> float:
    """Per-axis pixel noise from the median residual length (Rayleigh: median = 1.1774 sigma)."""
    return float(np.median(errors) / RAYLEIGH_MEDIAN)


def pixel_robust_loss(n_pixel_rows: int):
    """A least-squares loss (scipy's callable form) that is soft-L1 on the first
    `n_pixel_rows` rows (pixels: a wild one counts little) and plain on the rest (the
    offsets' priors: robust there, an offset would run off to absorb a wild pixel)."""

    def loss(z: np.ndarray) -> np.ndarray:
        out = np.empty((3, len(z)))
        pixel = z[:n_pixel_rows]
        root = np.sqrt(1.0 + pixel)
        out[0, :n_pixel_rows] = 2.0 * (root - 1.0)
        out[1, :n_pixel_rows] = 1.0 / root
        out[2, :n_pixel_rows] = -0.5 / root**3
        out[0, n_pixel_rows:] = z[n_pixel_rows:]
        out[1, n_pixel_rows:] = 1.0
        out[2, n_pixel_rows:] = 0.0
        return out

    return loss


MODEL_ERROR_MARKERS = 3  # markers that must show the model error before a tolerance is estimated
MAX_ESTIMATED_TOLERANCE = 0.2  # a fraction beyond this is a wrong model, not a tape measure
SHOWN_NOISE_RATIO = 1.5  # residuals whose robust SD is this many times the stated noise show model error
_FAR = 5.0  # residuals beyond this many of their SDs (wild pixels) are left out of the estimate


def model_error_fraction(squared: np.ndarray, scale: np.ndarray, markers: np.ndarray, noise_px: float,
                         shown_px: float, left: np.ndarray | None = None,
                         named: np.ndarray | None = None) -> float | None:
    """The tolerance (a fraction of each marker's coordinates) that a fit's residuals show,
    or None where they show none beyond the pixel noise.

    squared (N,) each observation's squared residual length px²; scale (N,) px, what a
    fraction of 1 moves it in its image (per axis: the projected SD of every coordinate off
    by up to itself, uniformly); markers (N,) marker indices; noise_px the pixel noise per
    axis (one frame cannot tell it from model error: the stated one); shown_px the noise the
    fit's residuals show (leverage counted, `pixel_noise`); left (N,) the share 1 - leverage
    of each residual's variance that the fit leaves (`standardised_errors`; 1 for an
    observation the fit did not see, an outlier): the exact model's fit absorbs part of the
    model error as it does of the noise, and its residuals alone would show too little.
    Model error is shown where the noise shown is SHOWN_NOISE_RATIO times the stated one,
    or above it where the fit named outliers (`named` (N,) bool) on MODEL_ERROR_MARKERS
    markers or more (the model error's largest residuals, named outliers, no longer raise
    the noise the rest show), and MODEL_ERROR_MARKERS markers lie beyond 2 of its SDs: many
    markers off, not a few wild pixels. Each standardised residual's variance per axis is
    then noise² + t² scale², t² fitted by weighted least squares on the squared lengths
    (iterated, residuals beyond 5 of their SDs left out as wild); `scale` is that of the
    uniform bound (every coordinate off by up to the fraction), so t is the tolerance as
    `Tolerance` reads it.
    """
    left = np.ones(len(squared)) if left is None else np.clip(np.asarray(left, dtype=float), INFORMATIVE, 1.0)
    y = np.asarray(squared, dtype=float) / 2.0 / left
    s2 = np.asarray(scale, dtype=float) ** 2
    noise2 = noise_px**2
    named_markers = 0 if named is None else len(np.unique(np.asarray(markers)[np.asarray(named, dtype=bool)]))
    shown = shown_px > (noise_px if named_markers >= MODEL_ERROR_MARKERS else SHOWN_NOISE_RATIO * noise_px)
    if len(y) < 8 or not shown:
        return None
    beyond = y > 4.0 * noise2
    if len(np.unique(np.asarray(markers)[beyond])) < MODEL_ERROR_MARKERS:
        return None
    b = float(np.median(np.maximum(y - noise2, 0.0) / np.maximum(s2, 1e-12)))
    for _ in range(30):
        variance = noise2 + b * s2
        w = (y <= _FAR**2 * variance) / variance**2
        b_new = max(float(np.sum(w * (y - noise2) * s2) / max(np.sum(w * s2 * s2), 1e-300)), 0.0)
        done = abs(b_new - b) <= 1e-6 * b
        b = b_new
        if done:
            break
    return float(min(np.sqrt(b), MAX_ESTIMATED_TOLERANCE)) if b > 0 else None
