"""Device-resident aggregation multigrid, the preconditioner of ``je.Multilevel``.

Two halves:

* **Setup on the host, once per (mesh, Dirichlet mask)** (:func:`build_hierarchy`, NumPy):
  greedy aggregation of the node graph (Vaněk, Mandel & Brezina 1996, "Algebraic multigrid
  by smoothed aggregation", Computing 56:179), the rigid-body modes
  (:func:`~jaxelastic.solvers.host.pattern.rigid_body_modes`) as near-null space, orthonormalised
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

Numbering: the aggregation visits the nodes in an order of their rest positions
(:func:`canonical_order`), not their indices, so a renumbered copy of the mesh gets the
same aggregates and coarse levels. That is what lets a mesh sharded over devices
(:func:`jaxelastic.shard`, renumbered and padded) use the hierarchy of the one-device
mesh: :class:`ShardedHierarchy` and :func:`sharded_preconditioner` keep level 0 per shard
(partial sums of its own cells, products with a halo exchange of interface values) and
the coarse levels replicated on every device (one ``psum`` of the level-1 matrix per
Newton step and of the level-1 vector per cycle), with the same iterates as one device.

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
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from .blocks import block_inverse_or_diagonal
from .host import rigid_body_modes

__all__ = [
    "Hierarchy",
    "Level",
    "ShardedHierarchy",
    "build_hierarchy",
    "build_sharded_hierarchy",
    "canonical_order",
    "preconditioner",
    "sharded_preconditioner",
    "ell_matvec",
]


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
        start: ``(n, dim)`` int32 index of each level-0 dof in the canonical order
            (:func:`canonical_order`; ``-1``: a node in no cell), which seeds the power
            iteration.
        k: static nodes per cell; dim: static dofs per node on level 0.
    """

    levels: tuple
    el_perm: jax.Array
    el_sorted: jax.Array
    start: jax.Array
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
    """Node adjacency (with the diagonal, also of nodes in no cell) of a mesh, CSR with
    sorted indices."""
    k = cells.shape[1]
    r = np.concatenate([np.repeat(cells, k, axis=1).ravel(), np.arange(n)])
    c = np.concatenate([np.tile(cells, (1, k)).ravel(), np.arange(n)])
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


def _aggregate(
    G: sp.csr_matrix, active: np.ndarray, rank: np.ndarray | None = None
) -> tuple[np.ndarray, int]:
    """Greedy distance-1 aggregation of the active nodes (Vaněk et al. 1996, passes 1–2):
    a node whose active neighbours are all free seeds an aggregate of them; leftovers join
    a neighbouring aggregate (or seed their own). Nodes are visited in the order of
    ``rank`` (default: their index) and a leftover joins the aggregate of its lowest-ranked
    aggregated neighbour, so the aggregates, numbered as they are made, depend on the
    ranks only, not on the node numbering. Returns ``(agg (n,), n_aggregates)``; inactive
    nodes get ``-1``."""
    n = _shape(G)[0]
    indptr: list[int] = np.asarray(G.indptr).tolist()
    ind: list[int] = np.asarray(G.indices).tolist()
    act: list[bool] = np.asarray(active).tolist()
    visit = range(n) if rank is None else np.argsort(rank, kind="stable").tolist()
    rk: list[int] = list(range(n)) if rank is None else np.asarray(rank).tolist()
    agg = [-1] * n
    na = 0
    for i in visit:
        if not act[i] or agg[i] >= 0:
            continue
        nb = [j for j in ind[indptr[i] : indptr[i + 1]] if act[j]]
        if all(agg[j] < 0 for j in nb):
            for j in nb:
                agg[j] = na
            na += 1
    for i in visit:
        if not act[i] or agg[i] >= 0:
            continue
        nb = [j for j in ind[indptr[i] : indptr[i + 1]] if act[j] and agg[j] >= 0]
        if nb:
            agg[i] = agg[min(nb, key=rk.__getitem__)]
        else:
            agg[i] = na
            na += 1
    return np.asarray(agg, np.int64), na


def _tentative(agg: np.ndarray, na: int, B: np.ndarray, rank=None, rtol: float = 1e-8):
    """Orthonormalise the near-null space ``B (n, b, m)`` per aggregate (batched SVD by
    aggregate size, members in ``rank`` order): ``T (n, b, m)`` with ``T[i] = Q`` rows of
    node i, coarse modes ``Bc (na, m, m)``, and ``dead (na, m)`` (modes an aggregate
    cannot carry)."""
    n, b, m = B.shape
    T = np.zeros((n, b, m))
    Bc = np.zeros((na, m, m))
    dead = np.ones((na, m))
    members = np.nonzero(agg >= 0)[0]
    key = members if rank is None else np.asarray(rank)[members]
    order = members[np.lexsort((key, agg[members]))]
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
    rank, start = canonical_order(cells, X)
    B = _modes(X, fixed, rank)
    active: np.ndarray = np.asarray(~fixed.all(axis=1) & (rank >= 0), bool)
    dead = np.zeros((n, d))
    levels = []
    nb, b = n, d
    level_rank: np.ndarray | None = rank  # level 0: canonical; coarse: aggregate order
    while True:
        diag = (lookup(np.arange(nb), np.arange(nb)) - np.arange(nb) * w).astype(np.int32)
        last = nb * b <= max_coarse or len(levels) + 1 >= max_levels
        agg, na = (None, 0) if last else _aggregate(Gagg, active, level_rank)
        if last or na >= 0.9 * nb:  # small enough, or coarsening stalled: the coarsest
            levels.append(Level(**_arrays(cols=cols, diag=diag, dead=dead), n=nb, b=b, w=w))
            break
        assert agg is not None
        T, Bc, dead_c = _tentative(agg, na, B, level_rank)
        level_rank = None
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
        start=jnp.asarray(start, jnp.int32),
        k=k,
        dim=d,
    )


def canonical_order(cells, points) -> tuple[np.ndarray, np.ndarray]:
    """A node order that depends on the mesh geometry only, not on its numbering.

    The nodes some cell uses are ranked by their rest position, lexicographically with the
    last coordinate first (ties: by index), which is the numbering of
    :func:`~jaxelastic.mesh.box` and :func:`~jaxelastic.mesh.rectangle` itself. The
    aggregation visits nodes in this order, so a renumbered or padded copy of a mesh (its
    sharded layout, :mod:`jaxelastic.parallel.partition`) gets the same aggregates, coarse
    levels and power-iteration start as the mesh itself.

    Args:
        cells: ``(n_cells, k)`` connectivity; points: ``(n_nodes, dim)`` rest positions.

    Returns:
        ``(rank (n_nodes,), start (n_nodes, dim))`` int64: the rank (``-1`` for a node in no
        cell) and ``rank·dim + component``, the index of each dof in the canonical order
        (``-1`` for a node in no cell).
    """
    X = np.asarray(points, np.float64)
    n, d = X.shape
    used = np.zeros(n, bool)
    used[np.asarray(cells, np.int64).ravel()] = True
    ids = np.flatnonzero(used)
    order = ids[np.lexsort(X[ids].T)]  # last coordinate first
    rank = np.full(n, -1, np.int64)
    rank[order] = np.arange(order.size)
    start = np.where(used[:, None], rank[:, None] * d + np.arange(d)[None], -1)
    return rank, start


def _modes(X: np.ndarray, fixed: np.ndarray, rank: np.ndarray) -> np.ndarray:
    """Rigid-body modes ``(n, d, m)`` of the used nodes (``rank >= 0``), computed in rank
    order (the centroid and scale are sums: the same bits for any numbering); zero on
    prescribed dofs and unused nodes."""
    n, d = X.shape
    order = np.argsort(np.where(rank >= 0, rank, n), kind="stable")[: int((rank >= 0).sum())]
    Bu = rigid_body_modes(X[order], fixed[order].reshape(-1)).reshape(order.size, d, -1)
    B = np.zeros((n, d, Bu.shape[2]))
    B[order] = Bu
    return B


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


def _galerkin(lv: Level, nxt: Level, A: jax.Array, P: jax.Array, dead: bool = True):
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
    return _add_dead(nxt, Ac) if dead else Ac


def _add_dead(nxt: Level, Ac: jax.Array) -> jax.Array:
    """``Ac`` with a unit diagonal on the dead dofs of level ``nxt``."""
    m = Ac.shape[-1]
    dead = nxt.dead.astype(Ac.dtype)
    eye = jnp.eye(m, dtype=Ac.dtype)[None]  # (1, m, m)
    return Ac.at[jnp.arange(nxt.n), nxt.diag].add(eye * dead[:, :, None])


def _block_inverse(D: jax.Array, lapack: bool = True) -> jax.Array:
    """Inverses of ``(n, b, b)`` diagonal blocks with the ``1/|diag|`` fallback of
    :func:`~jaxelastic.solvers.linear.block_jacobi` (``lapack=False`` in sharded programs,
    see :func:`~jaxelastic.solvers.blocks.block_inverse_or_diagonal`)."""
    return block_inverse_or_diagonal(D, lapack)


def _sum_dot(a, b):
    return jnp.sum(a * b)


def _start(index: jax.Array, dtype) -> jax.Array:
    """Power-iteration start ``sin(12.9898 i + 0.5) + 1.5`` of the dof indices ``i``
    (zero where ``i < 0``: padding)."""
    v = jnp.sin(index.astype(dtype) * 12.9898 + 0.5) + 1.5
    return jnp.where(index >= 0, v, 0.0)


def _lambda_max(matvec, D, Dinv, v, iters: int, dot=_sum_dot):
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


def _chebyshev(matvec, Dinv, lam, degree: int, lower: float):
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


def _chain(levels: tuple, A: jax.Array, power_iters: int, start=None, lapack=True) -> dict:
    """Per-Newton-step data of a chain of levels whose first matrix is ``A``: every level's
    matrix (Galerkin products), block-Jacobi inverse, ``λ_max`` estimate and prolongator,
    and the Cholesky factor of the coarsest (a dict of arrays; ``start``: the first level's
    power-iteration start, default the dof index; ``lapack=False`` in sharded programs,
    see :func:`_block_inverse`)."""
    mats, Dinvs, lams, Ps = [A], [], [], []
    for i, (lv, nxt) in enumerate(zip(levels[:-1], levels[1:], strict=True)):
        A = mats[-1]
        D = A[jnp.arange(lv.n), lv.diag]
        Dinv = _block_inverse(D, lapack)
        if i == 0 and start is not None:
            v0 = _start(start, A.dtype)
        else:
            v0 = _start(jnp.arange(lv.n * lv.b).reshape(lv.n, lv.b), A.dtype)
        lam = _lambda_max(partial(ell_matvec, A, lv.cols), D, Dinv, v0, power_iters)
        P = _prolongator(lv, A, Dinv, lam)
        mats.append(_galerkin(lv, nxt, A, P))
        Dinvs.append(Dinv)
        lams.append(lam)
        Ps.append(P)
    L = jnp.linalg.cholesky(_dense(levels[-1], mats[-1]))
    return dict(mats=mats, Dinvs=Dinvs, lams=lams, Ps=Ps, L=L)


def _cycle(levels: tuple, data: dict, *, degree: int, lower: float, cycle: str, scale):
    """``solve(level, r)``: the V- or W-cycle of a chain of levels (:func:`_chain`) from
    level ``level``; the coarsest level is solved by its Cholesky factor."""
    mats, L = data["mats"], data["L"]
    smoothers = [
        _chebyshev(partial(ell_matvec, A, lv.cols), Dinv, lam, degree, lower)
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
        fails, which :func:`~jaxelastic.solvers.linear.cg` reports as negative curvature).
    """
    dtype = Ke.dtype
    # the index maps are constants when a caller closes over the hierarchy: keep XLA from
    # constant-folding gathers of them (e.g. T[cols]) at compile time
    h = jax.lax.optimization_barrier(h)
    data = _chain(h.levels, _level0(h, Ke, md, free), power_iters, h.start)
    scale = jnp.asarray(coarse_scale, dtype)
    solve = _cycle(h.levels, data, degree=degree, lower=lower, cycle=cycle, scale=scale)

    def apply(r):
        return solve(0, r.astype(dtype))

    return apply


# ----------------------------------------------------------------------------------------
# sharded: level 0 over the shards of a halo, coarse levels replicated
# ----------------------------------------------------------------------------------------


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True, eq=False, repr=False)
class ShardedHierarchy:
    """The hierarchy of a sharded mesh (:class:`~jaxelastic.parallel.halo.Halo`): level 0 as
    per-shard local tables (leading shard axis ``S``, sharded), the coarse levels as the
    :class:`Level` s of the one-device hierarchy (replicated). A pytree, equal only to
    itself.

    Shard ``s`` holds the rows of its local nodes ``[owned (n_own) | ghosts (n_ghost)]``
    of its own cells' part of the level-0 matrix (a partial sum: the level-0 matrix is the
    sum over shards); the level-0 product is ``scatter_add(A_s · gather(x))`` (interface
    values only cross devices), the Galerkin product ``Σ_s T_sᵀ A_s T_s`` is a per-shard
    partial sum and one ``psum``, the restriction a partial ``Tᵀr`` and one ``psum`` of the
    coarse vector; the coarse levels and the prolongation are computed on every shard.

    Attributes:
        coarse: tuple of :class:`Level`, levels 1, 2, … (replicated; empty when the
            mesh has at most ``max_coarse`` dofs: then the whole matrix is summed over the
            shards and factorised densely, as on one device).
        cols: ``(S, n_loc, w)`` int32 local ELL columns of the shard's level-0 rows.
        diag: ``(S, n_loc)`` int32 diagonal slot of each local row.
        el_perm, el_sorted: ``(S, c_loc·k·k)`` int32 local element-block → slot map, sorted.
        T: ``(S, n_loc, d, m)`` tentative prolongator rows of the local nodes.
        y_slot: ``(S, n_loc, w)`` int32 slot of ``A_s T`` (width ``wy``) each block adds into
            (``n_loc·wy``: dropped); ycols: ``(S, n_loc, wy)`` int32 its coarse nodes.
        c_slot: ``(S, n_loc, wy)`` int32 slot of the level-1 matrix (``n_1·w_1``: dropped).
        agg: ``(S, n_own)`` int32 aggregate of each owned node (``n_1``: none).
        r_perm, r_sorted: ``(S, n_own)`` int32 owned nodes sorted by aggregate.
        start: ``(S, n_own, d)`` int32 canonical dof index (power-iteration start; ``-1``:
            padding).
        glob: ``(S, n_loc)`` int32 padded global node of each local node (``S·n_own``: an
            unused ghost slot).
        n_shards, n_own, n_loc, w, wy, k, dim: static sizes.
    """

    coarse: tuple
    cols: jax.Array
    diag: jax.Array
    el_perm: jax.Array
    el_sorted: jax.Array
    T: jax.Array
    y_slot: jax.Array
    ycols: jax.Array
    c_slot: jax.Array
    agg: jax.Array
    r_perm: jax.Array
    r_sorted: jax.Array
    start: jax.Array
    glob: jax.Array
    n_shards: int = dataclasses.field(metadata=dict(static=True), default=1)
    n_own: int = dataclasses.field(metadata=dict(static=True), default=0)
    n_loc: int = dataclasses.field(metadata=dict(static=True), default=0)
    w: int = dataclasses.field(metadata=dict(static=True), default=0)
    wy: int = dataclasses.field(metadata=dict(static=True), default=0)
    k: int = dataclasses.field(metadata=dict(static=True), default=0)
    dim: int = dataclasses.field(metadata=dict(static=True), default=0)

    @property
    def sizes(self) -> tuple[int, ...]:
        """Dofs per level, fine (real and padded) to coarse."""
        return (self.n_shards * self.n_own * self.dim,) + tuple(
            int(lv.n * lv.b) for lv in self.coarse
        )

    def describe(self) -> str:
        """One line: level 0 per shard, then the replicated coarse levels."""
        parts = [f"{self.n_shards} x {self.n_own * self.dim} dofs (sharded, width {self.w})"]
        parts += [f"{lv.n * lv.b} dofs ({lv.n}x{lv.b}, replicated)" for lv in self.coarse]
        return " -> ".join(parts)

    def __repr__(self) -> str:
        return f"ShardedHierarchy({self.describe()})"


def _ghost_nodes(halo) -> np.ndarray:
    """``(S, n_ghost)`` padded global index of every ghost slot of a halo (``-1``: an
    unused slot), from its send/receive tables."""
    S, n_own, n_ghost = halo.n_shards, halo.n_own, halo.n_ghost
    out = np.full((S, n_ghost), -1, np.int64)
    for delta, snd, rcv in zip(halo.shifts, halo.send, halo.recv, strict=True):
        snd, rcv = np.asarray(snd), np.asarray(rcv)
        for r in range(S):
            o = (r - delta) % S
            ok = rcv[r] < n_ghost
            out[r, rcv[r][ok]] = o * n_own + snd[o][ok]
    return out


def _lookup(cols: np.ndarray) -> Callable:
    """Slot lookup ``(r, c) -> r·w + position`` of a self-padded ELL pattern ``(n, w)``
    (the first occurrence of each pair: the real slot)."""
    n, w = cols.shape
    keys = np.repeat(np.arange(n, dtype=np.int64), w) * n + cols.ravel().astype(np.int64)
    uniq, first = np.unique(keys, return_index=True)

    def lookup(r, c):
        q = np.asarray(r, np.int64) * n + np.asarray(c, np.int64)
        p = np.searchsorted(uniq, q)
        if q.size and not np.array_equal(uniq[np.minimum(p, uniq.size - 1)], q):
            raise AssertionError("pair outside the coarse sparsity pattern")
        return first[p]

    return lookup


def build_sharded_hierarchy(h: Hierarchy, halo, cells) -> ShardedHierarchy:
    """The :class:`ShardedHierarchy` of a hierarchy ``h`` built on the padded mesh.

    Long because: one pass per shard builds its local level-0 pattern and every slot map
    of its partial Galerkin product and restriction, which share their arrays.

    Args:
        h: :func:`build_hierarchy` of the padded mesh (unsmoothed; its level-0 ``T`` and
            aggregates are in the padded numbering, its coarse levels those of the natural
            mesh, by :func:`canonical_order`).
        halo: the mesh's :class:`~jaxelastic.parallel.halo.Halo` (host-readable tables).
        cells: ``(S·c_loc, k)`` padded connectivity.
    """
    lv0 = h.levels[0]
    S, n_own, n_ghost, c_loc = halo.n_shards, halo.n_own, halo.n_ghost, halo.c_loc
    n_loc, k, d = n_own + n_ghost, h.k, h.dim
    start = np.asarray(h.start).reshape(S, n_own, d)
    cells = np.asarray(cells, np.int64)
    local_cells = np.asarray(halo.local_cells, np.int64)
    ghosts = _ghost_nodes(halo)
    if len(h.levels) == 1:  # one level (a dense solve): no prolongator, no aggregates
        n1, w1 = 0, 1
        T0 = np.zeros((lv0.n, d, 1))
        agg_pad = np.zeros(lv0.n, np.int64)
        lookup1 = None
    else:
        lv1 = h.levels[1]
        if lv0.smooth or lv0.wp != 1:
            raise ValueError("the sharded Multilevel supports plain aggregation (smooth=False)")
        n1, w1 = lv1.n, lv1.w
        T0 = np.asarray(lv0.T)
        tslot = np.asarray(lv0.tslot)
        agg_pad = np.where(tslot < lv0.n, np.asarray(lv0.pcols)[:, 0], n1)  # wp = 1
        lookup1 = _lookup(np.asarray(lv1.cols))
    per, globs = [], []
    for s in range(S):
        glob = np.concatenate([s * n_own + np.arange(n_own), ghosts[s]])
        used = glob >= 0
        lc = local_cells[s]
        blk = cells[s * c_loc : (s + 1) * c_loc]
        real = ~(blk == blk[:, :1]).all(axis=1)  # a padded cell repeats one node
        G = _graph(lc[real], n_loc)
        cols, w, deg, lookup = _ell(G)
        el = lookup(np.repeat(lc, k, axis=1).ravel(), np.tile(lc, (1, k)).ravel())
        el_perm = np.argsort(el, kind="stable")
        diag = lookup(np.arange(n_loc), np.arange(n_loc)) - np.arange(n_loc) * w
        agg = np.where(used, agg_pad[np.where(used, glob, 0)], n1)
        T = np.where(used[:, None, None], T0[np.where(used, glob, 0)], 0.0)
        rows = np.repeat(np.arange(n_loc), w)
        cj = cols.ravel().astype(np.int64)
        ok = (np.arange(w)[None, :] < deg[:, None]).ravel() & (agg[cj] < n1)
        Yp = sp.csr_matrix(
            (np.ones(int(ok.sum()), np.int8), (rows[ok], agg[cj[ok]])), shape=(n_loc, n1 + 1)
        )
        ycols, wy, ydeg, ylookup = _ell(_pattern(Yp), pad_self=False)
        per.append((cols, w, diag, el, el_perm, T, agg, rows, cj, ok, ycols, wy, ydeg, ylookup))
        globs.append(np.where(used, glob, S * n_own))
    W = max(p[1] for p in per)
    WY = max(p[11] for p in per)
    out = {f: [] for f in ("cols", "diag", "el_perm", "el_sorted", "T", "y_slot", "ycols")}
    out.update(c_slot=[], agg=[], r_perm=[], r_sorted=[])
    for cols, w, diag, el, el_perm, T, agg, rows, cj, ok, ycols, wy, ydeg, yl in per:
        # re-slot into the common widths W, WY
        cw = np.repeat(np.arange(n_loc)[:, None], W, axis=1)
        cw[:, :w] = cols
        el_w = (el // w) * W + el % w
        y_slot = np.full(n_loc * w, n_loc * WY, np.int64)
        yr = yl(rows[ok], agg[cj[ok]])
        y_slot[ok] = (yr // wy) * WY + yr % wy
        ys = np.full((n_loc, W), n_loc * WY, np.int64)
        ys[:, :w] = y_slot.reshape(n_loc, w)
        yc = np.zeros((n_loc, WY), np.int64)
        yc[:, :wy] = ycols
        yreal = np.zeros((n_loc, WY), bool)
        yreal[:, :wy] = np.arange(wy)[None, :] < ydeg[:, None]
        yreal &= (agg < n1)[:, None]
        c_slot = np.full((n_loc, WY), n1 * w1, np.int64)
        ri, ui = np.nonzero(yreal)
        if lookup1 is not None:
            c_slot[ri, ui] = lookup1(agg[ri], yc[ri, ui])
        agg_own = agg[:n_own]
        r_perm = np.argsort(agg_own, kind="stable")
        out["cols"].append(cw)
        out["diag"].append(diag)
        out["el_perm"].append(el_perm)
        out["el_sorted"].append(el_w[el_perm])
        out["T"].append(T)
        out["y_slot"].append(ys)
        out["ycols"].append(yc)
        out["c_slot"].append(c_slot)
        out["agg"].append(agg_own)
        out["r_perm"].append(r_perm)
        out["r_sorted"].append(agg_own[r_perm])
    sharded = halo.sharding()
    replicated = halo.sharding(replicated=True)
    arrays = {}
    for name, vals in out.items():
        a = np.stack(vals)
        a = a.astype(np.int32) if np.issubdtype(a.dtype, np.integer) else a
        arrays[name] = jax.device_put(a, sharded)
    coarse = jax.device_put(tuple(h.levels[1:]), replicated)
    return ShardedHierarchy(
        coarse=coarse,
        **arrays,
        glob=jax.device_put(np.stack(globs).astype(np.int32), sharded),
        start=jax.device_put(start.astype(np.int32), sharded),
        n_shards=S,
        n_own=n_own,
        n_loc=n_loc,
        w=W,
        wy=WY,
        k=k,
        dim=d,
    )


def _local_view(tree):
    """The per-shard block of a pytree of ``(1, ...)`` blocks (inside ``shard_map``)."""
    return jax.tree_util.tree_map(lambda t: t[0], tree)


def sharded_preconditioner(
    sh: ShardedHierarchy,
    halo,
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
    """:func:`preconditioner` on a sharded mesh (same arguments, in the global padded
    layout; ``halo`` is the mesh's :class:`~jaxelastic.parallel.halo.Halo`).

    Long because: the per-shard setup (level-0 partial matrix, block Jacobi, power
    iteration, partial Galerkin product) and the per-shard cycle are closures over the same
    local operators, each run under one ``shard_map``.

    Communication per Newton step: the level-0 block-Jacobi diagonal (one scatter of
    ghost blocks), 2·(``power_iters`` + 1) halo exchanges and scalar ``psum`` s, and one
    ``psum`` of the level-1 matrix. Per application: two halo exchanges per level-0
    product (``2·degree`` products) and one ``psum`` of the level-1 vector.
    """
    dtype = Ke.dtype
    axis, mesh = halo.axis, halo.device_mesh
    Psh, Prep = jax.sharding.PartitionSpec(axis), jax.sharding.PartitionSpec()
    coarse = sh.coarse
    n_own, n_loc, w, wy, d = sh.n_own, sh.n_loc, sh.w, sh.wy, sh.dim
    lv1 = coarse[0] if coarse else None
    local = {f: getattr(sh, f) for f in ("cols", "diag", "el_perm", "el_sorted", "T")}
    local.update({f: getattr(sh, f) for f in ("y_slot", "ycols", "c_slot", "agg")})
    local.update({f: getattr(sh, f) for f in ("r_perm", "r_sorted", "start", "glob")})
    halo_spec = jax.tree_util.tree_map(lambda _: Psh, halo)
    local_spec = jax.tree_util.tree_map(lambda _: Psh, local)
    coarse_spec = jax.tree_util.tree_map(lambda _: Prep, coarse)
    fm = free.astype(dtype)
    md = jnp.zeros(free.shape[:1], dtype) if md is None else md.astype(dtype)

    def views(hl, loc):
        hl = dataclasses.replace(_local_view(hl), local=True)
        return hl, _local_view(loc)

    def ops(hl, loc, A):
        def matvec(x):
            return hl.scatter_add(ell_matvec(A, loc["cols"], hl.gather(x)))

        def dot(a, b):
            return hl.psum(jnp.sum(a * b))

        return matvec, dot

    def setup(hl, loc, coarse, Ke, md, fm):
        hl, loc = views(hl, loc)
        c = Ke.shape[0]
        k = sh.k
        blocks = Ke.reshape(c, k, d, k, d).transpose(0, 1, 3, 2, 4).reshape(c * k * k, d, d)
        A = jax.ops.segment_sum(
            blocks[loc["el_perm"]],
            loc["el_sorted"],
            num_segments=n_loc * w,
            indices_are_sorted=True,
        ).reshape(n_loc, w, d, d)
        fl = hl.gather(fm)  # (n_loc, d)
        A = A * fl[:, None, :, None] * fl[loc["cols"]][:, :, None, :]
        eye = jnp.eye(d, dtype=dtype)[None]
        dblock = eye * (1.0 - fm)[:, :, None] + md[:, None, None] * eye * fm[:, :, None]
        A = A.at[jnp.arange(n_own), loc["diag"][:n_own]].add(dblock)  # once: owned rows
        if not coarse:  # one level: the whole matrix, summed over the shards, densely
            N = sh.n_shards * n_own
            g = loc["glob"]
            D4 = jnp.zeros((N, N, d, d), dtype).at[g[:, None], g[loc["cols"]]].add(A, mode="drop")
            L = jnp.linalg.cholesky(hl.psum(D4.transpose(0, 2, 1, 3).reshape(N * d, N * d)))
            return A[None], A[None, :0, 0], jnp.zeros((), dtype), dict(L=L)
        D = A[jnp.arange(n_loc), loc["diag"]]
        D = hl.scatter_add(D.reshape(n_loc, d * d)).reshape(n_own, d, d)
        Dinv = _block_inverse(D, lapack=False)
        matvec, dot = ops(hl, loc, A)
        lam = _lambda_max(matvec, D, Dinv, _start(loc["start"], dtype), power_iters, dot)
        lv = Level(
            **{f: loc[f] for f in ("cols", "y_slot", "c_slot", "ycols")},
            diag=loc["diag"],
            dead=jnp.zeros((0,), jnp.int32),
            T=loc["T"],
            pcols=jnp.zeros((0,), jnp.int32),
            tslot=jnp.zeros((0,), jnp.int32),
            at_perm=jnp.zeros((0,), jnp.int32),
            at_sorted=jnp.zeros((0,), jnp.int32),
            r_perm=jnp.zeros((0,), jnp.int32),
            r_sorted=jnp.zeros((0,), jnp.int32),
            n=n_loc,
            b=d,
            w=w,
            wp=1,
            wy=wy,
        )
        lv = dataclasses.replace(lv, y_slot=loc["y_slot"][None], c_slot=loc["c_slot"][None])
        assert lv1 is not None
        A1 = hl.psum(_galerkin(lv, lv1, A, loc["T"].astype(dtype)[:, None], dead=False))
        data = _chain(coarse, _add_dead(lv1, A1), power_iters, lapack=False)
        return A[None], Dinv[None], lam, data

    data_spec = dict(mats=Prep, Dinvs=Prep, lams=Prep, Ps=Prep, L=Prep) if coarse else dict(L=Prep)
    A0, Dinv0, lam0, data = jax.shard_map(
        setup,
        mesh=mesh,
        in_specs=(halo_spec, local_spec, coarse_spec, Psh, Psh, Psh),
        out_specs=(Psh, Psh, Prep, data_spec),
    )(halo, local, coarse, Ke, md, fm)
    scale = jnp.asarray(coarse_scale, dtype)

    def body(hl, loc, coarse, A, Dinv, lam, data, r):
        hl, loc = views(hl, loc)
        A, Dinv = A[0], Dinv[0]
        r = r.astype(dtype)
        if not coarse:  # one level: an exact solve with the replicated factor
            N, at = sh.n_shards * n_own, jax.lax.axis_index(axis) * n_own
            full = jnp.zeros((N, d), dtype).at[at + jnp.arange(n_own)].set(r)
            y = jax.scipy.linalg.cho_solve((data["L"], True), hl.psum(full).reshape(-1))
            return jax.lax.dynamic_slice_in_dim(y.reshape(N, d), at, n_own)
        assert lv1 is not None
        matvec, _ = ops(hl, loc, A)
        smooth = _chebyshev(matvec, Dinv, lam, degree, lower)
        solve = _cycle(coarse, data, degree=degree, lower=lower, cycle=cycle, scale=scale)
        T = loc["T"].astype(dtype)
        x = smooth(jnp.zeros_like(r), r, True)
        res = r - matvec(x)
        rt = jnp.einsum("nbm,nb->nm", T[:n_own], res)
        rc = jax.ops.segment_sum(
            rt[loc["r_perm"]], loc["r_sorted"], num_segments=lv1.n + 1, indices_are_sorted=True
        )[:-1]
        rc = hl.psum(rc)
        ec = solve(0, rc)
        if cycle == "W" and len(coarse) > 1:
            ec = ec + solve(0, rc - ell_matvec(data["mats"][0], lv1.cols, ec))
        ec = jnp.concatenate([ec, jnp.zeros((1,) + ec.shape[1:], dtype)])
        x = x + scale * jnp.einsum("nbm,nm->nb", T[:n_own], ec[loc["agg"]])
        return smooth(x, r, False)

    apply_sharded = jax.shard_map(
        body,
        mesh=mesh,
        in_specs=(halo_spec, local_spec, coarse_spec, Psh, Psh, Prep, data_spec, Psh),
        out_specs=Psh,
    )

    def apply(r):
        return apply_sharded(halo, local, coarse, A0, Dinv0, lam0, data, r)

    return apply
