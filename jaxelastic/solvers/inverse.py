"""Inverse elastostatics: the unloaded (stress-free) rest shape of a loaded body.

Given the loaded, observed configuration ``x̂`` (an image of an artery under blood
pressure, a part sagging under gravity), :func:`unloaded_shape` finds rest points X whose
loaded equilibrium is ``x̂`` on the free dofs. Two methods:

* ``"direct"`` — the inverse-motion (spatial) formulation (Govindjee & Mihalic 1996,
  *Comput. Methods Appl. Mech. Engrg.* 136:47): with x = x̂ fixed, the equilibrium residual
  ``R(X) = ∂Π/∂x (x̂; X)`` on the free dofs is a function of the rest points through the
  displacements ``x̂ − X``, the rest quantities (``dN``, weights: :meth:`Mesh.with_points`)
  and the loads built on the rest shape (gravity ∝ rest volume); Newton on ``R(X) = 0``.
  The Jacobian ``∂R/∂X`` is not symmetric (it is no Hessian), so the minimisation driver
  and its symmetric linear solvers do not apply: it is assembled exactly from a few JVPs
  (``jax.jvp``; one per colour of a distance-2 colouring of the nodes, times ``dim``: the
  columns of nodes that share no cell are recovered from one product) and factorised by a
  sparse LU on the host (SciPy's SuperLU). Quadratic convergence; a backtracking line
  search on ‖R‖ keeps every rest cell valid.
* ``"fixed_point"`` — the backward-displacement method (Sellier 2011, *J. Biomech.*
  44:1739; Bols et al. 2013, *J. Comput. Appl. Math.* 246:10): ``X ← X + (x̂ − x(X))`` with
  ``x(X)`` a forward :func:`~jaxelastic.solve` from rest X. Needs only the forward solver;
  converges linearly, at a rate that degrades as the load grows.

Both are host loops (call them outside ``jit``) and return a
:class:`~jaxelastic.solvers.results.Solution` whose ``x`` is the recovered rest points
``(n_nodes, dim)``, with a status and convergence histories. The result is checked by one
forward solve from it, started at the rest shape (``stats["round_trip"]``:
``‖x(X) − x̂‖ / ‖x̂ − X‖`` on the free dofs).
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from jax.core import Tracer

from ..loads import Dirichlet, with_rest_points
from ..mechanics import potential as pot_mod
from ..mechanics.potential import Potential
from ..mesh import MeshError
from .equilibrium import PreparedSolver, solve
from .newton import Newton
from .results import Solution, SolveError, Status

__all__ = ["unloaded_shape", "METHODS", "node_colouring"]

METHODS = ("direct", "fixed_point")

Loads = Callable[..., jax.Array] | None


def node_colouring(cells, n_nodes: int) -> np.ndarray:
    """A distance-2 colouring of the nodes, ``(n_nodes,)`` int: two nodes get the same
    colour only if no cell contains both, nor does any node share a cell with both. Then
    the Jacobian columns of all nodes of one colour (one displacement component) are
    recovered from one JVP: a residual row touches at most one of them (greedy colouring,
    nodes in index order)."""
    cells = np.asarray(cells, dtype=np.int64)
    k = cells.shape[1]
    rows = np.repeat(cells, k, axis=1).ravel()
    cols = np.tile(cells, (1, k)).ravel()
    A = sp.csr_matrix((np.ones(rows.size, dtype=np.int8), (rows, cols)), (n_nodes, n_nodes))
    A.data[:] = 1
    A2 = sp.csr_matrix(A @ A)  # nodes within distance 2 (sharing a neighbour)
    colour = np.full(n_nodes, -1, dtype=np.int64)
    for i in range(n_nodes):
        near = colour[A2.indices[A2.indptr[i] : A2.indptr[i + 1]]]
        used = np.zeros(near.max(initial=-1) + 2, dtype=bool)
        used[near[near >= 0]] = True
        colour[i] = int(np.argmin(used))  # the first free colour
    return colour


def _rest_potential(pot: Potential, loads: Loads, X, scale=None) -> Potential:
    """``pot`` on rest points X: the mesh moved, the loads rebuilt on it if ``loads``, and
    scaled by the load factor ``scale`` if given."""
    mesh = pot.mesh.with_points(X)
    f_ext = pot.f_ext if loads is None else jnp.asarray(loads(mesh), X.dtype)
    if f_ext is not None and scale is not None:
        f_ext = scale * f_ext
    return pot.replace(mesh=mesh, f_ext=f_ext)


@functools.partial(jax.jit, static_argnums=1)
def _residual(pot: Potential, loads: Loads, free, x_target, X, scale):
    """``(R(X) (n_nodes, dim) zero on prescribed dofs, every rest weight > 0)`` at load
    factor ``scale``."""
    p = _rest_potential(pot, loads, X, scale)
    r = jnp.where(free, pot_mod.gradient(p, x_target), 0.0)
    return r, jnp.all(p.mesh.weights > 0)


@functools.partial(jax.jit, static_argnums=1)
def _jacobian_products(pot: Potential, loads: Loads, free, x_target, X, scale, seeds):
    """``∂R/∂X · s`` for every seed ``s`` of ``seeds`` ``(m, n_nodes, dim)``."""

    def r(Y):
        return _residual(pot, loads, free, x_target, Y, scale)[0]

    return jax.vmap(lambda s: jax.jvp(r, (X,), (s,))[1])(seeds)


class _Jacobian:
    """The sparse Jacobian ``∂R/∂X`` from coloured JVPs (pattern and seeds built once)."""

    def __init__(self, mesh, free: np.ndarray):
        n, d = mesh.points.shape
        cells = np.asarray(mesh.cells, dtype=np.int64)
        colour = node_colouring(cells, n)
        n_col = int(colour.max()) + 1
        seeds = np.zeros((n_col, d, n, d))
        for j in range(d):
            seeds[colour, j, np.arange(n), j] = 1.0
        self.seeds = seeds.reshape(n_col * d, n, d)
        k = cells.shape[1]
        pairs = np.unique(
            np.stack([np.repeat(cells, k, axis=1).ravel(), np.tile(cells, (1, k)).ravel()], 1),
            axis=0,
        )  # (i, m): node i's residual depends on node m's rest position
        i, m = pairs[:, 0], pairs[:, 1]
        a, j = np.meshgrid(np.arange(d), np.arange(d), indexing="ij")
        self.rows = (i[:, None, None] * d + a[None]).ravel()
        self.cols = (m[:, None, None] * d + j[None]).ravel()
        # entry (i a, m j) is product (colour[m], j) at (i, a)
        seed = colour[m][:, None, None] * d + j[None]  # (pairs, d, d)
        self.take = ((seed * n + i[:, None, None]) * d + a[None]).ravel()
        self.free = np.flatnonzero(free.ravel())
        self.shape = (n * d, n * d)

    def factor(self, products: np.ndarray):
        vals = products.ravel()[self.take]
        J = sp.csc_matrix((vals, (self.rows, self.cols)), self.shape)
        return spla.splu(J[self.free][:, self.free].tocsc())


def _check_target(pot: Potential, x_target, X0):
    shape = tuple(pot.mesh.points.shape)
    out = []
    for name, a in (("x_target", x_target), ("X0", X0)):
        if a is None:
            out.append(None)
            continue
        if isinstance(a, Tracer):
            raise ValueError(f"unloaded_shape is a host loop: {name} must be concrete (not jit)")
        arr = np.asarray(a)
        if arr.shape != shape:
            raise ValueError(
                f"unloaded_shape: {name} must have shape (n_nodes, dim) = {shape} like "
                f"pot.mesh.points, got {arr.shape}"
            )
        bad = ~np.isfinite(arr).all(axis=1)
        if bad.any():
            raise ValueError(
                f"unloaded_shape: {name} has NaN/inf at {int(bad.sum())} node(s), e.g. "
                f"{np.flatnonzero(bad)[:5].tolist()}"
            )
        out.append(jnp.asarray(arr, pot.mesh.points.dtype))
    if pot.contact is not None:
        raise ValueError("unloaded_shape: potentials with contact terms are not supported")
    return out


def _newton(problem, X, scale: float, tol: float, max_steps: int, history: list):
    """Newton at one load factor, damped by Deuflhard's natural monotonicity test.

    A force-residual merit ‖R‖ is dominated by the stiff (axial) modes and lets a slender
    body creep by tiny steps; the test measures a trial point by its simplified Newton
    correction ``‖J_k⁻¹R(X + t·ΔX)‖ ≤ (1 − t/4)‖ΔX‖`` with the factorisation at hand
    (Deuflhard 2004, *Newton Methods for Nonlinear Problems*, §3.3, NLEQ-ERR), affine
    invariant and so blind to that scaling. Trial points that invert a rest cell are
    rejected. Returns ``(X, status, residual norm)``; ``history`` gets every accepted
    ``‖R‖``.
    """
    pot, loads, free_j, x_target, jac = problem
    s = jnp.asarray(scale, X.dtype)
    r, _ = _residual(pot, loads, free_j, x_target, X, s)
    norm = float(jnp.linalg.norm(r))

    def correction(lu, r):
        step = np.zeros(X.size)
        step[jac.free] = lu.solve(-np.asarray(r).ravel()[jac.free])
        return step

    for _ in range(max_steps):
        if norm <= tol:
            return X, Status.SUCCESS, norm
        if not np.isfinite(norm):
            return X, Status.NONFINITE, norm
        products = np.asarray(_jacobian_products(pot, loads, free_j, x_target, X, s, jac.seeds))
        lu = jac.factor(products)
        step = correction(lu, r)
        size = float(np.linalg.norm(step))
        dX = jnp.asarray(step.reshape(X.shape), X.dtype)
        t, any_valid = 1.0, False
        while t >= 1.0 / 1024:
            r_try, ok_try = _residual(pot, loads, free_j, x_target, X + t * dX, s)
            n_try = float(jnp.linalg.norm(r_try))
            any_valid |= bool(ok_try)
            if bool(ok_try) and np.isfinite(n_try):
                if n_try <= tol:
                    break
                simplified = float(np.linalg.norm(correction(lu, r_try)))
                if simplified <= (1.0 - t / 4.0) * size:
                    break
            t *= 0.5
        else:
            return X, (Status.LINE_SEARCH_FAILED if any_valid else Status.INVERTED), norm
        X, r, norm = X + t * dX, r_try, n_try
        history.append(norm)
    return X, (Status.SUCCESS if norm <= tol else Status.MAX_STEPS), norm


def _direct(pot, bc, loads, x_target, X, free, rtol, atol, max_steps, steps):
    """Newton on R(X) = 0, the loads applied in increments (halved on failure, as
    :func:`~jaxelastic.solvers.continuation.solve_incremental` does for forward solves).
    Returns ``(X, status, stats)``."""
    free_j = jnp.asarray(free)
    problem = (pot, loads, free_j, x_target, _Jacobian(pot.mesh, free))
    r, _ = _residual(pot, loads, free_j, x_target, X, jnp.asarray(1.0, X.dtype))
    history = [float(jnp.linalg.norm(r))]
    tol = max(rtol * history[0], atol)
    s, ds0 = 0.0, 1.0 / steps
    ds, increments = ds0, []
    status, norm = Status.SUCCESS, history[0]
    while s < 1.0:
        s_try = min(1.0, s + ds)
        X_try, status, norm = _newton(problem, X, s_try, tol, max_steps, history)
        increments.append(dict(s=s_try, status=status.name))
        if status == Status.SUCCESS:
            s, X, ds = s_try, X_try, min(ds0, 1.5 * ds)
        else:
            ds *= 0.5
            if ds < 1.0 / 1024:
                break
    stats = dict(residual=norm, residual_history=np.asarray(history), increments=increments)
    return X, status, dict(stats, load_factor=s)


def _fixed_point(pot, bc, loads, x_target, X, free, rtol, atol, max_steps, solver):
    """Sellier's backward-displacement iteration. Returns ``(X, status, stats)``."""
    free_j = jnp.asarray(free)
    history, warm, tol = [], x_target, atol
    status, norm = Status.MAX_STEPS, np.inf
    for _ in range(max_steps + 1):
        try:
            p = _rest_potential(pot, loads, X)
        except MeshError:
            status = Status.INVERTED
            break
        bc_X = with_rest_points(bc, pot.mesh.points, X)
        res = solve(p, bc_X, x0=warm, solver=solver, throw=False)
        if not bool(res.ok):
            status = Status(int(res.status))
            break
        mismatch = jnp.where(free_j, x_target - res.x, 0.0)
        norm = float(jnp.linalg.norm(mismatch))
        history.append(norm)
        tol = max(rtol * history[0], atol)  # relative to the first mismatch
        if norm <= tol:
            status = Status.SUCCESS
            break
        X, warm = X + mismatch, res.x
    return X, status, dict(residual=norm, residual_history=np.asarray(history))


def unloaded_shape(
    pot: Potential,
    bc: Dirichlet,
    x_target,
    *,
    method: str = "direct",
    loads: Loads = None,
    X0=None,
    rtol: float = 1e-10,
    atol: float = 0.0,
    max_steps: int = 50,
    steps: int = 1,
    solver: Newton | PreparedSolver = Newton(rtol=1e-12),
    throw: bool = True,
) -> Solution:
    """The rest points X whose loaded equilibrium is ``x_target`` on the free dofs.

    Args:
        pot: the potential: material, ψ parameters, loads (``f_ext``); its mesh gives the
            topology and, by default, the first guess of X (usually the mesh of the
            observed, loaded shape).
        bc: Dirichlet data built on ``pot.mesh``; the prescribed *displacements*
            ``bc.values − pot.mesh.points`` are kept, so a clamped node's rest position is
            its target position.
        x_target: ``(n_nodes, dim)`` the loaded configuration [length].
        method: ``"direct"`` (Newton on the inverse-motion residual) or ``"fixed_point"``
            (Sellier's backward displacements); see the module docstring.
        loads: optional ``mesh ↦ f_ext (n_nodes, dim)`` rebuilding the dead loads on each
            rest shape (e.g. ``lambda m: je.loads.gravity_load(m, rho, g)``: the weight
            depends on the rest volume); default: ``pot.f_ext`` as it is.
        X0: first guess of the rest points (default ``x_target``, the classical choice).
        rtol, atol: stop when the residual (direct: ``‖R(X)‖``; fixed point: the
            mismatch ``‖x(X) − x̂‖`` on free dofs [length]) is ``≤ max(rtol·first, atol)``,
            ``first`` its value at the first guess.
        max_steps: iteration cap (direct: Newton iterations per load increment).
        steps: direct method: the first number of load increments (the load factor goes
            from 0 to 1; an increment whose Newton fails is halved, down to 1/1024). Large
            rotations (a slender cantilever sagging by a fifth of its length) need a few.
        solver: Newton settings (or a prepared solver) of the forward solves (fixed point,
            round-trip check).
        throw: raise :class:`~jaxelastic.solvers.results.SolveError` unless SUCCESS.

    Returns:
        :class:`~jaxelastic.solvers.results.Solution` with ``x`` the rest points
        ``(n_nodes, dim)``; ``stats``: ``method``, ``steps``, ``residual``,
        ``residual_history``, ``round_trip`` (relative mismatch of a forward solve from
        the result, NaN if it failed), ``wall_time`` [s].

    Raises:
        ValueError: ``x_target`` or ``X0`` of the wrong shape, NaN/inf or traced; an
            unknown method; a contact term.
    """
    if method not in METHODS:
        raise ValueError(f"unloaded_shape: method must be one of {METHODS}, got {method!r}")
    x_target, X0 = _check_target(pot, x_target, X0)
    t0 = time.perf_counter()
    free = ~np.asarray(bc.mask, dtype=bool)
    X_D = x_target - (jnp.asarray(bc.values) - pot.mesh.points)  # rest of prescribed dofs
    X = jnp.where(jnp.asarray(free), x_target if X0 is None else X0, X_D)
    if method == "direct":
        X, status, stats = _direct(
            pot, bc, loads, x_target, X, free, rtol, atol, max_steps, int(steps)
        )
    else:
        X, status, stats = _fixed_point(
            pot, bc, loads, x_target, X, free, rtol, atol, max_steps, solver
        )
    stats: dict = dict(stats, method=method, steps=np.size(stats["residual_history"]) - 1)
    stats["round_trip"] = _round_trip(pot, bc, loads, x_target, X, free, solver)
    stats["wall_time"] = time.perf_counter() - t0
    out = Solution(x=X, status=jnp.asarray(status, jnp.int32), stats=stats)
    if throw and status != Status.SUCCESS:
        raise SolveError(out, what=f"unloaded_shape ({method})")
    return out


def _round_trip(pot, bc, loads, x_target, X, free, solver) -> float:
    """``‖x(X) − x̂‖ / ‖x̂ − X‖`` on the free dofs for a forward solve from the rest shape X
    (from x̂ if that one fails; NaN if both fail or X is not a valid rest shape)."""
    try:
        p = _rest_potential(pot, loads, X)
    except MeshError:
        return float("nan")
    bc_X = with_rest_points(bc, pot.mesh.points, X)
    res = solve(p, bc_X, solver=solver, throw=False)
    if not bool(res.ok):
        res = solve(p, bc_X, x0=x_target, solver=solver, throw=False)
        if not bool(res.ok):
            return float("nan")
    f = jnp.asarray(free)
    num = jnp.linalg.norm(jnp.where(f, res.x - x_target, 0.0))
    den = jnp.linalg.norm(jnp.where(f, x_target - X, 0.0))
    return float(num / jnp.where(den > 0, den, 1.0))
