"""The one projected retry of a Newton step's linear solve.

When a linear solve reports that the Hessian is not positive definite (a factorisation
fails: NOT_POSITIVE_DEFINITE), meets negative curvature (NEGATIVE_CURVATURE) or returns a
non-finite step, the step is solved once more with the element Hessians PSD-projected
(:func:`~jaxelastic.potential.projected_element_hessians`: eigenvalues clamped at zero,
the translations taken out first where elasticity alone contributes). :func:`with_retry`
is that rule for every linear solver and both loops: inside a trace the two attempts are
one ``lax.while_loop`` body (the solver is compiled once, not once per branch of a
``cond``); outside ``jit`` they are Python calls. On assembled host data the projection
is applied to the cells whose Hessian fails a PSD test only (:func:`projected_upper`):
projecting a positive semidefinite matrix changes it by less than :data:`PSD_SHIFT`, so
the matrix is the same to that tolerance, for a fraction of the eigen-decompositions.

A step that stays NOT_POSITIVE_DEFINITE after the projection (a singular projected matrix)
is used as it is: the line search decides.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ...mechanics.psd import project_element_psd, project_psd
from ..linear import assemble_upper
from ..results import Solution, Status

__all__ = [
    "RETRY_STATUSES",
    "needs_retry",
    "with_retry",
    "projected_upper",
    "not_psd",
    "PSD_SHIFT",
    "PROJECT_BLOCK_CELLS",
    "PROJECT_ALL_FRACTION",
]

RETRY_STATUSES = (Status.NOT_POSITIVE_DEFINITE, Status.NEGATIVE_CURVATURE)


def needs_retry(status, dx):
    """Whether a linear solve's outcome calls for the projected retry (traceable; a numpy
    bool for host values)."""
    if isinstance(dx, np.ndarray) and not isinstance(status, jax.Array):
        return int(status) in RETRY_STATUSES or not bool(np.all(np.isfinite(dx)))
    bad = (status == Status.NOT_POSITIVE_DEFINITE) | (status == Status.NEGATIVE_CURVATURE)
    return bad | ~jnp.all(jnp.isfinite(dx))


def _final(res: Solution, projected, its) -> Solution:
    st = jnp.asarray(res.status, jnp.int32)
    st = jnp.where(st == Status.NOT_POSITIVE_DEFINITE, jnp.int32(Status.SUCCESS), st)
    stats = dict(
        iterations=jnp.asarray(its, jnp.int32),
        residual=jnp.asarray(res.stats.get("residual", 0.0), res.x.dtype),
        projected=jnp.asarray(projected),
    )
    return Solution(x=res.x, status=st, stats=stats)


def with_retry(attempt: Callable, like: jax.Array, *, traced: bool, enabled: bool) -> Solution:
    """Run ``attempt(k, token) -> Solution`` for ``k = 0`` (the exact element Hessians) and,
    if :func:`needs_retry`, ``k = 1`` (their projection); ``token``: the previous attempt's
    status (orders host calls). ``like``: an array shaped like the step.

    Returns the last attempt's :class:`~jaxelastic.solvers.results.Solution` with stats
    ``iterations`` (both attempts), ``residual`` and ``projected`` (whether the retry ran).
    """
    i32 = jnp.int32
    if not enabled:
        res = attempt(0, jnp.asarray(0, i32))
        return _final(res, False, res.stats["iterations"])
    if not traced:
        res = attempt(0, jnp.asarray(0, i32))
        its = int(res.stats["iterations"])
        bad = bool(needs_retry(res.status, res.x))
        if bad:
            res = attempt(1, jnp.asarray(res.status, i32))
            its += int(res.stats["iterations"])
        return _final(res, bad, its)

    def body(c):
        k, _, its, st, _, projected, _ = c
        r = attempt(k, st)
        bad = needs_retry(r.status, r.x)
        its = its + jnp.asarray(r.stats["iterations"], i32)
        rn = jnp.asarray(r.stats.get("residual", 0.0), like.dtype)
        return (k + 1, r.x, its, jnp.asarray(r.status, i32), rn, projected | (k == 1), bad)

    def again(c):
        return (c[0] == 0) | ((c[0] == 1) & c[6])

    zero, no = jnp.asarray(0, i32), jnp.asarray(False)
    c0 = (zero, jnp.zeros_like(like), zero, zero, jnp.zeros((), like.dtype), no, no)
    _, dx, its, st, rn, projected, _ = lax.while_loop(again, body, c0)
    res = Solution(x=dx, status=st, stats=dict(residual=rn))
    return _final(res, projected, its)


@functools.partial(jax.jit, static_argnames="size")
def not_psd(Ke, start, size: int):
    """``(size,)`` bool: the element Hessians of cells ``start … start + size`` that are not
    positive semidefinite to :data:`PSD_SHIFT` (a Cholesky factorisation of
    ``K + PSD_SHIFT·max|diag K|·I`` fails: NaN)."""
    K = lax.dynamic_slice_in_dim(Ke, start, size)
    d = jnp.max(jnp.abs(jnp.diagonal(K, axis1=1, axis2=2)), axis=1)
    shift = PSD_SHIFT * jnp.where(d > 0, d, 1.0)
    eye = jnp.eye(K.shape[-1], dtype=K.dtype)[None]
    L = jnp.linalg.cholesky(K + shift[:, None, None] * eye)
    return ~jnp.all(jnp.isfinite(L), axis=(1, 2))


@functools.partial(jax.jit, static_argnames=("nnz_upper", "dim"), donate_argnums=0)
def _add_projection(acc, Ke, element_map, idx, valid, nnz_upper: int, dim: int):
    """``acc`` plus the upper data of ``project(K) − K`` over the cells ``idx``
    (``valid``: 0 on the padding); ``dim``: :func:`~jaxelastic.potential.projection_dim`
    (:func:`~jaxelastic.energy.project_element_psd`; 0: ``project_psd``)."""
    u = element_map.shape[0] // Ke.shape[0]
    K = Ke[idx]
    P = project_element_psd(K, dim) if dim else project_psd(K)
    D = (P - K) * valid[:, None, None]
    return acc + assemble_upper(D, element_map.reshape(-1, u)[idx].reshape(-1), nnz_upper)


PSD_SHIFT = 1e-12
"""An element Hessian whose smallest eigenvalue is above ``−PSD_SHIFT·max|diag K|``
counts as positive semidefinite in the host Newton loop's projected retry and is not
projected (its projection would change it by less than that)."""

PROJECT_BLOCK_CELLS = 65536
"""Cells per compiled call of the PSD test in the projected retry, from a Python
loop: a ``lax`` loop around the batched LAPACK eigensolver deadlocked XLA:CPU at 511k tets
(jaxlib 0.10), and no copy of all cells' Hessians is made."""


PROJECT_ALL_FRACTION = 0.9
"""When more than this fraction of the first :data:`PROJECT_BLOCK_CELLS` cells fail the PSD
test, the retry projects every cell without testing the rest (twist n = 44: 507k of
511k tets fail; the tests took 0.7 s of the 5.7 s retry)."""


def projected_upper(data, Ke, element_map, nnz_upper: int, dim: int):
    """The upper data of the PSD-projected element Hessians from ``data``, that of the
    unprojected ones: only the cells whose Hessian is not positive semidefinite
    (:func:`not_psd`) are projected and their change added. ``dim``: the element
    Hessians are elasticity's alone, projected through the 9×9 matrices without the
    translations (:func:`~jaxelastic.energy.project_element_psd`; twist n = 44, where 507k
    of 511k tets fail the test: 8.0 s with 12×12 ``eigh``); 0: ``project_psd``."""
    c = Ke.shape[0]
    tests = []
    for start in range(0, c, PROJECT_BLOCK_CELLS):
        tests.append(np.asarray(not_psd(Ke, start, min(PROJECT_BLOCK_CELLS, c - start))))
        if start == 0 and c > PROJECT_BLOCK_CELLS and tests[0].mean() > PROJECT_ALL_FRACTION:
            tests = [np.ones(c, bool)]  # most fail: project all, the tests cost more
            break
    idx = np.flatnonzero(np.concatenate(tests)).astype(np.int32)
    for lo in range(0, idx.size, PROJECT_BLOCK_CELLS):
        part = idx[lo : lo + PROJECT_BLOCK_CELLS]
        size = max(256, 1 << int(np.ceil(np.log2(part.size))))  # few compiled sizes
        valid = np.zeros(size, Ke.dtype)
        valid[: part.size] = 1.0
        padded = np.zeros(size, np.int32)
        padded[: part.size] = part
        data = _add_projection(data, Ke, element_map, padded, valid, nnz_upper, dim)
    return data
