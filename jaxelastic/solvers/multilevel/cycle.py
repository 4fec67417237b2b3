"""The device multigrid cycle: per Newton step, the preconditioner ``r ↦ M⁻¹r``.

On the device, jnp only (``jit``/``vmap``; :func:`preconditioner`): assemble the level-0
node-block matrix from the element Hessians (one sorted ``segment_sum``), form every
coarse operator exactly as the Galerkin product ``PᵀAP`` (``P = T``, plain aggregation,
the default: a block triple product per nonzero block, summed into precomputed slots; or
the smoothed ``P = T − ω/λ D⁻¹AT``), estimate ``λ_max(D⁻¹A)`` per level by power
iteration, factorise the coarsest level densely (Cholesky), and return ``r ↦ M⁻¹r``: one
V- (or W-) cycle with Chebyshev smoothing on block Jacobi (Adams, Brezina, Hu & Tuminaro
2003, "Parallel multigrid smoothing: polynomial versus Gauss–Seidel", J. Comput. Phys.
188:593), the same polynomial before and after the coarse correction, so ``M⁻¹`` is
symmetric positive definite for an SPD matrix (a preconditioner for
:func:`~jaxelastic.solvers.linear.krylov`).

Level 0 carries identity rows/columns for the Dirichlet dofs (the Newton operator's
masking), which block Jacobi inverts exactly.

Unsmoothed aggregation keeps the Galerkin product cheap (a coarse block per fine block);
Chebyshev degree 4 and a coarse-correction factor of 1.3 (over-correction of an
unsmoothed prolongator; any factor in (0, 2) keeps ``M⁻¹`` SPD) bring its iteration counts
within 1.5× of host smoothed aggregation on the twist (``scripts/bench_multilevel.py``);
the smoothed prolongator needs fewer iterations, but its Galerkin product costs ~14× as
much on CPU.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import jax
import jax.numpy as jnp

from ..blocks import block_inverse_or_diagonal
from .hierarchy import Hierarchy, Level

__all__ = [
    "preconditioner",
    "ell_matvec",
    "galerkin",
    "add_dead",
    "block_inverse",
    "power_start",
    "lambda_max",
    "chebyshev_smoother",
    "level_chain",
    "make_cycle",
]


def ell_matvec(A: jax.Array, cols: jax.Array, x: jax.Array) -> jax.Array:
    """Block ELL product ``y_i = Σ_s A[i, s] x[cols[i, s]]``: A ``(n, w, b, b)``, x ``(n, b)``."""
    return jnp.einsum("nsij,nsj->ni", A, x[cols])


def _level0(h: Hierarchy, Ke, md, free) -> jax.Array:
    """Level-0 block matrix ``(n, w, d, d)`` of the Dirichlet-masked Newton operator."""
    lv = h.levels[0]
    c, k, d = Ke.shape[0], h.k, h.dim
    blocks = Ke.reshape(c, k, d, k, d).transpose(0, 1, 3, 2, 4).reshape(c * k * k, d, d)
    A = jax.ops.segment_sum(
        blocks[h.el_perm], h.el_sorted, num_segments=lv.n * lv.w, indices_are_sorted=True
    ).reshape(lv.n, lv.w, d, d)
    fm = free.astype(Ke.dtype)  # (n, d)
    A = A * fm[:, None, :, None] * fm[lv.cols][:, :, None, :]
    eye = jnp.eye(d, dtype=Ke.dtype)[None]  # (1, d, d)
    dblock = eye * (1.0 - fm)[:, :, None]
    if md is not None:
        dblock = dblock + md[:, None, None] * eye * fm[:, :, None]
    return A.at[jnp.arange(lv.n), lv.diag].add(dblock)


def _prolongator(lv: Level, A, Dinv, lam) -> jax.Array:
    """Prolongator values ``(n, wp, b, m)`` on the pattern ``lv.pcols``: ``T``, or
    ``T − (4/3)/λ · D⁻¹ A T`` (smoothed aggregation, Jacobi weight ω = 4/(3λ))."""
    T = lv.T.astype(A.dtype)
    n, wp, b, m = lv.n, lv.wp, lv.b, T.shape[2]
    P = jnp.zeros((n * wp + 1, b, m), A.dtype).at[lv.tslot].add(T)[:-1]
    if lv.smooth:
        AT = jnp.einsum("nsij,nsjb->nsib", A, T[lv.cols]).reshape(n * lv.w, b, m)
        AT = jax.ops.segment_sum(
            AT[lv.at_perm], lv.at_sorted, num_segments=n * wp + 1, indices_are_sorted=True
        )[:-1].reshape(n, wp, b, m)
        P = P.reshape(n, wp, b, m) - (4.0 / 3.0) / lam * jnp.einsum("nij,ntjb->ntib", Dinv, AT)
    return P.reshape(n, wp, b, m)


def galerkin(lv: Level, nxt: Level, A: jax.Array, P: jax.Array, dead: bool = True):
    """Coarse operator ``PᵀAP`` ``(n_c, w_c, m, m)`` of a level matrix ``A (n, w, b, b)``
    and prolongator ``P (n, wp, b, m)``: ``AP`` then ``Pᵀ(AP)``, one block product per
    pattern entry, each summed into its precomputed slot; ``dead``: with the unit diagonal
    of the dead coarse dofs (off: a shard's partial sum)."""
    n, w, wp, wy, b, m = lv.n, lv.w, lv.wp, lv.wy, lv.b, P.shape[3]
    Pg = P[lv.cols]  # (n, w, wp, b, m): P rows of each column node
    Y = jnp.zeros((n * wy + 1, b, m), A.dtype)
    for t in range(wp):
        terms = jnp.einsum("nsij,nsjb->nsib", A, Pg[:, :, t]).reshape(n * w, b, m)
        Y = Y.at[lv.y_slot[t].reshape(-1)].add(terms)
    Y = Y[:-1].reshape(n, wy, b, m)
    Ac = jnp.zeros((nxt.n * nxt.w + 1, m, m), A.dtype)
    for t in range(wp):
        terms = jnp.einsum("nia,nuib->nuab", P[:, t], Y).reshape(n * wy, m, m)
        Ac = Ac.at[lv.c_slot[t].reshape(-1)].add(terms)
    Ac = Ac[:-1].reshape(nxt.n, nxt.w, m, m)
    return add_dead(nxt, Ac) if dead else Ac


def add_dead(nxt: Level, Ac: jax.Array) -> jax.Array:
    """``Ac`` with a unit diagonal on the dead dofs of level ``nxt``."""
    m = Ac.shape[-1]
    dead = nxt.dead.astype(Ac.dtype)
    eye = jnp.eye(m, dtype=Ac.dtype)[None]  # (1, m, m)
    return Ac.at[jnp.arange(nxt.n), nxt.diag].add(eye * dead[:, :, None])


def block_inverse(D: jax.Array, lapack: bool = True) -> jax.Array:
    """Inverses of ``(n, b, b)`` diagonal blocks with the ``1/|diag|`` fallback of
    :func:`~jaxelastic.solvers.linear.block_jacobi` (``lapack=False`` in sharded programs,
    see :func:`~jaxelastic.solvers.blocks.block_inverse_or_diagonal`)."""
    return block_inverse_or_diagonal(D, lapack)


def _sum_dot(a, b):
    return jnp.sum(a * b)


def power_start(index: jax.Array, dtype) -> jax.Array:
    """Power-iteration start ``sin(12.9898 i + 0.5) + 1.5`` of the dof indices ``i``
    (zero where ``i < 0``: padding)."""
    v = jnp.sin(index.astype(dtype) * 12.9898 + 0.5) + 1.5
    return jnp.where(index >= 0, v, 0.0)


def lambda_max(matvec, D, Dinv, v, iters: int, dot=_sum_dot):
    """Power-iteration estimate of ``λ_max(D⁻¹A)`` (a Rayleigh quotient in the D-inner
    product, from the fixed pseudo-random start ``v``); ``matvec(v) = A v``, ``dot`` the
    inner product (a sum over shards when sharded)."""
    dtype = Dinv.dtype

    def body(_, v):
        w = jnp.einsum("nij,nj->ni", Dinv, matvec(v))
        return w / jnp.maximum(jnp.sqrt(dot(w, w)), jnp.finfo(dtype).tiny)

    v = jax.lax.fori_loop(0, iters, body, v)
    Av = matvec(v)
    Dv = jnp.einsum("nij,nj->ni", D, v)
    lam = dot(v, Av) / dot(v, Dv)
    return jnp.where(jnp.isfinite(lam) & (lam > 0), lam, 2.0)


def chebyshev_smoother(matvec, Dinv, lam, degree: int, lower: float):
    """Chebyshev smoother ``(x, r) ↦ x'`` on block-Jacobi ``D⁻¹A`` over ``[lower·λ, 1.2·λ]``
    (first kind, three-term recurrence; one matvec ``A x`` per degree after the first
    step). The power estimate ``λ`` is below ``λ_max`` (by 6–10 % after 15 iterations on
    the twist): the margin keeps the top of the spectrum inside the interval, where the
    smoother contracts (above it the polynomial grows)."""
    hi = 1.2 * lam
    lo = lower * lam
    theta, delta = (hi + lo) / 2, (hi - lo) / 2

    def Minv(r):
        return jnp.einsum("nij,nj->ni", Dinv, r)

    def smooth(x, rhs, from_zero: bool):
        sigma = theta / delta
        rho = 1.0 / sigma
        res = rhs if from_zero else rhs - matvec(x)
        dk = Minv(res) / theta
        x = dk if from_zero else x + dk
        for _ in range(degree - 1):
            res = rhs - matvec(x)
            rho_new = 1.0 / (2.0 * sigma - rho)
            dk = rho_new * rho * dk + 2.0 * rho_new / delta * Minv(res)
            x = x + dk
            rho = rho_new
        return x

    return smooth


def _restrict(lv: Level, nxt: Level, P: jax.Array, r: jax.Array) -> jax.Array:
    """``Pᵀ r``: ``(n, b) → (n_c, m)``."""
    m = P.shape[3]
    rt = jnp.einsum("ntbm,nb->ntm", P, r).reshape(lv.n * lv.wp, m)
    out = jax.ops.segment_sum(
        rt[lv.r_perm], lv.r_sorted, num_segments=nxt.n + 1, indices_are_sorted=True
    )
    return out[:-1]


def _prolong(lv: Level, P: jax.Array, e: jax.Array) -> jax.Array:
    """``P e``: ``(n_c, m) → (n, b)`` (padding slots of ``P`` are zero)."""
    return jnp.einsum("ntbm,ntm->nb", P, e[lv.pcols])


def _dense(lv: Level, A: jax.Array) -> jax.Array:
    """The coarsest level's block matrix ``(n, w, b, b)`` as a dense ``(n·b, n·b)`` matrix."""
    n, b = lv.n, lv.b
    D4 = jnp.zeros((n, n, b, b), A.dtype).at[jnp.arange(n)[:, None], lv.cols].add(A)
    return D4.transpose(0, 2, 1, 3).reshape(n * b, n * b)


def level_chain(levels: tuple, A: jax.Array, power_iters: int, start=None, lapack=True) -> dict:
    """Per-Newton-step data of a chain of levels whose first matrix is ``A``: every level's
    matrix (Galerkin products), block-Jacobi inverse, ``λ_max`` estimate and prolongator,
    and the Cholesky factor of the coarsest (a dict of arrays; ``start``: the first level's
    power-iteration start, default the dof index; ``lapack=False`` in sharded programs,
    see :func:`block_inverse`)."""
    mats, Dinvs, lams, Ps = [A], [], [], []
    for i, (lv, nxt) in enumerate(zip(levels[:-1], levels[1:], strict=True)):
        A = mats[-1]
        D = A[jnp.arange(lv.n), lv.diag]
        Dinv = block_inverse(D, lapack)
        if i == 0 and start is not None:
            v0 = power_start(start, A.dtype)
        else:
            v0 = power_start(jnp.arange(lv.n * lv.b).reshape(lv.n, lv.b), A.dtype)
        lam = lambda_max(partial(ell_matvec, A, lv.cols), D, Dinv, v0, power_iters)
        P = _prolongator(lv, A, Dinv, lam)
        mats.append(galerkin(lv, nxt, A, P))
        Dinvs.append(Dinv)
        lams.append(lam)
        Ps.append(P)
    L = jnp.linalg.cholesky(_dense(levels[-1], mats[-1]))
    return dict(mats=mats, Dinvs=Dinvs, lams=lams, Ps=Ps, L=L)


def make_cycle(levels: tuple, data: dict, *, degree: int, lower: float, cycle: str, scale):
    """``solve(level, r)``: the V- or W-cycle of a chain of levels (:func:`level_chain`) from
    level ``level``; the coarsest level is solved by its Cholesky factor."""
    mats, L = data["mats"], data["L"]
    smoothers = [
        chebyshev_smoother(partial(ell_matvec, A, lv.cols), Dinv, lam, degree, lower)
        for lv, A, Dinv, lam in zip(levels, mats, data["Dinvs"], data["lams"], strict=False)
    ]

    def coarsest(r):
        y = jax.scipy.linalg.cho_solve((L, True), r.reshape(-1))
        return y.reshape(r.shape)

    def solve(level: int, r):
        if level == len(levels) - 1:
            return coarsest(r)
        lv, nxt, A, S = levels[level], levels[level + 1], mats[level], smoothers[level]
        P = data["Ps"][level]
        x = S(jnp.zeros_like(r), r, True)
        rc = _restrict(lv, nxt, P, r - ell_matvec(A, lv.cols, x))
        ec = solve(level + 1, rc)
        if cycle == "W" and level + 1 < len(levels) - 1:
            ec = ec + solve(level + 1, rc - ell_matvec(mats[level + 1], nxt.cols, ec))
        x = x + scale * _prolong(lv, P, ec)
        return S(x, r, False)

    return solve


def preconditioner(
    h: Hierarchy,
    Ke: jax.Array,
    md: jax.Array | None,
    free: jax.Array,
    *,
    degree: int = 4,
    lower: float = 1.0 / 30.0,
    power_iters: int = 15,
    cycle: str = "V",
    coarse_scale: float = 1.3,
) -> Callable[[jax.Array], jax.Array]:
    """Build the multigrid cycle for the current element Hessians (jnp only; jit/vmap).

    Args:
        h: the :class:`Hierarchy` of the mesh and mask.
        Ke: ``(n_cells, k·d, k·d)`` element Hessians (any float dtype: the cycle runs in it).
        md: ``(n_nodes,)`` lumped-mass diagonal of the Hessian or None (statics).
        free: ``(n_nodes, d)`` bool free dofs.
        degree: Chebyshev degree of each pre- and post-smoothing.
        lower: lower end of the Chebyshev interval as a fraction of ``λ_max``.
        power_iters: power iterations for ``λ_max(D⁻¹A)`` per level.
        cycle: ``"V"`` or ``"W"``.
        coarse_scale: factor of the coarse-grid correction (``(0, 2)`` keeps ``M⁻¹`` SPD).

    Returns:
        ``r ↦ M⁻¹r`` on ``(n_nodes, d)`` arrays: one cycle from a zero guess, symmetric
        positive definite when the assembled matrix is (NaN if the coarsest factorisation
        fails, which :func:`~jaxelastic.solvers.linear.krylov` reports as negative curvature).
    """
    dtype = Ke.dtype
    # the index maps are constants when a caller closes over the hierarchy: keep XLA from
    # constant-folding gathers of them (e.g. T[cols]) at compile time
    h = jax.lax.optimization_barrier(h)
    data = level_chain(h.levels, _level0(h, Ke, md, free), power_iters, h.start)
    scale = jnp.asarray(coarse_scale, dtype)
    solve = make_cycle(h.levels, data, degree=degree, lower=lower, cycle=cycle, scale=scale)

    def apply(r):
        return solve(0, r.astype(dtype))

    return apply
