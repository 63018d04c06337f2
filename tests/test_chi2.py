"""The chi-square quantiles the fit and the outlier check use, without scipy at run time,
against scipy's."""

import numpy as np
import pytest
from scipy.special import chdtri

from mocap.reconstruct.chi2 import upper_quantile


@pytest.mark.parametrize("tail", [1e-9, 1e-4, 0.05, 0.5, 0.9])
def test_upper_quantiles_match_scipy(tail):
    dof = np.arange(1, 301)
    np.testing.assert_allclose(upper_quantile(dof, tail), chdtri(dof, tail), rtol=1e-12)


def test_any_shape_and_repeats_and_none():
    dof = np.array([[3, 5], [3, 1]])
    np.testing.assert_allclose(upper_quantile(dof, 0.5), chdtri(dof, 0.5), rtol=1e-12)
    assert upper_quantile(np.zeros(0, int), 0.5).shape == (0,)


def test_refuses_what_it_cannot_compute():
    with pytest.raises(ValueError, match="whole numbers"):
        upper_quantile([2.5], 0.5)
    with pytest.raises(ValueError, match="whole numbers"):
        upper_quantile([0], 0.5)
    with pytest.raises(ValueError, match="tail must be"):
        upper_quantile([3], 1.0)
