"""The bundle adjustment's Levenberg-Marquardt: the minimum scipy's least_squares finds, on a
problem with a known truth, plain and with the Huber loss."""

import numpy as np
import pytest
import scipy.sparse
from scipy.optimize import least_squares

from mocap.reconstruct.sparse_lm import huber_cost, levenberg_marquardt

NOISE = 0.01


def circles(seed: int, outliers: int):
    """Points on 30 circles of known centres and radii (90 parameters), 40 points each with
    noise, some of them wild: residuals sparse in the parameters (each point sees its circle)."""
    rng = np.random.default_rng(seed)
    n, k = 30, 40
    truth = np.c_[rng.uniform(-5, 5, (n, 2)), rng.uniform(1, 3, n)]  # cx, cy, radius
    angle = rng.uniform(0, 2 * np.pi, (n, k))
    points = truth[:, None, :2] + truth[:, None, 2:] * np.stack([np.cos(angle), np.sin(angle)], -1)
    points += rng.normal(0, NOISE, points.shape)
    wild = rng.choice(n * k, outliers, replace=False)
    points.reshape(-1, 2)[wild] += rng.uniform(0.5, 1.5, (outliers, 2))
    owner = np.repeat(np.arange(n), k)

    def residuals(x):
        p = x.reshape(n, 3)
        d = points.reshape(-1, 2) - p[owner, :2]
        return np.linalg.norm(d, axis=1) - p[owner, 2]

    def jacobian(x):
        p = x.reshape(n, 3)
        d = points.reshape(-1, 2) - p[owner, :2]
        u = d / np.linalg.norm(d, axis=1)[:, None]
        rows = np.repeat(np.arange(n * k), 3)
        cols = (3 * owner[:, None] + np.arange(3)).ravel()
        values = np.c_[-u, -np.ones(n * k)].ravel()
        return scipy.sparse.csr_matrix((values, (rows, cols)), shape=(n * k, 3 * n))

    x0 = (truth + rng.normal(0, 0.3, truth.shape)).ravel()
    return truth, residuals, jacobian, x0


@pytest.mark.parametrize("outliers, scale", [(0, None), (60, 3 * NOISE)])
def test_finds_the_least_squares_minimum_and_the_truth(outliers, scale):
    truth, residuals, jacobian, x0 = circles(3, outliers)
    ours = levenberg_marquardt(residuals, jacobian, x0, scale=scale)
    theirs = least_squares(residuals, x0, jac=jacobian, method="trf", x_scale="jac",
                           **({} if scale is None else {"loss": "huber", "f_scale": scale}))
    assert ours.message.startswith("converged")
    assert ours.cost <= theirs.cost * (1 + 1e-6)  # scipy's cost is ½ Σ ρ too
    assert huber_cost(residuals(ours.x), scale) == pytest.approx(ours.cost)
    # each circle's 40 points fix its centre and radius to about NOISE / sqrt(20); two solvers
    # stopped at the same minimum agree to a hundredth of that (the Huber cost is flat there)
    np.testing.assert_allclose(ours.x, theirs.x, atol=0.01 * NOISE / np.sqrt(20))
    error = np.abs(ours.x.reshape(-1, 3) - truth)
    assert np.sqrt(np.mean(error**2)) < 2 * NOISE / np.sqrt(20)


def test_plain_loss_is_dragged_by_wild_points_and_huber_is_not():
    truth, residuals, jacobian, x0 = circles(4, 60)
    plain = levenberg_marquardt(residuals, jacobian, x0)
    robust = levenberg_marquardt(residuals, jacobian, x0, scale=3 * NOISE)
    rmse = [np.sqrt(np.mean((s.x.reshape(-1, 3) - truth) ** 2)) for s in (plain, robust)]
    assert rmse[1] < 2 * NOISE / np.sqrt(20) < rmse[0]
