"""User-style functions referenced by the shipped scene files as ``"module:function"``.

They show what a scene's ``module:function`` entries expect (a user strain-energy density
``psi(F, params) -> scalar`` is shown by ``jaxelastic.materials:isochoric_neo_hookean``,
the material of the twist scene):

* an initial velocity ``v(X) -> (m, dim)`` of the rest positions ``X`` ``(m, dim)``;
* a prescribed displacement ``u(X) -> (m, dim)`` or, in dynamic scenes, ``u(X, t)``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["pendulum_velocity", "shear_wave"]


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
