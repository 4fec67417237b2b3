"""Broad phase of self-contact on the host: a uniform spatial hash in NumPy.

Design: a **uniform-grid spatial hash**, vectorised in NumPy, run on the host between
Newton iterations. Each primitive's axis-aligned box, grown by ``r/2`` on every side (r =
d̂ plus twice the motion bound), is entered into every grid cell it covers (cell size:
the mean box extent, so a box covers 1–2 cells per axis); sorting the (cell, primitive)
keys and one ``searchsorted`` per primitive type give the pairs that share a cell, which
an exact box-overlap test then filters. Why this and not a BVH or sweep and prune:

* the surface meshes here are near-uniform (a FE boundary), where a uniform grid is
  O(n) with no tree to build or refit, and every step is a whole-array NumPy operation
  (sort, searchsorted, repeat) rather than a Python loop over nodes;
* sweep and prune along one axis tests every pair in a slab, O(n^{5/3}) for a 3D
  surface; it is simpler but ~10× more tests at 20k triangles;
* a device version (fixed-size hashing in JAX) would have to size every buffer for the
  worst case at compile time; the candidate count varies by orders of magnitude over a
  fold, so the host builds an exact list and hands a fixed-capacity, padded buffer to the
  jitted energy (capacity grown by powers of 2 with headroom, never shrunk, both kinds
  on one chain of shapes: a re-jit only on growth, :func:`capacity_for`).

Pairs (node indices): 3D point–triangle ``(p, t0, t1, t2)`` and edge–edge
``(a0, a1, b0, b1)``; 2D point–edge ``(p, e0, e1)``. Pairs that share a node are left out
(their distance is zero by construction and adjacent primitives are held apart by the
elasticity). Measured cost: ``scripts/bench_broadphase.py``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = [
    "Surface",
    "surface_of",
    "candidate_pairs",
    "capacity_for",
    "pad_pairs",
    "HEADROOM",
    "MIN_CAPACITY",
]


@dataclasses.dataclass(frozen=True)
class Surface:
    """The boundary primitives of a body (host arrays, int32 node indices).

    Attributes:
        dim: 2 or 3.
        faces: ``(n_f, 3)`` boundary triangles (3D; P2 faces split into 4), ``(0, 3)`` in 2D.
        edges: ``(n_e, 2)`` boundary edges (the triangles' edges in 3D; P2 edges split in 2).
        nodes: ``(m,)`` sorted nodes on them.
    """

    dim: int
    faces: np.ndarray
    edges: np.ndarray
    nodes: np.ndarray


def surface_of(mesh) -> Surface:
    """The :class:`Surface` of a mesh's boundary (``boundary_facets``, outward oriented)."""
    from ..mesh import boundary_facets

    fac = np.asarray(boundary_facets(mesh), dtype=np.int64)
    dim = int(mesh.dim)
    if dim == 2:
        if fac.shape[1] == 3:  # (a, b, mid)
            fac = np.concatenate([fac[:, [0, 2]], fac[:, [2, 1]]])
        edges = fac[:, :2]
        faces = np.zeros((0, 3), np.int64)
    else:
        if fac.shape[1] == 6:  # (a, b, c, m_ab, m_bc, m_ca)
            a, b, c, ab, bc, ca = fac.T
            fac = np.concatenate(
                [np.stack(t, axis=1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))]
            )
        faces = fac[:, :3]
        e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        edges = np.unique(np.sort(e, axis=1), axis=0)
    nodes = np.unique(np.concatenate([edges.ravel(), faces.ravel()]))
    i32 = np.int32
    return Surface(dim, faces.astype(i32), edges.astype(i32), nodes.astype(i32))


CELL_FACTOR = 0.5
"""Grid cell size relative to the mean box extent (measured at 20k triangles: 0.5 is
~2× faster than 1; smaller cells put each box in more cells)."""


def _boxes(x, prims, r):
    p = x[prims]  # (k, q, d)
    return p.min(axis=1) - 0.5 * r, p.max(axis=1) + 0.5 * r


def _cell_keys(lo, hi, h, origin, dims):
    """(box index, cell key) for every grid cell each box covers."""
    c0 = np.floor((lo - origin) / h).astype(np.int64)
    c1 = np.floor((hi - origin) / h).astype(np.int64)
    n = c1 - c0 + 1  # (k, d)
    total = np.prod(n, axis=1)
    box = np.repeat(np.arange(len(lo)), total)
    return box, _ravel(c0, n, box, dims)


def _ravel(c0, n, box, dims):
    total = np.prod(n, axis=1)
    off = np.arange(len(box)) - np.repeat(np.cumsum(total) - total, total)
    d = c0.shape[1]
    coords = []
    for ax in range(d - 1, -1, -1):
        coords.append(c0[box, ax] + off % n[box, ax])
        off = off // n[box, ax]
    coords = coords[::-1]
    key = coords[0]
    for ax in range(1, d):
        key = key * dims[ax] + coords[ax]
    return key


def _pairs_sharing_cells(lo_a, hi_a, lo_b, hi_b, same: bool):
    """Index pairs (ia, ib) of boxes of a and b that overlap (ia < ib if ``same``)."""
    if len(lo_a) == 0 or len(lo_b) == 0:
        z = np.zeros(0, np.int64)
        return z, z
    ext = np.concatenate([hi_a - lo_a, hi_b - lo_b])
    h = max(CELL_FACTOR * float(np.mean(ext.max(axis=1))), 1e-300)
    origin = np.minimum(lo_a.min(axis=0), lo_b.min(axis=0))
    top = np.maximum(hi_a.max(axis=0), hi_b.max(axis=0))
    dims = np.floor((top - origin) / h).astype(np.int64) + 1
    if float(np.prod(dims.astype(np.float64))) > 2.0**62:  # a degenerate spread: coarser
        h = float(np.max(top - origin)) / 2.0**20
        dims = np.floor((top - origin) / h).astype(np.int64) + 1
    box_a, key_a = _cell_keys(lo_a, hi_a, h, origin, dims)
    box_b, key_b = _cell_keys(lo_b, hi_b, h, origin, dims)
    order = np.argsort(key_b, kind="stable")
    kb, bb = key_b[order], box_b[order]
    left = np.searchsorted(kb, key_a, "left")
    cnt = np.searchsorted(kb, key_a, "right") - left
    ia = np.repeat(box_a, cnt)
    cell = np.repeat(key_a, cnt)
    pos = np.repeat(left - np.cumsum(cnt) + cnt, cnt) + np.arange(int(cnt.sum()))
    ib = bb[pos]
    keep = ia < ib if same else np.ones(len(ia), bool)
    ia, ib, cell = ia[keep], ib[keep], cell[keep]
    ok = np.all((lo_a[ia] <= hi_b[ib]) & (lo_b[ib] <= hi_a[ia]), axis=1)
    ia, ib, cell = ia[ok], ib[ok], cell[ok]
    # a pair of overlapping boxes shares every cell of the overlap: report it only in the
    # "home" cell holding the overlap's lower corner (no duplicates, no sort to remove them)
    corner = np.maximum(lo_a[ia], lo_b[ib])
    home = np.floor((corner - origin) / h).astype(np.int64)
    n1 = np.ones_like(home)
    key = _ravel(home, n1, np.arange(len(home)), dims)
    keep = key == cell
    return ia[keep], ib[keep]


def candidate_pairs(x, surf: Surface, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Candidate pairs of ``surf`` at positions ``x`` ``(n, dim)`` [m] whose primitives'
    boxes come within ``radius`` [m] of each other (a superset of every pair closer than
    ``radius``), without pairs that share a node.

    Returns:
        ``(pt, ee)`` int32: 3D ``(k₁, 4)`` point–triangle ``(p, t0, t1, t2)`` and
        ``(k₂, 4)`` edge–edge ``(a0, a1, b0, b1)``; 2D ``(k₁, 3)`` point–edge
        ``(p, e0, e1)`` and an empty ``(0, 4)``.
    """
    x = np.asarray(x, dtype=np.float64)
    r = float(radius)
    pts = surf.nodes[:, None]
    lo_p, hi_p = _boxes(x, pts, r)
    if surf.dim == 2:
        lo_e, hi_e = _boxes(x, surf.edges, r)
        ip, ie = _pairs_sharing_cells(lo_p, hi_p, lo_e, hi_e, same=False)
        p, e = surf.nodes[ip], surf.edges[ie]
        keep = (p != e[:, 0]) & (p != e[:, 1])
        pt = np.concatenate([p[keep, None], e[keep]], axis=1).astype(np.int32)
        return pt, np.zeros((0, 4), np.int32)
    lo_f, hi_f = _boxes(x, surf.faces, r)
    ip, jf = _pairs_sharing_cells(lo_p, hi_p, lo_f, hi_f, same=False)
    p, f = surf.nodes[ip], surf.faces[jf]
    keep = np.all(f != p[:, None], axis=1)
    pt = np.concatenate([p[keep, None], f[keep]], axis=1).astype(np.int32)
    lo_e, hi_e = _boxes(x, surf.edges, r)
    ia, ib = _pairs_sharing_cells(lo_e, hi_e, lo_e, hi_e, same=True)
    ea, eb = surf.edges[ia], surf.edges[ib]
    keep = np.all(ea[:, :, None] != eb[:, None, :], axis=(1, 2))
    ee = np.concatenate([ea[keep], eb[keep]], axis=1).astype(np.int32)
    return pt, ee


HEADROOM = 2.0
"""A buffer that grows is sized for at least this multiple of the pairs it must hold."""

MIN_CAPACITY = (1024, 2048)
"""Smallest point–primitive and edge–edge capacities (level 0; about 1:2.5 is the ratio of
the two counts on a triangulated surface)."""


def capacity_for(
    counts: tuple[int, int],
    current: tuple[int, int] = (0, 0),
    bounds: tuple[int, int] | None = None,
) -> tuple[int, int]:
    """Buffer capacities ``(C₁, C₂)`` for ``counts`` ``(k₁, k₂)`` point–primitive and
    edge–edge pairs: ``current`` if both fit, else level L's
    ``min(MIN_CAPACITY_i·2^L, bounds_i)`` for the smallest L at or above the current one
    with room for :data:`HEADROOM` × the counts. One level for both kinds: the capacities
    move along one chain of shapes (each a re-jit of what takes the buffer), never shrink,
    and stop at ``bounds`` (the numbers of all possible pairs, default unbounded)."""
    k = tuple(int(c) for c in counts)
    cur = tuple(int(c) for c in current)
    if all(a <= b for a, b in zip(k, cur, strict=True)):
        return cur[0], cur[1]
    big = 1 << 62
    bd = (big, big) if bounds is None else tuple(int(b) for b in bounds)

    def at(level: int) -> tuple[int, ...]:
        return tuple(min(m << level, b) for m, b in zip(MIN_CAPACITY, bd, strict=True))

    level = 0
    while any(c < min(a, b) for c, a, b in zip(at(level), cur, bd, strict=True)):
        level += 1  # the current level: capacities never shrink
    want = tuple(min(int(np.ceil(HEADROOM * c)), b) for c, b in zip(k, bd, strict=True))
    while any(c < w for c, w in zip(at(level), want, strict=True)):
        level += 1
    c1, c2 = at(level)
    return c1, c2


def pad_pairs(pairs: np.ndarray, capacity: int) -> tuple[np.ndarray, np.ndarray]:
    """``(padded (capacity, q) int32, valid (capacity,) bool)``; padding rows are node 0."""
    k, q = pairs.shape
    out = np.zeros((capacity, q), np.int32)
    out[:k] = pairs
    valid = np.zeros(capacity, bool)
    valid[:k] = True
    return out, valid
