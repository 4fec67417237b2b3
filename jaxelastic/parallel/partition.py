"""Host-side mesh partitioning for sharded solves: cells into S parts, node ownership,
and the padded global numbering every sharded array uses.

Layout (the "global padded layout"): shard ``s`` owns the contiguous block
``[s·n_own, (s+1)·n_own)`` of nodes and ``[s·c_loc, (s+1)·c_loc)`` of cells. Real nodes and
cells keep their natural relative order inside their shard; the block is filled up to the
common size with *padded* nodes (copies of a real node of the shard: same position, no
cell) and *padded* cells (zero weights and shape-function gradients, so F = I and they
contribute nothing). :class:`Partition` maps arrays between the natural and the padded
numbering and reports per-shard statistics.

Cells are split by METIS (Karypis & Kumar 1998, SIAM J. Sci. Comput. 20:359, through
pymetis, on the dual graph of cells sharing a facet) or by a Morton (Z-order)
space-filling curve of the cell centroids cut into S equal pieces. A node is owned by one
of the parts its cells belong to (so the ghost count, Σ over nodes of ``parts − 1``, is
the same whichever), chosen greedily to balance the owned counts.

Everything here is NumPy on the host; :mod:`jaxelastic.parallel.halo` builds the device
tables from a :class:`Partition`.
"""

from __future__ import annotations

import dataclasses
import importlib.util

import numpy as np

__all__ = ["Partition", "partition_cells", "partition_mesh", "METHODS", "morton_order"]

METHODS = ("auto", "metis", "sfc")


def morton_order(points: np.ndarray) -> np.ndarray:
    """Indices that sort ``points`` ``(n, dim)`` along a Morton (Z-order) curve.

    Coordinates are scaled to a ``2^b`` grid (b = 31 in 2D, 21 in 3D) and their bits
    interleaved into one 63-bit key (Morton 1966); ties keep the input order.
    """
    p = np.asarray(points, dtype=np.float64)
    n, d = p.shape
    bits = 31 if d == 2 else 21
    lo, hi = p.min(axis=0), p.max(axis=0)
    span = np.where(hi > lo, hi - lo, 1.0)
    q = np.floor((p - lo) / span * ((1 << bits) - 1)).astype(np.uint64)
    key = np.zeros(n, dtype=np.uint64)
    for b in range(bits):
        for a in range(d):
            bit = (q[:, a] >> np.uint64(b)) & np.uint64(1)
            key |= bit << np.uint64(b * d + a)
    return np.argsort(key, kind="stable")


def _metis_available() -> bool:
    return importlib.util.find_spec("pymetis") is not None


def partition_cells(
    points: np.ndarray, cells: np.ndarray, n_parts: int, method: str = "auto"
) -> tuple[np.ndarray, str]:
    """The part ``(n_cells,)`` int of every cell, and the method used.

    Args:
        points: ``(n_nodes, dim)`` rest points; cells: ``(n_cells, k)`` connectivity (only
            the ``dim + 1`` corner nodes are used, so P2 cells partition like P1).
        n_parts: S ≥ 1.
        method: ``"metis"`` (pymetis on the facet dual graph; every part non-empty),
            ``"sfc"`` (Morton order of centroids cut into S pieces of equal size ±1) or
            ``"auto"`` (METIS when pymetis is installed, else the curve).

    Raises:
        ValueError: unknown method, fewer cells than parts, or ``"metis"`` without pymetis.
    """
    if method not in METHODS:
        raise ValueError(f"partition method must be one of {METHODS}, got {method!r}")
    n_cells, dim = cells.shape[0], points.shape[1]
    if n_parts < 1 or n_parts > n_cells:
        raise ValueError(f"cannot split {n_cells} cells into {n_parts} parts")
    if n_parts == 1:
        return np.zeros(n_cells, dtype=np.int64), "sfc" if method == "sfc" else method
    if method == "metis" and not _metis_available():
        raise ValueError("method='metis' needs pymetis (pip install pymetis); or use 'sfc'")
    if method in ("auto", "metis") and _metis_available():
        part = _metis_parts(cells[:, : dim + 1], n_parts, dim)
        if np.unique(part).size == n_parts:
            return part, "metis"
        if method == "metis":
            raise ValueError(f"METIS left a part empty splitting {n_cells} cells in {n_parts}")
    order = morton_order(points[cells[:, : dim + 1]].mean(axis=1))
    part = np.empty(n_cells, dtype=np.int64)
    part[order] = (np.arange(n_cells) * n_parts) // n_cells
    return part, "sfc"


def _metis_parts(corners: np.ndarray, n_parts: int, dim: int) -> np.ndarray:
    import pymetis

    # renumber the corner nodes densely (P2 mid-edge nodes are left out)
    used, dense = np.unique(corners, return_inverse=True)
    del used
    conn = dense.reshape(corners.shape).astype(np.int64)
    res = pymetis.part_mesh(n_parts, list(conn), gtype=pymetis.GType.DUAL, ncommon=dim)
    return np.asarray(res.element_part, dtype=np.int64)


def _owners(cells: np.ndarray, part: np.ndarray, n_nodes: int, n_parts: int) -> np.ndarray:
    """Owner part of every node: one of its cells' parts, balancing the owned counts
    (interior nodes first, then each interface node to its least loaded candidate)."""
    k = cells.shape[1]
    pairs = np.unique(cells.ravel().astype(np.int64) * n_parts + np.repeat(part, k))
    node, cand = pairs // n_parts, pairs % n_parts
    n_cand = np.bincount(node, minlength=n_nodes)
    owner = np.full(n_nodes, -1, dtype=np.int64)
    single = n_cand[node] == 1
    owner[node[single]] = cand[single]
    counts = np.bincount(owner[owner >= 0], minlength=n_parts)
    start = np.concatenate([[0], np.cumsum(n_cand)])
    for v in np.flatnonzero(n_cand > 1):
        c = cand[start[v] : start[v + 1]]
        best = c[np.argmin(counts[c])]  # ties: the lowest part
        owner[v] = best
        counts[best] += 1
    return owner


@dataclasses.dataclass(frozen=True, eq=False)
class Partition:
    """A mesh split into S shards in the global padded layout (host NumPy arrays).

    Attributes:
        n_shards: S.
        n_own: nodes per shard (owned, padded included); the padded node count is S·n_own.
        c_loc: cells per shard (padded included); the padded cell count is S·c_loc.
        method: ``"metis"`` or ``"sfc"`` (what was used).
        cell_part: ``(n_cells,)`` shard of each natural cell.
        node_owner: ``(n_nodes,)`` owning shard of each natural node.
        node_index: ``(n_nodes,)`` padded index of each natural node.
        cell_index: ``(n_cells,)`` padded index of each natural cell.
        node_source: ``(S·n_own,)`` natural node each padded node copies (itself for a
            real node, a real node of the same shard for a padded one).
        cell_source: ``(S·c_loc,)`` natural cell each padded cell copies (its parameters).
        node_real, cell_real: ``(S·n_own,)`` / ``(S·c_loc,)`` bool, False on padding.
        padded_cells: ``(S·c_loc, k)`` int32 connectivity in padded node indices (a padded
            cell lists its shard's first node k times).
        ghosts: per shard, the padded indices ``(n_ghost_s,)`` of the nodes its cells use
            but another shard owns, sorted by owner then index.
        dim: spatial dimension (for the byte counts of :meth:`stats`).
    """

    n_shards: int
    n_own: int
    c_loc: int
    method: str
    cell_part: np.ndarray
    node_owner: np.ndarray
    node_index: np.ndarray
    cell_index: np.ndarray
    node_source: np.ndarray
    cell_source: np.ndarray
    node_real: np.ndarray
    cell_real: np.ndarray
    padded_cells: np.ndarray
    ghosts: tuple
    dim: int = 3

    @property
    def n_nodes(self) -> int:
        """Natural node count."""
        return int(self.node_index.size)

    @property
    def n_cells(self) -> int:
        """Natural cell count."""
        return int(self.cell_index.size)

    @property
    def n_padded_nodes(self) -> int:
        return self.n_shards * self.n_own

    @property
    def n_padded_cells(self) -> int:
        return self.n_shards * self.c_loc

    def _kind(self, a, kind: str | None) -> str:
        if kind is not None:
            if kind not in ("nodes", "cells"):
                raise ValueError(f"kind must be 'nodes' or 'cells', got {kind!r}")
            return kind
        n = int(np.shape(a)[0]) if np.ndim(a) else -1
        sizes = {
            "nodes": (self.n_nodes, self.n_padded_nodes),
            "cells": (self.n_cells, self.n_padded_cells),
        }
        hits = [k for k, s in sizes.items() if n in s]
        if len(hits) != 1:
            raise ValueError(
                f"cannot tell whether an array of leading size {n} is a node or a cell field "
                f"(nodes: {sizes['nodes']}, cells: {sizes['cells']}, natural/padded); pass "
                "kind='nodes' or kind='cells'"
            )
        return hits[0]

    def to_padded(self, a, kind: str | None = None, fill=None):
        """A natural node field ``(n_nodes, ...)`` or cell field ``(n_cells, ...)`` in the
        padded numbering ``(S·n_own, ...)`` / ``(S·c_loc, ...)``.

        Padding entries copy a real entry of their shard (``fill=None``) or are set to
        ``fill``. NumPy in, NumPy out; a JAX array (or tracer) gives a JAX array
        (differentiable, a gather).
        """
        kind = self._kind(a, kind)
        src = self.node_source if kind == "nodes" else self.cell_source
        real = self.node_real if kind == "nodes" else self.cell_real
        want = self.n_nodes if kind == "nodes" else self.n_cells
        if int(np.shape(a)[0]) != want:
            raise ValueError(
                f"to_padded: expected a natural {kind} field of {want}, got {np.shape(a)}"
            )
        if isinstance(a, np.ndarray) or np.isscalar(a):
            out = np.asarray(a)[src]
            if fill is not None:
                out[~real] = fill
            return out
        import jax.numpy as jnp

        out = jnp.take(a, jnp.asarray(src), axis=0)
        if fill is not None:
            m = jnp.asarray(real).reshape((-1,) + (1,) * (out.ndim - 1))
            out = jnp.where(m, out, jnp.asarray(fill, out.dtype))
        return out

    def to_natural(self, a, kind: str | None = None):
        """A padded node field ``(S·n_own, ...)`` (e.g. ``sol.x``) or cell field
        ``(S·c_loc, ...)`` back in the natural numbering (padding dropped). NumPy in, NumPy
        out; a JAX array gives a JAX array (a differentiable gather, replicated layout
        decided by XLA)."""
        kind = self._kind(a, kind)
        idx = self.node_index if kind == "nodes" else self.cell_index
        want = self.n_padded_nodes if kind == "nodes" else self.n_padded_cells
        if int(np.shape(a)[0]) != want:
            raise ValueError(
                f"to_natural: expected a padded {kind} field of {want}, got {np.shape(a)}"
            )
        if isinstance(a, np.ndarray):
            return a[idx]
        import jax.numpy as jnp

        return jnp.take(a, jnp.asarray(idx), axis=0)

    def stats(self, dim: int | None = None, itemsize: int = 8) -> dict:
        """Per-shard statistics (lists of length S) and totals, JSON-ready.

        Keys: ``method``, ``shards``, ``cells`` (real cells per shard), ``cells_padded``
        (c_loc), ``owned_nodes`` (real owned), ``nodes_padded`` (n_own), ``ghost_nodes``
        (nodes used but owned elsewhere), ``interface_nodes`` (owned nodes some other shard
        uses), ``halo_bytes`` (per shard, one exchange of a ``dim``-vector per ghost at
        ``itemsize`` bytes: what one gather receives), ``halo_bytes_total``, and
        ``replicated_bytes`` (one all-reduce of the whole padded node vector, for contrast).
        """
        S, dim = self.n_shards, self.dim if dim is None else dim
        cells = np.bincount(self.cell_part, minlength=S)
        owned = np.bincount(self.node_owner, minlength=S)
        ghosts = [int(g.size) for g in self.ghosts]
        used_elsewhere = np.zeros(self.n_padded_nodes, dtype=bool)
        for g in self.ghosts:
            used_elsewhere[g] = True
        iface = np.bincount(np.flatnonzero(used_elsewhere) // self.n_own, minlength=S)
        hb = [g * dim * itemsize for g in ghosts]
        return dict(
            method=self.method,
            shards=S,
            cells=cells.tolist(),
            cells_padded=int(self.c_loc),
            owned_nodes=owned.tolist(),
            nodes_padded=int(self.n_own),
            ghost_nodes=ghosts,
            interface_nodes=iface.tolist(),
            halo_bytes=hb,
            halo_bytes_total=int(sum(hb)),
            replicated_bytes=int(self.n_padded_nodes * dim * itemsize),
        )


def partition_mesh(points, cells, n_parts: int, method: str = "auto") -> Partition:
    """Partition a mesh (host arrays) into ``n_parts`` shards: see the module docstring.

    Args:
        points: ``(n_nodes, dim)`` rest points; cells: ``(n_cells, k)`` connectivity.
        n_parts: S ≥ 1 (at most the number of cells).
        method: ``"auto"``, ``"metis"`` or ``"sfc"`` (:func:`partition_cells`).
    """
    pts = np.asarray(points, dtype=np.float64)
    cls = np.asarray(cells).astype(np.int64)
    n_nodes, S = pts.shape[0], int(n_parts)
    part, used = partition_cells(pts, cls, S, method)
    owner = _owners(cls, part, n_nodes, S)
    if (owner < 0).any():
        raise ValueError("every node must belong to a cell (prune unused nodes first)")
    n_own = int(np.bincount(owner, minlength=S).max())
    c_loc = int(np.bincount(part, minlength=S).max())
    # padded indices: natural order inside each shard
    node_index = np.empty(n_nodes, dtype=np.int64)
    cell_index = np.empty(cls.shape[0], dtype=np.int64)
    node_source = np.empty(S * n_own, dtype=np.int64)
    cell_source = np.empty(S * c_loc, dtype=np.int64)
    node_real = np.zeros(S * n_own, dtype=bool)
    cell_real = np.zeros(S * c_loc, dtype=bool)
    for s in range(S):
        mine = np.flatnonzero(owner == s)
        mc = np.flatnonzero(part == s)
        if mine.size == 0:  # a shard owning nothing: its padding copies a node its cells use
            mine_src = cls[mc[0], :1]
        else:
            mine_src = mine
        node_index[mine] = s * n_own + np.arange(mine.size)
        node_source[s * n_own : (s + 1) * n_own] = mine_src[0]
        node_source[s * n_own : s * n_own + mine.size] = mine
        node_real[s * n_own : s * n_own + mine.size] = True
        cell_index[mc] = s * c_loc + np.arange(mc.size)
        cell_source[s * c_loc : (s + 1) * c_loc] = mc[0]
        cell_source[s * c_loc : s * c_loc + mc.size] = mc
        cell_real[s * c_loc : s * c_loc + mc.size] = True
    k = cls.shape[1]
    padded_cells = np.repeat((np.arange(S) * n_own)[:, None], c_loc * k, axis=1).reshape(-1, k)
    padded_cells[cell_index] = node_index[cls]
    ghosts = []
    for s in range(S):
        used_nodes = np.unique(
            padded_cells[s * c_loc : (s + 1) * c_loc][cell_real[s * c_loc : (s + 1) * c_loc]]
        )
        g = used_nodes[(used_nodes // n_own) != s]
        ghosts.append(np.sort(g))  # padded indices sort by owner, then index
    return Partition(
        n_shards=S,
        n_own=n_own,
        c_loc=c_loc,
        method=used,
        cell_part=part,
        node_owner=owner,
        node_index=node_index,
        cell_index=cell_index,
        node_source=node_source,
        cell_source=cell_source,
        node_real=node_real,
        cell_real=cell_real,
        padded_cells=padded_cells.astype(np.int32),
        ghosts=tuple(ghosts),
        dim=int(pts.shape[1]),
    )
