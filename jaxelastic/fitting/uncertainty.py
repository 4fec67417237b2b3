"""Gauss–Newton uncertainty of a least-squares fit at its optimum.

For weighted residuals ``r_i(θ) = (pred_i(θ) − data_i) / σ_i`` with independent Gaussian
measurement errors of standard deviation ``σ_i``, the linearised (Gauss–Newton) covariance of
the estimate ``θ̂`` is ``(JᵀJ)⁻¹`` with ``J = ∂r/∂θ`` at ``θ̂`` (Bates & Watts 1988,
*Nonlinear Regression Analysis and Its Applications*, §2.3; Press et al. 2007, *Numerical
Recipes*, §15.5). When the σ are only relative weights, the residual variance
``s² = ‖r‖² / (m − p)`` (the reduced χ²) rescales it: ``s² (JᵀJ)⁻¹``.

The inverse is taken through the SVD of ``J``: singular values below ``rcond·s_max`` count as
unidentifiable directions, whose parameters get infinite standard errors, and the condition
number ``s_max / s_min`` of ``J`` is reported (the condition number of ``JᵀJ`` is its square).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["Uncertainty", "gauss_newton_uncertainty"]


class Uncertainty(NamedTuple):
    """Linearised uncertainty of fitted parameters (host NumPy arrays).

    Attributes:
        covariance: ``(p, p)`` covariance of the parameters, in their units squared.
        standard_errors: ``(p,)`` square roots of its diagonal (``inf`` where a parameter
            lies along an unidentifiable direction).
        correlation: ``(p, p)`` correlation matrix (NaN rows/columns for unidentifiable
            parameters).
        condition_number: ``s_max / s_min`` of the weighted Jacobian (``inf`` if rank
            deficient).
        rank: numerical rank of the Jacobian.
        reduced_chi2: ``‖r‖² / (m − p)`` (≈ 1 when the σ are the true measurement errors;
            NaN when ``m ≤ p``).
        scaled: whether the covariance was multiplied by ``reduced_chi2``.
    """

    covariance: np.ndarray
    standard_errors: np.ndarray
    correlation: np.ndarray
    condition_number: float
    rank: int
    reduced_chi2: float
    scaled: bool


def gauss_newton_uncertainty(
    jacobian, residuals, *, known_sigma: bool = True, rcond: float = 1e-12
) -> Uncertainty:
    """The Gauss–Newton covariance, standard errors and correlation at an optimum.

    Args:
        jacobian: ``(m, p)`` Jacobian of the weighted residuals with respect to the
            parameters (in the units the standard errors should be in).
        residuals: ``(m,)`` weighted residuals ``(pred − data) / σ`` at the optimum.
        known_sigma: True when σ are the measurement standard deviations (covariance
            ``(JᵀJ)⁻¹``); False when they are only relative weights (covariance scaled by
            the reduced χ²).
        rcond: relative singular-value cut-off for the pseudo-inverse.
    Returns:
        :class:`Uncertainty`.
    Raises:
        ValueError: shapes that do not match, or non-finite entries.
    """
    J = np.asarray(jacobian, dtype=np.float64)
    r = np.asarray(residuals, dtype=np.float64).reshape(-1)
    if J.ndim != 2 or J.shape[0] != r.shape[0]:
        raise ValueError(
            f"jacobian must be (m, p) with m = len(residuals) = {r.shape[0]}; got {J.shape}"
        )
    if not (np.all(np.isfinite(J)) and np.all(np.isfinite(r))):
        raise ValueError("the Jacobian or the residuals contain NaN or inf")
    m, p = J.shape
    _, s, Vt = np.linalg.svd(J, full_matrices=False)
    s_max = float(s[0]) if s.size else 0.0
    keep = s > rcond * s_max if s_max > 0 else np.zeros_like(s, dtype=bool)
    rank = int(np.count_nonzero(keep))
    inv_s2 = np.where(keep, 1.0 / np.where(keep, s, 1.0) ** 2, 0.0)
    cov = (Vt.T * inv_s2) @ Vt
    chi2 = float(r @ r / (m - p)) if m > p else float("nan")
    scaled = not known_sigma
    if scaled and np.isfinite(chi2):
        cov = cov * chi2
    var = np.diag(cov).copy()
    if rank < p:
        # a parameter whose unit vector leaves the identified row space is not identifiable
        outside = 1.0 - np.sum(Vt[keep] ** 2, axis=0)  # (p,)
        var[outside > 1e-8] = np.inf
    se = np.sqrt(np.maximum(var, 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(se, se)
    corr[~np.isfinite(se), :] = np.nan
    corr[:, ~np.isfinite(se)] = np.nan
    s_min = float(s[-1]) if s.size == p else 0.0
    cond = s_max / s_min if rank == p and s_min > 0 else float("inf")
    return Uncertainty(cov, se, corr, float(cond), rank, chi2, scaled)
