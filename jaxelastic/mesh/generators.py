"""Mesh generators: structured rectangles and boxes, Cook's membrane, thick spherical
shells and annuli (the inflation benchmarks), the truncated thick ellipsoid of an idealised
left ventricle.

Each returns a validated :class:`~jaxelastic.mesh.Mesh`; ``order=2`` lifts it to P2 and
``formulation="fbar"``/``"bbar"`` selects F-bar/B-bar (with ``order=1``: the composite
element), see :func:`~jaxelastic.mesh.to_quadratic`.
"""

from __future__ import annotations

import numpy as np

from ..cache import ensure_persistent_cache
from .core import Mesh, check_formulation, from_arrays
from .elements import edge_table
from .quadratic import to_quadratic

__all__ = [
    "rectangle",
    "box",
    "cook_membrane",
    "spherical_shell",
    "annulus",
    "truncated_ellipsoid",
    "ellipsoid_surfaces",
]


def _check_counts(**counts):
    for k, v in counts.items():
        if int(v) != v or v < 1:
            raise ValueError(f"{k} must be a positive integer, got {v!r}")


def _check_extent(size, origin, d: int) -> tuple[np.ndarray, np.ndarray]:
    """``size`` and ``origin`` as ``(d,)`` float arrays, or a ValueError naming the one
    of the wrong length or with a bad value (sizes must be finite and > 0)."""
    out = []
    for name, v in (("size", size), ("origin", origin)):
        a = np.asarray(v, dtype=np.float64)
        if a.shape != (d,):
            raise ValueError(f"{name} must have {d} entries (one per axis), got {v!r}")
        if not np.all(np.isfinite(a)) or (name == "size" and not np.all(a > 0)):
            what = "finite and > 0" if name == "size" else "finite"
            raise ValueError(f"{name} entries must be {what}, got {v!r}")
        out.append(a)
    return out[0], out[1]


def rectangle(
    nx: int,
    ny: int,
    size=(1.0, 1.0),
    origin=(0.0, 0.0),
    *,
    order: int = 1,
    formulation: str = "standard",
    **kw,
) -> Mesh:
    """Structured triangle mesh of a rectangle: ``nx × ny`` cells, 2 triangles each.

    Args:
        nx, ny: cells along x and y.
        size: ``(Lx, Ly)`` [length].
        origin: lower-left corner.
        order, formulation: see :func:`_finish` (``order=2`` → ``tri6``;
            ``formulation="fbar"`` with order 1 → composite ``tri3x4``).

    Returns:
        For the default order 1, a ``tri3`` mesh with ``(nx+1)(ny+1)`` nodes and
        ``2·nx·ny`` triangles. Node ``i + (nx+1)·j`` sits at ``origin + (i·Lx/nx, j·Ly/ny)``.
    """
    _check_counts(nx=nx, ny=ny)
    size, origin = _check_extent(size, origin, 2)
    x = np.linspace(0.0, size[0], nx + 1) + origin[0]
    y = np.linspace(0.0, size[1], ny + 1) + origin[1]
    X, Y = np.meshgrid(x, y, indexing="xy")
    pts = np.stack([X.ravel(), Y.ravel()], axis=1)
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="xy")
    n0 = (i + (nx + 1) * j).ravel()
    n1, n2, n3 = n0 + 1, n0 + nx + 2, n0 + nx + 1
    tris = np.concatenate([np.stack([n0, n1, n2], 1), np.stack([n0, n2, n3], 1)])
    return _finish(pts, tris, "tri3", order, formulation, kw)


# Kuhn (Freudenthal) subdivision of the unit cube along the main diagonal 0→7: six tets,
# positively oriented. Corner c = bx + 2·by + 4·bz.
_KUHN = np.array(
    [[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]]
)


def box(
    nx: int,
    ny: int,
    nz: int,
    size=(1.0, 1.0, 1.0),
    origin=(0.0, 0.0, 0.0),
    *,
    order: int = 1,
    formulation: str = "standard",
    **kw,
) -> Mesh:
    """Structured tetrahedral mesh of a box: ``nx·ny·nz`` cubes, 6 conforming tets each.

    Each cube is split into six tets along a diagonal (Kuhn/Freudenthal); the split is
    mirrored in alternate cubes along each axis so the mesh has no preferred direction.

    Args:
        nx, ny, nz: cells along each axis.
        size: ``(Lx, Ly, Lz)`` [length].
        origin: the minimum corner.
        order, formulation: see :func:`_finish` (``order=2`` → ``tet10``;
            ``formulation="fbar"`` with order 1 → composite ``tet4x8``).

    Returns:
        For the default order 1, a ``tet4`` mesh with ``(nx+1)(ny+1)(nz+1)`` nodes and
        ``6·nx·ny·nz`` tets; node ``i + (nx+1)(j + (ny+1)k)`` sits at
        ``origin + (i·Lx/nx, j·Ly/ny, k·Lz/nz)``.
    """
    _check_counts(nx=nx, ny=ny, nz=nz)
    size, origin = _check_extent(size, origin, 3)
    axes = [np.linspace(0.0, size[a], n + 1) + origin[a] for a, n in enumerate((nx, ny, nz))]
    Z, Y, X = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)

    def node(i, j, k):
        return i + (nx + 1) * (j + (ny + 1) * k)

    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    i, j, k = i.ravel(), j.ravel(), k.ravel()
    # Mirror the Kuhn split in every other cube along each axis (corner bit b -> b xor
    # parity): the mesh stays conforming (neighbours across a face share its mirror state
    # in the two in-face axes, so they split that face along the same diagonal) and has no
    # preferred diagonal direction, so a symmetric load gives a symmetric response.
    pi, pj, pk = i & 1, j & 1, k & 1
    corners = np.stack(
        [
            node(
                i + ((c & 1) ^ pi),
                j + (((c >> 1) & 1) ^ pj),
                k + (((c >> 2) & 1) ^ pk),
            )
            for c in range(8)
        ],
        axis=1,
    )
    tets = corners[:, _KUHN]  # (cubes, 6, 4)
    flip = ((pi + pj + pk) & 1).astype(bool)  # an odd number of mirrors reverses orientation
    tets[flip] = tets[flip][:, :, [0, 2, 1, 3]]
    tets = tets.reshape(-1, 4)
    return _finish(pts, tets, "tet4", order, formulation, kw)


def cook_membrane(n: int, *, order: int = 1, formulation: str = "standard", **kw) -> Mesh:
    """Cook's membrane: the trapezoid (0,0), (48,44), (48,60), (0,44), ``n × n`` quads split
    into ``2n²`` triangles.

    The left edge ``x = 0`` is the clamped side, the right edge ``x = 48`` the loaded one;
    node ``i + (n+1)·j`` is at parameter ``(i/n, j/n)``, so the loaded-edge mid-point
    (48, 52) is a node when ``n`` is even (for ``order=2`` always: the mid-edge node of
    the middle edge). ``order``/``formulation`` as in :func:`_finish`. See Cook (1974);
    REFERENCES "Cook's membrane".
    """
    _check_counts(n=n)
    s = np.linspace(0.0, 1.0, n + 1)
    S, T = np.meshgrid(s, s, indexing="xy")
    S, T = S.ravel(), T.ravel()
    x = 48.0 * S
    y_bot = 44.0 * S
    y_top = 44.0 + 16.0 * S
    y = y_bot + T * (y_top - y_bot)
    pts = np.stack([x, y], 1)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="xy")
    n0 = (i + (n + 1) * j).ravel()
    n1, n2, n3 = n0 + 1, n0 + n + 2, n0 + n + 1
    tris = np.concatenate([np.stack([n0, n1, n2], 1), np.stack([n0, n2, n3], 1)])
    return _finish(pts, tris, "tri3", order, formulation, kw)


def _merge(pts: np.ndarray, cells: np.ndarray, scale: float):
    """Merge coincident points (rounded to 1e-9 of ``scale``): ``(points, cells)``."""
    key = np.round(pts / (1e-9 * scale)).astype(np.int64)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return pts[first], inv.ravel()[cells]


def _oriented(pts: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """P1 cells with negative measure reoriented (first two corners swapped after vertex 0)."""
    D = pts[cells[:, 1:]] - pts[cells[:, :1]]  # (c, d, d)
    neg = np.linalg.det(D) < 0
    cells = cells.copy()
    cells[neg, 1], cells[neg, 2] = cells[neg, 2], cells[neg, 1].copy()
    return cells


def _curved(m: Mesh, order: int, formulation: str) -> Mesh:
    """Lift a P1 mesh of a shell centred at the origin; the mid-edge nodes of P2 moved to
    the mean radius of the edge's ends along their own direction (a curved, isoparametric
    boundary: the P2 volume error is then O(h⁴), not the straight-edged O(h²))."""
    if order == 1:  # P1, or the composite element (straight edges)
        if formulation == "standard":
            return m
        return to_quadratic(m, composite=True, formulation=formulation)
    q = to_quadratic(m, formulation=formulation)
    if order == 1:
        return q
    cells = np.asarray(q.cells)
    X = np.asarray(q.points, dtype=np.float64).copy()
    loc = edge_table(m.element_type)  # (e, 2) corner pairs of the P1 cell
    d = m.dim
    ends = cells[:, loc]  # (c, e, 2)
    mids = cells[:, d + 1 :]  # (c, e) the mid-edge nodes, in edge order
    r = np.linalg.norm(X[ends], axis=-1).mean(axis=-1)  # (c, e)
    dirs = X[mids] / np.linalg.norm(X[mids], axis=-1, keepdims=True)
    X[mids.ravel()] = (r[..., None] * dirs).reshape(-1, d)
    return from_arrays(
        X, cells, q.element, orient="refuse", dtype=q.points.dtype, formulation=formulation
    )


def spherical_shell(
    inner: float,
    outer: float,
    n: int,
    n_r: int,
    *,
    octant: bool = True,
    order: int = 1,
    formulation: str = "standard",
    **kw,
) -> Mesh:
    """Tetrahedral mesh of a thick spherical shell ``inner ≤ |X| ≤ outer`` centred at 0.

    The octant ``X ≥ 0`` (or the whole shell, its eight mirror images) is the radial
    projection of three faces of the cube (equiangular "cubed sphere": each face an
    ``n × n`` grid, ``tan`` spacing), ``n_r`` layers through the wall, each hexahedron
    split into 6 tets like :func:`box`. ``order=2``: mid-edge nodes on the spheres (curved
    facets). The octant's cut faces lie on the planes ``X_i = 0``.

    Args:
        inner, outer: radii ``0 < inner < outer`` [length].
        n: cells along each cube-face edge (an octant has ``3 n²`` per layer).
        n_r: layers through the wall.
        octant: the octant only (default) or the whole shell.
        order, formulation: as in :func:`rectangle`.
    """
    _check_counts(n=n, n_r=n_r)
    if not 0 < inner < outer or not np.isfinite(outer):
        raise ValueError(f"need 0 < inner < outer, got inner={inner!r}, outer={outer!r}")
    base = box(n, n, n_r, size=(1.0, 1.0, 1.0))
    P = np.asarray(base.points, dtype=np.float64)
    cells = np.asarray(base.cells, dtype=np.int64)
    t = np.tan(0.25 * np.pi * P[:, :2])  # equiangular face coordinates in [0, 1]
    rad = inner + (outer - inner) * P[:, 2]
    pts, cls = [], []
    for face in range(3):  # the cube faces X_face = 1 of the octant
        q = np.insert(t, face, 1.0, axis=1)
        q = q / np.linalg.norm(q, axis=1, keepdims=True) * rad[:, None]
        cls.append(cells + sum(len(p) for p in pts))
        pts.append(q)
    X, C = _merge(np.concatenate(pts), np.concatenate(cls), outer)
    if not octant:
        signs = np.array([[sx, sy, sz] for sx in (1, -1) for sy in (1, -1) for sz in (1, -1)])
        X, C = _merge(
            np.concatenate([X * sg for sg in signs]),
            np.concatenate([C + i * len(X) for i in range(8)]),
            outer,
        )
    m = from_arrays(X, _oriented(X, C), "tet4", **kw)
    return _curved(m, order, formulation)


def annulus(
    inner: float,
    outer: float,
    n_theta: int,
    n_r: int,
    *,
    quarter: bool = True,
    order: int = 1,
    formulation: str = "standard",
    **kw,
) -> Mesh:
    """Triangle mesh of the annulus ``inner ≤ |X| ≤ outer`` (a thick tube's cross-section).

    The quarter ``X ≥ 0`` (cut edges on ``x = 0`` and ``y = 0``) or the whole ring:
    ``n_theta`` cells around (per quarter), ``n_r`` through the wall. ``order=2``:
    mid-edge nodes on the circles. ``order``/``formulation`` as in :func:`rectangle`.
    """
    _check_counts(n_theta=n_theta, n_r=n_r)
    if not 0 < inner < outer or not np.isfinite(outer):
        raise ValueError(f"need 0 < inner < outer, got inner={inner!r}, outer={outer!r}")
    nt = n_theta if quarter else 4 * n_theta
    base = rectangle(nt, n_r)
    P = np.asarray(base.points, dtype=np.float64)
    th = P[:, 0] * (0.5 * np.pi if quarter else 2.0 * np.pi)
    r = inner + (outer - inner) * P[:, 1]
    X = np.stack([r * np.cos(th), r * np.sin(th)], axis=1)
    X, C = _merge(X, np.asarray(base.cells, dtype=np.int64), outer)
    m = from_arrays(X, _oriented(X, C), "tri3", **kw)
    return _curved(m, order, formulation)


def _check_radii(endo, epi, base: float) -> tuple[tuple[float, float], tuple[float, float]]:
    """``endo``, ``epi`` as float pairs ``(r_short, r_long)``, or a ValueError unless
    ``0 < endo < epi`` in both radii and the base plane cuts every layer below its equator
    and above its apex (``|base| < r_long``)."""
    out = []
    for name, r in (("endo", endo), ("epi", epi)):
        a = np.asarray(r, dtype=np.float64)
        if a.shape != (2,) or not np.all(np.isfinite(a)) or not np.all(a > 0):
            raise ValueError(f"{name} must be two finite radii > 0 (r_short, r_long), got {r!r}")
        out.append((float(a[0]), float(a[1])))
    (a0, b0), (a1, b1) = out
    if not (a0 < a1 and b0 < b1):
        raise ValueError(f"need endo < epi in both radii, got endo={endo!r}, epi={epi!r}")
    if not (np.isfinite(base) and -b0 < base < b0):
        raise ValueError(
            f"the base plane z = {base!r} must cut the endocardium: need |base| < {b0!r}"
        )
    return out[0], out[1]


def _ellipsoid_map(s, v, t, endo, epi, base: float) -> np.ndarray:
    """Points ``(n, 3)`` at parameters ``s`` (0 apex … 1 base), ``v`` (around) and ``t``
    (0 endocardium … 1 epicardium): radii interpolated linearly in t, the angle
    ``u = −π + s (u_b(t) + π)`` with ``u_b(t) = −arccos(base / r_long(t))``, so s = 1 lies
    on the base plane ``z = base`` in every layer and s = 0 on the axis (both set exactly)."""
    (a0, b0), (a1, b1) = endo, epi
    rs, rl = a0 + t * (a1 - a0), b0 + t * (b1 - b0)
    u = -np.pi + s * (np.pi - np.arccos(base / rl))
    z = np.where(s == 1.0, base, rl * np.cos(u))
    rho = np.where(s == 0.0, 0.0, rs * np.sin(u))  # the apex on the axis, exactly
    return np.stack([rho * np.cos(v), rho * np.sin(v), z], axis=1)


def truncated_ellipsoid(
    n_u: int,
    n_v: int,
    n_t: int,
    *,
    endo=(7.0, 17.0),
    epi=(10.0, 20.0),
    base: float = 5.0,
    order: int = 1,
    formulation: str = "standard",
    **kw,
) -> Mesh:
    """Tetrahedral mesh of a thick prolate ellipsoid (long axis z) cut by the plane
    ``z = base``: the idealised left ventricle of Land et al. (2015, *Proc. R. Soc. A*
    471:20150641, problems 2 and 3; the defaults are its radii in mm).

    Each layer ``t ∈ [0, 1]`` is the ellipsoid of radii ``endo + t (epi − endo)``
    (``(r_short, r_long)``), ``X = (r_s sin u cos v, r_s sin u sin v, r_l cos u)`` with
    ``u ∈ [−π, −arccos(base / r_l)]`` (its own range per layer: the base is the plane
    ``z = base`` on every layer, the apex ``u = −π`` the point ``(0, 0, −r_l)``) and
    ``v ∈ [−π, π)``. The layers are the surfaces of constant transmural coordinate of
    :func:`jaxelastic.materials.transmural_coordinate`, so the helix fibre rule reads t
    off the mesh. The surface grid is ``n_u`` steps in u (uniform, apex to base) by ``n_v``
    around: ``n_v`` triangles at the apex (a fan around its node, so the apex is a line of
    ``n_t + 1`` nodes on the axis) and two triangles per quadrilateral elsewhere (the
    diagonals alternate); each triangle is extruded through ``n_t`` layers into prisms of
    three tets, split by the node numbers so neighbouring prisms share their face diagonals.
    ``order=2``: the mid-edge nodes at the parametric midpoints, on the ellipsoids and the
    base plane (curved, isoparametric facets). The composite element (``order=1`` with
    F-bar/B-bar) keeps them at the straight edges' midpoints (curving them inverts sub-tets
    of coarse meshes).

    Args:
        n_u: cells from the apex to the base (≥ 1).
        n_v: cells around the axis (≥ 3).
        n_t: layers through the wall (≥ 1).
        endo, epi: ``(r_short, r_long)`` of the inner and outer surfaces [length],
            ``endo < epi`` in both.
        base: the base plane's z [length], ``|base| < endo[1]``.
        order, formulation: as in :func:`rectangle`.

    Returns:
        ``(n_t + 1)(1 + n_u n_v)`` P1 nodes and ``3 n_t n_v (2 n_u − 1)`` tets; node
        ``k (1 + n_u n_v) + 0`` is the apex of layer k, node ``k (1 + n_u n_v) + 1 +
        (i − 1) n_v + j`` the point at ``s = i/n_u``, ``v = −π + 2π j/n_v``, ``t = k/n_t``.
        :func:`ellipsoid_surfaces` selects the endocardium, epicardium and base facets.
    """
    _check_counts(n_u=n_u, n_v=n_v, n_t=n_t)
    if n_v < 3:
        raise ValueError(f"n_v must be at least 3, got {n_v!r}")
    if order not in (1, 2):
        raise ValueError(f"order must be 1 or 2, got {order!r}")
    check_formulation(formulation)
    endo, epi = _check_radii(endo, epi, float(base))
    base = float(base)
    ensure_persistent_cache()  # the library's default cache, before the first compile
    tets, svt = _ellipsoid_grid(n_u, n_v, n_t)
    s3, v3, t3 = svt.T
    X = _ellipsoid_map(s3, v3, t3, endo, epi, base)
    m = from_arrays(X, _oriented(X, tets), "tet4", **kw)
    if order == 1:  # P1, or the composite element (straight edges)
        if formulation == "standard":
            return m
        return to_quadratic(m, composite=True, formulation=formulation)
    return _curved_ellipsoid(m, svt, endo, epi, base, formulation)


def _ellipsoid_grid(n_u: int, n_v: int, n_t: int) -> tuple[np.ndarray, np.ndarray]:
    """The ventricle's topology: ``(tets, svt)`` — the tets ``(c, 4)`` and each node's
    parameters ``svt`` ``(n, 3)`` (s, v, t of :func:`_ellipsoid_map`), numbered as
    :func:`truncated_ellipsoid` documents."""
    # the surface grid: the apex, then rings i = 1 … n_u of n_v nodes
    ring_s = np.repeat(np.arange(1, n_u + 1) / n_u, n_v)
    ring_v = np.tile(-np.pi + 2.0 * np.pi * np.arange(n_v) / n_v, n_u)
    s2 = np.concatenate([[0.0], ring_s])
    v2 = np.concatenate([[0.0], ring_v])
    n2 = s2.size

    def ring(i, j):
        return 1 + (i - 1) * n_v + (j % n_v)

    j = np.arange(n_v)
    tris = [np.stack([np.zeros(n_v, np.int64), ring(1, j), ring(1, j + 1)], axis=1)]
    i, j = (a.ravel() for a in np.meshgrid(np.arange(1, n_u), np.arange(n_v), indexing="ij"))
    a, b, c, d = ring(i, j), ring(i, j + 1), ring(i + 1, j + 1), ring(i + 1, j)
    alt = ((i + j) & 1).astype(bool)  # alternate the quadrilaterals' diagonals
    t1 = np.where(alt[:, None], np.stack([a, b, c], 1), np.stack([a, b, d], 1))
    t2 = np.where(alt[:, None], np.stack([a, c, d], 1), np.stack([b, c, d], 1))
    tris = np.sort(np.concatenate(tris + [t1, t2]), axis=1)  # (m, 3), a < b < c
    # extrude: prism (a, b, c) → (a', b', c') one layer up, three tets; on the side face of
    # a pair p < q the diagonal runs from p to q' whichever prism it belongs to (conforming)
    k = np.arange(n_t)
    lo = (tris[None, :, :] + (k * n2)[:, None, None]).reshape(-1, 3)
    hi = lo + n2
    A, B, Cc = lo.T
    A1, B1, C1 = hi.T
    tets = np.concatenate(
        [np.stack([A, B, Cc, C1], 1), np.stack([A, B, B1, C1], 1), np.stack([A, A1, B1, C1], 1)]
    )
    t3 = np.repeat(np.arange(n_t + 1) / n_t, n2)
    s3, v3 = np.tile(s2, n_t + 1), np.tile(v2, n_t + 1)
    return tets, np.stack([s3, v3, t3], axis=1)


def _curved_ellipsoid(m: Mesh, svt: np.ndarray, endo, epi, base: float, formulation: str):
    """P2 lift of the P1 ventricle ``m`` whose nodes have the parameters ``svt`` ``(n, 3)``
    (s, v, t of :func:`_ellipsoid_map`): each mid-edge node at the parametric midpoint of
    its edge (on the ellipsoids and the base plane: curved, isoparametric facets)."""
    s3, v3, t3 = svt.T
    q = to_quadratic(m, formulation=formulation)
    cells = np.asarray(q.cells)
    ends = cells[:, :4][:, edge_table(m.element_type)].reshape(-1, 2)  # (c·6, 2)
    mids = cells[:, 4:].reshape(-1)
    first = np.unique(mids, return_index=True)[1]
    mids, ends = mids[first], ends[first]
    sa, sb = s3[ends[:, 0]], s3[ends[:, 1]]
    va, vb = v3[ends[:, 0]], v3[ends[:, 1]]
    va = np.where(sa == 0.0, vb, va)  # an apex node takes the other end's angle
    vb = np.where(sb == 0.0, va, vb)
    dv = np.mod(vb - va + np.pi, 2.0 * np.pi) - np.pi  # across v = ±π the short way
    Xq = np.asarray(q.points, dtype=np.float64).copy()
    Xq[mids] = _ellipsoid_map(
        0.5 * (sa + sb), va + 0.5 * dv, t3[ends].mean(axis=1), endo, epi, base
    )
    return from_arrays(
        Xq, cells, q.element, orient="refuse", dtype=q.points.dtype, formulation=formulation
    )


def ellipsoid_surfaces(
    mesh: Mesh, *, endo=(7.0, 17.0), epi=(10.0, 20.0), base: float = 5.0, tol: float = 1e-9
) -> dict[str, np.ndarray]:
    """The boundary facets of a :func:`truncated_ellipsoid` mesh by surface.

    A facet belongs to a surface when its corners lie on it within ``tol`` relative:
    ``ρ²/r_s² + z²/r_l² = 1`` for the endocardium and epicardium (radii ``endo``, ``epi``),
    ``z = base`` for the base.

    Returns:
        ``{"endocardium": ..., "epicardium": ..., "base": ...}``, each ``(m, k)`` facets
        oriented with the body's outward normal (:func:`~jaxelastic.mesh.boundary_facets`).

    Raises:
        ValueError: a surface without facets, or boundary facets on none of the three
            (not a truncated ellipsoid with these radii and base).
    """
    from .boundary import boundary_facets

    (a0, b0), (a1, b1) = _check_radii(endo, epi, float(base))
    X = np.asarray(mesh.points, dtype=np.float64)
    rho2, z = X[:, 0] ** 2 + X[:, 1] ** 2, X[:, 2]
    on = {
        "endocardium": np.abs(rho2 / a0**2 + z**2 / b0**2 - 1.0) <= tol * 10.0,
        "epicardium": np.abs(rho2 / a1**2 + z**2 / b1**2 - 1.0) <= tol * 10.0,
        "base": np.abs(z - base) <= tol * max(b1, abs(base)),
    }
    facets = boundary_facets(mesh)
    out, seen = {}, np.zeros(len(facets), dtype=bool)
    for name, mask in on.items():
        sel = mask[facets[:, : mesh.dim]].all(axis=1)  # the corners
        if not sel.any():
            raise ValueError(f"the mesh has no boundary facet on the {name}")
        out[name] = facets[sel]
        seen |= sel
    if not seen.all():
        raise ValueError(
            f"{int((~seen).sum())} boundary facets lie on none of the endocardium, "
            "epicardium and base (radii endo, epi and base must be the mesh's)"
        )
    return out


def _finish(pts, cells, p1: str, order: int, formulation: str, kw) -> Mesh:
    """Build the generator's mesh: P1 for ``order=1``; ``order=2`` → P2 (``tri6``/``tet10``);
    ``formulation="fbar"`` (or ``"bbar"``) with order 1 → the composite element
    (``tri3x4``/``tet4x8``, P1 displacements on the P2 node set with one volume constraint
    per cell), with order 2 → P2 + F-bar (B-bar)."""
    if order not in (1, 2):
        raise ValueError(f"order must be 1 or 2, got {order!r}")
    check_formulation(formulation)
    ensure_persistent_cache()  # the library's default cache, before the first compile
    m = from_arrays(pts, cells, p1, **kw)
    if order == 1 and formulation == "standard":
        return m
    return to_quadratic(m, composite=order == 1, formulation=formulation)
