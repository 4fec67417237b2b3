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
data, weights and tolerances are traced arguments). Residuals that are not one traceable
function — finite-element solves with warm starts and failure reports
(:func:`~jaxelastic.fitting.fit` with ``optimizer="lm"``) — run the same step, acceptance
and stop tests (:func:`lm_proposal`, :func:`lm_update`) in a host loop, :func:`lm_iterate`.
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

__all__ = [
    "LMSettings",
    "LMState",
    "Linearization",
    "LeastSquaresResult",
    "STOP_REASONS",
    "levenberg_marquardt",
    "linearization",
    "lm_initial",
    "lm_iterate",
    "lm_proposal",
    "lm_update",
    "traced_settings",
]

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


class LMState(NamedTuple):
    """The iterate of the Levenberg–Marquardt loop (the compiled one and :func:`lm_iterate`).

    Attributes:
        z: ``(p,)`` the accepted point; r: ``(m,)`` its residuals; J: ``(m, p)`` their
        Jacobian ``∂r/∂z``; cost: ``½‖r‖²``; pred: the undamped Gauss–Newton predicted
        decrease at z; mu, nu: the damping and its growth factor; iteration: iterations
        (accepted and rejected steps; −1 before the first linearisation); rejections:
        consecutive rejected steps; status: the index into :data:`STOP_REASONS`.
    """

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


class Linearization(NamedTuple):
    """The residuals at a trial point and their local linear model (:func:`linearization`).

    Attributes:
        r: ``(m,)`` residuals; ok: bool, the residuals (and J) are usable; J: ``(m, p)``
        ``∂r/∂z``; cost: ``½‖r‖²``; pred: the undamped Gauss–Newton predicted decrease
        ``½‖J h_GN‖²``, ``h_GN = argmin‖J h + r‖``.
    """

    r: jax.Array
    ok: jax.Array
    J: jax.Array
    cost: jax.Array
    pred: jax.Array


def _residuals(fun, z, args):
    """``(r, ok)``: ``fun`` may return ``r`` or ``(r, ok)``; ok also needs finite r."""
    out = fun(z, *args)
    r, ok = out if isinstance(out, tuple) else (out, jnp.asarray(True))
    return r, jnp.logical_and(ok, jnp.all(jnp.isfinite(r)))


def linearization(r, J, ok) -> Linearization:
    """The :class:`Linearization` of residuals ``r (m,)`` with Jacobian ``J (m, p)``
    (``ok`` False: a failed evaluation, rejected like a step that increases the cost)."""
    ok = jnp.logical_and(ok, jnp.all(jnp.isfinite(r)) & jnp.all(jnp.isfinite(J)))
    safe = jnp.where(ok, J, 0.0), jnp.where(ok, r, 0.0)  # lstsq of NaN: undefined
    h = jnp.linalg.lstsq(safe[0], -safe[1])[0]
    Jh = safe[0] @ h
    return Linearization(r, ok, J, 0.5 * jnp.dot(r, r), 0.5 * jnp.dot(Jh, Jh))


def _linearize(fun, z, args) -> Linearization:
    """The :class:`Linearization` at z, ``J`` by :func:`jax.jacfwd`."""

    def with_aux(z):
        r, ok = _residuals(fun, z, args)
        return r, (r, ok)

    J, (r, ok) = jax.jacfwd(with_aux, has_aux=True)(z)
    return linearization(r, J, ok)


def _damped_step(J, r, mu):
    """``(h, predicted decrease)`` of ``(JᵀJ + μ D) h = −Jᵀr``, D = diag(JᵀJ) floored."""
    A = J.T @ J
    g = J.T @ r
    d = jnp.diag(A)
    d = jnp.maximum(d, 1e-12 * jnp.max(d))
    d = jnp.where(d > 0, d, 1.0)  # a zero column: unit scaling (XLA flushes denormals)
    h = jnp.linalg.solve(A + jnp.diag(mu * d), -g)
    return h, 0.5 * jnp.dot(h, mu * d * h - g)


def _status(s: LMState, settings: LMSettings):
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


def lm_initial(z0, m: int, settings: LMSettings) -> LMState:
    """The state before the first linearisation at ``z0`` (``m`` residuals): infinite
    cost, iteration −1 (:func:`lm_proposal` then proposes the zero step)."""
    one = jnp.ones((), z0.dtype)
    return LMState(
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


def lm_proposal(s: LMState):
    """``(trial point, predicted decrease of the damped model)``: the damped step from
    ``s.z`` (Marquardt's scaling), or ``s.z`` itself before the first linearisation."""
    h, lin = _damped_step(s.J, s.r, s.mu)
    h = jnp.where(s.iteration < 0, jnp.zeros_like(h), h)  # the first pass linearises at z0
    return s.z + h, lin


def lm_update(s: LMState, zt, lin, trial: Linearization, settings: LMSettings) -> LMState:
    """The next state after evaluating the trial point ``zt`` of :func:`lm_proposal`:
    accepted when it is usable and lowers the cost (the gain ratio ρ then scales μ by
    ``max(1/3, 1 − (2ρ − 1)³)``), else rejected (μ ← μν, ν ← 2ν); then the stop test
    (module docstring). ``settings`` as arrays (:func:`traced_settings`)."""
    first = s.iteration < 0
    rho = (s.cost - trial.cost) / jnp.maximum(lin, jnp.finfo(lin.dtype).tiny)
    accept = trial.ok & jnp.isfinite(trial.cost) & (trial.cost < s.cost) & ((lin > 0) | first)
    factor = jnp.where(first, 1.0, jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3))
    pick = functools.partial(jnp.where, accept)
    one = jnp.ones((), s.mu.dtype)
    t = LMState(
        z=pick(zt, s.z),
        r=pick(trial.r, s.r),
        J=pick(trial.J, s.J),
        cost=pick(trial.cost, s.cost),
        pred=pick(trial.pred, s.pred),
        mu=pick(s.mu * factor, s.mu * s.nu),
        nu=pick(2.0 * one, 2.0 * s.nu),
        iteration=s.iteration + 1,
        rejections=jnp.where(accept, jnp.zeros_like(s.rejections), s.rejections + 1),
        status=s.status,
    )
    status = jnp.where(first & ~accept, _NONFINITE, _status(t, settings))
    return t._replace(status=status.astype(jnp.int32))


@functools.partial(jax.jit, static_argnames=("fun", "physical"))
def _solve(fun, physical, z0, args, settings: LMSettings):
    """The compiled loop: final state, θ and ``∂r/∂θ`` at its z.

    The residuals and their Jacobian are traced once: the first pass of the loop body
    (``iteration = −1``, a zero step from a state of infinite cost) linearises at ``z0``.
    """
    m = jax.eval_shape(lambda z: _residuals(fun, z, args)[0], z0).shape[0]

    def body(s: LMState) -> LMState:
        zt, lin = lm_proposal(s)
        return lm_update(s, zt, lin, _linearize(fun, zt, args), settings)

    s = jax.lax.while_loop(lambda s: s.status == _RUNNING, body, lm_initial(z0, m, settings))
    theta = physical(s.z, *args)
    dtheta = jax.jacfwd(physical)(s.z, *args)  # (p, p)
    J_theta = jnp.linalg.solve(dtheta.T, s.J.T).T  # ∂r/∂θ = ∂r/∂z (∂θ/∂z)⁻¹
    return s, theta, J_theta


_proposal_jit = jax.jit(lm_proposal)
_update_jit = jax.jit(lm_update)


def lm_iterate(
    linearize: Callable, z0, settings: LMSettings, accepted: Callable | None = None
) -> tuple[LMState, bool]:
    """The Levenberg–Marquardt iteration on the host, for residuals that are not one
    traceable function (finite-element solves with warm starts and failure reports).

    The same steps, acceptance, damping and stop tests as :func:`levenberg_marquardt`
    (:func:`lm_proposal`, :func:`lm_update`); only the loop runs in Python.

    Args:
        linearize: ``linearize(z) -> (r (m,), J (m, p), ok)`` at a trial point (``r``
            and ``J`` may be None when ``ok`` is False: the trial is rejected).
        z0: ``(p,)`` initial unconstrained vector.
        settings: :class:`LMSettings`.
        accepted: called with the new :class:`LMState` after every accepted point (the
            initial one included, at iteration 0); returns True to stop there (ignored
            when the iteration stops there anyway).
    Returns:
        ``(final state (host values), stopped by accepted)``; ``STOP_REASONS[status]``
        says why it stopped otherwise (``"nonfinite"``: ``linearize`` failed at z0).
    """
    z0 = jnp.asarray(z0)
    traced = traced_settings(settings)

    m = 0  # the number of residuals, from the first successful evaluation

    def trial(z):
        r, J, ok = linearize(z)
        if r is None:  # a failed evaluation: rejected
            r = jnp.full((m,), jnp.nan, z0.dtype)
        r = jnp.asarray(r)
        J = jnp.full((r.shape[0], z0.shape[0]), jnp.nan, r.dtype) if J is None else J
        return linearization(r, jnp.asarray(J), jnp.asarray(bool(ok)))

    zt, lin, lt = z0, jnp.zeros((), z0.dtype), trial(z0)
    s = lm_initial(z0, int(lt.r.shape[0]), traced)
    if not bool(lt.ok):
        return jax.device_get(s._replace(status=jnp.int32(_NONFINITE))), False
    m = int(lt.r.shape[0])
    while True:
        s = _update_jit(s, zt, lin, lt, traced)
        stop = accepted is not None and int(s.rejections) == 0 and bool(accepted(s))
        if int(s.status) != _RUNNING:
            break
        if stop:
            return jax.device_get(s), True
        zt, lin = _proposal_jit(s)
        lt = trial(zt)
    return jax.device_get(s), False


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
    s, theta, J_theta = _solve(fun, physical or _identity, z0, args, traced_settings(settings))
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


def traced_settings(settings: LMSettings) -> LMSettings:
    """Settings as arrays (traced arguments: new tolerances do not recompile)."""
    floats = np.float64, np.float64, np.int32, np.int32, np.float64
    return LMSettings._make(t(v) for t, v in zip(floats, settings, strict=True))
