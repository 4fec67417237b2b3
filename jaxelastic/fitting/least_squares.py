"""Levenberg–Marquardt least squares for few parameters: :func:`levenberg_marquardt`.

Minimises ``½‖r(z)‖²`` of weighted residuals ``r_i = (pred_i − data_i) / σ_i`` over an
unconstrained vector ``z`` of a few (≲ 20) parameters; positivity and bounds enter through
the transforms of :mod:`~jaxelastic.fitting.transforms` (``θ = forward(z)``), and the
result reports the physical parameters θ and their Gauss–Newton uncertainty
(:func:`~jaxelastic.fitting.uncertainty.gauss_newton_uncertainty`).

The method (Levenberg 1944; Marquardt 1963, *J. SIAM* 11:431; the damping update of
Nielsen 1999, as given by Madsen, Nielsen & Tingleff 2004, *Methods for Non-linear Least
Squares Problems*, §3.2): with ``J = ∂r/∂z`` from :func:`jax.jacfwd`, the step solves
``(JᵀJ + μ D) h = −Jᵀr`` with Marquardt's scaling ``D = diag(JᵀJ)``; the gain ratio
``ρ = (actual decrease) / (decrease predicted by the linear model)`` accepts (ρ > 0) or
rejects the step and updates μ (``μ ← μ·max(1/3, 1 − (2ρ − 1)³)`` on acceptance, ``μ ← μν,
ν ← 2ν`` on rejection). A trial point whose residuals are not finite, or whose residual
function reports a failure, is rejected like a step that increases the cost.

Stopping, honestly:

* **converged** (``stop_reason = "converged"``) only when, at an accepted point, the
  decrease that an *undamped* Gauss–Newton step predicts, ``½‖J h_GN‖²`` with
  ``h_GN = argmin‖J h + r‖``, is at most ``rtol·cost + atol``: the local model says no
  further relative decrease above ``rtol`` exists (``rtol = 1e-12`` puts the parameters
  within ``√(rtol·m)`` standard errors of the optimum);
* ``"max_iterations"``: the iteration budget ran out — not convergence;
* ``"stalled"``: ``max_rejections`` consecutive steps were rejected (the damping grew
  without progress) — not convergence, even though the steps became tiny;
* ``"nonfinite"``: the residuals at the initial guess are not finite (or the residual
  function reported a failure there).

The whole iteration is one ``lax.while_loop`` compiled once per residual function (``fun``
and ``physical`` are static: pass the same hashable callables to reuse the compilation;
data, weights and tolerances are traced arguments).
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .uncertainty import Uncertainty, gauss_newton_uncertainty

__all__ = ["LMSettings", "LeastSquaresResult", "levenberg_marquardt", "STOP_REASONS"]

STOP_REASONS = ("running", "converged", "max_iterations", "stalled", "nonfinite")
"""``stop_reason`` values, indexed by the integer status of the compiled loop."""
_RUNNING, _CONVERGED, _MAX_ITER, _STALLED, _NONFINITE = range(5)


class LMSettings(NamedTuple):
    """Tolerances of :func:`levenberg_marquardt` (traced: changing them does not recompile).

    Attributes:
        rtol: converged when the undamped Gauss–Newton predicted decrease of the cost is
            ``≤ rtol·cost + atol``.
        atol: absolute part of that test [cost units, ½ Σ r²] (e.g. the cost of residuals
            at the data's round-off, so that an exact fit is recognised).
        max_iterations: iterations (accepted and rejected steps) before giving up.
        max_rejections: consecutive rejected steps before declaring the fit stalled.
        initial_damping: μ at the start, relative to ``diag(JᵀJ)``.
    """

    rtol: float = 1e-12
    atol: float = 0.0
    max_iterations: int = 500
    max_rejections: int = 40
    initial_damping: float = 1e-3


class LeastSquaresResult(NamedTuple):
    """Result of :func:`levenberg_marquardt` (host values).

    Attributes:
        z: ``(p,)`` final unconstrained vector.
        params: ``(p,)`` physical parameters θ = ``physical(z)`` (``z`` itself by default).
        residuals: ``(m,)`` weighted residuals at ``z`` (NaN when ``"nonfinite"``).
        cost: ``½‖r‖²``.
        jacobian: ``(m, p)`` ``∂r/∂θ`` at ``z`` (physical units).
        predicted_decrease: the undamped Gauss–Newton predicted decrease divided by the cost
            (the convergence measure; ``0`` for an exact fit).
        iterations: iterations taken (accepted and rejected steps).
        converged: True only when ``stop_reason == "converged"``.
        stop_reason: one of :data:`STOP_REASONS` (never ``"running"``).
        uncertainty: :class:`~jaxelastic.fitting.uncertainty.Uncertainty` of θ (None when
            the residuals are not finite).
        wall_time: seconds, including compilation on the first call.
    """

    z: np.ndarray
    params: np.ndarray
    residuals: np.ndarray
    cost: float
    jacobian: np.ndarray
    predicted_decrease: float
    iterations: int
    converged: bool
    stop_reason: str
    uncertainty: Uncertainty | None
    wall_time: float


class _State(NamedTuple):
    z: jax.Array
    r: jax.Array
    J: jax.Array
    cost: jax.Array
    pred: jax.Array  # undamped Gauss–Newton predicted decrease at z
    mu: jax.Array
    nu: jax.Array
    iteration: jax.Array
    rejections: jax.Array
    status: jax.Array


def _residuals(fun, z, args):
    """``(r, ok)``: ``fun`` may return ``r`` or ``(r, ok)``; ok also needs finite r."""
    out = fun(z, *args)
    r, ok = out if isinstance(out, tuple) else (out, jnp.asarray(True))
    return r, jnp.logical_and(ok, jnp.all(jnp.isfinite(r)))


def _linearize(fun, z, args):
    """``(r, ok, J, cost, pred)`` at z; ``pred`` the undamped Gauss–Newton decrease."""

    def with_aux(z):
        r, ok = _residuals(fun, z, args)
        return r, (r, ok)

    J, (r, ok) = jax.jacfwd(with_aux, has_aux=True)(z)
    h = jnp.linalg.lstsq(J, -r)[0]
    Jh = J @ h
    pred = 0.5 * jnp.dot(Jh, Jh)
    ok = jnp.logical_and(ok, jnp.all(jnp.isfinite(J)))
    return r, ok, J, 0.5 * jnp.dot(r, r), pred


def _damped_step(J, r, mu):
    """``(h, predicted decrease)`` of ``(JᵀJ + μ D) h = −Jᵀr``, D = diag(JᵀJ) floored."""
    A = J.T @ J
    g = J.T @ r
    d = jnp.diag(A)
    d = jnp.maximum(d, 1e-12 * jnp.max(d))
    d = jnp.where(d > 0, d, 1.0)  # a zero column: unit scaling (XLA flushes denormals)
    h = jnp.linalg.solve(A + jnp.diag(mu * d), -g)
    return h, 0.5 * jnp.dot(h, mu * d * h - g)


def _status(s: _State, settings: LMSettings):
    conv = s.pred <= settings.rtol * s.cost + settings.atol
    return jnp.where(
        conv,
        _CONVERGED,
        jnp.where(
            s.iteration >= settings.max_iterations,
            _MAX_ITER,
            jnp.where(s.rejections >= settings.max_rejections, _STALLED, _RUNNING),
        ),
    )


@functools.partial(jax.jit, static_argnames=("fun", "physical"))
def _solve(fun, physical, z0, args, settings: LMSettings):
    """The compiled loop: final state, θ and ``∂r/∂θ`` at its z.

    The residuals and their Jacobian are traced once: the first pass of the loop body
    (``iteration = −1``, a zero step from a state of infinite cost) linearises at ``z0``.
    """
    m = jax.eval_shape(lambda z: _residuals(fun, z, args)[0], z0).shape[0]
    one = jnp.ones((), z0.dtype)
    s0 = _State(
        z=z0,
        r=jnp.zeros((m,), z0.dtype),
        J=jnp.zeros((m, z0.shape[0]), z0.dtype),
        cost=jnp.inf * one,
        pred=jnp.inf * one,
        mu=settings.initial_damping * one,
        nu=2.0 * one,
        iteration=-jnp.ones((), jnp.int32),
        rejections=jnp.zeros((), jnp.int32),
        status=jnp.full((), _RUNNING, jnp.int32),
    )

    def body(s: _State) -> _State:
        first = s.iteration < 0
        h, lin = _damped_step(s.J, s.r, s.mu)
        h = jnp.where(first, jnp.zeros_like(h), h)  # the first pass linearises at z0
        rt, okt, Jt, costt, predt = _linearize(fun, s.z + h, args)
        rho = (s.cost - costt) / jnp.maximum(lin, jnp.finfo(lin.dtype).tiny)
        accept = okt & jnp.isfinite(costt) & (costt < s.cost) & ((lin > 0) | first)
        factor = jnp.where(first, 1.0, jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3))
        pick = functools.partial(jnp.where, accept)
        t = _State(
            z=pick(s.z + h, s.z),
            r=pick(rt, s.r),
            J=pick(Jt, s.J),
            cost=pick(costt, s.cost),
            pred=pick(predt, s.pred),
            mu=pick(s.mu * factor, s.mu * s.nu),
            nu=pick(2.0 * one, 2.0 * s.nu),
            iteration=s.iteration + 1,
            rejections=jnp.where(accept, jnp.zeros_like(s.rejections), s.rejections + 1),
            status=s.status,
        )
        status = jnp.where(first & ~accept, _NONFINITE, _status(t, settings))
        return t._replace(status=status.astype(jnp.int32))

    s = jax.lax.while_loop(lambda s: s.status == _RUNNING, body, s0)
    theta = physical(s.z, *args)
    dtheta = jax.jacfwd(physical)(s.z, *args)  # (p, p)
    J_theta = jnp.linalg.solve(dtheta.T, s.J.T).T  # ∂r/∂θ = ∂r/∂z (∂θ/∂z)⁻¹
    return s, theta, J_theta


def _identity(z, *args):
    return z


def levenberg_marquardt(
    fun: Callable,
    z0,
    args: tuple = (),
    *,
    physical: Callable | None = None,
    known_sigma: bool = True,
    settings: LMSettings | None = None,
) -> LeastSquaresResult:
    """Minimise ``½‖r(z)‖²`` by Levenberg–Marquardt (module docstring).

    Args:
        fun: ``fun(z, *args) -> r`` or ``-> (r, ok)``: ``(m,)`` weighted residuals
            ``(pred − data)/σ`` and, optionally, a boolean that is False when the
            prediction failed (e.g. an inner solve did not converge). Static under jit:
            a hashable callable (the same object reuses the compilation).
        z0: ``(p,)`` initial unconstrained vector.
        args: pytree of traced extra arguments (data, weights, a parametrisation).
        physical: ``physical(z, *args) -> θ`` ``(p,)``, the physical parameters the
            Jacobian and the uncertainty are reported in (default: θ = z). Must be a
            bijection near the optimum (the transforms of
            :mod:`~jaxelastic.fitting.transforms` are).
        known_sigma: True when σ are measurement standard deviations; False when they are
            relative weights (the covariance is then scaled by the reduced χ²).
        settings: :class:`LMSettings` (defaults).
    Returns:
        :class:`LeastSquaresResult`; check ``converged`` (the status is never hidden).
    Raises:
        ValueError: ``z0`` not a finite 1-D vector.
    """
    settings = LMSettings() if settings is None else settings
    z0 = jnp.asarray(z0)
    if z0.ndim != 1 or z0.size == 0 or not bool(jnp.all(jnp.isfinite(z0))):
        raise ValueError(f"z0 must be a finite, non-empty 1-D vector, got shape {z0.shape}")
    tic = time.perf_counter()
    s, theta, J_theta = _solve(fun, physical or _identity, z0, args, _traced(settings))
    s, theta, J_theta = jax.device_get((s, theta, J_theta))
    wall = time.perf_counter() - tic
    status = int(s.status)
    if status == _NONFINITE:  # nothing was evaluated successfully: no residuals to report
        s = s._replace(r=np.full_like(s.r, np.nan))
        J_theta = np.full_like(J_theta, np.nan)
    finite = bool(np.all(np.isfinite(s.r)) and np.all(np.isfinite(J_theta)))
    unc = gauss_newton_uncertainty(J_theta, s.r, known_sigma=known_sigma) if finite else None
    cost = float(s.cost)
    return LeastSquaresResult(
        z=np.asarray(s.z),
        params=np.asarray(theta),
        residuals=np.asarray(s.r),
        cost=cost,
        jacobian=np.asarray(J_theta),
        predicted_decrease=float(s.pred) / cost if cost > 0 else 0.0,
        iterations=int(s.iteration),
        converged=status == _CONVERGED,
        stop_reason=STOP_REASONS[status],
        uncertainty=unc,
        wall_time=wall,
    )


def _traced(settings: LMSettings) -> LMSettings:
    """Settings as arrays (traced arguments: new tolerances do not recompile)."""
    floats = np.float64, np.float64, np.int32, np.int32, np.float64
    return LMSettings._make(t(v) for t, v in zip(floats, settings, strict=True))
