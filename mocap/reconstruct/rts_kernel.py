"""The smoother's passes, compiled (numba): a forward information-form Kalman filter with a
constant-velocity model and the Rauch-Tung-Striebel backward pass, one frame after the
other in linear time (mocap.reconstruct.smooth describes the model).

State per frame: the P parameters, then their P velocities (S = 2P). Shapes: F frames.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from mocap.reconstruct.linear_kernel import solve


@njit(cache=True, nogil=True)
def _mul(a, b):
    """a (N, K) @ b (K, L) without BLAS (small matrices)."""
    out = np.zeros((a.shape[0], b.shape[1]))
    for i in range(a.shape[0]):
        for k in range(a.shape[1]):
            if a[i, k] != 0.0:
                for j in range(b.shape[1]):
                    out[i, j] += a[i, k] * b[k, j]
    return out


@njit(cache=True, nogil=True)
def _predict(x, cov, dt, q):
    """The constant-velocity prediction over dt: (mean (S,), covariance (S, S))."""
    p = len(q)
    x = x.copy()
    for i in range(p):
        x[i] += dt * x[p + i]
    # F cov Fᵀ with F = [[I, dt I], [0, I]], then + the white-noise-acceleration Q
    c = cov.copy()
    for i in range(p):  # rows: c[i] += dt c[p + i]
        for j in range(2 * p):
            c[i, j] += dt * c[p + i, j]
    for j in range(p):  # columns: c[:, j] += dt c[:, p + j]
        for i in range(2 * p):
            c[i, j] += dt * c[i, p + j]
    for i in range(p):
        c[i, i] += dt**3 / 3.0 * q[i]
        c[i, p + i] += dt**2 / 2.0 * q[i]
        c[p + i, i] += dt**2 / 2.0 * q[i]
        c[p + i, p + i] += dt * q[i]
    return x, c


@njit(cache=True, nogil=True)
def rts(steps, values, information, valid, q, gate, start, prior_var):
    """Forward filter and backward smoother.

    steps (F,) s between frames (the first unused); values (F, P) measurements;
    information (F, P, P) their inverse covariances; valid (F,) frames measured; q (P,)
    process noise densities; gate: the chi-square value beyond which a measurement is
    rejected; start (P,) the initial values; prior_var the initial state variance.
    Returns mean (F, S), covariance (F, S, S), rejected (F,).
    """
    n, p = values.shape
    s = 2 * p
    x = np.zeros(s)
    x[:p] = start
    cov = prior_var * np.eye(s)
    pred_mean = np.empty((n, s))
    pred_cov = np.empty((n, s, s))
    post_mean = np.empty((n, s))
    post_cov = np.empty((n, s, s))
    rejected = np.zeros(n, np.bool_)
    eye_p = np.eye(p)
    for k in range(n):
        x, cov = _predict(x, cov, steps[k], q)
        pred_mean[k], pred_cov[k] = x, cov
        if valid[k]:
            info = information[k]
            innovation = values[k] - x[:p]
            # (H P Hᵀ + R)⁻¹ = info (I + P_pp info)⁻¹, which allows a singular info
            s_info = _mul(info, solve(eye_p + _mul(cov[:p, :p], info), eye_p))
            distance = np.sum(innovation * _mul(s_info, innovation.reshape(p, 1))[:, 0])
            if distance > gate:
                rejected[k] = True
            else:
                gain = _mul(cov[:, :p], s_info)
                x = x + _mul(gain, innovation.reshape(p, 1))[:, 0]
                cov = cov - _mul(gain, cov[:p, :])
                cov = 0.5 * (cov + cov.T)
        post_mean[k], post_cov[k] = x, cov
    mean = post_mean.copy()
    smoothed = post_cov.copy()
    transition = np.eye(s)
    for k in range(n - 2, -1, -1):
        for i in range(p):
            transition[i, p + i] = steps[k + 1]
        # gain = post_cov[k] Fᵀ pred_cov[k+1]⁻¹, by solving pred_cov[k+1] gainᵀ = F post_cov[k]
        gain = solve(pred_cov[k + 1], _mul(transition, post_cov[k])).T
        mean[k] = post_mean[k] + _mul(gain, (mean[k + 1] - pred_mean[k + 1]).reshape(s, 1))[:, 0]
        smoothed[k] = post_cov[k] + _mul(_mul(gain, smoothed[k + 1] - pred_cov[k + 1]), gain.T)
    return mean, smoothed, rejected
