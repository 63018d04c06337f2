"""Levenberg-Marquardt on the normal equations of a sparse Jacobian, for the bundle
adjustments (`mocap refine`): a few hundred to a few thousand parameters, tens of thousands
of residuals, every residual touching a handful of them.

scipy's `least_squares` solves each trust-region step of a sparse problem iteratively (LSMR),
which on a bundle adjustment takes hundreds of products with the Jacobian per step and
hundreds of steps. Here each step forms JᵀWJ once (sparse product, then dense: the
parameters are few) and solves it by Cholesky, with Marquardt's damping by its diagonal
(invariant to the parameters' scales, as `x_scale="jac"`). A Huber loss enters as iteratively
reweighted least squares: the weights of the current residuals (1 within the scale, scale /
|r| beyond), the cost scipy's "huber" minimises.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg

DENSE_LIMIT = 4000  # parameters: up to this many the normal equations are solved dense


@dataclass(frozen=True)
class Solution:
    """x the parameters at the end; cost the loss there (½ Σ ρ(r²), scipy's convention);
    iterations the Jacobians evaluated; message why it stopped."""

    x: np.ndarray
    cost: float
    iterations: int
    message: str


def huber_cost(r: np.ndarray, scale: float | None) -> float:
    """½ Σ ρ(r²) with scipy's Huber ρ at `scale` (plain squares when None)."""
    if scale is None:
        return 0.5 * float(r @ r)
    a = np.abs(r)
    return 0.5 * float(np.where(a <= scale, a * a, 2 * scale * a - scale * scale).sum())


def levenberg_marquardt(residuals: Callable[[np.ndarray], np.ndarray], jacobian: Callable[[np.ndarray], object],
                        x0: np.ndarray, scale: float | None = None, max_iterations: int = 100,
                        ftol: float = 1e-8, xtol: float = 1e-8) -> Solution:
    """Minimise ½ Σ ρ(r(x)²) from x0; `jacobian(x)` gives the (rows, n) Jacobian of
    `residuals(x)`, sparse or dense. Stops when a step lowers the cost by less than `ftol` of
    it or moves x by less than `xtol` of its size, or after `max_iterations` Jacobians."""
    x = np.asarray(x0, dtype=float).copy()
    r = residuals(x)
    cost = huber_cost(r, scale)
    damping = 1e-3
    for iteration in range(1, max_iterations + 1):
        normal, gradient = _normal_equations(jacobian(x), r, _weights(r, scale))
        diagonal = _diagonal(normal)
        diagonal = np.maximum(diagonal, 1e-12 * max(float(diagonal.max()), 1e-300))
        while True:  # raise the damping until a step lowers the cost
            step = _solve(normal, diagonal * damping, -gradient)
            if step is None:
                damping *= 10
                continue
            x_new = x + step
            r_new = residuals(x_new)
            cost_new = huber_cost(r_new, scale)
            if np.isfinite(cost_new) and cost_new < cost:
                break
            damping *= 10
            if damping > 1e16:
                return Solution(x, cost, iteration, "no step lowers the cost")
        reduction = cost - cost_new
        small_step = np.linalg.norm(step) <= xtol * (xtol + np.linalg.norm(x))
        x, r, cost = x_new, r_new, cost_new
        damping = max(damping / 10, 1e-12)
        if reduction <= ftol * cost_new or small_step:
            message = "converged: " + ("the cost's change below ftol" if not small_step else "the step below xtol")
            return Solution(x, cost, iteration, message)
    return Solution(x, cost, max_iterations, f"{max_iterations} iterations reached")


def _weights(r: np.ndarray, scale: float | None) -> np.ndarray | None:
    if scale is None:
        return None
    a = np.abs(r)
    return np.where(a <= scale, 1.0, scale / np.maximum(a, 1e-300))


def _normal_equations(J, r: np.ndarray, weights: np.ndarray | None):
    """JᵀWJ (n, n) dense or sparse, and JᵀWr (n,)."""
    Jw = J if weights is None else (scipy.sparse.diags(weights) @ J if scipy.sparse.issparse(J) else J * weights[:, None])
    gradient = np.asarray(Jw.T @ r).ravel()
    normal = Jw.T @ J
    if scipy.sparse.issparse(normal) and normal.shape[0] <= DENSE_LIMIT:
        normal = normal.toarray()
    return normal, gradient


def _diagonal(normal) -> np.ndarray:
    return normal.diagonal().copy() if scipy.sparse.issparse(normal) else np.diag(normal).copy()


def _solve(normal, damping: np.ndarray, rhs: np.ndarray) -> np.ndarray | None:
    """(normal + diag(damping))⁻¹ rhs, None when not positive definite."""
    if scipy.sparse.issparse(normal):
        try:
            return scipy.sparse.linalg.spsolve((normal + scipy.sparse.diags(damping)).tocsc(), rhs)
        except RuntimeError:
            return None
    matrix = normal + np.diag(damping)
    try:
        return scipy.linalg.cho_solve(scipy.linalg.cho_factor(matrix, check_finite=False), rhs, check_finite=False)
    except np.linalg.LinAlgError:
        return None
