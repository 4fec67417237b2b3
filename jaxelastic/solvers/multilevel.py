"""Device-resident aggregation multigrid, the preconditioner of ``je.Multilevel``.

Two halves:

* **Setup on the host, once per (mesh, Dirichlet mask)** (:func:`build_hierarchy`, NumPy):
  greedy aggregation of the node graph (Vaněk, Mandel & Brezina 1996, "Algebraic multigrid
  by smoothed aggregation", Computing 56:179), the rigid-body modes
  (:func:`~jaxelastic.solvers.pattern.rigid_body_modes`) as near-null space, orthonormalised
  per aggregate into a tentative prolongator ``T`` with one ``(b, m)`` block per fine node
  (``b`` = dofs per node on that level, ``m`` = 3 in 2D, 6 in 3D), and integer index maps:
  the padded row layout (ELL) of every level's block matrix, the element-block → level-0
  slot map and the slot → coarse-slot Galerkin maps. Everything is int32/float arrays in a
  :class:`Hierarchy` pytree, so it can travel as a ``jit`` argument (no XLA constants).
* **Per Newton step, on the device** (:func:`preconditioner`, jnp only, ``jit``/``vmap``):
  assemble the level-0 node-block matrix from the element Hessians (one sorted
  ``segment_sum``), form every coarse operator exactly as the Galerkin product ``PᵀAP``
  (``P = T``, plain aggregation, the default: a block triple product per nonzero block,
  summed into precomputed slots; or the smoothed ``P = T − ω/λ D⁻¹AT``), estimate
  ``λ_max(D⁻¹A)`` per level by power iteration, factorise the coarsest level densely
  (Cholesky), and return ``r ↦ M⁻¹r``: one V- (or W-) cycle with Chebyshev smoothing on
  block Jacobi (Adams, Brezina, Hu & Tuminaro 2003, "Parallel multigrid smoothing:
  polynomial versus Gauss–Seidel", J. Comput. Phys. 188:593), the same polynomial before
  and after the coarse correction, so ``M⁻¹`` is symmetric positive definite for an SPD
  matrix (a preconditioner for :func:`~jaxelastic.solvers.linear.cg`).

Dirichlet dofs: the rows of the near-null space are zeroed there, so ``T`` has zero rows
on prescribed dofs; level 0 carries identity rows/columns for them (the Newton operator's
masking), which block Jacobi inverts exactly. Coarse dofs whose aggregate cannot carry all
``m`` modes (a one- or two-node aggregate, a partly fixed one) are "dead": their rows and
columns of ``T`` are zero and their coarse diagonal gets a 1.

Unsmoothed aggregation keeps the Galerkin product cheap (a coarse block per fine block);
Chebyshev degree 4 and a coarse-correction factor of 1.3 (over-correction of an
unsmoothed prolongator; any factor in (0, 2) keeps ``M⁻¹`` SPD) bring its iteration counts
within 1.5× of host smoothed aggregation on the twist (``scripts/bench_multilevel.py``);
the smoothed prolongator needs fewer iterations, but its Galerkin product costs ~14× as
much on CPU.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from .pattern import rigid_body_modes

__all__ = ["Hierarchy", "Level", "build_hierarchy", "preconditioner", "ell_matvec"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Level:
    """One level's block layout and its prolongator to the next coarser level (a pytree).

    The prolongator ``P`` is stored by its pattern ``pcols``; its values are computed on
    the device: ``P = T`` (unsmoothed) or ``P = T − ω/λ D⁻¹ A T`` (smoothed aggregation).

    Attributes:
        cols: ``(n, w)`` int32 ELL column (node) indices of the level's block matrix, rows
            padded with their own index (the padded blocks stay zero).
        diag: ``(n,)`` int32 slot of the diagonal block in each row.
        dead: ``(n, b)`` float 1.0 on coarse dofs without a mode (diagonal set to 1).
        T: ``(n, b, m)`` tentative prolongator blocks (zero rows on prescribed dofs).
        pcols: ``(n, wp)`` int32 coarse node of each prolongator slot (padding: 0, zero).
        tslot: ``(n,)`` int32 prolongator slot of the node's own aggregate (``n·wp``:
            none, an unaggregated node).
        at_perm, at_sorted: ``(n·w,)`` int32, matrix slots sorted by the prolongator slot
            of ``(i, agg(cols[i, s]))`` they add into in ``A T`` (``n·wp`` = dropped;
            empty when unsmoothed).
        y_slot: ``(wp, n, w)`` int32 slot of ``A P`` (ELL width ``wy``) that
            ``A[i, s] P[cols[i, s], t]`` adds into (``n·wy`` = dropped).
        ycols: ``(n, wy)`` int32 coarse node of each ``A P`` slot.
        c_slot: ``(wp, n, wy)`` int32 coarse-matrix slot that ``P[i, t]ᵀ (AP)[i, u]`` adds
            into (``n_c·w_c`` = dropped).
        r_perm, r_sorted: ``(n·wp,)`` int32, prolongator slots sorted by coarse node
            (``n_c`` = dropped), for the restriction ``Pᵀr``.
        n, b, w, wp, wy: static sizes; smooth: static, whether ``P`` is smoothed.
    """

    cols: jax.Array
    diag: jax.Array
    dead: jax.Array
    T: jax.Array
    pcols: jax.Array
    tslot: jax.Array
    at_perm: jax.Array
    at_sorted: jax.Array
    y_slot: jax.Array
    ycols: jax.Array
    c_slot: jax.Array
    r_perm: jax.Array
    r_sorted: jax.Array
    n: int = dataclasses.field(metadata=dict(static=True), default=0)
    b: int = dataclasses.field(metadata=dict(static=True), default=0)
    w: int = dataclasses.field(metadata=dict(static=True), default=0)
    wp: int = dataclasses.field(metadata=dict(static=True), default=0)
    wy: int = dataclasses.field(metadata=dict(static=True), default=0)
    smooth: bool = dataclasses.field(metadata=dict(static=True), default=False)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True, eq=False, repr=False)
class Hierarchy:
    """The host-built aggregation hierarchy of one (mesh, Dirichlet mask) (a pytree; equal
    only to itself, so a solver holding one is never confused with another mesh's).

    Attributes:
        levels: tuple of :class:`Level`, fine to coarse.
        el_perm: ``(c·k·k,)`` int32 element node-pair blocks sorted by level-0 slot.
        el_sorted: ``(c·k·k,)`` int32 their level-0 ELL slot (``n·w``), sorted.
        k: static nodes per cell; dim: static dofs per node on level 0.
    """

    levels: tuple
    el_perm: jax.Array
    el_sorted: jax.Array
    k: int = dataclasses.field(metadata=dict(static=True), default=0)
    dim: int = dataclasses.field(metadata=dict(static=True), default=0)

    @property
    def sizes(self) -> tuple[int, ...]:
        """Dofs per level, fine to coarse."""
        return tuple(int(lv.n * lv.b) for lv in self.levels)

    def describe(self) -> str:
        """One line: dofs per level (nodes × dofs per node, ELL row width)."""
        parts = [f"{lv.n * lv.b} dofs ({lv.n}x{lv.b}, width {lv.w})" for lv in self.levels]
        return " -> ".join(parts)

    def __repr__(self) -> str:
        return f"Hierarchy({self.describe()})"


# ----------------------------------------------------------------------------------------
# host setup
# ----------------------------------------------------------------------------------------


def _graph(cells: np.ndarray, n: int) -> sp.csr_matrix:
    """Node adjacency (with the diagonal) of a mesh, CSR with sorted indices."""
    k = cells.shape[1]
    r = np.repeat(cells, k, axis=1).ravel()
    c = np.tile(cells, (1, k)).ravel()
    G = sp.csr_matrix((np.ones(r.size, np.int8), (r, c)), shape=(n, n))
    G.sum_duplicates()
    G.sort_indices()
    return G


def _shape(M) -> tuple[int, int]:
    shape = M.shape
    return int(shape[0]), int(shape[1])


def _pattern(M) -> sp.csr_matrix:
    """Sparsity pattern of a sparse matrix as a sorted CSR matrix of ones."""
    M = sp.csr_matrix(M)
    M.sum_duplicates()
    M.sort_indices()
    return sp.csr_matrix((np.ones(M.indices.size, np.int8), M.indices, M.indptr), shape=M.shape)


def _ell(G: sp.csr_matrix, pad_self: bool = True):
    """``(cols (n, w), w, deg, lookup)`` of a sorted CSR pattern; ``lookup(r, c)`` gives the
    ELL slot ``r·w + position`` of each pair. Padding columns are the row itself
    (``pad_self``, square patterns) or 0."""
    n, nc = _shape(G)
    deg = np.diff(G.indptr)
    w = int(deg.max(initial=1)) or 1
    pos = np.arange(G.indices.size) - np.repeat(G.indptr[:-1], deg)
    rows = np.repeat(np.arange(n), deg)
    cols = np.repeat(np.arange(n)[:, None], w, axis=1) if pad_self else np.zeros((n, w), int)
    cols[rows, pos] = G.indices
    keys = rows.astype(np.int64) * nc + G.indices  # sorted (row-major, sorted columns)

    def lookup(r, c):
        q = np.asarray(r, np.int64) * nc + np.asarray(c, np.int64)
        p = np.searchsorted(keys, q)
        if q.size and not np.array_equal(keys[np.minimum(p, keys.size - 1)], q):
            raise AssertionError("pair outside the sparsity pattern")
        return rows[p] * w + pos[p]

    return cols.astype(np.int32), w, deg, lookup


def _aggregate(G: sp.csr_matrix, active: np.ndarray) -> tuple[np.ndarray, int]:
    """Greedy distance-1 aggregation of the active nodes (Vaněk et al. 1996, passes 1–2):
    a node whose active neighbours are all free seeds an aggregate of them; leftovers join
    a neighbouring aggregate (or seed their own). Returns ``(agg (n,), n_aggregates)``;
    inactive nodes get ``-1``."""
    n = _shape(G)[0]
    indptr: list[int] = np.asarray(G.indptr).tolist()
    ind: list[int] = np.asarray(G.indices).tolist()
    act: list[bool] = np.asarray(active).tolist()
    agg = [-1] * n
    na = 0
    for i in range(n):
        if not act[i] or agg[i] >= 0:
            continue
        nb = [j for j in ind[indptr[i] : indptr[i + 1]] if act[j]]
        if all(agg[j] < 0 for j in nb):
            for j in nb:
                agg[j] = na
            na += 1
    for i in range(n):
        if not act[i] or agg[i] >= 0:
            continue
        nb = [agg[j] for j in ind[indptr[i] : indptr[i + 1]] if act[j] and agg[j] >= 0]
        if nb:
            agg[i] = nb[0]
        else:
            agg[i] = na
            na += 1
    return np.asarray(agg, np.int64), na


def _tentative(agg: np.ndarray, na: int, B: np.ndarray, rtol: float = 1e-8):
    """Orthonormalise the near-null space ``B (n, b, m)`` per aggregate (batched SVD by
    aggregate size): ``T (n, b, m)`` with ``T[i] = Q`` rows of node i, coarse modes
    ``Bc (na, m, m)``, and ``dead (na, m)`` (modes an aggregate cannot carry)."""
    n, b, m = B.shape
    T = np.zeros((n, b, m))
    Bc = np.zeros((na, m, m))
    dead = np.ones((na, m))
    members = np.nonzero(agg >= 0)[0]
    order = members[np.argsort(agg[members], kind="stable")]
    counts = np.bincount(agg[members], minlength=na)
    starts = np.concatenate([[0], np.cumsum(counts)])
    for size in np.unique(counts):
        if size == 0:
            continue
        ids = np.nonzero(counts == size)[0]  # aggregates of this size
        nodes = order[starts[ids][:, None] + np.arange(size)[None]]  # (g, size)
        Ba = B[nodes].reshape(len(ids), size * b, m)
        U, s, Vt = np.linalg.svd(Ba, full_matrices=False)  # (g, size·b, r), r = min(.., m)
        r = s.shape[1]
        keep = s > rtol * np.maximum(s[:, :1], 1e-300)  # (g, r)
        U = U * keep[:, None, :]
        Q = np.zeros((len(ids), size * b, m))
        Q[:, :, :r] = U
        R = np.zeros((len(ids), m, m))
        R[:, :r, :] = (s * keep)[:, :, None] * Vt
        T[nodes.ravel()] = Q.reshape(len(ids), size, b, m).reshape(-1, b, m)
        Bc[ids] = R
        dead[ids, :r] = 1.0 - keep
    return T, Bc, dead


def build_hierarchy(
    cells, points, fixed, *, smooth: bool = True, max_coarse: int = 1500, max_levels: int = 10
):
    """Aggregation hierarchy of a mesh and Dirichlet mask (host, once per scene).

    Long because: one pass per level builds every index map of that level (aggregates,
    tentative prolongator, the patterns of ``P``, ``AP`` and ``PᵀAP`` and the slot maps
    between them), which share their intermediate arrays.

    Args:
        cells: ``(n_cells, k)`` connectivity; points: ``(n_nodes, dim)`` rest positions.
        fixed: ``(n_nodes, dim)`` bool Dirichlet mask.
        smooth: smoothed aggregation (``P = T − ω/λ D⁻¹AT`` on the device, wider coarse
            operators, fewer iterations) or plain aggregation (``P = T``).
        max_coarse: stop coarsening at or below this many dofs (the coarsest level is
            factorised densely on every Newton step: its cost grows as its size cubed).
        max_levels: at most this many levels.

    Returns:
        :class:`Hierarchy` (int32 index maps and float64 prolongator blocks, as jax arrays).
    """
    cells = np.asarray(cells, np.int64)
    X = np.asarray(points, np.float64)
    n, d = X.shape
    fixed = np.asarray(fixed, bool).reshape(n, d)
    k = cells.shape[1]
    G = _graph(cells, n)  # the level's matrix pattern
    Gagg = G  # the graph aggregated (level 0: the mesh; then aggregate adjacency)
    cols, w, deg, lookup = _ell(G)
    # element node-pair (a, b) of cell c -> level-0 slot of (cells[c, a], cells[c, b])
    el_slot = lookup(np.repeat(cells, k, axis=1).ravel(), np.tile(cells, (1, k)).ravel())
    el_perm = np.argsort(el_slot, kind="stable")
    B = rigid_body_modes(X, fixed.reshape(-1)).reshape(n, d, -1)
    active: np.ndarray = np.asarray(~fixed.all(axis=1), bool)
    dead = np.zeros((n, d))
    levels = []
    nb, b = n, d
    while True:
        diag = (lookup(np.arange(nb), np.arange(nb)) - np.arange(nb) * w).astype(np.int32)
        last = nb * b <= max_coarse or len(levels) + 1 >= max_levels
        agg, na = (None, 0) if last else _aggregate(Gagg, active)
        if last or na >= 0.9 * nb:  # small enough, or coarsening stalled: the coarsest
            levels.append(Level(**_arrays(cols=cols, diag=diag, dead=dead), n=nb, b=b, w=w))
            break
        assert agg is not None
        T, Bc, dead_c = _tentative(agg, na, B)
        act = np.nonzero(active)[0]
        Ind = sp.csr_matrix((np.ones(act.size), (act, agg[act])), shape=(nb, na))
        Pp = _pattern(G @ Ind) if smooth else _pattern(Ind)  # (nb, na)
        pcols, wp, pdeg, plookup = _ell(Pp, pad_self=False)
        tslot = np.full(nb, nb * wp, np.int64)
        tslot[act] = plookup(act, agg[act])
        rows = np.repeat(np.arange(nb), w)
        cj = cols.ravel().astype(np.int64)
        real = (np.arange(w)[None, :] < deg[:, None]).ravel()
        at_perm = at_sorted = np.zeros(0, np.int64)
        if smooth:  # A T adds A[i, s] T[j] into P slot (i, agg j)
            ok = real & active[cj]
            at = np.full(nb * w, nb * wp, np.int64)
            at[ok] = plookup(rows[ok], agg[cj[ok]])
            at_perm = np.argsort(at, kind="stable")
            at_sorted = at[at_perm]
        Yp = _pattern(G @ Pp)  # (nb, na): A P
        ycols, wy, ydeg, ylookup = _ell(Yp, pad_self=False)
        y_slot = np.full((wp, nb * w), nb * wy, np.int64)
        for t in range(wp):
            ok = real & (t < pdeg[cj])
            y_slot[t, ok] = ylookup(rows[ok], pcols[cj[ok], t])
        Gc = _pattern(Pp.T @ Yp + sp.eye(na))  # (na, na): Pᵀ A P
        cols_c, w_c, deg_c, lookup_c = _ell(Gc)
        c_slot = np.full((wp, nb * wy), na * w_c, np.int64)
        ry = np.repeat(np.arange(nb), wy)
        yreal = (np.arange(wy)[None, :] < ydeg[:, None]).ravel()
        for t in range(wp):
            ok = yreal & (t < pdeg[ry])
            c_slot[t, ok] = lookup_c(pcols[ry[ok], t], ycols.ravel()[ok])
        preal = (np.arange(wp)[None, :] < pdeg[:, None]).ravel()
        r_key = np.where(preal, pcols.ravel(), na)
        r_perm = np.argsort(r_key, kind="stable")
        arrays = _arrays(
            cols=cols,
            diag=diag,
            dead=dead,
            T=T,
            pcols=pcols,
            tslot=tslot,
            at_perm=at_perm,
            at_sorted=at_sorted,
            y_slot=y_slot.reshape(wp, nb, w),
            ycols=ycols,
            c_slot=c_slot.reshape(wp, nb, wy),
            r_perm=r_perm,
            r_sorted=r_key[r_perm],
        )
        levels.append(Level(**arrays, n=nb, b=b, w=w, wp=wp, wy=wy, smooth=smooth))
        Gagg = _pattern(Ind.T @ Gagg @ Ind + sp.eye(na))
        G, cols, w, deg, lookup = Gc, cols_c, w_c, deg_c, lookup_c
        B, dead, active, nb, b = Bc, dead_c, np.ones(na, bool), na, B.shape[2]
    return Hierarchy(
        levels=tuple(levels),
        el_perm=jnp.asarray(el_perm, jnp.int32),
        el_sorted=jnp.asarray(el_slot[el_perm], jnp.int32),
        k=k,
        dim=d,
    )


_LEVEL_ARRAYS = tuple(f.name for f in dataclasses.fields(Level) if not f.metadata.get("static"))


def _arrays(**given) -> dict:
    """Every array field of :class:`Level` as a jax array (int32 / float64; empty if not
    given: the coarsest level has no prolongator)."""
    out = {}
    for name in _LEVEL_ARRAYS:
        a = given.get(name)
        if a is None:
            out[name] = jnp.zeros((0,), jnp.int32)
        elif np.issubdtype(np.asarray(a).dtype, np.integer):
            out[name] = jnp.asarray(a, jnp.int32)
        else:
            out[name] = jnp.asarray(a)
    return out


# ----------------------------------------------------------------------------------------
# device: operators, Galerkin products, cycle
# ----------------------------------------------------------------------------------------


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


def _galerkin(lv: Level, nxt: Level, A: jax.Array, P: jax.Array) -> jax.Array:
    """Coarse operator ``PᵀAP`` ``(n_c, w_c, m, m)`` of a level matrix ``A (n, w, b, b)``
    and prolongator ``P (n, wp, b, m)``: ``AP`` then ``Pᵀ(AP)``, one block product per
    pattern entry, each summed into its precomputed slot."""
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
    dead = nxt.dead.astype(A.dtype)
    eye = jnp.eye(m, dtype=A.dtype)[None]  # (1, m, m)
    return Ac.at[jnp.arange(nxt.n), nxt.diag].add(eye * dead[:, :, None])


def _block_inverse(D: jax.Array) -> jax.Array:
    """Inverses of ``(n, b, b)`` diagonal blocks; a block that is not positive definite
    falls back to ``1/|diag|`` (as :func:`~jaxelastic.solvers.linear.block_jacobi`)."""
    b = D.shape[-1]
    eye = jnp.eye(b, dtype=D.dtype)[None]
    L = jnp.linalg.cholesky(D)
    ok = jnp.all(jnp.isfinite(L), axis=(1, 2))
    diag = jnp.abs(jnp.diagonal(D, axis1=1, axis2=2))
    diag = jnp.where(diag > 0, diag, 1.0)
    inv = jnp.linalg.inv(jnp.where(ok[:, None, None], D, eye))
    return jnp.where(ok[:, None, None], inv, eye / diag[:, :, None])


def _lambda_max(A, cols, D, Dinv, iters: int):
    """Power-iteration estimate of ``λ_max(D⁻¹A)`` (a Rayleigh quotient in the D-inner
    product, from a fixed pseudo-random start)."""
    n, b = Dinv.shape[:2]
    v = jnp.sin(jnp.arange(n * b, dtype=A.dtype) * 12.9898 + 0.5).reshape(n, b) + 1.5

    def body(_, v):
        w = jnp.einsum("nij,nj->ni", Dinv, ell_matvec(A, cols, v))
        return w / jnp.maximum(jnp.sqrt(jnp.sum(w * w)), jnp.finfo(A.dtype).tiny)

    v = jax.lax.fori_loop(0, iters, body, v)
    Av = ell_matvec(A, cols, v)
    Dv = jnp.einsum("nij,nj->ni", D, v)
    lam = jnp.sum(v * Av) / jnp.sum(v * Dv)
    return jnp.where(jnp.isfinite(lam) & (lam > 0), lam, 2.0)


def _chebyshev(A, cols, Dinv, lam, degree: int, lower: float):
    """Chebyshev smoother ``(x, r) ↦ x'`` on block-Jacobi ``D⁻¹A`` over ``[lower·λ, 1.2·λ]``
    (first kind, three-term recurrence; one matvec per degree after the first step). The
    power estimate ``λ`` is below ``λ_max`` (by 6–10 % after 15 iterations on the twist):
    the margin keeps the top of the spectrum inside the interval, where the smoother
    contracts (above it the polynomial grows)."""
    hi = 1.2 * lam
    lo = lower * lam
    theta, delta = (hi + lo) / 2, (hi - lo) / 2

    def Minv(r):
        return jnp.einsum("nij,nj->ni", Dinv, r)

    def smooth(x, rhs, from_zero: bool):
        sigma = theta / delta
        rho = 1.0 / sigma
        res = rhs if from_zero else rhs - ell_matvec(A, cols, x)
        dk = Minv(res) / theta
        x = dk if from_zero else x + dk
        for _ in range(degree - 1):
            res = rhs - ell_matvec(A, cols, x)
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
        fails, which :func:`~jaxelastic.solvers.linear.cg` reports as negative curvature).
    """
    dtype = Ke.dtype
    # the index maps are constants when a caller closes over the hierarchy: keep XLA from
    # constant-folding gathers of them (e.g. T[cols]) at compile time
    h = jax.lax.optimization_barrier(h)
    mats = [_level0(h, Ke, md, free)]
    smoothers, prolongators = [], []
    for lv, nxt in zip(h.levels[:-1], h.levels[1:], strict=True):
        A = mats[-1]
        D = A[jnp.arange(lv.n), lv.diag]
        Dinv = _block_inverse(D)
        lam = _lambda_max(A, lv.cols, D, Dinv, power_iters)
        smoothers.append(_chebyshev(A, lv.cols, Dinv, lam, degree, lower))
        P = _prolongator(lv, A, Dinv, lam)
        prolongators.append(P)
        mats.append(_galerkin(lv, nxt, A, P))
    L = jnp.linalg.cholesky(_dense(h.levels[-1], mats[-1]))
    scale = jnp.asarray(coarse_scale, dtype)

    def coarsest(r):
        y = jax.scipy.linalg.cho_solve((L, True), r.reshape(-1))
        return y.reshape(r.shape)

    def solve(level: int, r):
        if level == len(h.levels) - 1:
            return coarsest(r)
        lv, nxt, A, S = h.levels[level], h.levels[level + 1], mats[level], smoothers[level]
        P = prolongators[level]
        x = S(jnp.zeros_like(r), r, True)
        rc = _restrict(lv, nxt, P, r - ell_matvec(A, lv.cols, x))
        ec = solve(level + 1, rc)
        if cycle == "W" and level + 1 < len(h.levels) - 1:
            ec = ec + solve(level + 1, rc - ell_matvec(mats[level + 1], nxt.cols, ec))
        x = x + scale * _prolong(lv, P, ec)
        return S(x, r, False)

    def apply(r):
        return solve(0, r.astype(dtype))

    return apply
