"""Cook's membrane: a tapered panel clamped on x = 0 and sheared on x = 48.

Geometry (Cook 1974): the trapezoid (0,0), (48,44), (48,60), (0,44); uniform vertical shear
on the edge x = 48 (length 16). Three published variants:

* :func:`cook_linear`: linear, plane stress, E = 1, ν = 1/3, total shear 1; vertical
  displacement at the loaded edge's mid-point (48, 52): 23.96 (Cook 1974; converged value
  quoted by Simo & Rifai 1990, IJNME 29:1595).
* :func:`cook_incompressible`: linear, nearly incompressible, plane strain, G = 0.375,
  λ = 7500, total shear 1; u_y(48, 52) = 16.43 (Richardson-extrapolated). P1 locks
  (≈ 4.6–5.1).
* :func:`cook_neo_hookean`: neo-Hookean, nearly incompressible, plane strain, G = 80.1938,
  K = 40.0942·10⁴, total shear 100; corner (48, 60) u_y ≈ 6.91 (de Souza Neto et al. 1996,
  IJSS 33:3277; Elguedj et al. 2008, CMAME 197:2732). P1 locks badly.

Every builder takes the mesh keywords of :func:`~jaxelastic.mesh.cook_membrane`
(``order=2``, ``formulation="fbar"``/``"bbar"``) and returns a
:class:`~jaxelastic.verification.Benchmark` whose probe ``"point"`` is the scored node.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .. import loads
from ..materials import Lame, linear, neo_hookean
from ..mechanics.potential import Potential
from ..mesh import cook_membrane
from .problem import Benchmark, node_at

__all__ = [
    "cook_linear",
    "cook_incompressible",
    "cook_neo_hookean",
    "COOK_LINEAR_REF",
    "COOK_INCOMPRESSIBLE_REF",
    "COOK_NEO_HOOKEAN_REF",
]

COOK_LINEAR_REF = 23.96  # u_y(48, 52), Cook 1974
COOK_INCOMPRESSIBLE_REF = 16.43  # u_y(48, 52), Richardson-extrapolated
COOK_NEO_HOOKEAN_REF = 6.91  # u_y(48, 60), de Souza Neto et al. 1996


def _cook(name, n, mesh_kw, *, psi, params, total, point, ref, citation, steps=0) -> Benchmark:
    """Clamp x = 0, shear x = 48 by ``total`` [force], score u_y at ``point``."""
    m = cook_membrane(n, **mesh_kw)
    facets = loads.facets_where(m, lambda X: np.abs(X[:, 0] - 48.0) < 1e-9)
    f = loads.traction_load(m, facets, [0.0, total / 16.0])  # edge length 16
    bc = loads.fix(m, loads.nodes_on_plane(m, 0, 0.0))
    pot = Potential(mesh=m, params=params, f_ext=jnp.asarray(f), psi=psi)
    return Benchmark(
        name=name,
        pot=pot,
        bc=bc,
        reference={"u_y": ref},
        citation=citation,
        probes={"point": np.array([node_at(m, point)])},
        lame=(float(params.mu), float(params.lam)),
        steps=steps,
    )


def cook_linear(n: int, **mesh_kw) -> Benchmark:
    """Linear plane-stress Cook's membrane (E = 1, ν = 1/3, total shear 1) on an ``n × n``
    mesh; reference u_y(48, 52) = 23.96. ``n`` even for P1 (the probe must be a node)."""
    p = Lame.from_E_nu(1.0, 1.0 / 3.0, dim=2, plane="stress")
    return _cook(
        "cook",
        n,
        mesh_kw,
        psi=linear,
        params=p,
        total=1.0,
        point=(48.0, 52.0),
        ref=COOK_LINEAR_REF,
        citation="Cook 1974; Simo & Rifai 1990",
    )


def cook_incompressible(n: int, **mesh_kw) -> Benchmark:
    """Nearly incompressible linear Cook (plane strain, G = 0.375, λ = 7500, total shear 1);
    reference u_y(48, 52) = 16.43. Locking-free variants: B-bar (Hughes 1980), the
    small-strain form of F-bar (u ≈ 16 on a 48-long body is a large rotation, so F-bar with
    the linear ψ would answer a geometrically nonlinear question)."""
    return _cook(
        "cook_incompressible",
        n,
        mesh_kw,
        psi=linear,
        params=Lame(0.375, 7500.0),
        total=1.0,
        point=(48.0, 52.0),
        ref=COOK_INCOMPRESSIBLE_REF,
        citation="Richardson-extrapolated reference (plane strain, G = 0.375, λ = 7500)",
    )


def cook_neo_hookean(n: int, **mesh_kw) -> Benchmark:
    """Nearly incompressible neo-Hookean Cook (plane strain, G = 80.1938, K = 40.0942e4,
    λ = K − 2G/3, total shear 100); reference corner u_y(48, 60) = 6.91. Suggests 2 load
    increments."""
    G, K = 80.1938, 40.0942e4
    return _cook(
        "cook_nh",
        n,
        mesh_kw,
        psi=neo_hookean,
        params=Lame(G, K - 2.0 * G / 3.0),
        total=100.0,
        point=(48.0, 60.0),
        ref=COOK_NEO_HOOKEAN_REF,
        citation="de Souza Neto et al. 1996; Elguedj et al. 2008",
        steps=2,
    )
