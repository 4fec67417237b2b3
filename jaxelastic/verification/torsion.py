"""The JAX-FEM "twist" hyperelasticity benchmark.

Unit cube ``box(n, n, n)``, face x = 1 clamped, face x = 0 given u_x = 0 and half of a 60°
rotation about the x axis through (y, z) = (0.5, 0.5); isochoric neo-Hookean
(:func:`~jaxelastic.materials.isotropic.isochoric_neo_hookean`)
ψ = μ/2 (J^(−2/3) I_C − 3) + κ/2 (J − 1)² with E = 10, ν = 0.3, κ = E/(3(1 − 2ν)) (the
hyperelasticity example of JAX-FEM, Xue et al. 2023, Comput. Phys. Commun. 291:108802).
No closed form: score against a fine-mesh solution.
"""

from __future__ import annotations

import numpy as np

from .. import loads
from ..materials import Lame, isochoric_neo_hookean
from ..mechanics.potential import Potential
from ..mesh import box
from .problem import Benchmark

__all__ = ["TWIST_THETA", "twist", "twist_displacement"]

TWIST_THETA = np.pi / 3  # the full rotation angle; the face x = 0 turns by half of it


def twist_displacement(X, theta: float = TWIST_THETA):
    """Prescribed displacement ``(k, 3)`` of the x = 0 face at points ``X (k, 3)``: half
    of the rotation by ``theta`` [rad] about the x axis through (y, z) = (0.5, 0.5)."""
    y, z = X[:, 1], X[:, 2]
    return np.stack(
        [
            0 * y,
            (0.5 + (y - 0.5) * np.cos(theta) - (z - 0.5) * np.sin(theta) - y) / 2,
            (0.5 + (y - 0.5) * np.sin(theta) + (z - 0.5) * np.cos(theta) - z) / 2,
        ],
        1,
    )


def twist(n: int, **mesh_kw) -> Benchmark:
    """The twist benchmark on ``box(n, n, n, **mesh_kw)`` (6n³ tets for P1).

    Probes ``"turned"`` (x = 0) and ``"clamped"`` (x = 1); no reference value.
    """
    mesh = box(n, n, n, **mesh_kw)
    E, nu = 10.0, 0.3
    mu = E / (2 * (1 + nu))
    kappa = E / (3 * (1 - 2 * nu))
    clamped = loads.nodes_on_plane(mesh, 0, 1.0)
    turned = loads.nodes_on_plane(mesh, 0, 0.0)
    bc = loads.combine(
        loads.fix(mesh, clamped),
        loads.fix(mesh, turned, displacement=twist_displacement),
    )
    pot = Potential(mesh=mesh, params=Lame(mu, kappa), psi=isochoric_neo_hookean)
    return Benchmark(
        name="twist",
        pot=pot,
        bc=bc,
        citation="JAX-FEM hyperelasticity example (Xue et al. 2023)",
        probes={"turned": turned, "clamped": clamped},
    )
