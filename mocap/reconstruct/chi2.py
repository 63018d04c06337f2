"""Chi-square quantiles for whole degrees of freedom, in numpy alone (scipy.special costs a
command's start about 0.1-0.4 s to import, for two numbers).

The survival function has a closed form for whole degrees of freedom k (y = x / 2):
Q = e^-y sum_{i < k/2} y^i / i! for even k, and erfc(sqrt(y)) + e^-y sum_{i < (k-1)/2}
y^(i+1/2) / Gamma(i + 3/2) for odd k; the quantile is found by bisection to the last bit.
"""

from __future__ import annotations

import math

import numpy as np

_ERFC = np.frompyfunc(math.erfc, 1, 1)


def upper_quantile(dof, tail: float) -> np.ndarray:
    """x with P(chi-square of `dof` degrees of freedom > x) = `tail` (scipy's chdtri), for
    dof (any shape) whole numbers >= 1 and 0 < tail < 1."""
    dof = np.asarray(dof)
    if not 0 < tail < 1:
        raise ValueError(f"tail must be in (0, 1), got {tail}")
    if dof.size and (np.any(dof < 1) or np.any(dof != np.round(dof))):
        raise ValueError("dof must be whole numbers >= 1")
    if not dof.size:
        return np.zeros(dof.shape)
    unique, inverse = np.unique(dof.astype(np.int64), return_inverse=True)
    survival = _survival(unique)
    k = unique.astype(float)
    lower, upper = np.zeros_like(k), k + 20.0 * np.sqrt(2.0 * k) + 80.0  # Q(upper) far below 1e-15
    for _ in range(200):
        middle = 0.5 * (lower + upper)
        above = survival(middle) > tail  # the quantile lies above the middle
        lower, upper = np.where(above, middle, lower), np.where(above, upper, middle)
        if np.all(upper - lower <= 2e-15 * upper):
            break
    return (0.5 * (lower + upper))[inverse].reshape(dof.shape)


def _survival(dof: np.ndarray):
    """x (N,) > 0 -> P(chi-square > x) for whole dof (N,)."""
    odd = dof % 2 == 1
    count = np.where(odd, (dof - 1) // 2, dof // 2)  # terms of the sum
    i = np.arange(max(int(count.max()), 1))[None]
    power = i + np.where(odd, 0.5, 0.0)[:, None]  # (N, T): i, or i + 1/2 for odd dof
    # log Gamma(power + 1): lgamma(1) = 0 or lgamma(3/2), then Gamma(p + 1) = p Gamma(p) along the row
    log_gamma = np.where(odd, math.lgamma(1.5), 0.0)[:, None] + np.concatenate(
        [np.zeros((len(dof), 1)), np.cumsum(np.log(power[:, 1:]), axis=1)], axis=1)
    log_gamma = np.where(i < count[:, None], log_gamma, np.inf)  # beyond a row's count: no term

    def survival(x: np.ndarray) -> np.ndarray:
        y = 0.5 * x
        terms = np.exp(power * np.log(y)[:, None] - y[:, None] - log_gamma).sum(1)
        return np.where(odd, _ERFC(np.sqrt(y)).astype(float), 0.0) + terms

    return survival
