"""The compiled solvers' one linear solver (numba): Gaussian elimination with partial
pivoting and back substitution, for the small dense systems of the joint fit's
Levenberg-Marquardt steps and the smoother's passes."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def solve_into(lhs, rhs, out):
    """out (N, K) with lhs (N, N) out = rhs (N, K), by Gaussian elimination with partial
    pivoting (lhs and rhs are overwritten; no allocation)."""
    n, k = rhs.shape
    for col in range(n):
        pivot = col
        for r in range(col + 1, n):
            if abs(lhs[r, col]) > abs(lhs[pivot, col]):
                pivot = r
        if pivot != col:
            for c in range(n):
                lhs[col, c], lhs[pivot, c] = lhs[pivot, c], lhs[col, c]
            for j in range(k):
                rhs[col, j], rhs[pivot, j] = rhs[pivot, j], rhs[col, j]
        for r in range(col + 1, n):
            factor = lhs[r, col] / lhs[col, col]
            if factor != 0.0:
                for c in range(col, n):
                    lhs[r, c] -= factor * lhs[col, c]
                for j in range(k):
                    rhs[r, j] -= factor * rhs[col, j]
    for r in range(n - 1, -1, -1):
        for j in range(k):
            total = rhs[r, j]
            for c in range(r + 1, n):
                total -= lhs[r, c] * out[c, j]
            out[r, j] = total / lhs[r, r]


@njit(cache=True, nogil=True)
def solve(a, b):
    """x (N, K) with a x = b for a (N, N) and b (N, K) (a and b are left unchanged)."""
    out = np.empty(b.shape)
    solve_into(a.copy(), b.copy(), out)
    return out
