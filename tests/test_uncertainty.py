"""Gauss–Newton uncertainty: a linear model with a closed-form covariance."""

import numpy as np
import pytest

from jaxelastic.fitting import gauss_newton_uncertainty


def test_linear_regression_covariance_matches_the_closed_form():
    rng = np.random.default_rng(0)
    x = np.linspace(0.0, 1.0, 50)
    sigma = 0.1
    A = np.stack([np.ones_like(x), x], axis=1)  # y = a + b x
    y = A @ np.array([1.0, 2.0]) + sigma * rng.standard_normal(x.size)
    theta = np.linalg.lstsq(A, y, rcond=None)[0]
    r = (A @ theta - y) / sigma
    u = gauss_newton_uncertainty(A / sigma, r)
    cov = sigma**2 * np.linalg.inv(A.T @ A)
    np.testing.assert_allclose(u.covariance, cov, rtol=1e-10)
    np.testing.assert_allclose(u.standard_errors, np.sqrt(np.diag(cov)), rtol=1e-10)
    np.testing.assert_allclose(np.diag(u.correlation), 1.0, rtol=1e-12)
    assert u.rank == 2 and np.isfinite(u.condition_number) and 0.5 < u.reduced_chi2 < 1.6
    # σ as relative weights: the covariance takes the residual variance
    v = gauss_newton_uncertainty(A, A @ theta - y, known_sigma=False)
    np.testing.assert_allclose(v.standard_errors, u.standard_errors * np.sqrt(u.reduced_chi2))


def test_unidentifiable_parameter_gets_an_infinite_standard_error():
    x = np.linspace(0.0, 1.0, 10)
    J = np.stack([x, 2 * x, np.ones_like(x)], axis=1)  # the first two columns are collinear
    u = gauss_newton_uncertainty(J, np.zeros(10))
    assert u.rank == 2 and u.condition_number == np.inf
    assert np.isinf(u.standard_errors[:2]).all() and np.isfinite(u.standard_errors[2])


def test_bad_shapes_and_nan_are_refused():
    with pytest.raises(ValueError, match="jacobian must be"):
        gauss_newton_uncertainty(np.ones((3, 2)), np.ones(4))
    with pytest.raises(ValueError, match="NaN"):
        gauss_newton_uncertainty(np.full((3, 2), np.nan), np.ones(3))
