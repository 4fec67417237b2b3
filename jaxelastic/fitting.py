"""Material identification: fit (E, ν) to observed deformed shapes with optax.

:func:`fit` identifies (E, ν) from observed deformed positions in one or several load
cases with an optax optimiser (L-BFGS by default), under the constraint-enforcing
reparametrisation ``E = E₀·exp(a)``, ``ν = −1 + 1.5·sigmoid(b)``. Gradients come from
:mod:`jaxelastic.implicit` (one adjoint solve per load case, never the Newton iterations).
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .implicit import (
    DEFAULT_ADJOINT,
    AdjointSettings,
    GradientError,
    _check_finite_grads,
    equilibrium,
    equilibrium_result,
    value_and_grad,
)
from .loads import Dirichlet
from .materials import Lame, lame
from .potential import Potential
from .solvers.newton import NewtonSettings, Status

__all__ = [
    # re-exported from jaxelastic.implicit for convenience
    "AdjointSettings",
    "GradientError",
    "equilibrium",
    "equilibrium_result",
    "value_and_grad",
    # fitting
    "LoadCase",
    "FitResult",
    "fit",
    "to_unconstrained",
    "from_unconstrained",
]


# --------------------------------------------------------------------------------------
# fitting (E, ν)
# --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class LoadCase:
    """One experiment: a potential (its ``params`` are replaced by the fitted ones), the
    Dirichlet data, and observed positions.

    Attributes:
        pot: potential (mesh, ``f_ext``, ψ); ``params`` is ignored.
        bc: Dirichlet data.
        observed: ``(n_obs, dim)`` observed deformed positions of ``nodes``.
        nodes: ``(n_obs,)`` node indices (marker nodes), or None for all nodes.
        weight: weight of this case in the loss.
    """

    pot: Potential
    bc: Dirichlet
    observed: Any
    nodes: Any = None
    weight: float = 1.0


jax.tree_util.register_dataclass(
    LoadCase, data_fields=["pot", "bc", "observed", "nodes", "weight"], meta_fields=[]
)


def to_unconstrained(E, nu, E_ref):
    """(E, ν) → (a, b) with ``E = E_ref·exp(a)``, ``ν = −1 + 1.5·sigmoid(b)``."""
    s = (nu + 1.0) / 1.5
    return jnp.stack([jnp.log(E / E_ref), jnp.log(s) - jnp.log1p(-s)])


def from_unconstrained(z, E_ref):
    """Inverse of :func:`to_unconstrained`: returns (E, ν), E > 0 and −1 < ν < 0.5."""
    return E_ref * jnp.exp(z[0]), -1.0 + 1.5 * jax.nn.sigmoid(z[1])


class FitResult(NamedTuple):
    """Result of :func:`fit`.

    Attributes:
        E, nu: fitted values.
        loss: final loss.
        converged: stopping criterion met (else ``max_iter`` reached).
        iterations: optimiser iterations.
        loss_history: ``(iterations + 1,)`` loss at each iterate.
        param_history: ``(iterations + 1, 2)`` (E, ν) at each iterate.
        grad_norm_history: gradient norm (w.r.t. the unconstrained variables).
        newton_steps: ``(iterations + 1, n_cases)`` Newton iterations of each forward solve.
        linear_iterations: ``(iterations + 1, n_cases)`` CG iterations of each forward solve.
        solutions: final equilibrium positions per case.
        wall_time: seconds.
    """

    E: float
    nu: float
    loss: float
    converged: bool
    iterations: int
    loss_history: np.ndarray
    param_history: np.ndarray
    grad_norm_history: np.ndarray
    newton_steps: np.ndarray
    linear_iterations: np.ndarray
    solutions: list
    wall_time: float


def _case_loss(case: LoadCase, x):
    X = case.pot.mesh.points
    if case.nodes is None:
        xo, Xo = x, X
    else:
        xo, Xo = x[case.nodes], X[case.nodes]
    obs = case.observed
    scale = jnp.sum((obs - Xo) ** 2)  # observed displacement magnitude
    return case.weight * jnp.sum((xo - obs) ** 2) / scale


def fit(
    cases: Sequence[LoadCase],
    E0: float,
    nu0: float,
    *,
    plane: str = "strain",
    optimizer=None,
    max_iter: int = 100,
    gtol: float = 1e-10,
    ftol: float = 1e-24,
    settings: NewtonSettings = NewtonSettings(rtol=1e-11),
    adjoint: AdjointSettings = DEFAULT_ADJOINT,
    progress: bool = False,
) -> FitResult:
    """Fit Young's modulus and Poisson's ratio to observed positions.

    The loss is ``Σ_cases w·‖x*(E, ν)[nodes] − observed‖² / ‖observed − X[nodes]‖²``
    (each case normalised by its observed displacement). Parameters are optimised in
    unconstrained variables (:func:`to_unconstrained`, with ``E_ref = E0``). Each forward
    solve is warm-started from the previous iterate's solution of the same case.

    Args:
        cases: load cases (matrix-free CG forward/adjoint solves, under jit).
        E0, nu0: initial guess.
        plane: 2D only: ``"strain"`` or ``"stress"`` (see :func:`~jaxelastic.materials.lame`).
        optimizer: an optax ``GradientTransformation``; default ``optax.lbfgs()`` (with its
            zoom line search, which is given the loss function and the warm start).
        max_iter: maximum optimiser iterations.
        gtol: stop when the unconstrained gradient norm is below this.
        ftol: stop when the loss is below this.
        settings, adjoint: Newton and adjoint settings.
        progress: print one line per iteration.

    Raises:
        GradientError: a forward solve at an accepted iterate failed.
    """
    import optax

    t_start = time.perf_counter()
    cases = list(cases)
    dim = cases[0].pot.mesh.dim
    E_ref = float(E0)
    if optimizer is None:
        optimizer = optax.lbfgs()

    def params_of(z):
        E, nu = from_unconstrained(z, E_ref)
        mu, lam = lame(E, nu, dim=dim, plane=plane)
        return Lame(mu, lam)

    def total(z, cases, x0s):
        p = params_of(z)
        loss = 0.0
        results = []
        ok = True
        for c, x0 in zip(cases, x0s, strict=True):
            r = equilibrium_result(c.pot.replace(params=p), c.bc, x0, settings, None, adjoint)
            loss = loss + _case_loss(c, r.x)
            ok = ok & (r.status == Status.SUCCESS)
            results.append(r)
        return loss, (results, ok)

    vg = jax.jit(jax.value_and_grad(total, has_aux=True))

    def value_fn(z, cases, x0s):  # for the line search: failed solves are +inf
        loss, (_, ok) = total(z, cases, x0s)
        return jnp.where(ok, loss, jnp.inf)

    @jax.jit
    def opt_step(z, state, g, value, cases, x0s):
        fn = functools.partial(value_fn, cases=cases, x0s=x0s)
        updates, state = optimizer.update(g, state, z, value=value, grad=g, value_fn=fn)
        return optax.apply_updates(z, updates), state

    z = to_unconstrained(jnp.asarray(E0, jnp.float64), jnp.asarray(nu0, jnp.float64), E_ref)
    state = optimizer.init(z)
    x0s = [c.pot.mesh.points for c in cases]
    hist_loss, hist_p, hist_g, hist_nw, hist_lin = [], [], [], [], []
    converged = False
    k = 0
    while True:
        (loss, (results, ok)), g = vg(z, cases, x0s)
        if not bool(ok):
            bad = [int(r.status) for r in results]
            raise GradientError(f"forward solve failed at iterate {k} (statuses {bad})")
        _check_finite_grads(g)
        x0s = [r.x for r in results]
        E, nu = from_unconstrained(z, E_ref)
        gn = float(jnp.linalg.norm(g))
        hist_loss.append(float(loss))
        hist_p.append((float(E), float(nu)))
        hist_g.append(gn)
        hist_nw.append([int(r.steps) for r in results])
        hist_lin.append([int(r.linear_iterations) for r in results])
        if progress:
            print(
                f"fit {k:4d}  loss {float(loss):.3e}  E {float(E):.6g}  nu {float(nu):.6f}"
                f"  |g| {gn:.2e}  newton {hist_nw[-1]}"
            )
        if gn <= gtol or float(loss) <= ftol:
            converged = True
            break
        if k >= max_iter:
            break
        z_new, state = opt_step(z, state, g, loss, cases, x0s)
        if bool(jnp.all(z_new == z)):  # no progress possible (line search stalled)
            converged = gn <= 1e3 * gtol
            break
        z = z_new
        k += 1
    E, nu = from_unconstrained(z, E_ref)
    return FitResult(
        E=float(E),
        nu=float(nu),
        loss=hist_loss[-1],
        converged=converged,
        iterations=k,
        loss_history=np.array(hist_loss),
        param_history=np.array(hist_p),
        grad_norm_history=np.array(hist_g),
        newton_steps=np.array(hist_nw),
        linear_iterations=np.array(hist_lin),
        solutions=x0s,
        wall_time=time.perf_counter() - t_start,
    )
