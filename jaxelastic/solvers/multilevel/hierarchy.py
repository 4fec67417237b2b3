"""Host setup of the device multigrid: aggregation, tentative prolongators, index maps.

Once per (mesh, Dirichlet mask), in NumPy (:func:`build_hierarchy`): greedy aggregation of
the node graph (Vaněk, Mandel & Brezina 1996, "Algebraic multigrid by smoothed
aggregation", Computing 56:179), the rigid-body modes
(:func:`~jaxelastic.solvers.host.pattern.rigid_body_modes`) as near-null space,
orthonormalised per aggregate into a tentative prolongator ``T`` with one ``(b, m)`` block
per fine node (``b`` = dofs per node on that level, ``m`` = 3 in 2D, 6 in 3D), and integer
index maps: the padded row layout (ELL) of every level's block matrix, the element-block →
level-0 slot map and the slot → coarse-slot Galerkin maps. Everything is int32/float arrays
in a :class:`Hierarchy` pytree of :class:`Level` s, so it can travel as a ``jit`` argument
(no XLA constants).

Numbering: the aggregation visits the nodes in an order of their rest positions
(:func:`canonical_order`), not their indices, so a renumbered copy of the mesh gets the
same aggregates and coarse levels (what lets a sharded mesh use the hierarchy of the
one-device mesh, :mod:`~jaxelastic.solvers.multilevel.sharded`).

Dirichlet dofs: the rows of the near-null space are zeroed there, so ``T`` has zero rows
on prescribed dofs. Coarse dofs whose aggregate cannot carry all ``m`` modes (a one- or
two-node aggregate, a partly fixed one) are "dead": their rows and columns of ``T`` are
zero and their coarse diagonal gets a 1.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from ..host.pattern import rigid_body_modes

__all__ = [
    "Hierarchy",
    "Level",
    "build_hierarchy",
    "canonical_order",
    "node_graph",
    "pattern_of",
    "ell_pattern",
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


def node_graph(cells: np.ndarray, n: int) -> sp.csr_matrix:
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


def pattern_of(M) -> sp.csr_matrix:
    """Sparsity pattern of a sparse matrix as a sorted CSR matrix of ones."""
    M = sp.csr_matrix(M)
    M.sum_duplicates()
    M.sort_indices()
    return sp.csr_matrix((np.ones(M.indices.size, np.int8), M.indices, M.indptr), shape=M.shape)


def ell_pattern(G: sp.csr_matrix, pad_self: bool = True):
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
    G = node_graph(cells, n)  # the level's matrix pattern
    Gagg = G  # the graph aggregated (level 0: the mesh; then aggregate adjacency)
    cols, w, deg, lookup = ell_pattern(G)
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
        Pp = pattern_of(G @ Ind) if smooth else pattern_of(Ind)  # (nb, na)
        pcols, wp, pdeg, plookup = ell_pattern(Pp, pad_self=False)
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
        Yp = pattern_of(G @ Pp)  # (nb, na): A P
        ycols, wy, ydeg, ylookup = ell_pattern(Yp, pad_self=False)
        y_slot = np.full((wp, nb * w), nb * wy, np.int64)
        for t in range(wp):
            ok = real & (t < pdeg[cj])
            y_slot[t, ok] = ylookup(rows[ok], pcols[cj[ok], t])
        Gc = pattern_of(Pp.T @ Yp + sp.eye(na))  # (na, na): Pᵀ A P
        cols_c, w_c, deg_c, lookup_c = ell_pattern(Gc)
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
        Gagg = pattern_of(Ind.T @ Gagg @ Ind + sp.eye(na))
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
