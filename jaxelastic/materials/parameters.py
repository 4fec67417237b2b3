"""Lamé parameters: the parameter type of the built-in laws, E/ν conversion, validation.

:class:`Lame` holds the shear modulus μ and the first Lamé parameter λ [Pa] (scalars, or
``(n_cells,)`` per-cell fields); :func:`lame` converts Young's modulus and Poisson's ratio
(3D, plane strain, plane stress); :func:`check_lame` refuses concrete parameters no elastic
solid has or float64 cannot resolve (used by ``je.solve`` and the scene builder).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import numpy as np

__all__ = ["Lame", "lame", "check_lame", "LAME_RATIO_MAX"]


class Lame(NamedTuple):
    """Lamé parameters, the parameter pytree of the built-in models.

    Attributes:
        mu: shear modulus μ [Pa]; scalar, or ``(n_cells,)`` for a per-cell field.
        lam: first Lamé parameter λ [Pa]; same shape convention.
    """

    mu: jax.Array | float
    lam: jax.Array | float

    @classmethod
    def from_E_nu(cls, E, nu, dim: int = 3, plane: str = "strain") -> Lame:
        """Lamé parameters from Young's modulus E [Pa] and Poisson's ratio ν
        (:func:`lame`: 3D and plane strain, or ``plane="stress"`` in 2D); traceable and
        differentiable in E and ν, validated where concrete.

        Example: ``je.Lame.from_E_nu(1e6, 0.3)``; ``je.Lame.from_E_nu(1e4, 0.3, dim=2)``.
        """
        return cls(*lame(E, nu, dim=dim, plane=plane))


LAME_RATIO_MAX = 1e12
"""The largest λ/μ :func:`check_lame` accepts: ν = 0.5 − 5·10⁻¹³, beyond which float64
cannot resolve the shear response next to the volumetric one (the residual's round-off
floor exceeds the loads, and a solve would stop at it with a meaningless answer)."""


def check_lame(params: Lame, dim: int) -> None:
    """Refuse concrete Lamé parameters no elastic solid has, or float64 cannot resolve.

    Needs μ > 0 and a positive bulk modulus ``λ + 2μ/dim`` (stability of the linearised
    response), everything finite, and ``λ/μ ≤`` :data:`LAME_RATIO_MAX`. Traced parameters
    (inside ``jit``/``grad``) are not checked.

    Raises:
        ValueError: naming the parameter, the first offending cell and what to do.
    """
    try:
        mu = np.asarray(params.mu, dtype=np.float64)
        lam = np.asarray(params.lam, dtype=np.float64)
    except Exception:  # noqa: BLE001 — traced, or a global array another process holds
        return  # (multi-process sharding): not checked here
    mu, lam = np.broadcast_arrays(np.atleast_1d(mu), np.atleast_1d(lam))

    def where(bad) -> str:
        i = int(np.flatnonzero(bad.ravel())[0])
        return "" if bad.size == 1 else f" (at {int(bad.sum())} cell(s), first cell {i})"

    bad = ~(np.isfinite(mu) & np.isfinite(lam))
    if bad.any():
        raise ValueError(f"Lame parameters must be finite{where(bad)}")
    if (bad := mu <= 0).any():
        raise ValueError(
            f"shear modulus mu must be > 0{where(bad)}, got {mu.ravel()[bad.ravel()][0]!r}: "
            "build the parameters with je.Lame.from_E_nu(E, nu)"
        )
    if (bad := lam + 2.0 * mu / dim <= 0).any():
        raise ValueError(
            f"the bulk modulus lam + 2 mu / {dim} must be > 0{where(bad)} (Poisson's ratio "
            "above -1): build the parameters with je.Lame.from_E_nu(E, nu)"
        )
    if (bad := lam > LAME_RATIO_MAX * mu).any():
        raise ValueError(
            f"lam / mu exceeds {LAME_RATIO_MAX:.0e}{where(bad)} (Poisson's ratio within 5e-13 "
            "of 0.5): float64 cannot resolve the shear response next to the volumetric one. "
            "Use nu <= 0.4999999 with an F-bar or P2 element for near-incompressibility"
        )


def lame(E, nu, dim: int = 3, plane: str = "strain") -> tuple:
    """Lamé parameters (μ, λ) from Young's modulus E [Pa] and Poisson's ratio ν.

    ``μ = E/(2(1+ν))``; in 3D and in 2D plane strain ``λ = Eν/((1+ν)(1−2ν))``; in 2D plane
    stress ``λ = Eν/((1+ν)(1−ν))`` (the effective 2D λ* of a thin plate). Works on traced
    arrays (differentiable in E, ν); concrete values are validated.

    Args:
        E: Young's modulus, > 0.
        nu: Poisson's ratio in (−1, 0.5).
        dim: 2 or 3.
        plane: ``"strain"`` or ``"stress"`` (used only when ``dim == 2``).

    Raises:
        ValueError: E ≤ 0, ν outside (−1, 0.5), NaN/inf, bad ``dim`` or ``plane``.
    """
    if dim not in (2, 3):
        raise ValueError(f"dim must be 2 or 3, got {dim!r}")
    if plane not in ("strain", "stress"):
        raise ValueError(f"plane must be 'strain' or 'stress', got {plane!r}")
    E_c, nu_c = _concrete(E, "Young's modulus E"), _concrete(nu, "Poisson's ratio nu")
    if E_c is not None:
        if not np.all(np.isfinite(E_c)):
            raise ValueError(f"Young's modulus E must be finite, got {E!r}")
        if np.any(E_c <= 0):
            raise ValueError(f"Young's modulus E must be > 0, got {E!r}")
    if nu_c is not None:
        if not np.all(np.isfinite(nu_c)):
            raise ValueError(f"Poisson's ratio nu must be finite, got {nu!r}")
        if np.any(nu_c <= -1.0) or np.any(nu_c >= 0.5):
            raise ValueError(f"Poisson's ratio nu must lie in (-1, 0.5), got {nu!r}")
    mu = E / (2.0 * (1.0 + nu))
    if dim == 2 and plane == "stress":
        lam = E * nu / ((1.0 + nu) * (1.0 - nu))
    else:
        lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return mu, lam


def _concrete(v, name: str = "value"):
    """NumPy value of ``v``, or None when it is a tracer (validated only when concrete)."""
    try:
        a = np.asarray(v)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return None
    if a.dtype.kind not in "biuf":
        raise TypeError(f"{name} must be a real number or an array of them, got {v!r}")
    return a
