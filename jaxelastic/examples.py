"""User-style functions referenced by the shipped scene files as ``"module:function"``.

They show what a scene's ``module:function`` entries expect:

* a strain-energy density ``psi(F, params) -> scalar`` for one ``(d, d)`` F, written with
  ``jax.numpy`` (the scene passes ``params = Lame(mu, lam)``);
* an initial velocity ``v(X) -> (m, dim)`` of the rest positions ``X`` ``(m, dim)``;
* a prescribed displacement ``u(X) -> (m, dim)`` or, in dynamic scenes, ``u(X, t)``.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .materials import Lame
from .mechanics.kinematics import det

__all__ = ["isochoric_neo_hookean", "pendulum_velocity", "shear_wave"]


def isochoric_neo_hookean(F, params: Lame):
    """Isochoric neo-Hookean ``ψ = μ/2 (J^(−2/d)·tr(FᵀF) − d) + κ/2 (J − 1)²``.

    The hyperelasticity demo of JAX-FEM (the "twist" benchmark). ``params.mu`` is the
    shear modulus μ and ``params.lam`` carries the **bulk modulus** κ (not Lamé's λ).
    Undefined for J ≤ 0: returns ``+inf`` there, like the built-in neo-Hookean.
    """
    d = F.shape[0]
    J = det(F)
    ok = J > 0
    Js = jnp.where(ok, J, 1.0)
    IC = jnp.sum(F * F)
    psi = 0.5 * params.mu * (Js ** (-2.0 / d) * IC - d) + 0.5 * params.lam * (J - 1.0) ** 2
    return jnp.where(ok, psi, jnp.inf)


def pendulum_velocity(X):
    """A rigid swing about the origin: ``v = ω × X`` with ω = 2 rad/s about z (2D or 3D).

    Args:
        X: ``(m, dim)`` rest positions [m]. Returns ``(m, dim)`` velocities [m/s].
    """
    X = np.asarray(X, dtype=float)
    omega = 2.0
    v = np.zeros_like(X)
    v[:, 0] = -omega * X[:, 1]
    v[:, 1] = omega * X[:, 0]
    return v


def shear_wave(X, t):
    """A time-dependent displacement ``u = (0.05·sin(2π t), 0, …)`` (one period per second).

    Args:
        X: ``(m, dim)`` rest positions; t: time [s]. Returns ``(m, dim)`` [m].
    """
    X = np.asarray(X, dtype=float)
    u = np.zeros_like(X)
    u[:, 0] = 0.05 * np.sin(2.0 * np.pi * t)
    return u
