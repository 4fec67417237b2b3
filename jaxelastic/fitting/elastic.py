"""The (E, ν) convenience of fitting: :class:`Material` and its Lamé mapping.

Young's modulus and Poisson's ratio are one parametrisation among others
(:mod:`jaxelastic.fitting.parameters`): E is :class:`~jaxelastic.fitting.transforms.Positive`
(``E = E₀·exp(a)``, relative to the initial guess) and ν is
:class:`~jaxelastic.fitting.transforms.Bounded` in (−1, 0.5) (the range where λ, μ > 0 in
3D and plane strain; Bower 2009, *Applied Mechanics of Solids*, §3.2.2), and
:class:`LameOf` maps the region-expanded (E, ν) to :class:`~jaxelastic.materials.Lame`
with :func:`~jaxelastic.materials.lame` for the ψ of :mod:`jaxelastic.materials`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

from ..materials import Lame
from .parameters import Parametrization, make_parametrization
from .transforms import Bounded, Fixed, Positive

__all__ = ["Material", "LameOf", "material_parametrization", "NU_BOUNDS"]

NU_BOUNDS = (-1.0, 0.5)
FIELDS = ("E", "nu")


class Material(NamedTuple):
    """Young's modulus ``E`` [Pa] and Poisson's ratio ``nu`` [-]: scalars (shared by the
    whole body) or ``(n_regions,)`` arrays (one value per region label)."""

    E: Any
    nu: Any


@dataclasses.dataclass(frozen=True)
class LameOf:
    """Hashable map :class:`Material` → :class:`~jaxelastic.materials.Lame` (``to_psi`` of a
    :class:`~jaxelastic.fitting.parameters.Parametrization`).

    Attributes:
        dim: 2 or 3; plane: 2D only, ``"strain"`` or ``"stress"``.
    """

    dim: int = 3
    plane: str = "strain"

    def __call__(self, m: Material) -> Lame:
        return Lame.from_E_nu(m.E, m.nu, dim=self.dim, plane=self.plane)


def material_parametrization(
    init: Material,
    mesh=None,
    *,
    regions=None,
    fields: Sequence[str] = FIELDS,
    plane: str = "strain",
    dim: int | None = None,
    nu_bounds: tuple[float, float] = NU_BOUNDS,
    regularization: float = 0.0,
    reg_kind: str = "tikhonov",
) -> Parametrization:
    """The (E, ν) :class:`~jaxelastic.fitting.parameters.Parametrization` (ψ form: Lamé).

    Args:
        init: initial :class:`Material`; scalars, or ``(n_regions,)`` arrays with regions.
        mesh: the mesh region labels refer to (and its ``dim``).
        regions: None (one shared E, ν), ``(n_cells,)`` int labels ``0..R−1`` or ``"cells"``.
        fields: which of ``"E"``, ``"nu"`` are fitted (the others stay at ``init``).
        plane: 2D only, ``"strain"`` or ``"stress"``.
        dim: spatial dimension (default ``mesh.dim``).
        nu_bounds: the open interval of ν, (−1, 0.5) by default; (0, 0.5) excludes auxetics.
        regularization, reg_kind: penalty over adjacent regions (see
            :mod:`jaxelastic.fitting.parameters`).

    Raises:
        ValueError: unknown field, bad labels or shapes, E ≤ 0 or ν out of its bounds.
    """
    fields = tuple(fields)
    if not fields or any(f not in FIELDS for f in fields) or len(set(fields)) != len(fields):
        raise ValueError(f"fields must be a non-empty subset of {FIELDS}, got {fields!r}")
    if dim is None:
        if mesh is None:
            raise ValueError("material_parametrization needs a mesh or dim")
        dim = int(mesh.dim)
    dim = int(dim)
    lo, hi = (float(b) for b in nu_bounds)
    if lo < -1.0 or hi > 0.5:
        raise ValueError(f"nu_bounds must lie within (-1, 0.5), got {nu_bounds!r}")
    LameOf(dim, plane)(Material(1.0, 0.0))  # validates dim and plane
    transforms = Material(
        E=Positive() if "E" in fields else Fixed(),
        nu=Bounded(lo, hi) if "nu" in fields else Fixed(),
    )
    if "nu" not in fields:  # a held ν must still be admissible for lame()
        Bounded(-1.0, 0.5).check(init.nu, "nu")
    if "E" not in fields:
        Positive().check(init.E, "E")
    init = Material(*init)
    if regions is not None and mesh is not None:  # held fields reported per region too
        n_reg = mesh.n_cells if isinstance(regions, str) else int(np.max(regions)) + 1
        init = Material(
            *(
                v if f in fields or np.ndim(v) else np.full(n_reg, float(v))
                for f, v in zip(FIELDS, init, strict=True)
            )
        )
    return make_parametrization(
        init,
        transforms,
        regions=regions,
        mesh=mesh,
        regularization=regularization,
        reg_kind=reg_kind,
        to_psi=LameOf(dim, plane),
    )
