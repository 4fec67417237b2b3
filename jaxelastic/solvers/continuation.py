"""Load stepping: apply loads and Dirichlet motion in increments, cutting back on failure.

For loads too large for one Newton solve (buckling-prone, strongly nonlinear, or a boundary
motion that would tangle the mesh in one step), the load factor ``s`` goes from 0 to 1;
at each trial ``s`` the potential's external forces are ``s·f_ext`` (pressures ``s·p``),
the Dirichlet data ``path(s)`` (default: the prescribed displacement scaled by ``s``) and,
when given, the material parameters ``params_path(s)`` (e.g. an active fibre tension
``s·T_a``: :meth:`~jaxelastic.materials.ActiveTension.scaled`).
A failed solve halves the increment (from the last converged state); a success grows it
again (×1.5, at most the initial increment). Every increment is one
:func:`~jaxelastic.solvers.equilibrium.solve`; all share one compilation (only array values
change between them). With a contact term (``pot.contact``) the obstacles' prescribed
motion is evaluated at ``s``, friction is lagged at the last converged state, and nodes an
obstacle swept over are pushed out of it before the increment's Newton solve.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import jax.numpy as jnp

from ..loads import Dirichlet
from ..mechanics.potential import Potential
from .equilibrium import PreparedSolver, prepare_solver, solve
from .newton import Newton
from .results import Solution, SolveError, Status

__all__ = ["scaled_dirichlet", "solve_incremental"]


def scaled_dirichlet(mesh, bc: Dirichlet) -> Callable[[float], Dirichlet]:
    """``s ↦`` Dirichlet data with the prescribed *displacement* scaled by ``s``."""
    X = mesh.points

    def path(s):
        return Dirichlet(mask=bc.mask, values=X + s * (bc.values - X))

    return path


def _record(s: float, res: Solution) -> dict:
    st = res.stats
    return dict(
        s=s,
        status=Status(int(res.status)).name,
        steps=int(st["steps"]),
        linear_iterations=int(st["linear_iterations"]),
        residual=float(st["residual"]),
        min_J=float(st["min_J"]),
        max_strain=float(st["max_strain"]),
        achieved_rtol=float(st["achieved_rtol"]),
        floor_limited=bool(st.get("floor_limited", False)),
        wall_time=float(st["wall_time"]),
        accepted=bool(res.ok),
    )


def _at_load_factor(pot: Potential, f_full, s: float, params_path) -> Potential:
    """``pot`` at load factor ``s``: forces and pressures scaled (and the parameters of
    ``params_path``, when given)."""
    p = pot if f_full is None else pot.replace(f_ext=s * f_full)
    if pot.pressure is not None:  # pressures ramped like the forces
        p = p.replace(pressure=pot.pressure.scaled(s))
    return p if params_path is None else p.replace(params=params_path(s))


def solve_incremental(
    pot: Potential,
    bc: Dirichlet,
    *,
    x0=None,
    solver: Newton | PreparedSolver = Newton(),
    steps: int = 1,
    min_increment: float = 1.0 / 1024,
    path: Callable[[float], Dirichlet] | None = None,
    throw: bool = True,
    callback: Callable[[float, Solution], None] | None = None,
    params_path: Callable[[float], object] | None = None,
) -> Solution:
    """Solve the static problem at load factor 1 by increments with automatic cut-back.

    Args:
        pot: potential with the *full* external forces (scaled by ``s`` internally).
        bc: full Dirichlet data (its displacement is scaled by ``s`` unless ``path`` is
            given).
        x0: initial positions (default: rest).
        solver: :class:`~jaxelastic.solvers.newton.Newton` (bound once for all increments).
        steps: initial number of increments (the first try is ``s = 1/steps``).
        min_increment: give up when the increment would fall below this.
        path: optional ``s ↦ Dirichlet`` (the mask must not depend on ``s``); e.g. a
            rotation by ``s·θ`` instead of a scaled displacement.
        throw: raise :class:`~jaxelastic.solvers.results.SolveError` when it fails.
        callback: called with ``(s, solution)`` after every converged increment.
        params_path: optional ``s ↦`` material parameters (the same pytree structure and
            shapes as ``pot.params`` at every ``s``: one compilation); default
            ``pot.params`` throughout.

    Returns:
        The :class:`~jaxelastic.solvers.results.Solution` of the last solve tried, with
        ``x`` at the last converged load factor, ``status`` SUCCESS when ``s = 1`` was
        reached, and extra stats ``load_factor`` (float), ``increments`` (one dict per
        trial: ``s``, ``status``, ``steps``, ``linear_iterations``, ``residual``,
        ``wall_time``, ``accepted``) and ``wall_time`` (total seconds).
    """
    if int(steps) < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    if not 0 < min_increment <= 1:
        raise ValueError(f"min_increment must be in (0, 1], got {min_increment}")
    path = path if path is not None else scaled_dirichlet(pot.mesh, bc)
    x = pot.mesh.points if x0 is None else jnp.asarray(x0, pot.mesh.points.dtype)
    prepared = prepare_solver(solver, pot.mesh, path(1.0))
    f_full = pot.f_ext
    s, ds0 = 0.0, 1.0 / steps
    ds = ds0
    history: list = []
    last: Solution | None = None
    t0 = time.perf_counter()
    while s < 1.0:
        s_try = min(1.0, s + ds)
        p = _at_load_factor(pot, f_full, s_try, params_path)
        x_start = x
        if pot.contact is not None:  # obstacles at time s_try, friction lagged at x (time s)
            c = pot.contact.at_time(s)
            if c.self_friction is not None:  # lagged over the candidate pairs: complete
                c = c.refreshed(x)  # them at x (host)
            c = (c.lag(x) if c.has_friction else c).at_time(s_try)
            p, x_start = p.replace(contact=c), c.make_feasible(x)
        last = solve(p, path(s_try), x0=x_start, solver=prepared, throw=False)
        history.append(_record(s_try, last))
        if bool(last.ok):
            s, x = s_try, last.x
            if callback is not None:
                callback(s, last)
            ds = min(ds0, 1.5 * ds)
        else:
            ds = 0.5 * ds
            if ds < min_increment:
                break
    assert last is not None
    status = last.status if s < 1.0 else jnp.asarray(Status.SUCCESS, jnp.int32)
    stats = dict(last.stats, load_factor=s, increments=history, wall_time=time.perf_counter() - t0)
    out = Solution(x=x, status=status, stats=stats)
    if throw and s < 1.0:
        raise SolveError(out, what=f"load stepping (stalled at load factor {s:.4g})")
    return out
