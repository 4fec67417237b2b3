"""Volume control: prescribe cavity volumes and solve for the pressures.

A cavity inflated by a prescribed *pressure* cannot go past a pressure maximum (a thick
neo-Hookean sphere has one, at 0.816 μ for B/A = 2): there the pressure-controlled
equilibrium turns unstable and Newton has nothing to converge to. Prescribing the
*volume* instead traces the whole pressure–volume curve. :func:`solve_volume_controlled`
does it with the augmented Lagrangian method (Hestenes 1969; Powell 1969; Bertsekas 1982,
ch. 2): for a multiplier estimate ``λ`` (the pressure) it minimises

``Π(x) + (−λ (V(x) − T) + κ/2 (V(x) − T)²)``

with the one Newton driver (:func:`~jaxelastic.solvers.equilibrium.solve`: the term is
:class:`~jaxelastic.mechanics.pressure.Pressure` with ``target`` and ``kappa``; its
rank-one Hessian ``κ ∇V ∇Vᵀ`` is applied as an operator next to the element Hessians), then
updates ``λ ← λ − κ(V − T)``, the pressure that equilibrium carries. The volume error falls
by about ``k_c/(k_c + κ)`` per update, with ``k_c = dp/dV`` the cavity's stiffness: the
default ``κ = 100/c₀`` with ``c₀ = dV/dp`` at rest (one tangent solve) makes that ~1/100,
and keeps ``K − p∇²V + κ∇V∇Vᵀ`` positive definite past the limit point, where
``k_c < 0``. Each update is one more Newton solve from the previous solution (a few
iterations).

This is an equivalent of the bordered Lagrange-multiplier system
``[K −∇V; −∇Vᵀ 0]``: the same equilibrium and pressure at convergence, but every linear
system stays symmetric positive definite, so the energy line search and every linear solver
(Cholesky, CG, multigrid) apply unchanged.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from ..loads import Dirichlet
from ..mechanics.potential import Potential
from .adjoint import ImplicitAdjoint
from .equilibrium import prepare_solver, solve
from .newton import Newton
from .results import Solution, SolveError, Status

__all__ = ["solve_volume_controlled", "cavity_compliance"]


def cavity_compliance(pot: Potential, bc: Dirichlet, solver: Newton = Newton()) -> np.ndarray:
    """``(n_s,)`` ``dV_s/dp_s`` at the rest shape [length^d/Pa]: each surface's volume
    change per unit of its own pressure (one tangent solve through the implicit
    derivative of :func:`~jaxelastic.solvers.equilibrium.solve`)."""
    term = pot.pressure
    if term is None:
        raise ValueError("cavity_compliance needs a potential with a pressure term")
    n_s = term.n_surfaces
    zero = jnp.zeros((n_s,), term.pressure.dtype)

    def volumes(p):
        q = pot.replace(pressure=term.replace(pressure=p, target=None, kappa=None))
        x = solve(q, bc, solver=solver, adjoint=ImplicitAdjoint(mode="forward")).x
        return term.volumes(x)

    out = []
    for s in range(n_s):
        e = jnp.zeros((n_s,), zero.dtype).at[s].set(1.0)
        out.append(float(jax.jvp(volumes, (zero,), (e,))[1][s]))
    return np.asarray(out)


def _record(s, j, res: Solution, V, p) -> dict:
    return dict(
        load_factor=s,
        update=j,
        status=Status(int(res.status)).name,
        steps=int(res.stats["steps"]),
        linear_iterations=int(res.stats["linear_iterations"]),
        residual=float(res.stats["residual"]),
        wall_time=float(res.stats.get("wall_time", 0.0)),
        volume=[float(v) for v in V],
        pressure=[float(q) for q in p],
    )


def solve_volume_controlled(
    pot: Potential,
    bc: Dirichlet,
    volumes,
    *,
    steps: int = 1,
    kappa=None,
    rtol: float = 1e-9,
    max_updates: int = 30,
    solver: Newton = Newton(),
    x0=None,
    callback: Callable[[float, Solution, np.ndarray, np.ndarray], None] | None = None,
    throw: bool = True,
) -> Solution:
    """Reach prescribed cavity volumes in ``steps`` equal volume increments; the pressures
    are the unknowns (augmented Lagrangian, see the module docstring).

    Long because: the volume path, the multiplier updates and the record of every solve
    read best as one loop.

    Args:
        pot: a potential with a :class:`~jaxelastic.mechanics.pressure.Pressure` term (its
            pressures are the first multiplier estimates; 0 is fine).
        bc: Dirichlet data (held fixed along the path).
        volumes: ``(n_s,)`` or a scalar, the prescribed final volumes [length^d], > 0.
        steps: volume increments from the rest volumes (linear in between).
        kappa: ``(n_s,)`` penalties [Pa/length^d]; default ``100 / dV/dp`` at rest
            (:func:`cavity_compliance`).
        rtol: stop updating once ``|V − T| ≤ rtol·T`` for every surface.
        max_updates: multiplier updates per increment before giving up.
        solver: the Newton settings of every inner solve.
        x0: initial positions (default: rest).
        callback: ``callback(s, solution, volumes, pressures)`` after every converged
            increment.
        throw: raise :class:`~jaxelastic.solvers.results.SolveError` when it fails.

    Returns:
        The :class:`~jaxelastic.solvers.results.Solution` at the last converged increment
        with extra stats ``pressure`` and ``volume`` (``(n_s,)`` lists), ``path`` (one dict
        per converged increment: ``load_factor``, ``volume``, ``pressure``, ``updates``)
        and ``solves`` (one dict per inner solve: ``load_factor``, ``update``, ``status``,
        ``steps``, ``linear_iterations``, ``residual``, ``wall_time``, ``volume``,
        ``pressure``), ``wall_time``.

    Raises:
        ValueError: no pressure term, a non-finite or non-positive target volume, or a
            rest volume that is not positive (the facets bound no cavity).
    """
    term = pot.pressure
    if term is None:
        raise ValueError("solve_volume_controlled needs a potential with a pressure term")
    n_s, dt = term.n_surfaces, pot.mesh.points.dtype
    T = np.broadcast_to(np.asarray(volumes, dtype=np.float64), (n_s,))
    if not np.all(np.isfinite(T)) or not np.all(T > 0):
        raise ValueError(f"prescribed volumes must be finite and > 0, got {T.tolist()}")
    V0 = np.asarray(term.volumes(pot.mesh.points), dtype=np.float64)
    if not np.all(V0 > 0):
        raise ValueError(
            f"the loaded surfaces enclose rest volumes {V0.tolist()}: a prescribed volume "
            "needs a cavity (V > 0 at rest; an outer surface encloses a negative one)"
        )
    if int(steps) < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    free = term.replace(target=None, kappa=None)
    if kappa is None:
        kappa = 100.0 / cavity_compliance(pot.replace(pressure=free), bc, solver)
    k = jnp.asarray(np.broadcast_to(np.asarray(kappa, np.float64), (n_s,)), dt)
    prepared = prepare_solver(solver, pot.mesh, bc)
    x = pot.mesh.points if x0 is None else jnp.asarray(x0, dt)
    lam = jnp.asarray(term.pressure, dt)
    path, solves, t0 = [], [], time.perf_counter()
    res: Solution | None = None
    ok = True
    for i in range(1, int(steps) + 1):
        s = i / int(steps)
        target = jnp.asarray(V0 + s * (T - V0), dt)
        done = False
        for j in range(max_updates):
            al = free.replace(pressure=lam, target=target, kappa=k)
            res = solve(pot.replace(pressure=al), bc, x0=x, solver=prepared, throw=False)
            if not bool(res.ok):
                break
            x = res.x
            V = al.volumes(x)
            lam = al.effective_pressures(x)  # λ ← λ − κ(V − T)
            solves.append(_record(s, j, res, V, lam))
            if bool(jnp.all(jnp.abs(V - target) <= rtol * target)):
                done = True
                break
        if not done:
            ok = False
            break
        assert res is not None
        path.append(
            dict(
                load_factor=s,
                volume=solves[-1]["volume"],
                pressure=solves[-1]["pressure"],
                updates=solves[-1]["update"] + 1,
            )
        )
        if callback is not None:
            callback(s, res, np.asarray(solves[-1]["volume"]), np.asarray(lam))
    assert res is not None
    last = path[-1] if path else dict(volume=V0.tolist(), pressure=[0.0] * n_s)
    stats = dict(
        res.stats,
        pressure=last["pressure"],
        volume=last["volume"],
        path=path,
        solves=solves,
        wall_time=time.perf_counter() - t0,
    )
    status = jnp.asarray(Status.SUCCESS, jnp.int32) if ok else res.status
    if ok is False and int(status) == Status.SUCCESS:
        status = jnp.asarray(Status.MAX_STEPS, jnp.int32)
    out = Solution(x=x, status=status, stats=stats)
    if throw and not ok:
        reached = path[-1]["load_factor"] if path else 0.0
        raise SolveError(out, what=f"volume control (stalled at volume factor {reached:.4g})")
    return out
