"""Temporal smoothing of the fitted parameters, with gap filling.

A Rauch-Tung-Striebel smoother with a constant-velocity model (white-noise acceleration
of spectral density ``q`` per parameter). Each frame's measurement is the kinematic fit's
parameter vector with its information matrix (the inverse covariance from the normal
equations, singular where a joint was not observed), used in information form so that a
frame that saw nothing of the bucket still constrains the other joints and leaves the
bucket to the model, where those joints agree with the frames that observe every parameter
(a frame with too few markers can be fitted on a far branch that explains them as well: on
a random digger whose trackers lost the moving markers for a second, such stretches set the
path 5 m off at 5 cm SD). Frames that the fit could not determine are predicted (filled);
gaps longer than `max_gap_s` are left NaN. Measurements whose innovation is improbable
(chi-square gate) are skipped as failed fits.

Shapes: F frames, P parameters (J joints, then the base's 6 with base motion).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

_PRIOR_SD = 1e3  # initial state SD (rad, m, per second): uninformative


@dataclass(frozen=True)
class SmoothOptions:
    """process_noise: (P,) or scalar white-noise acceleration spectral density (unit^2/s^3),
    None to estimate it from the data at the `stride_s` time scale; max_gap_s: longer gaps
    stay unfilled; gate_probability: measurements beyond this chi-square quantile are
    rejected (1 disables the gate); unobserved_factor: a parameter whose fit SD exceeds this
    multiple of its median counts as unobserved (the frame is marked filled); partial_probability:
    such a frame's observed parameters are used where they lie within this chi-square quantile
    (by their own information) of the smoother of the frames that observe every parameter, else
    (or when it observes none) the frame is left out and filled."""

    process_noise: float | np.ndarray | None = None
    max_gap_s: float = 2.0
    stride_s: float = 0.5
    gate_probability: float = 1.0
    unobserved_factor: float = 20.0
    partial_probability: float = 0.9999

    def __post_init__(self) -> None:
        if not self.max_gap_s >= 0 or not self.stride_s > 0:
            raise ValueError("max_gap_s must be >= 0 and stride_s > 0")
        if not 0 < self.gate_probability <= 1:
            raise ValueError(f"gate_probability must be in (0, 1], got {self.gate_probability}")
        if self.process_noise is not None and np.any(~(np.asarray(self.process_noise) > 0)):
            raise ValueError("process_noise must be positive")


@dataclass(frozen=True)
class Smoothed:
    """values (F, P), velocities (F, P) per second, covariance (F, P, P) of the values,
    velocity_covariance (F, P, P); filled (F,) frames predicted across a gap or with an
    unobserved parameter; rejected (F,) measurements the gate refused; process_noise (P,)."""

    values: np.ndarray
    velocities: np.ndarray
    covariance: np.ndarray
    velocity_covariance: np.ndarray
    filled: np.ndarray
    rejected: np.ndarray
    process_noise: np.ndarray

    def __post_init__(self) -> None:
        n, p = np.shape(self.values)
        if np.shape(self.covariance) != (n, p, p) or np.shape(self.velocities) != (n, p):
            raise ValueError(f"Smoothed needs velocities ({n}, {p}) and covariance ({n}, {p}, {p})")


def smooth(
    time: np.ndarray,
    values: np.ndarray,
    information: np.ndarray,
    valid: np.ndarray,
    wrap: np.ndarray | None = None,
    options: SmoothOptions | None = None,
) -> Smoothed:
    """Smooth per-frame parameter measurements.

    Parameters
    ----------
    time : (F,) seconds, increasing.
    values : (F, P) measured parameters (NaN where not valid).
    information : (F, P, P) inverse covariance of each measurement (may be singular).
    valid : (F,) frames with a measurement.
    wrap : (P,) bool, angles measured modulo 2 pi (unwrapped here, returned unwrapped).
    """
    options = options or SmoothOptions()
    time = np.asarray(time, dtype=float)
    values = np.asarray(values, dtype=float)
    n, p = values.shape
    if time.shape != (n,) or np.shape(information) != (n, p, p) or np.shape(valid) != (n,):
        raise ValueError(f"smooth needs time ({n},), information ({n}, {p}, {p}) and valid ({n},)")
    if n > 1 and np.any(np.diff(time) <= 0):
        raise ValueError("time must increase")
    valid = np.asarray(valid, dtype=bool) & np.isfinite(values).all(1)
    wrap = np.zeros(p, bool) if wrap is None else np.asarray(wrap, bool)
    values = _unwrap(values, valid, wrap)
    fit_sd = fit_sds(information)
    typical = np.nanmedian(np.where(valid[:, None], fit_sd, np.nan), axis=0) if valid.any() else np.ones(p)
    observed = valid[:, None] & (fit_sd <= options.unobserved_factor * typical)
    q = _process_noise(time, values, observed, fit_sd, options) if options.process_noise is None else (
        np.broadcast_to(np.asarray(options.process_noise, dtype=float), (p,)).copy()
    )
    if not valid.any():
        nan = np.full((n, p), np.nan)
        return Smoothed(nan, nan.copy(), np.full((n, p, p), np.nan), np.full((n, p, p), np.nan), np.zeros(n, bool), np.zeros(n, bool), q)
    partial = valid & ~observed.all(1)
    if partial.any() and (valid & ~partial).any():
        # A frame whose fit leaves parameters unobserved (too few markers: its fit can lie on a
        # far branch that explains its few pixels as well, and a stretch of such frames agrees
        # with itself) takes part only where the parameters it observes agree, within their own
        # SDs, with the smoother of the frames that observe every one; one that observes none is
        # left out (over a stretch of them its weak information would set the path).
        mean, _, _ = _rts(time, values, information, valid & ~partial, q, options)
        held = np.flatnonzero(partial)
        gap = _deviations(values[held], mean[held, :p], np.ones(len(held), bool), wrap)
        chi2 = np.einsum("ni,nij,nj->n", gap, information[held], gap)
        dof = observed[held].sum(1)
        bound = np.full(len(held), -np.inf)  # a frame that observes nothing: left out
        for k in np.unique(dof[dof > 0]):
            bound[dof == k] = chi2_quantile(options.partial_probability, int(k))
        agree = chi2 <= bound
        valid = valid.copy()
        valid[held[~agree]] = False
    mean, cov, rejected = _rts(time, values, information, valid, q, options)
    long_gap = _long_gaps(time, valid, options.max_gap_s)
    mean[long_gap] = np.nan
    cov[long_gap] = np.nan
    filled = ~long_gap & ~(observed.all(1) & valid & ~rejected)
    return Smoothed(mean[:, :p], mean[:, p:], cov[:, :p, :p], cov[:, p:, p:], filled, rejected, q)


def scatter_scale(values: np.ndarray, information: np.ndarray, used: np.ndarray, smoothed: Smoothed,
                  wrap: np.ndarray | None = None) -> tuple[float, float, float]:
    """How far the smoothed covariance understates the error: the fits' values (F, P) with
    their information (F, P, P), in the frames `used` (F,), scatter about the smoothed values
    by a chi-square over what the model expects of it (a fit's deviation from the smoothed
    value has the fit's covariance less the smoothed one: P - tr(information x smoothed
    covariance) a frame), `variance_factor` (at least 1), and their deviations correlate from
    one frame to the next by rho (`frame_correlation`): a smoother that takes the fits as
    independent averages errors that are not (a marker's centroid pulled the same way over
    frames, two reference frames interpolated from one camera frame), by 1 + 2 rho.
    -> (scale = variance_factor (1 + 2 max(rho, 0)), variance_factor, rho); 1 where fewer
    than 10 pairs of frames tell."""
    p = values.shape[1]
    covariance = smoothed.covariance
    ok = used & np.isfinite(values).all(1) & np.isfinite(smoothed.values).all(1) & np.isfinite(covariance).all((1, 2))
    rho = frame_correlation(values, information, ok, smoothed.values, wrap)
    if rho is None:
        return 1.0, 1.0, 0.0
    deviation = _deviations(values, smoothed.values, ok, wrap)
    chi2 = np.einsum("ki,kij,kj->", deviation[ok], information[ok], deviation[ok])
    expected = ok.sum() * p - np.einsum("kij,kji->", information[ok], covariance[ok])
    factor = max(float(chi2 / expected), 1.0) if expected > 0 else 1.0
    return factor * (1.0 + 2.0 * max(rho, 0.0)), factor, rho


def frame_correlation(values: np.ndarray, information: np.ndarray, used: np.ndarray, smoothed: np.ndarray,
                      wrap: np.ndarray | None = None) -> float | None:
    """The fits' deviations (values (F, P) in the frames `used` (F,)) from the smoothed values
    (F, P), correlated from one frame to the next, weighed by the fits' information (F, P, P);
    None where fewer than 10 pairs of frames tell."""
    ok = used & np.isfinite(values).all(1) & np.isfinite(smoothed).all(1)
    pairs = ok[1:] & ok[:-1]
    if pairs.sum() < 10:
        return None
    deviation = _deviations(values, smoothed, ok, wrap)
    weighed = np.einsum("kij,kj->ki", information, deviation)
    cross = np.einsum("ki,ki->k", weighed[:-1], deviation[1:])[pairs].sum()
    norm = np.einsum("ki,ki->k", weighed, deviation)
    return float(cross / np.sqrt(norm[:-1][pairs].sum() * norm[1:][pairs].sum()))


def _deviations(values: np.ndarray, smoothed: np.ndarray, ok: np.ndarray, wrap: np.ndarray | None) -> np.ndarray:
    """(F, P) values less smoothed where `ok`, else 0; angles (the columns `wrap`) in [-pi, pi)."""
    deviation = np.where(ok[:, None], values - smoothed, 0.0)
    if wrap is not None:
        wrap = np.asarray(wrap, bool)
        deviation[:, wrap] = np.mod(deviation[:, wrap] + np.pi, 2 * np.pi) - np.pi
    return deviation


def _unwrap(values: np.ndarray, valid: np.ndarray, wrap: np.ndarray) -> np.ndarray:
    values = values.copy()
    for j in np.nonzero(wrap)[0]:
        values[valid, j] = np.unwrap(values[valid, j])
    return values


def _process_noise(time, values, observed, fit_sd, options) -> np.ndarray:
    """Per parameter: the mean squared second difference at stride h minus its measurement
    part, over (2/3) h^3 (the white-noise-acceleration variance of a second difference)."""
    n, p = values.shape
    dt = np.median(np.diff(time)) if n > 1 else 1.0
    stride = max(1, int(round(options.stride_s / dt)))
    q = np.full(p, 1e-6)
    if n <= 2 * stride:
        return q
    h = stride * dt
    for j in range(p):
        ok = observed[: n - 2 * stride, j] & observed[stride : n - stride, j] & observed[2 * stride :, j]
        if ok.sum() < 3:
            continue
        d2 = values[2 * stride :, j] - 2 * values[stride : n - stride, j] + values[: n - 2 * stride, j]
        noise = 6.0 * np.mean(fit_sd[stride : n - stride, j][ok] ** 2)
        q[j] = max(np.mean(d2[ok] ** 2) - noise, 1e-6 * noise, 1e-12) / (2.0 / 3.0 * h**3)
    return q


def _long_gaps(time: np.ndarray, valid: np.ndarray, max_gap_s: float) -> np.ndarray:
    """(F,) frames inside a run of invalid frames whose span between measurements exceeds
    `max_gap_s`, and frames before the first or after the last measurement."""
    out = np.zeros(len(time), bool)
    index = np.nonzero(valid)[0]
    out[: index[0]] = True
    out[index[-1] + 1 :] = True
    for a, b in zip(index[:-1], index[1:]):
        if b - a > 1 and time[b] - time[a] > max_gap_s:
            out[a + 1 : b] = True
    return out


def fit_sds(information: np.ndarray) -> np.ndarray:
    """(N, P) each parameter's SD from the fits' information (N, P, P), as `smooth` takes it.
    A direction a fit leaves unobserved (too few markers in its frame: the information
    singular) gets an SD about a million times the frame's typical one: the ridge that keeps
    the inverse finite is relative to the information's own scale (a fixed 1e-12 is lost in
    the rounding of entries of 1e5 and more, and the inverse failed)."""
    size = information.shape[-1]
    ridge = 1e-12 * np.maximum(np.trace(information, axis1=-2, axis2=-1) / size, 1.0)
    covariance = np.linalg.inv(information + ridge[..., None, None] * np.eye(size))
    return np.sqrt(np.abs(np.diagonal(covariance, axis1=-2, axis2=-1)))


def chi2_quantile(probability: float, dof: int) -> float:
    """The chi-square distribution's `probability` quantile with `dof` degrees of freedom."""
    from scipy.special import gammaincinv

    return 2.0 * float(gammaincinv(dof / 2.0, probability))


def _rts(time, values, information, valid, q, options):
    """Forward information-form Kalman filter and RTS backward pass (compiled:
    mocap.reconstruct.rts_kernel) -> mean (F, 2P), covariance (F, 2P, 2P), rejected (F,)."""
    from mocap.reconstruct.rts_kernel import rts

    gate = np.inf
    if options.gate_probability < 1:
        gate = chi2_quantile(options.gate_probability, values.shape[1])
    steps = np.round(np.r_[0.0, np.diff(time)], 9)
    first = int(np.argmax(valid))
    mean, cov, rejected = rts(steps, np.ascontiguousarray(values), np.ascontiguousarray(information, dtype=float),
                              np.ascontiguousarray(valid), np.ascontiguousarray(q, dtype=float), float(gate),
                              np.ascontiguousarray(values[first]), _PRIOR_SD**2)
    if rejected.any():
        log.info("smoother rejected %d measurement(s) as failed fits", int(rejected.sum()))
    return mean, cov, rejected
