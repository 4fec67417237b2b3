"""Patch tests on the MacNeal & Harder (1985) membrane patch.

The patch: 0.24 × 0.12 with interior nodes (0.04, 0.02), (0.18, 0.03), (0.16, 0.08),
(0.08, 0.08); 5 quadrilaterals split into 10 triangles (MacNeal & Harder 1985, *A proposed
standard set of problems to test finite element accuracy*, Finite Elem. Anal. Des. 1:3).

* :func:`macneal_harder_patch`: linear, plane stress, E = 10⁶, ν = 0.25, boundary
  u = 10⁻³(x + y/2), v = 10⁻³(y + x/2) → σx = σy = 1333.3, τ = 400 in every element.
* :func:`affine_patch`: the nonlinear form: the boundary map x = F₀X + c must be
  reproduced exactly inside by every material.
"""

from __future__ import annotations

import numpy as np

from .. import loads
from ..materials import BUILTIN, Lame, lame, linear
from ..mechanics.potential import Potential
from ..mesh import Mesh, from_arrays
from .problem import Benchmark

__all__ = [
    "MH_POINTS",
    "MH_QUADS",
    "PATCH_F0",
    "PATCH_C",
    "patch_mesh",
    "macneal_harder_patch",
    "affine_patch",
]

MH_POINTS = np.array(
    [
        [0, 0],
        [0.24, 0],
        [0.24, 0.12],
        [0, 0.12],
        [0.04, 0.02],
        [0.18, 0.03],
        [0.16, 0.08],
        [0.08, 0.08],
    ]
)
MH_QUADS = ((0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7), (4, 5, 6, 7))
# the affine map of the nonlinear patch test, x = F0 X + c
PATCH_F0 = np.array([[1.3, 0.2], [-0.1, 0.8]])
PATCH_C = np.array([0.01, -0.02])
_OUTER = [0, 1, 2, 3]  # the corner nodes carry the boundary data


def patch_mesh() -> Mesh:
    """The MacNeal & Harder membrane patch: 8 nodes, 10 ``tri3`` cells."""
    tris = [t for a, b, c, d in MH_QUADS for t in ((a, b, c), (a, c, d))]
    return from_arrays(MH_POINTS, np.array(tris), "tri3")


def macneal_harder_patch() -> Benchmark:
    """Linear plane-stress patch test: u = 1e-3(x + y/2), v = 1e-3(y + x/2) on the outer
    corners; reference ``"sigma"``: the exact Cauchy stress ``[[4000/3, 400], [400,
    4000/3]]`` (flattened row-major as ``sxx, sxy, syx, syy``) in every element."""
    m = patch_mesh()
    mu, lam = lame(1.0e6, 0.25, dim=2, plane="stress")

    def u(X):
        return 1e-3 * np.stack([X[:, 0] + X[:, 1] / 2, X[:, 1] + X[:, 0] / 2], 1)

    def exact(X):
        g = np.broadcast_to(1e-3 * np.array([[1.0, 0.5], [0.5, 1.0]]), (X.shape[0], 2, 2))
        return u(X), g.copy()

    pot = Potential(mesh=m, params=Lame(mu, lam), psi=linear)
    s = 4000.0 / 3.0
    return Benchmark(
        name="patch",
        pot=pot,
        bc=loads.fix(m, _OUTER, displacement=u),
        reference={"sxx": s, "sxy": 400.0, "syx": 400.0, "syy": s},
        citation="MacNeal & Harder 1985",
        exact=exact,
        lame=(mu, lam),
    )


def affine_patch(model: str) -> Benchmark:
    """Nonlinear patch test for the built-in 2D material ``model`` (E = 10⁶, ν = 0.25):
    boundary map x = F₀X + c (:data:`PATCH_F0`, :data:`PATCH_C`); the exact solution is
    that map at every node (``exact`` gives its displacement). Suggests 1 load increment."""
    m = patch_mesh()

    def exact(X):
        g = np.broadcast_to(PATCH_F0 - np.eye(2), (X.shape[0], 2, 2))
        return X @ PATCH_F0.T + PATCH_C - X, g.copy()

    pot = Potential(mesh=m, params=Lame.from_E_nu(1.0e6, 0.25, dim=2), psi=BUILTIN[model])
    return Benchmark(
        name=f"patch_affine[{model}]",
        pot=pot,
        bc=loads.fix(m, _OUTER, displacement=lambda X: exact(X)[0]),
        citation="MacNeal & Harder 1985 (nonlinear form: any affine map is exact)",
        exact=exact,
        steps=1,
    )
