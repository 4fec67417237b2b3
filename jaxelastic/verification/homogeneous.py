"""Homogeneous deformations of a neo-Hookean unit cube with closed-form answers.

* :func:`uniaxial_tension`: stretch a along x with symmetry planes and free lateral faces,
  F = diag(a, b, b): μ(b² − 1) + λ ln(a b²) = 0 and nominal stress P₁₁ = μ(a − b²/a).
* :func:`simple_shear`: x = X + γ Y e₁ imposed on the whole boundary: P₁₂ = μγ and Cauchy
  σ₁₁ = μγ² (the Poynting effect) in every cell.

Closed forms: Bonet & Wood 2008, *Nonlinear Continuum Mechanics for Finite Element
Analysis*, §6.4.
"""

from __future__ import annotations

import numpy as np

from .. import loads
from ..materials import Lame, lame, neo_hookean
from ..mechanics.potential import Potential
from ..mesh import boundary_nodes, box
from .problem import Benchmark, node_at

__all__ = ["uniaxial_tension", "simple_shear", "pull_bc", "pull_nodes"]


def uniaxial_tension(k: int, a: float = 1.5, **mesh_kw) -> Benchmark:
    """Neo-Hookean unit cube (``k³`` cubes, E = 1000, ν = 0.3) stretched to ``a`` along x.

    References: ``"b"`` (lateral stretch) and ``"P11"`` (nominal stress, the reaction on
    x = 1 per unit area); probes ``"corner"`` (node (1, 1, 1), whose y is b) and ``"pull"``
    (the nodes of x = 1). For the reaction on x = 1 use :func:`pull_bc` (the pulled face's
    Dirichlet data alone). Suggests 2 load increments.
    """
    m = box(k, k, k, **mesh_kw)
    mu, lam = lame(1000.0, 0.3)
    sym = [loads.fix(m, loads.nodes_on_plane(m, ax, 0.0), components=(ax,)) for ax in range(3)]
    pull = pull_bc(m, a)
    from scipy.optimize import brentq  # here: scipy.optimize costs ~1 s of import time

    b = brentq(lambda b: mu * (b * b - 1) + lam * np.log(a * b * b), 0.2, 1.0)
    assert not isinstance(b, tuple)  # no full_output: the root alone
    return Benchmark(
        name="uniaxial",
        pot=Potential(mesh=m, params=Lame(mu, lam), psi=neo_hookean),
        bc=loads.combine(*sym, pull),
        reference={"b": float(b), "P11": float(mu * (a - b * b / a))},
        citation="Bonet & Wood 2008, §6.4",
        probes={"corner": np.array([node_at(m, (1.0, 1.0, 1.0))]), "pull": pull_nodes(m)},
        steps=2,
    )


def pull_nodes(mesh) -> np.ndarray:
    """Nodes of the pulled face x = 1 of :func:`uniaxial_tension`."""
    return loads.nodes_on_plane(mesh, 0, 1.0)


def pull_bc(mesh, a: float = 1.5):
    """The Dirichlet data of the pulled face alone (u_x = a − 1 on x = 1), for reactions."""
    return loads.fix(mesh, pull_nodes(mesh), components=(0,), displacement=[a - 1, 0, 0])


def simple_shear(k: int, gamma: float = 0.5, **mesh_kw) -> Benchmark:
    """Simple shear x = X + γ Y e₁ on the boundary of a neo-Hookean unit cube (``k³`` cubes,
    E = 1000, ν = 0.3); references ``"P12"`` = μγ and ``"sigma11"`` = μγ²; the interior
    nodes follow the same affine map (``exact``). Suggests 1 load increment."""
    m = box(k, k, k, **mesh_kw)
    mu, lam = lame(1000.0, 0.3)
    G = np.zeros((3, 3))
    G[0, 1] = gamma

    def exact(X):
        return X @ G.T, np.broadcast_to(G, (X.shape[0], 3, 3)).copy()

    return Benchmark(
        name="shear",
        pot=Potential(mesh=m, params=Lame(mu, lam), psi=neo_hookean),
        bc=loads.fix(m, boundary_nodes(m), displacement=lambda X: exact(X)[0]),
        reference={"P12": mu * gamma, "sigma11": mu * gamma**2},
        citation="Bonet & Wood 2008, §6.4 (Poynting effect)",
        exact=exact,
        steps=1,
    )
