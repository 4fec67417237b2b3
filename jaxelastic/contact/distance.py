"""Unsigned squared distances between boundary primitives, for self-contact.

IPC (Li et al. 2020, "Incremental Potential Contact", ACM TOG 39(4), §4 and its
supplement) writes the distance of a point–triangle or edge–edge pair as the distance of
one of a few simpler pairs, chosen by where the closest points lie:

* point–triangle: point–point (closest point a triangle corner), point–edge (on a side,
  distance to the side's *line*) or point–plane (inside: distance to the triangle's plane);
* edge–edge: point–point, point–edge or line–line (both closest points interior);
* 2D point–edge: point–point or point–line.

Each formula is a smooth (rational) function of the coordinates, equal to the true
distance in its region, so the chosen distance is C¹ across region boundaries and
autodiff gives exact gradients and Hessians inside every region (the Hessian jumps at a
boundary, as in IPC). The case is an integer computed from the positions (no
derivative). Near-parallel edges make the line–line formula ill-conditioned (and its
Hessian unbounded); IPC multiplies the edge–edge barrier by the mollifier
:func:`edge_edge_mollifier` of ``c = ‖e_a × e_b‖²`` (Li et al. 2020, §4.3, eq. 23):
``m(c) = −c²/ε_×² + 2c/ε_×`` for ``c < ε_× = 10⁻³‖ē_a‖²‖ē_b‖²`` (rest lengths), 1 beyond.

Every function takes coordinates ``(dim,)`` [m] and returns a scalar: squared distances
[m²], the mollifier [1].
"""

from __future__ import annotations

import jax.numpy as jnp

__all__ = [
    "point_point_d2",
    "point_line_d2",
    "point_plane_d2",
    "line_line_d2",
    "point_triangle_case",
    "point_triangle_d2",
    "edge_edge_case",
    "edge_edge_d2",
    "point_edge_case_2d",
    "point_edge_d2_2d",
    "edge_cross2",
    "edge_edge_mollifier",
    "mollifier_eps",
    "MOLLIFIER_REL",
]

MOLLIFIER_REL = 1e-3
"""ε_× = MOLLIFIER_REL · ‖ē_a‖²‖ē_b‖² (IPC's choice, rest edge lengths)."""


def _dot(a, b):
    return jnp.sum(a * b, axis=-1)


def _cross2(a, b):
    """z-component of the 2D cross product (scalar)."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _safe_div(a, b):
    ok = b > 0
    return jnp.where(ok, a / jnp.where(ok, b, 1.0), 0.0)


def point_point_d2(p, a):
    """‖p − a‖² [m²]."""
    v = p - a
    return _dot(v, v)


def point_line_d2(p, a, b):
    """Squared distance [m²] of ``p`` to the *line* through ``a``, ``b`` (2D or 3D)."""
    e, v = b - a, p - a
    if p.shape[-1] == 2:
        c = _cross2(e, v)
        return _safe_div(c * c, _dot(e, e))
    c = jnp.cross(e, v)
    return _safe_div(_dot(c, c), _dot(e, e))


def point_plane_d2(p, a, b, c):
    """Squared distance [m²] of ``p`` to the plane through ``a, b, c`` (3D)."""
    n = jnp.cross(b - a, c - a)
    s = _dot(n, p - a)
    return _safe_div(s * s, _dot(n, n))


def line_line_d2(a0, a1, b0, b1):
    """Squared distance [m²] between the infinite lines through ``a0 a1`` and ``b0 b1``
    (3D; 0 for parallel lines, where the mollifier switches the pair off)."""
    n = jnp.cross(a1 - a0, b1 - b0)
    s = _dot(n, b0 - a0)
    return _safe_div(s * s, _dot(n, n))


# -------------------------------------------------------------------- point–triangle
# cases: 0–2 point–corner (t0, t1, t2), 3–5 point–side (t0t1, t1t2, t2t0), 6 point–plane


def point_triangle_case(p, t0, t1, t2):
    """Which distance is the point–triangle distance (int32 ``()`` in 0..6): 0–2 corners
    t0/t1/t2, 3–5 sides t0t1/t1t2/t2t0, 6 the interior (Ericson 2004, "Real-Time
    Collision Detection", §5.1.5, closest point on a triangle)."""
    ab, ac, ap = t1 - t0, t2 - t0, p - t0
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    bp = p - t1
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    cp = p - t2
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4
    case = jnp.asarray(6, jnp.int32)
    # later tests take precedence: write them in reverse order of Ericson's returns
    case = jnp.where((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), 4, case)  # side t1t2
    case = jnp.where((vb <= 0) & (d2 >= 0) & (d6 <= 0), 5, case)  # side t2t0
    case = jnp.where((d6 >= 0) & (d5 <= d6), 2, case)  # corner t2
    case = jnp.where((vc <= 0) & (d1 >= 0) & (d3 <= 0), 3, case)  # side t0t1
    case = jnp.where((d3 >= 0) & (d4 <= d3), 1, case)  # corner t1
    case = jnp.where((d1 <= 0) & (d2 <= 0), 0, case)  # corner t0
    return case.astype(jnp.int32)


# rows of the stacked (p, t0, t1, t2) per case: point–point pair, point–line triple
_PT_PP = ((0, 1), (0, 2), (0, 3), (0, 1), (0, 1), (0, 1), (0, 1))
_PT_PL = ((0, 1, 2),) * 3 + ((0, 1, 2), (0, 2, 3), (0, 3, 1)) + ((0, 1, 2),)


def _by_case(xs, case, pp_rows, pl_rows, pp_cases, pl_cases, last):
    """One formula per kind on the rows the case selects (3 formulas, not one per case:
    a smaller graph to differentiate twice and compile)."""
    pp = jnp.asarray(pp_rows, jnp.int32)[case]
    pl = jnp.asarray(pl_rows, jnp.int32)[case]
    d_pp = point_point_d2(xs[pp[0]], xs[pp[1]])
    d_pl = point_line_d2(xs[pl[0]], xs[pl[1]], xs[pl[2]])
    return jnp.where(case < pp_cases, d_pp, jnp.where(case < pp_cases + pl_cases, d_pl, last))


def point_triangle_d2(p, t0, t1, t2, case=None):
    """Squared point–triangle distance [m²] (3D), by IPC's case split
    (:func:`point_triangle_case` unless ``case`` is given)."""
    case = point_triangle_case(p, t0, t1, t2) if case is None else case
    xs = jnp.stack([p, t0, t1, t2])
    return _by_case(xs, case, _PT_PP, _PT_PL, 3, 3, point_plane_d2(p, t0, t1, t2))


# ------------------------------------------------------------------------- edge–edge
# cases: 0 a0–b0, 1 a0–b1, 2 a1–b0, 3 a1–b1 (points); 4 a0–edge b, 5 a1–edge b,
# 6 b0–edge a, 7 b1–edge a; 8 line–line


def edge_edge_case(a0, a1, b0, b1):
    """Which distance is the segment–segment distance (int32 ``()`` in 0..8), from the
    clamped closest-point parameters (Ericson 2004, §5.1.9; parallel segments take an
    end point of ``a``)."""
    d1, d2, r = a1 - a0, b1 - b0, a0 - b0
    a, e, f = _dot(d1, d1), _dot(d2, d2), _dot(d2, r)
    c, b = _dot(d1, r), _dot(d1, d2)
    denom = a * e - b * b
    parallel = denom <= 1e-14 * a * e
    s = jnp.where(parallel, 0.0, jnp.clip(_safe_div(b * f - c * e, denom), 0.0, 1.0))
    t = _safe_div(b * s + f, e)
    s = jnp.where(t < 0, jnp.clip(_safe_div(-c, a), 0.0, 1.0), s)
    s = jnp.where(t > 1, jnp.clip(_safe_div(b - c, a), 0.0, 1.0), s)
    t = jnp.clip(t, 0.0, 1.0)
    s_in, t_in = (s > 0) & (s < 1), (t > 0) & (t < 1)
    s1, t1 = s >= 1, t >= 1
    pp = jnp.where(s1, 2, 0) + jnp.where(t1, 1, 0)
    case = jnp.where(s_in & t_in, 8, pp)
    case = jnp.where(~s_in & t_in, jnp.where(s1, 5, 4), case)
    case = jnp.where(s_in & ~t_in, jnp.where(t1, 7, 6), case)
    return case.astype(jnp.int32)


_EE_PP = ((0, 2), (0, 3), (1, 2), (1, 3)) + ((0, 2),) * 5
_EE_PL = ((0, 2, 3),) * 4 + ((0, 2, 3), (1, 2, 3), (2, 0, 1), (3, 0, 1)) + ((0, 2, 3),)


def edge_edge_d2(a0, a1, b0, b1, case=None):
    """Squared segment–segment distance [m²] (3D), by IPC's case split
    (:func:`edge_edge_case` unless ``case`` is given)."""
    case = edge_edge_case(a0, a1, b0, b1) if case is None else case
    xs = jnp.stack([a0, a1, b0, b1])
    return _by_case(xs, case, _EE_PP, _EE_PL, 4, 4, line_line_d2(a0, a1, b0, b1))


def edge_cross2(a0, a1, b0, b1):
    """``c = ‖(a1 − a0) × (b1 − b0)‖²`` [m⁴], the mollifier's argument."""
    n = jnp.cross(a1 - a0, b1 - b0)
    return _dot(n, n)


def edge_edge_mollifier(a0, a1, b0, b1, eps_x):
    """IPC's edge–edge mollifier (Li et al. 2020, eq. 23) [1]: ``m(c) = −c²/ε_×² + 2c/ε_×``
    for ``c = ‖e_a × e_b‖² < ε_×`` [m⁴], else 1 (C¹ at c = ε_×, 0 for parallel edges)."""
    c = edge_cross2(a0, a1, b0, b1)
    s = c / eps_x
    return jnp.where(c < eps_x, -s * s + 2 * s, 1.0)


def mollifier_eps(a0, a1, b0, b1, rel: float = MOLLIFIER_REL):
    """``ε_× = rel · ‖ē_a‖² ‖ē_b‖²`` [m⁴] from the *rest* positions of the two edges."""
    return rel * point_point_d2(a1, a0) * point_point_d2(b1, b0)


# ---------------------------------------------------------------------- 2D point–edge
# cases: 0 p–e0, 1 p–e1, 2 p–line


def point_edge_case_2d(p, e0, e1):
    """Which distance is the 2D point–segment distance (int32 ``()``: 0 end e0, 1 end e1,
    2 interior)."""
    e = e1 - e0
    t = _safe_div(_dot(p - e0, e), _dot(e, e))
    return jnp.where(t <= 0, 0, jnp.where(t >= 1, 1, 2)).astype(jnp.int32)


def point_edge_d2_2d(p, e0, e1, case=None):
    """Squared point–segment distance [m²] in 2D (IPC's case split)."""
    case = point_edge_case_2d(p, e0, e1) if case is None else case
    xs = jnp.stack([p, e0, e1])
    return _by_case(xs, case, ((0, 1), (0, 2), (0, 1)), ((0, 1, 2),) * 3, 2, 1, 0.0)
