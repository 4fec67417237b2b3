"""Load stepping: apply loads and Dirichlet motion in increments, cutting back on failure.

For loads too large for one Newton solve (buckling-prone, strongly nonlinear, or a boundary
motion that would tangle the mesh in one step), the load factor ``s`` goes from 0 to 1;
at each trial ``s`` the potential's external forces are ``s·f_ext`` and the Dirichlet data
``bc_fn(s)``. A failed solve halves the increment (from the last converged state); a
success grows it again (×1.5, at most the initial increment). All solves share one
compilation: only array values change between them.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import NamedTuple

import jax.numpy as jnp

from ..loads import Dirichlet
from ..potential import Potential
from .newton import NewtonResult, NewtonSettings, SolveError, Status, make_linear, solve

__all__ = ["IncrementalResult", "scaled_dirichlet", "solve_incremental"]


class IncrementalResult(NamedTuple):
    """Result of :func:`solve_incremental`.

    Attributes:
        x: ``(n_nodes, dim)`` positions at the last converged load factor.
        status: :class:`~jaxelastic.solvers.newton.Status` of the whole continuation
            (SUCCESS when s = 1 was reached).
        load_factor: the last converged load factor (1.0 on success).
        last: the :class:`~jaxelastic.solvers.newton.NewtonResult` of the last solve tried.
        history: one dict per trial: ``s``, ``status``, Newton and linear iterations,
            residual, wall time, ``accepted``.
        wall_time: total seconds.
    """

    x: object
    status: int
    load_factor: float
    last: NewtonResult
    history: list
    wall_time: float

    @property
    def ok(self) -> bool:
        return self.status == Status.SUCCESS


def scaled_dirichlet(mesh, bc: Dirichlet) -> Callable[[float], Dirichlet]:
    """``s ↦`` Dirichlet data with the prescribed *displacement* scaled by ``s``."""
    X = mesh.points

    def bc_fn(s):
        return Dirichlet(mask=bc.mask, values=X + s * (bc.values - X))

    return bc_fn


def solve_incremental(
    pot: Potential,
    bc: Dirichlet | Callable[[float], Dirichlet],
    x0=None,
    *,
    steps: int = 1,
    min_increment: float = 1.0 / 1024,
    settings: NewtonSettings = NewtonSettings(),
    linear="auto",
    throw: bool = True,
    callback: Callable[[float, NewtonResult], None] | None = None,
) -> IncrementalResult:
    """Solve the static problem at load factor 1 by increments with automatic cut-back.

    Args:
        pot: potential with the *full* external forces (scaled by ``s`` internally).
        bc: full Dirichlet data (its displacement is scaled by ``s``), or ``s ↦ Dirichlet``
            (the mask must not depend on ``s``).
        x0: initial positions (default: rest).
        steps: initial number of increments (the first try is ``s = 1/steps``).
        min_increment: give up when the increment would fall below this.
        settings, linear: as in :func:`~jaxelastic.solvers.newton.solve`.
        throw: raise :class:`SolveError` when the continuation fails.
        callback: called with ``(s, result)`` after every converged increment.
    """
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    bc_fn = bc if callable(bc) else scaled_dirichlet(pot.mesh, bc)
    x = pot.mesh.points if x0 is None else jnp.asarray(x0, pot.mesh.points.dtype)
    if isinstance(linear, str):
        linear = make_linear(pot.mesh, bc_fn(1.0), linear)
    f_full = pot.f_ext
    s, ds0 = 0.0, 1.0 / steps
    ds = ds0
    history: list = []
    last = None
    t0 = time.perf_counter()
    status = Status.SUCCESS
    while s < 1.0:
        s_try = min(1.0, s + ds)
        p = pot if f_full is None else pot.replace(f_ext=s_try * f_full)
        res = solve(p, bc_fn(s_try), x, settings=settings, linear=linear, throw=False)
        last = res
        ok = res.ok
        history.append(
            dict(
                s=s_try,
                status=Status(int(res.status)).name,
                newton_steps=int(res.steps),
                linear_iterations=int(res.linear_iterations),
                residual=float(res.residual),
                wall_time=float(res.wall_time),
                accepted=bool(ok),
            )
        )
        if ok:
            s, x = s_try, res.x
            if callback is not None:
                callback(s, res)
            ds = min(ds0, 1.5 * ds)
        else:
            ds = 0.5 * ds
            if ds < min_increment:
                status = Status(int(res.status))
                break
    out = IncrementalResult(
        x=x,
        status=int(status),
        load_factor=s,
        last=last,
        history=history,
        wall_time=time.perf_counter() - t0,
    )
    if throw and not out.ok:
        raise SolveError(last, what=f"load stepping (stalled at load factor {s:.4g})")
    return out
