"""Host-side sparsity pattern of the global Hessian and the rigid-body near-null space.

The global Hessian's sparsity depends only on the connectivity, so it is analysed once:
:meth:`SparsityPattern.build` precomputes the CSR structure of the full matrix and of its
upper triangle, and an **int32** map from every upper-triangular entry of every element
Hessian to the upper-triangle CSR slot it adds into. Assembling a new Hessian (every
Newton step) is then one segment sum over that map — done on the device in XLA by the
host linear solvers (:mod:`jaxelastic.solvers.linear`), so only the ``(nnz_upper,)`` data
vector reaches the host — with the symmetrisation folded in: entry ``(p, q)``, ``p ≤ q``,
of the element-local upper triangle carries ``½(Ke[p, q] + Ke[q, p])``.

Dirichlet dofs are eliminated *keeping the pattern* (their rows and columns are zeroed,
their diagonal set to 1), so the matrix stays symmetric and a factorisation's symbolic
analysis or an AMG hierarchy can be reused across Newton steps. The full CSR matrix
(AMG, SuperLU, cholespy) is a gather of the upper data (``full_from_upper``).

Dof ordering is node-major everywhere: dof ``a*dim + i`` is component ``i`` of node ``a``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import tempfile
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

__all__ = ["SparsityPattern", "rigid_body_modes", "local_upper"]

_INT32_MAX = np.iinfo(np.int32).max
_CHUNK = 1 << 20  # element entries per vectorised chunk of the map computation


def local_upper(m: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices ``(m(m+1)/2,)`` of the upper triangle of an ``(m, m)`` element
    Hessian, row-major: the order of :attr:`SparsityPattern.element_map` per cell."""
    return np.triu_indices(m)


# ----------------------------------------------------------------------------------------
# sparsity pattern and assembly
# ----------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class SparsityPattern:
    """CSR structure of the global Hessian (full and upper triangle) and the int32
    element→CSR map.

    Built once per (mesh, Dirichlet mask) by :meth:`build`. All dofs are kept (fixed ones
    get an identity row/column after elimination), so ``n_dofs = n_nodes * dim``. Every
    diagonal entry is in the pattern (PARDISO and CHOLMOD need it; an unused node gets an
    identity row). Index arrays are int32 (the CSR limit is checked).

    Attributes:
        n_nodes, dim: mesh size and spatial dimension.
        indptr: ``(n_dofs + 1,)`` int32 row pointers of the full matrix.
        indices: ``(nnz,)`` int32 column indices, sorted within each row.
        upper_indptr, upper_indices: ``(n_dofs + 1,)``, ``(nnz_upper,)`` int32 CSR of the
            upper triangle (diagonal first in each row, columns sorted).
        element_map: ``(n_cells * m(m+1)/2,)`` int32 with ``m = k*dim``: the upper-triangle
            slot of entry ``(p, q)``, ``p ≤ q`` (order :func:`local_upper`), of every cell's
            element Hessian; ``upper_data = Σ ½(Ke + Keᵀ)[c, p, q]`` over the entries mapped
            to a slot.
        full_from_upper: ``(nnz,)`` int32; full CSR data ``= upper_data[full_from_upper]``.
        fixed: ``(n_dofs,)`` bool Dirichlet mask.
        zeroed: int32 upper slots in a fixed row or column (diagonals included).
        fixed_diag: int32 upper slots of the diagonals of fixed dofs.
        diag_slots: ``(n_dofs,)`` int32 upper slot of each diagonal entry ``(i, i)``.
        node_indptr, node_indices: the node-level (block) pattern; with ``bsr_perm`` it
            gives the full matrix as a BSR matrix with ``(dim, dim)`` blocks.
        bsr_perm: ``(nnz,)`` int32; ``data[bsr_perm].reshape(-1, dim, dim)`` is BSR data.
    """

    n_nodes: int
    dim: int
    indptr: np.ndarray
    indices: np.ndarray
    upper_indptr: np.ndarray
    upper_indices: np.ndarray
    element_map: np.ndarray
    full_from_upper: np.ndarray
    fixed: np.ndarray
    zeroed: np.ndarray
    fixed_diag: np.ndarray
    diag_slots: np.ndarray
    node_indptr: np.ndarray
    node_indices: np.ndarray
    bsr_perm: np.ndarray

    @property
    def n_dofs(self) -> int:
        return self.n_nodes * self.dim

    @property
    def nnz(self) -> int:
        """Stored entries of the full matrix."""
        return int(self.indices.size)

    @property
    def nnz_upper(self) -> int:
        """Stored entries of the upper triangle (diagonal included)."""
        return int(self.upper_indices.size)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.n_dofs, self.n_dofs)

    @property
    def nbytes(self) -> int:
        """Host memory of the index arrays [bytes]."""
        return sum(
            int(getattr(self, f.name).nbytes)
            for f in dataclasses.fields(self)
            if isinstance(getattr(self, f.name), np.ndarray)
        )

    @classmethod
    def build_cached(
        cls, cells: np.ndarray, n_nodes: int, dim: int, fixed: np.ndarray | None = None
    ) -> SparsityPattern:
        """:meth:`build`, kept on disk next to the persistent compilation cache for large
        meshes (at least :data:`DISK_MIN_SLOTS` element-node slots) while that cache is on
        (:mod:`jaxelastic.cache`): a later process loads the arrays instead of analysing
        the connectivity again. Measured at twist n = 29 (146k tets, 97 MB of index
        arrays): the analysis 4.3 s, the load a small fraction of it (loaded machine).
        The file is written atomically (a temporary, then a rename), so concurrent
        processes read whole files only; the last :data:`DISK_KEEP` are kept."""
        cells = np.asarray(cells)
        folder = _disk_folder() if cells.size >= DISK_MIN_SLOTS else None
        if folder is None:
            return cls.build(cells, n_nodes, dim, fixed)
        fx = np.zeros(n_nodes * dim, bool) if fixed is None else np.asarray(fixed, bool)
        h = hashlib.sha1(f"{_DISK_FORMAT}:{n_nodes}:{dim}:{cells.shape}".encode())
        h.update(np.ascontiguousarray(cells, np.int64).tobytes())
        h.update(np.ascontiguousarray(fx.reshape(-1)).tobytes())
        path = os.path.join(folder, h.hexdigest() + ".npz")
        loaded = _load(path, n_nodes, dim)
        if loaded is not None:
            return loaded
        pattern = cls.build(cells, n_nodes, dim, fixed)
        _save(path, pattern)
        return pattern

    @classmethod
    def build(
        cls, cells: np.ndarray, n_nodes: int, dim: int, fixed: np.ndarray | None = None
    ) -> SparsityPattern:
        """Analyse the connectivity once.

        Args:
            cells: ``(n_cells, k)`` node indices of each element.
            n_nodes: number of mesh nodes.
            dim: spatial dimension (dofs per node).
            fixed: ``(n_nodes*dim,)`` bool Dirichlet mask (node-major), or ``None``.

        Cost: one stable argsort of the ``n_cells*k²`` node pairs plus linear passes over
        the ``n_cells*m(m+1)/2`` element entries, done in chunks so the transient memory
        stays near the size of the int32 map itself (4 bytes per element-Hessian entry of
        the upper triangle: 46 MB at 146k tets, where the old int64 full map was 161 MB).
        """
        cells, n, d, fixed = _check_inputs(cells, n_nodes, dim, fixed)
        blocks = _node_blocks(cells, n)
        indptr = _row_pointers(np.repeat(d * blocks.deg, d))
        bsr_perm, indices = _block_layout(blocks, d, int(indptr[-1]))
        up = _upper(blocks, d)
        full_from_upper = np.empty(indices.size, dtype=np.int32)
        full_from_upper[bsr_perm.reshape(-1)] = up.table.reshape(-1)
        element_map = _element_map(cells, blocks, up, d)
        zeroed, fixed_diag = _dirichlet_slots(up, fixed, d)
        return cls(
            n_nodes=n,
            dim=d,
            indptr=indptr.astype(np.int32),
            indices=indices,
            upper_indptr=up.indptr.astype(np.int32),
            upper_indices=up.indices,
            element_map=element_map,
            full_from_upper=full_from_upper,
            fixed=fixed,
            zeroed=zeroed,
            fixed_diag=fixed_diag,
            diag_slots=up.indptr[:-1].astype(np.int32),
            node_indptr=blocks.indptr.astype(np.int32),
            node_indices=blocks.col.astype(np.int32),
            bsr_perm=bsr_perm.reshape(-1).astype(np.int32),
        )

    # -- assembly --------------------------------------------------------------------

    def upper_data(self, Ke) -> np.ndarray:
        """Upper-triangle data ``(nnz_upper,)`` of ``Σ_c ½(Ke_c + Ke_cᵀ)`` on the host.

        ``Ke``: ``(n_cells, m, m)`` element Hessians, ``m = k*dim``. The library's solvers do
        this sum on the device (:mod:`jaxelastic.solvers.linear`); this NumPy version is for
        host callers (tests, benchmarks, :meth:`assemble`).
        """
        Ke = np.asarray(Ke, dtype=np.float64)
        m = Ke.shape[-1]
        iu, ju = local_upper(m)
        if Ke.ndim != 3 or Ke.shape[1] != m or Ke.shape[0] * iu.size != self.element_map.size:
            raise ValueError(
                f"element Hessians have shape {Ke.shape}, the pattern expects "
                f"({self.element_map.size * 2 // (m * (m + 1)) if m else 0}, k*dim, k*dim) "
                "for its mesh"
            )
        w = 0.5 * (Ke[:, iu, ju] + Ke[:, ju, iu])
        return np.bincount(self.element_map, weights=w.reshape(-1), minlength=self.nnz_upper)

    def finish(self, data, *, diag=None, eliminate: bool = True) -> np.ndarray:
        """Add a diagonal and eliminate the Dirichlet dofs, in place on upper data.

        Args:
            data: ``(nnz_upper,)`` float64 upper data (modified and returned).
            diag: optional ``(n_dofs,)`` added to the diagonal before elimination (e.g. a
                lumped mass / dt² term); keeps the pattern.
            eliminate: zero fixed rows/columns and put 1 on their diagonals.
        """
        if diag is not None:
            data[self.diag_slots] += np.asarray(diag, dtype=np.float64).reshape(-1)
        if eliminate:
            data[self.zeroed] = 0.0
            data[self.fixed_diag] = 1.0
        return data

    def full_data(self, upper) -> np.ndarray:
        """Full CSR data ``(nnz,)`` from upper data ``(nnz_upper,)`` (one gather)."""
        return np.asarray(upper)[self.full_from_upper]

    def assemble_data(self, Ke, *, eliminate: bool = True, diag=None) -> np.ndarray:
        """Full CSR data ``(nnz,)`` of the symmetrised ``Σ_c Ke_c`` (``(n_cells, m, m)``),
        with an optional ``(n_dofs,)`` diagonal and Dirichlet elimination."""
        return self.full_data(self.finish(self.upper_data(Ke), diag=diag, eliminate=eliminate))

    def matrix(self, data: np.ndarray) -> sp.csr_matrix:
        """Wrap full CSR data ``(nnz,)`` in a ``scipy.sparse.csr_matrix`` (no copy)."""
        return sp.csr_matrix((data, self.indices, self.indptr), shape=self.shape, copy=False)

    def upper_matrix(self, upper: np.ndarray) -> sp.csr_matrix:
        """Wrap upper data ``(nnz_upper,)`` in an upper-triangular CSR matrix (no copy)."""
        return sp.csr_matrix(
            (upper, self.upper_indices, self.upper_indptr), shape=self.shape, copy=False
        )

    def assemble(self, Ke, *, diag=None) -> sp.csr_matrix:
        """Global Hessian with Dirichlet elimination, ``(n_dofs, n_dofs)`` CSR.

        ``Ke``: ``(n_cells, k*d, k*d)`` (symmetrised); ``diag``: optional ``(n_dofs,)``.
        """
        return self.matrix(self.assemble_data(Ke, eliminate=True, diag=diag))

    def assemble_full(self, Ke, *, diag=None) -> sp.csr_matrix:
        """Global Hessian without elimination (all dofs), ``(n_dofs, n_dofs)`` CSR."""
        return self.matrix(self.assemble_data(Ke, eliminate=False, diag=diag))

    def to_bsr(self, K: sp.csr_matrix) -> sp.bsr_matrix:
        """The same matrix as BSR with ``(dim, dim)`` node blocks (a gather, no search).

        ``K`` must have this (full) pattern (e.g. come from :meth:`assemble`).
        """
        d = self.dim
        blocks = K.data[self.bsr_perm].reshape(-1, d, d)
        return sp.bsr_matrix(
            (blocks, self.node_indices, self.node_indptr), shape=self.shape, copy=False
        )

    def has_pattern(self, K) -> bool:
        """Whether CSR matrix ``K`` has exactly this (full) structure (identity test first)."""
        if not sp.issparse(K) or K.format != "csr" or K.shape != self.shape:
            return False
        if K.indices is self.indices and K.indptr is self.indptr:
            return True
        return (
            K.nnz == self.nnz
            and np.array_equal(K.indptr, self.indptr)
            and np.array_equal(K.indices, self.indices)
        )


# ----------------------------------------------------------------------------------------
# the steps of SparsityPattern.build
# ----------------------------------------------------------------------------------------


class _NodeBlocks(NamedTuple):
    """Node-level (block) pattern: the unique (row node, column node) pairs, row-major.

    ``key``: ``(n_blocks,)`` int64 ``row*n_nodes + col``, sorted; ``row``, ``col``: its
    parts; ``deg``: ``(n_nodes,)`` blocks per node row; ``indptr``: ``(n_nodes + 1,)``
    int64 block-row pointers; ``of_entry``: ``(n_cells, k, k)`` int32 block index of the
    node pair ``(cells[c, a], cells[c, b])``; ``diag``: ``(n_nodes,)`` block index of
    ``(a, a)``; ``transpose``: ``(n_blocks,)`` index of the transposed block.
    """

    key: np.ndarray
    row: np.ndarray
    col: np.ndarray
    deg: np.ndarray
    indptr: np.ndarray
    of_entry: np.ndarray
    diag: np.ndarray
    transpose: np.ndarray


DISK_MIN_SLOTS = 1 << 18
"""Meshes with at least this many element-node slots (``n_cells · k``; 65,536 tet4) keep
their :class:`SparsityPattern` on disk (:meth:`SparsityPattern.build_cached`)."""

DISK_KEEP = 4
"""Number of sparsity patterns kept on disk (the least recently used are removed)."""

_DISK_FORMAT = 1


def _disk_folder() -> str | None:
    """``<persistent cache>/jaxelastic-patterns`` while JAX's persistent cache is on."""
    from ...cache import persistent_cache_dir

    base = persistent_cache_dir()
    if not base or "://" in base:
        return None
    folder = os.path.join(base, "jaxelastic-patterns")
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError:
        return None
    return folder


def _load(path: str, n_nodes: int, dim: int) -> SparsityPattern | None:
    """The pattern stored at ``path``, or None (missing or unreadable: built again)."""
    try:
        with np.load(path) as z:
            arrays = {f.name: z[f.name] for f in dataclasses.fields(SparsityPattern)[2:]}
        os.utime(path)  # recently used
    except (OSError, KeyError, ValueError):
        return None
    return SparsityPattern(n_nodes=n_nodes, dim=dim, **arrays)


def _save(path: str, pattern: SparsityPattern) -> None:
    """Write atomically, then keep the :data:`DISK_KEEP` most recently used files."""
    folder = os.path.dirname(path)
    arrays = {f.name: getattr(pattern, f.name) for f in dataclasses.fields(pattern)[2:]}
    try:
        fd, tmp = tempfile.mkstemp(dir=folder, suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **arrays)
        os.replace(tmp, path)
        entries = list(os.scandir(folder))
        files = sorted((e for e in entries if e.name.endswith(".npz")), key=_mtime)
        stale = [e for e in entries if e.name.endswith(".tmp") and _mtime(e) < _now() - 3600]
        for e in files[:-DISK_KEEP] + stale:  # (a .tmp of a process killed while writing)
            os.remove(e.path)
    except OSError:
        pass  # a full or read-only disk: the pattern is only not kept


def _mtime(e: os.DirEntry) -> float:
    return e.stat().st_mtime


def _now() -> float:
    import time

    return time.time()


def _check_inputs(cells, n_nodes, dim, fixed):
    """Validated ``(cells (n_cells, k) int64, n, d, fixed (n*d,) bool)``."""
    cells = np.asarray(cells)
    if cells.ndim != 2:
        raise ValueError(f"cells must have shape (n_cells, k), got {cells.shape}")
    n, d = int(n_nodes), int(dim)
    nd = n * d
    if fixed is None:
        fixed = np.zeros(nd, dtype=bool)
    fixed = np.asarray(fixed, dtype=bool).reshape(-1)
    if fixed.shape != (nd,):
        raise ValueError(f"fixed must have n_nodes*dim = {nd} entries, got {fixed.size}")
    if cells.size and (cells.min() < 0 or cells.max() >= n):
        raise ValueError(f"cells reference nodes outside [0, {n})")
    return cells.astype(np.int64), n, d, fixed


def _node_blocks(cells: np.ndarray, n: int) -> _NodeBlocks:
    """Unique node pairs of the connectivity ``(n_cells, k)`` over ``n`` nodes, with every
    diagonal pair ``(a, a)`` included.

    A stable argsort of int64 keys (radix/timsort) is ~5x faster than np.unique's quicksort.
    """
    c, k = cells.shape
    diag_keys = np.arange(n, dtype=np.int64) * (n + 1)
    key = np.concatenate([(cells[:, :, None] * n + cells[:, None, :]).reshape(-1), diag_keys])
    order = np.argsort(key, kind="stable")
    skey = key[order]
    del key
    new_block = np.empty(skey.size, dtype=bool)
    new_block[0] = True
    np.not_equal(skey[1:], skey[:-1], out=new_block[1:])
    ukey = skey[new_block]  # (n_blocks,)
    del skey
    if ukey.size > _INT32_MAX:
        raise ValueError(f"{ukey.size} node blocks exceed int32 indices")
    q = np.empty(order.size, dtype=np.int32)
    q[order] = np.cumsum(new_block, dtype=np.int64) - 1  # block index of every key
    del order, new_block
    row = ukey // n
    col = ukey - row * n
    deg = np.bincount(row, minlength=n)
    indptr = _row_pointers(deg)
    transpose = np.searchsorted(ukey, col * n + row).astype(np.int32)
    return _NodeBlocks(
        ukey, row, col, deg, indptr, q[: c * k * k].reshape(c, k, k), q[c * k * k :], transpose
    )


def _row_pointers(row_len: np.ndarray) -> np.ndarray:
    """CSR row pointers ``(len + 1,)`` int64 from row lengths (checked against int32)."""
    indptr = np.zeros(row_len.size + 1, dtype=np.int64)
    np.cumsum(row_len, out=indptr[1:])
    if indptr[-1] >= _INT32_MAX:
        raise ValueError(f"{int(indptr[-1])} nonzeros exceed int32 CSR indices")
    return indptr


def _block_layout(blocks: _NodeBlocks, d: int, nnz: int):
    """``(bsr_perm (n_blocks, d, d) int64, indices (nnz,) int32)`` of the full matrix.

    ``bsr_perm[b, i, j]`` is the CSR slot of entry (i, j) of block b (BSR order).
    """
    ii = np.arange(d)
    row = blocks.row
    start = blocks.indptr[row]
    bsr_perm = (
        (d * d * start + d * (np.arange(row.size) - start))[:, None, None]
        + (ii * d)[None, :, None] * blocks.deg[row][:, None, None]
        + ii[None, None, :]
    )
    indices = np.empty(nnz, dtype=np.int32)
    indices[bsr_perm] = (blocks.col * d)[:, None, None] + ii[None, None, :]
    return bsr_perm, indices


class _Upper(NamedTuple):
    """Upper-triangle CSR layout: ``indptr (n*d + 1,)`` int64, ``indices (nnz_upper,)``
    int32, and ``table (n_blocks, d, d)`` int32, the upper slot of entry ``(i, j)`` of
    every block of the symmetric matrix (blocks below the diagonal, and ``i > j`` in
    diagonal blocks, mirrored).

    Row ``a*d + i`` holds the diagonal block's columns ``a*d + j`` for ``j ≥ i`` (diagonal
    first), then the ``d`` columns of every block ``(a, b)`` with ``b > a``, in order.
    """

    indptr: np.ndarray
    indices: np.ndarray
    table: np.ndarray


def _upper(blocks: _NodeBlocks, d: int) -> _Upper:
    """The upper-triangle layout of the block pattern (see :class:`_Upper`)."""
    n_up = blocks.indptr[1:] - blocks.diag - 1  # blocks (a, b) with b > a, per node
    ii = np.arange(d)
    row_len = (d - ii)[None, :] + d * n_up[:, None]  # (n, d)
    indptr = _row_pointers(row_len.reshape(-1))
    # slot of (i, j) in an upper block q of node row a: U0[a] + i*d*n_up[a] + c[i] +
    # d*(q - diag[a] - 1) + j, with c[i] = i*d - i(i-1)/2 + (d - i) the entries of the
    # diagonal block in rows <= i; in the diagonal block: U0[a] + i*d*n_up[a] + c[i] - (d - i)
    # + (j - i) for j >= i
    c = ii * d - ii * (ii - 1) // 2
    u0 = indptr[:-1:d]  # (n,)
    row, col = blocks.row, blocks.col
    up = col > row
    q_up = np.where(col < row, blocks.transpose, np.arange(row.size))  # its upper twin
    a = row[q_up]
    base = u0[a] + d * (q_up - blocks.diag[a] - 1)  # (n_blocks,)
    stride = d * n_up[a]
    table = np.empty((row.size, d, d), dtype=np.int32)
    for i in range(d):
        for j in range(d):
            off_up = base + i * stride + c[i] + (d - i) + j  # block (a, b), b > a, entry (i, j)
            off_lo = base + j * stride + c[j] + (d - j) + i  # mirrored: (j, i) of the twin
            lo, hi = min(i, j), max(i, j)
            off_dg = u0[a] + lo * stride + c[lo] + (hi - lo)
            table[:, i, j] = np.where(up, off_up, np.where(col < row, off_lo, off_dg))
    indices = np.empty(int(indptr[-1]), dtype=np.int32)
    for i in range(d):
        for j in range(d):
            keep = up | ((col == row) & (i <= j))
            indices[table[keep, i, j]] = col[keep] * d + j
    return _Upper(indptr, indices, table)


def _element_map(cells: np.ndarray, blocks: _NodeBlocks, up: _Upper, d: int) -> np.ndarray:
    """Upper slot of every local upper entry of every element Hessian, int32 (a gather
    from the block table, in chunks of cells to bound the transient memory)."""
    c, k = cells.shape
    m = k * d
    p, r = local_upper(m)
    a, b = p // d, r // d
    within = ((p % d) * d + r % d).astype(np.int64)
    flat = up.table.reshape(-1)
    out = np.empty(c * p.size, dtype=np.int32)
    step = max(1, _CHUNK // max(p.size, 1))
    for s in range(0, c, step):
        e = min(c, s + step)
        q = blocks.of_entry[s:e][:, a, b].astype(np.int64)  # (chunk, n_local)
        out[s * p.size : e * p.size] = flat[q * (d * d) + within].reshape(-1)
    return out


def _dirichlet_slots(up: _Upper, fixed: np.ndarray, d: int):
    """``(zeroed, fixed_diag)`` int32 upper slots (see :class:`SparsityPattern`)."""
    rows = np.repeat(np.arange(fixed.size), np.diff(up.indptr))
    zeroed = np.flatnonzero(fixed[rows] | fixed[up.indices]).astype(np.int32)
    fixed_diag = up.indptr[:-1][fixed].astype(np.int32)
    return zeroed, fixed_diag


# ----------------------------------------------------------------------------------------
# near-null space
# ----------------------------------------------------------------------------------------


def rigid_body_modes(points, fixed=None) -> np.ndarray:
    """Infinitesimal rigid-body motions of a node cloud, the elasticity near-null space.

    Args:
        points: ``(n_nodes, dim)`` positions (rest or current configuration).
        fixed: optional ``(n_nodes*dim,)`` bool Dirichlet mask; those rows are zeroed.

    Returns:
        ``(n_nodes*dim, 3)`` in 2D (2 translations, 1 rotation) or ``(n_nodes*dim, 6)``
        in 3D (3 translations, 3 rotations), node-major rows. Rotations are taken about
        the centroid and scaled by the cloud's size, so all columns have similar norms.
    """
    X = np.asarray(points, dtype=np.float64)
    n, d = X.shape
    if d not in (2, 3):
        raise ValueError(f"points must be (n_nodes, 2) or (n_nodes, 3), got {X.shape}")
    Y = X - X.mean(axis=0)
    scale = float(np.sqrt((Y**2).sum(axis=1).mean())) or 1.0
    Y = Y / scale
    if d == 2:
        B = np.zeros((n, 2, 3))
        B[:, 0, 0] = B[:, 1, 1] = 1.0
        B[:, 0, 2], B[:, 1, 2] = -Y[:, 1], Y[:, 0]
    else:
        B = np.zeros((n, 3, 6))
        B[:, 0, 0] = B[:, 1, 1] = B[:, 2, 2] = 1.0
        x, y, z = Y.T
        B[:, 1, 3], B[:, 2, 3] = -z, y  # rotation about x: e_x × Y
        B[:, 0, 4], B[:, 2, 4] = z, -x  # about y
        B[:, 0, 5], B[:, 1, 5] = -y, x  # about z
    B = B.reshape(n * d, -1)
    if fixed is not None:
        B[np.asarray(fixed, dtype=bool).reshape(-1)] = 0.0
    return B
