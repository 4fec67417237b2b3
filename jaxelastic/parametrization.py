"""Material parametrisation for fitting: (E, ν) shared, per region or per cell.

The optimiser works on unconstrained variables ``z``; constraints are enforced by the
reparametrisation

    E = E_ref · exp(a)                (E > 0)
    ν = −1 + 1.5 · sigmoid(b)         (−1 < ν < 0.5, the range where λ, μ > 0 in 3D and
                                       plane strain; Bower 2009, *Applied Mechanics of
                                       Solids*, §3.2.2)

with ``E_ref`` the initial guess, so ``a = 0`` at the start and both variables are O(1).
This module also holds the pieces a *fitting case* needs (see :mod:`jaxelastic.fitting`
for the protocol): :class:`CaseAux`, :func:`observation_loss` and :func:`add_noise`. It
imports nothing from :mod:`jaxelastic.implicit` or :mod:`jaxelastic.fitting`, so case
implementations anywhere can import it at module level.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .materials import Lame, lame

__all__ = [
    "CaseAux",
    "Material",
    "ParamMap",
    "add_noise",
    "from_unconstrained",
    "make_param_map",
    "observation_loss",
    "region_adjacency",
    "to_unconstrained",
]

FIELDS = ("E", "nu")


class CaseAux(NamedTuple):
    """Auxiliary output of ``case.evaluate`` (one per case and evaluation).

    Attributes:
        warm: the new warm start (same pytree structure as ``case.initial_warm()``).
        ok: bool scalar, every forward solve of the case converged (status SUCCESS).
        newton_steps: int scalar, total Newton iterations of the case.
        linear_iterations: int scalar, total linear-solver (CG) iterations of the case.
    """

    warm: Any
    ok: jax.Array
    newton_steps: jax.Array
    linear_iterations: jax.Array


class Material(NamedTuple):
    """Young's modulus ``E`` [Pa] and Poisson's ratio ``nu`` [-]: scalars (shared by the
    whole body) or ``(n_regions,)`` arrays (one value per region label)."""

    E: Any
    nu: Any


def to_unconstrained(E, nu, E_ref):
    """(E, ν) → ``stack([a, b])`` with ``E = E_ref·exp(a)``, ``ν = −1 + 1.5·sigmoid(b)``.

    Shapes: E, nu, E_ref broadcastable; returns ``(2, *shape)``.
    """
    s = (jnp.asarray(nu) + 1.0) / 1.5
    return jnp.stack([jnp.log(jnp.asarray(E) / E_ref), jnp.log(s) - jnp.log1p(-s)])


def from_unconstrained(z, E_ref):
    """Inverse of :func:`to_unconstrained`: ``z (2, ...)`` → (E, ν), E > 0, −1 < ν < 0.5."""
    return E_ref * jnp.exp(z[0]), -1.0 + 1.5 * jax.nn.sigmoid(z[1])


def observation_loss(x, observed, reference, nodes=None):
    """Relative squared misfit of observed positions (one load case or time step).

    ``‖x[nodes] − observed‖² / ‖observed − reference[nodes]‖²``: 1 for the rest shape,
    0 for a perfect fit, so cases with different load magnitudes weigh alike.

    Args:
        x: ``(n_nodes, dim)`` computed positions.
        observed: ``(n_obs, dim)`` observed positions (``n_obs = n_nodes`` if nodes is None).
        reference: ``(n_nodes, dim)`` rest positions.
        nodes: ``(n_obs,)`` int marker-node indices, or None for all nodes.
    """
    if nodes is not None:
        x, reference = x[nodes], reference[nodes]
    return jnp.sum((x - observed) ** 2) / jnp.sum((observed - reference) ** 2)


def add_noise(observed, reference, rel, key):
    """Observed positions with i.i.d. Gaussian noise on every component.

    ``σ = rel × RMS displacement``, ``RMS displacement = sqrt(mean_a ‖observed_a −
    reference_a‖²)`` over the observed nodes a; each coordinate gets ``N(0, σ²)``.

    Args:
        observed: ``(n_obs, dim)`` positions; reference: ``(n_obs, dim)`` rest positions
            of the same nodes; rel: relative noise level (0.01 = 1 %); key: PRNG key.
    """
    observed = jnp.asarray(observed)
    u = observed - jnp.asarray(reference)
    sigma = rel * jnp.sqrt(jnp.mean(jnp.sum(u * u, axis=-1)))
    return observed + sigma * jax.random.normal(key, observed.shape, observed.dtype)


def region_adjacency(cells, labels) -> np.ndarray:
    """Pairs of distinct region labels whose cells share a facet, ``(n_pairs, 2)`` int.

    Args:
        cells: ``(n_cells, dim + 1)`` connectivity (triangles or tetrahedra).
        labels: ``(n_cells,)`` region label of each cell.
    """
    cells = np.asarray(cells)
    labels = np.asarray(labels)
    k = cells.shape[1]
    facets = np.concatenate([np.sort(np.delete(cells, i, axis=1), axis=1) for i in range(k)])
    owner = np.tile(np.arange(cells.shape[0]), k)
    order = np.lexsort(facets.T[::-1])
    f, o = facets[order], owner[order]
    same = np.all(f[1:] == f[:-1], axis=1)
    a, b = labels[o[:-1][same]], labels[o[1:][same]]
    pairs = np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1)[a != b]
    return np.unique(pairs, axis=0).reshape(-1, 2).astype(np.int32)


@dataclasses.dataclass(frozen=True)
class ParamMap:
    """Map from the unconstrained vector ``z`` to material parameters (a pytree).

    ``z`` concatenates ``a (n_regions,)`` if E is fitted and ``b (n_regions,)`` if ν is;
    the other field is held at its initial value. Built by :func:`make_param_map`.

    Attributes:
        regions: ``(n_cells,)`` int32 labels, or None (shared scalars, one "region").
        E_ref: ``(n_regions,)`` reference moduli (the initial guess).
        E0, nu0: ``(n_regions,)`` initial values (used for the fields not fitted).
        pairs: ``(n_pairs, 2)`` adjacent region pairs (regularisation), or None.
        reg_weight: regularisation weight (scalar).
        fields: the fitted fields, a subset of ``("E", "nu")`` (static).
        dim, plane: for :func:`~jaxelastic.materials.lame` (static).
        reg_kind: ``"tikhonov"`` or ``"tv"`` (static).
    """

    regions: Any
    E_ref: Any
    E0: Any
    nu0: Any
    pairs: Any
    reg_weight: Any
    fields: tuple = dataclasses.field(metadata=dict(static=True), default=FIELDS)
    dim: int = dataclasses.field(metadata=dict(static=True), default=3)
    plane: str = dataclasses.field(metadata=dict(static=True), default="strain")
    reg_kind: str = dataclasses.field(metadata=dict(static=True), default="tikhonov")

    @property
    def n_regions(self) -> int:
        return self.E_ref.shape[0]

    def initial_z(self):
        """Unconstrained vector of the initial guess, ``(len(fields) · n_regions,)``."""
        ab = to_unconstrained(self.E0, self.nu0, self.E_ref)
        return jnp.concatenate([ab[FIELDS.index(f)] for f in self.fields])

    def material(self, z) -> Material:
        """Material of z: ``(n_regions,)`` arrays, or scalars when regions is None; fields
        not fitted are exactly their initial values."""
        r = self.n_regions
        vals = {"E": self.E0, "nu": self.nu0}
        for i, f in enumerate(self.fields):
            zi = z[i * r : (i + 1) * r]
            if f == "E":
                vals[f] = self.E_ref * jnp.exp(zi)
            else:
                vals[f] = -1.0 + 1.5 * jax.nn.sigmoid(zi)
        E, nu = vals["E"], vals["nu"]
        if self.regions is None:
            return Material(E[0], nu[0])
        return Material(E, nu)

    def lame(self, z) -> Lame:
        """Lamé parameters for the potential: scalars, or ``(n_cells,)`` per-cell fields."""
        E, nu = self.material(z)
        if self.regions is not None:
            E, nu = E[self.regions], nu[self.regions]
        return Lame(*lame(E, nu, dim=self.dim, plane=self.plane))

    def penalty(self, z):
        """Regulariser over adjacent regions on the unconstrained variables of the fitted
        fields: Tikhonov ``w Σ_pairs (z_i − z_j)²`` (a graph-Laplacian smoothness term) or
        total variation ``w Σ_pairs (sqrt((z_i − z_j)² + ε²) − ε)``, ε = 1e-6."""
        if self.pairs is None:
            return jnp.zeros((), z.dtype)
        r = self.n_regions
        total = jnp.zeros((), z.dtype)
        for i in range(len(self.fields)):
            zi = z[i * r : (i + 1) * r]
            d = zi[self.pairs[:, 0]] - zi[self.pairs[:, 1]]
            if self.reg_kind == "tikhonov":
                total = total + jnp.sum(d * d)
            else:
                eps = 1e-6
                total = total + jnp.sum(jnp.sqrt(d * d + eps * eps) - eps)
        return self.reg_weight * total


jax.tree_util.register_dataclass(
    ParamMap,
    data_fields=["regions", "E_ref", "E0", "nu0", "pairs", "reg_weight"],
    meta_fields=["fields", "dim", "plane", "reg_kind"],
)


def make_param_map(
    init: Material,
    mesh=None,
    *,
    regions=None,
    fields: Sequence[str] = FIELDS,
    plane: str = "strain",
    dim: int | None = None,
    regularization: float = 0.0,
    reg_kind: str = "tikhonov",
) -> ParamMap:
    """Build the :class:`ParamMap` for :func:`jaxelastic.fitting.fit`.

    Args:
        init: initial :class:`Material`; scalars, or ``(n_regions,)`` arrays with regions.
        mesh: the mesh the region labels refer to (needed for regions or regularisation).
        regions: None (one shared E, ν), ``(n_cells,)`` int labels ``0..R−1`` (piecewise
            constant fields), or ``"cells"`` (one region per cell).
        fields: which of ``"E"``, ``"nu"`` are fitted (the others stay at ``init``).
        plane: 2D only, ``"strain"`` or ``"stress"``.
        dim: spatial dimension (default: ``mesh.dim``).
        regularization: weight w ≥ 0 of the regulariser over adjacent regions.
        reg_kind: ``"tikhonov"`` or ``"tv"`` (see :meth:`ParamMap.penalty`).

    Raises:
        ValueError: unknown field, bad labels, shapes or values out of range.
    """
    fields = tuple(fields)
    if not fields or any(f not in FIELDS for f in fields) or len(set(fields)) != len(fields):
        raise ValueError(f"fields must be a non-empty subset of {FIELDS}, got {fields!r}")
    fields = tuple(f for f in FIELDS if f in fields)
    if reg_kind not in ("tikhonov", "tv"):
        raise ValueError(f"reg_kind must be 'tikhonov' or 'tv', got {reg_kind!r}")
    if regularization < 0:
        raise ValueError(f"regularization must be >= 0, got {regularization!r}")
    if dim is None:
        if mesh is None:
            raise ValueError("make_param_map needs a mesh or dim")
        dim = mesh.dim
    if isinstance(regions, str):
        if regions != "cells":
            raise ValueError(f"regions must be None, 'cells' or an int array, got {regions!r}")
        regions = np.arange(mesh.n_cells)
    if regions is not None:
        if mesh is None:
            raise ValueError("regions need the mesh they label")
        regions = np.asarray(regions)
        if regions.shape != (mesh.n_cells,) or not np.issubdtype(regions.dtype, np.integer):
            raise ValueError(
                f"regions must be ({mesh.n_cells},) integer labels, got shape "
                f"{regions.shape} dtype {regions.dtype}"
            )
        n_reg = int(regions.max()) + 1
        if regions.min() < 0 or len(np.unique(regions)) != n_reg:
            raise ValueError(f"region labels must be 0..R-1, each used; got {np.unique(regions)}")
    else:
        n_reg = 1
    E0 = np.broadcast_to(np.asarray(init.E, np.float64), (n_reg,)).copy()
    nu0 = np.broadcast_to(np.asarray(init.nu, np.float64), (n_reg,)).copy()
    lame(E0, nu0, dim=dim, plane=plane)  # validates E > 0, -1 < nu < 0.5
    pairs = None
    if regularization > 0:
        if regions is None:
            raise ValueError("regularization needs regions (or regions='cells')")
        pairs = jnp.asarray(region_adjacency(mesh.cells, regions))
    return ParamMap(
        regions=None if regions is None else jnp.asarray(regions, jnp.int32),
        E_ref=jnp.asarray(E0),
        E0=jnp.asarray(E0),
        nu0=jnp.asarray(nu0),
        pairs=pairs,
        reg_weight=jnp.asarray(float(regularization)),
        fields=fields,
        dim=int(dim),
        plane=plane,
        reg_kind=reg_kind,
    )
