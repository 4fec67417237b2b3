"""Cantilevers: the 2D Timoshenko–Goodier beam (exact field) and a 3D tet beam.

* :func:`timoshenko_cantilever`: plane stress, L = 48, D = 12, E = 3·10⁷, ν = 0.3,
  parabolic end shear P = 1000 (Timoshenko & Goodier 1970, *Theory of Elasticity*, §21).
  The exact field :func:`timoshenko_exact` is imposed on x = 0, so the FE solution can be
  scored in the L2 and energy norms; tip u_y = PL³/(3EI) + (4+5ν)PL/(2ED) = 0.0089.
* :func:`cantilever3d`: a 10 × 1 × 1 tet beam clamped at x = 0, uniform shear totalling P
  on x = L, against Timoshenko beam theory :func:`beam_deflection`
  δ = PL³/(3EI) + PL/(κGA), κ = 10(1+ν)/(12+11ν) (Cowper 1966, J. Appl. Mech. 33:335).
  P1 tets shear-lock (≈ 22 %, 50 %, 79 %, 93 % of δ with 1, 2, 4, 8 cells through the depth).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .. import loads
from ..materials import Lame, lame, linear
from ..mechanics.potential import Potential
from ..mesh import box, rectangle
from .problem import Benchmark, edge_load_2d

__all__ = [
    "TIMOSHENKO",
    "CANTILEVER3D",
    "timoshenko_exact",
    "timoshenko_cantilever",
    "beam_deflection",
    "cantilever3d",
]

# Timoshenko & Goodier plane-stress beam: length, depth, Young's modulus, ν, end load
TIMOSHENKO = dict(L=48.0, D=12.0, E=3.0e7, nu=0.3, P=1000.0)
# 3D tet beam: length, square section side, Young's modulus, ν, end load
CANTILEVER3D = dict(L=10.0, D=1.0, E=1000.0, nu=0.3, P=1.0)


def timoshenko_exact(X, L=48.0, D=12.0, E=3.0e7, nu=0.3, P=1000.0):
    """Exact plane-stress displacement of the end-loaded cantilever.

    Origin at the mid-depth of x = 0, load P upward at x = L (Timoshenko & Goodier 1970,
    §21): u_x = −Py/(6EI)[(6L−3x)x + (2+ν)(y² − D²/4)],
    u_y = P/(6EI)[3νy²(L−x) + (4+5ν)D²x/4 + (3L−x)x²].

    Args:
        X: ``(k, 2)`` points [length].

    Returns:
        ``(u (k, 2), ∂u_i/∂X_j (k, 2, 2))``.
    """
    x, y = X[:, 0], X[:, 1]
    I = D**3 / 12.0
    c = P / (6.0 * E * I)
    ux = -c * y * ((6 * L - 3 * x) * x + (2 + nu) * (y**2 - D**2 / 4))
    uy = c * (3 * nu * y**2 * (L - x) + (4 + 5 * nu) * D**2 * x / 4 + (3 * L - x) * x**2)
    g = np.empty((x.size, 2, 2))
    g[:, 0, 0] = -c * y * (6 * L - 6 * x)
    g[:, 0, 1] = -c * ((6 * L - 3 * x) * x + (2 + nu) * (3 * y**2 - D**2 / 4))
    g[:, 1, 0] = c * (-3 * nu * y**2 + (4 + 5 * nu) * D**2 / 4 + 6 * L * x - 3 * x**2)
    g[:, 1, 1] = c * 6 * nu * y * (L - x)
    return np.stack([ux, uy], 1), g


def timoshenko_cantilever(k: int, **mesh_kw) -> Benchmark:
    """Timoshenko–Goodier cantilever on a ``4k × k`` rectangle mesh: exact field on x = 0,
    parabolic shear traction τ = P/(2I)(D²/4 − y²) on x = L (consistent nodal forces).

    Probe ``"tip"``: the nodes of x = L (their exact u_y does not depend on y), reference
    ``"u_y"`` the exact tip deflection; ``exact`` is :func:`timoshenko_exact`.
    """
    L, D, E, nu, P = (TIMOSHENKO[key] for key in ("L", "D", "E", "nu", "P"))
    m = rectangle(4 * k, k, (L, D), (0.0, -D / 2), **mesh_kw)
    I = D**3 / 12.0
    facets = loads.facets_where(m, lambda X: np.abs(X[:, 0] - L) < 1e-9)

    def t(Xq):
        return np.stack([0 * Xq[:, 1], P / (2 * I) * (D**2 / 4 - Xq[:, 1] ** 2)], 1)

    f = edge_load_2d(m, facets, t)
    bc = loads.fix(
        m, loads.nodes_on_plane(m, 0, 0.0), displacement=lambda X: timoshenko_exact(X)[0]
    )
    mu, lam = lame(E, nu, dim=2, plane="stress")
    pot = Potential(mesh=m, params=Lame(mu, lam), f_ext=jnp.asarray(f), psi=linear)
    tip = loads.nodes_on_plane(m, 0, L)
    tip_exact = float(timoshenko_exact(np.asarray(m.points)[tip[:1]])[0][0, 1])
    return Benchmark(
        name="timoshenko",
        pot=pot,
        bc=bc,
        reference={"u_y": tip_exact},
        citation="Timoshenko & Goodier 1970, §21",
        probes={"tip": tip},
        exact=timoshenko_exact,
        lame=(mu, lam),
    )


def beam_deflection(L=10.0, D=1.0, E=1000.0, nu=0.3, P=1.0) -> float:
    """Timoshenko beam tip deflection of a square D × D section [length]:
    PL³/(3EI) + PL/(κGA), κ = 10(1+ν)/(12+11ν) (Cowper 1966)."""
    I, A, G = D**4 / 12.0, D * D, E / (2 * (1 + nu))
    kappa = 10 * (1 + nu) / (12 + 11 * nu)
    return P * L**3 / (3 * E * I) + P * L / (kappa * G * A)


def cantilever3d(m_depth: int, **mesh_kw) -> Benchmark:
    """10 × 1 × 1 tet cantilever with cube cells, ``m_depth`` cells through the depth;
    clamped at x = 0, uniform shear traction totalling P (−z) on x = L.

    Probe ``"end"``: the nodes of x = L (score: minus their mean u_z), reference ``"delta"``
    of :func:`beam_deflection`. The material is ``linear`` (the tip deflection is 0.4 L, so
    finite-strain kinematics, F-bar included, would answer a geometrically nonlinear
    question: use B-bar here).
    """
    L, D, E, nu, P = (CANTILEVER3D[key] for key in ("L", "D", "E", "nu", "P"))
    md = m_depth
    m = box(int(round(L / D)) * md, md, md, (L, D, D), **mesh_kw)
    facets = loads.facets_where(m, lambda X: np.abs(X[:, 0] - L) < 1e-9)
    f = loads.traction_load(m, facets, [0.0, 0.0, -P / (D * D)])
    bc = loads.fix(m, loads.nodes_on_plane(m, 0, 0.0))
    mu, lam = lame(E, nu)
    pot = Potential(mesh=m, params=Lame(mu, lam), f_ext=jnp.asarray(f), psi=linear)
    return Benchmark(
        name="cantilever3d",
        pot=pot,
        bc=bc,
        reference={"delta": beam_deflection(L, D, E, nu, P)},
        citation="Timoshenko beam theory, shear coefficient of Cowper 1966",
        probes={"end": loads.nodes_on_plane(m, 0, L)},
        lame=(mu, lam),
    )
