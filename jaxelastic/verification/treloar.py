"""Treloar's (1944) vulcanised-rubber data: uniaxial, equibiaxial and pure-shear tension.

Source: L. R. G. Treloar, "Stress-strain data for vulcanised rubber under various types of
deformation", *Trans. Faraday Soc.* 40 (1944) 59–70. Nominal stress P (force per
*undeformed* area, the first Piola–Kirchhoff stress) against the stretch λ in the loaded
direction of incompressible specimens of 8 % sulphur natural rubber:

* uniaxial tension (λ₁ = λ, λ₂ = λ₃ = λ^-½): :data:`TRELOAR_UNIAXIAL`, 24 points;
* equibiaxial tension (λ₁ = λ₂ = λ, λ₃ = λ⁻²): :data:`TRELOAR_EQUIBIAXIAL`, 16 points;
* pure shear (λ₁ = λ, λ₂ = 1, λ₃ = λ⁻¹): :data:`TRELOAR_PURE_SHEAR`, 13 points.

Units: stretch [-], nominal stress [MPa]. The uniaxial and equibiaxial values were typed in
the original unit kg/cm² (kilogram-force per square centimetre, 1 kg/cm² =
0.0980665 MPa, :data:`KGF_PER_CM2`) and converted here; the pure-shear values were typed in
MPa as transcribed. The public transcriptions of the figures (FElupe's hyperelastic fitting
example; the "Hyperelastic-fitting" data repository) agree with one another to ≤ 1.5 %, a
bound on the reading error of these numbers.

Each curve is a :class:`TreloarCurve` of read-only numpy arrays; nothing is computed at
import beyond the unit conversion.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = [
    "KGF_PER_CM2",
    "TRELOAR_CITATION",
    "TreloarCurve",
    "TRELOAR_UNIAXIAL",
    "TRELOAR_EQUIBIAXIAL",
    "TRELOAR_PURE_SHEAR",
    "TRELOAR",
]

KGF_PER_CM2 = 0.0980665
"""One kilogram-force per square centimetre in MPa (standard gravity 9.80665 m/s²)."""

TRELOAR_CITATION = (
    "Treloar, L. R. G. (1944). Stress-strain data for vulcanised rubber under various "
    "types of deformation. Trans. Faraday Soc. 40, 59-70."
)


class TreloarCurve(NamedTuple):
    """One homogeneous test curve of incompressible rubber.

    Attributes:
        test: ``"uniaxial"``, ``"equibiaxial"`` or ``"pure_shear"``.
        stretch: (n,) stretch λ in the loaded direction [-].
        stress: (n,) nominal (first Piola–Kirchhoff) stress P in that direction [MPa].
    """

    test: str
    stretch: np.ndarray
    stress: np.ndarray


def _curve(test: str, stretch: list[float], stress: list[float], scale: float) -> TreloarCurve:
    lam = np.asarray(stretch, dtype=np.float64)
    p = np.asarray(stress, dtype=np.float64) * scale
    assert lam.shape == p.shape
    lam.setflags(write=False)
    p.setflags(write=False)
    return TreloarCurve(test, lam, p)


TRELOAR_UNIAXIAL = _curve(
    "uniaxial",
    [1.02, 1.125, 1.24, 1.39, 1.585, 1.90, 2.18, 2.42, 3.02, 3.57, 4.03, 4.76]
    + [5.36, 5.75, 6.15, 6.40, 6.60, 6.85, 7.05, 7.15, 7.25, 7.40, 7.50, 7.60],
    [0.26, 1.37, 2.30, 3.23, 4.16, 5.10, 6.00, 6.90, 8.80, 10.7, 12.5, 16.2]
    + [19.9, 23.6, 27.4, 31.0, 34.8, 38.5, 42.1, 45.8, 49.6, 53.3, 57.0, 64.4],
    KGF_PER_CM2,
)
"""Uniaxial tension, λ ∈ [1.02, 7.60], P [MPa] (typed in kg/cm²)."""

TRELOAR_EQUIBIAXIAL = _curve(
    "equibiaxial",
    [1.03, 1.07, 1.12, 1.14, 1.20, 1.31, 1.42, 1.68, 1.94, 2.49, 3.03, 3.43, 3.75, 4.07]
    + [4.26, 4.45],
    [0.95, 1.60, 2.42, 2.62, 3.32, 4.43, 5.18, 6.60, 7.78, 9.79, 12.6, 14.7, 17.4, 20.1]
    + [22.5, 24.7],
    KGF_PER_CM2,
)
"""Equibiaxial tension, λ ∈ [1.03, 4.45], P [MPa] (typed in kg/cm²)."""

TRELOAR_PURE_SHEAR = _curve(
    "pure_shear",
    [1.03, 1.12, 1.19, 1.31, 1.46, 1.84, 2.38, 2.97, 3.47, 3.95, 4.37, 4.69, 4.97],
    [0.0667, 0.1589, 0.2452, 0.3326, 0.4189, 0.5925, 0.7652, 0.9418, 1.1183, 1.2851]
    + [1.4617, 1.6285, 1.8050],
    1.0,
)
"""Pure shear (planar tension), λ ∈ [1.03, 4.97], P [MPa] (typed in MPa)."""

TRELOAR: tuple[TreloarCurve, ...] = (TRELOAR_UNIAXIAL, TRELOAR_EQUIBIAXIAL, TRELOAR_PURE_SHEAR)
"""The three curves in the order uniaxial, equibiaxial, pure shear."""
