"""Parametrisation of any ψ parameter pytree for fitting: transforms, spatial layout, penalty.

A :class:`Parametrization` maps the optimiser's flat unconstrained vector ``z`` to a
material-parameter pytree (a user ``NamedTuple``, :class:`~jaxelastic.materials.Lame`, a
dict, …) and back. Each leaf has

* a :mod:`~jaxelastic.fitting.transforms` transform (``Positive``, ``Bounded``, ``Free``,
  ``Fixed``), and
* a spatial layout: one shared value, one value per region (``(n_cells,)`` integer labels
  ``0..R−1``, piecewise-constant fields) or one value per cell (``"cells"``).

Three forms of the parameters appear:

* ``z``: ``(n_unknowns,)``, the fitted leaves' unconstrained blocks concatenated in leaf
  order (a shared leaf contributes its size, a region leaf ``R`` values);
* *region form* (:meth:`Parametrization.from_unconstrained`): shared leaves as given,
  region leaves ``(R,)``: what a fit reports;
* *ψ form* (:meth:`Parametrization.psi_params`): region leaves gathered to ``(n_cells,)``
  fields, then ``to_psi`` (e.g. (E, ν) → Lamé): what the potential receives.

An optional regulariser over adjacent regions acts on the unconstrained variables of each
fitted region leaf: Tikhonov ``w Σ_pairs (z_i − z_j)²`` (a graph-Laplacian smoothness term)
or total variation ``w Σ_pairs (sqrt((z_i − z_j)² + ε²) − ε)``, ε = 1e-6.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .transforms import Fixed, Positive, Transform

__all__ = ["Parametrization", "make_parametrization", "region_adjacency"]

REG_KINDS = ("tikhonov", "tv")
_TV_EPS = 1e-6


def region_adjacency(cells, labels) -> np.ndarray:
    """Pairs of distinct region labels whose cells share a facet, ``(n_pairs, 2)`` int.

    Args:
        cells: ``(n_cells, dim + 1)`` connectivity (triangles or tetrahedra; for P2 cells
            the first ``dim + 1`` columns, the vertices, are used).
        labels: ``(n_cells,)`` region label of each cell.
    """
    cells = np.asarray(cells)
    labels = np.asarray(labels)
    k = cells.shape[1]
    if k in (6, 10):  # quadratic triangles / tetrahedra: vertices first
        k = 3 if k == 6 else 4
        cells = cells[:, :k]
    facets = np.concatenate([np.sort(np.delete(cells, i, axis=1), axis=1) for i in range(k)])
    owner = np.tile(np.arange(cells.shape[0]), k)
    order = np.lexsort(facets.T[::-1])
    f, o = facets[order], owner[order]
    same = np.all(f[1:] == f[:-1], axis=1)
    a, b = labels[o[:-1][same]], labels[o[1:][same]]
    pairs = np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1)[a != b]
    return np.unique(pairs, axis=0).reshape(-1, 2).astype(np.int32)


@dataclasses.dataclass(frozen=True)
class Parametrization:
    """Map between the unconstrained vector ``z`` and a parameter pytree (a pytree itself;
    built by :func:`make_parametrization`).

    Attributes:
        init: region-form initial values (pytree of arrays, the parameters' structure).
        refs: per leaf, the transform's reference array (region form) or None (Fixed).
        labels: per leaf, ``(n_cells,)`` int32 region labels, or None (shared, or held with
            its own layout).
        pairs: per leaf, ``(n_pairs, 2)`` adjacent region pairs, or None (no penalty).
        reg_weight: regularisation weight (scalar).
        transforms: per leaf :class:`~jaxelastic.fitting.transforms.Transform` (static).
        names: per leaf, a readable path such as ``"c10"`` or ``"[0]"`` (static).
        reg_kind: ``"tikhonov"`` or ``"tv"`` (static).
        to_psi: None or a hashable callable, region-expanded parameters → the pytree ψ
            takes (static; e.g. :class:`~jaxelastic.fitting.elastic.LameOf`).
    """

    init: Any
    refs: tuple
    labels: tuple
    pairs: tuple
    reg_weight: Any
    transforms: tuple = dataclasses.field(metadata=dict(static=True), default=())
    names: tuple = dataclasses.field(metadata=dict(static=True), default=())
    reg_kind: str = dataclasses.field(metadata=dict(static=True), default="tikhonov")
    to_psi: Callable | None = dataclasses.field(metadata=dict(static=True), default=None)

    @property
    def fitted(self) -> tuple[str, ...]:
        """Names of the fitted leaves."""
        return tuple(n for n, t in zip(self.names, self.transforms, strict=True) if t.fitted)

    def _leaves(self) -> tuple[list, Any]:
        return jax.tree_util.tree_flatten(self.init)

    def sizes(self) -> tuple[int, ...]:
        """Number of unknowns of each leaf (0 for Fixed leaves), static."""
        leaves, _ = self._leaves()
        return tuple(
            int(np.prod(jnp.shape(v), dtype=int)) if t.fitted else 0
            for v, t in zip(leaves, self.transforms, strict=True)
        )

    @property
    def size(self) -> int:
        """Length of ``z``."""
        return sum(self.sizes())

    def blocks(self, z) -> list:
        """``z`` split per leaf: arrays of each fitted leaf's region-form shape, None for Fixed."""
        leaves, _ = self._leaves()
        out, i = [], 0
        for v, n in zip(leaves, self.sizes(), strict=True):
            out.append(None if n == 0 else z[i : i + n].reshape(jnp.shape(v)))
            i += n
        return out

    def to_unconstrained(self, params) -> jax.Array:
        """Region-form ``params`` (same structure as ``init``) → ``z`` ``(size,)``."""
        leaves = jax.tree_util.tree_structure(self.init).flatten_up_to(params)
        zs = [
            jnp.ravel(t.inverse(jnp.asarray(v), r))
            for v, r, t in zip(leaves, self.refs, self.transforms, strict=True)
            if t.fitted
        ]
        if not zs:
            return jnp.zeros((0,))
        return jnp.concatenate(zs)

    def initial_z(self) -> jax.Array:
        """``z`` of the initial values, ``(size,)``."""
        return self.to_unconstrained(self.init)

    def from_unconstrained(self, z):
        """``z`` ``(size,)`` → region-form parameters; Fixed leaves exactly ``init``."""
        leaves, treedef = self._leaves()
        vals = [
            v if b is None else t.forward(b, r)
            for v, b, r, t in zip(leaves, self.blocks(z), self.refs, self.transforms, strict=True)
        ]
        return jax.tree_util.tree_unflatten(treedef, vals)

    def expand(self, params):
        """Region form → ψ form: region leaves gathered to ``(n_cells,)``, then ``to_psi``."""
        leaves, treedef = jax.tree_util.tree_flatten(params)
        vals = [v if lab is None else v[lab] for v, lab in zip(leaves, self.labels, strict=True)]
        out = jax.tree_util.tree_unflatten(treedef, vals)
        return out if self.to_psi is None else self.to_psi(out)

    def psi_params(self, z):
        """The parameters the potential receives at ``z`` (:meth:`expand` of
        :meth:`from_unconstrained`)."""
        return self.expand(self.from_unconstrained(z))

    def penalty(self, z) -> jax.Array:
        """Regulariser over adjacent regions of the fitted region leaves (scalar)."""
        total = jnp.zeros((), z.dtype)
        for b, p in zip(self.blocks(z), self.pairs, strict=True):
            if b is None or p is None:
                continue
            d = b[p[:, 0]] - b[p[:, 1]]
            if self.reg_kind == "tikhonov":
                total = total + jnp.sum(d * d)
            else:
                total = total + jnp.sum(jnp.sqrt(d * d + _TV_EPS * _TV_EPS) - _TV_EPS)
        return self.reg_weight * total


jax.tree_util.register_dataclass(
    Parametrization,
    data_fields=["init", "refs", "labels", "pairs", "reg_weight"],
    meta_fields=["transforms", "names", "reg_kind", "to_psi"],
)


def _leaf_names(params) -> tuple[str, ...]:
    paths, _ = jax.tree_util.tree_flatten_with_path(params)
    names = []
    for path, _leaf in paths:
        s = "".join(
            f".{k.name}" if hasattr(k, "name") else f"[{getattr(k, 'key', getattr(k, 'idx', k))}]"
            for k in path
        )
        names.append(s.lstrip(".") or "params")
    return tuple(names)


def _labels(spec, mesh, name: str):
    """``(n_cells,)`` int labels of a layout spec (None, ``"cells"`` or labels) or None."""
    if spec is None:
        return None
    if mesh is None:
        raise ValueError(f"parameter {name}: regions need the mesh they label (mesh=...)")
    if isinstance(spec, str):
        if spec != "cells":
            raise ValueError(f"regions must be None, 'cells' or an int array, got {spec!r}")
        return np.arange(mesh.n_cells, dtype=np.int32)
    lab = np.asarray(spec)
    if lab.shape != (mesh.n_cells,) or not np.issubdtype(lab.dtype, np.integer):
        raise ValueError(
            f"regions must be ({mesh.n_cells},) integer labels, got shape {lab.shape} "
            f"dtype {lab.dtype}"
        )
    n = int(lab.max()) + 1
    if lab.min() < 0 or len(np.unique(lab)) != n:
        raise ValueError(f"region labels must be 0..R-1, each used; got {np.unique(lab)}")
    return lab.astype(np.int32)


def _is_single_layout(regions) -> bool:
    return regions is None or isinstance(regions, str | np.ndarray | jax.Array | list)


def _per_leaf(treedef, spec, what: str) -> list:
    """``spec`` broadcast to one entry per leaf: a single value, or a prefix tree."""
    try:
        return treedef.flatten_up_to(spec)
    except (ValueError, TypeError) as e:
        raise ValueError(
            f"{what} must be one value for all leaves or a tree with the parameters' "
            f"structure {treedef}; got {spec!r}"
        ) from e


def _leaf_init(value, transform: Transform, lab, name: str):
    """(region-form initial value, reference) of one leaf, validated."""
    v = np.asarray(value, dtype=np.float64) if transform.fitted else value
    if lab is not None and transform.fitted:
        n_reg = int(lab.max()) + 1
        if np.ndim(v) not in (0, 1) or (np.ndim(v) == 1 and v.shape[0] != n_reg):
            raise ValueError(
                f"parameter {name}: with {n_reg} regions the initial value must be a scalar "
                f"or ({n_reg},), got shape {np.shape(v)}"
            )
        v = np.broadcast_to(v, (n_reg,)).copy()
    transform.check(v, name)
    v = jnp.asarray(v)
    return v, (transform.reference(v) if transform.fitted else None)


def _layout(leaves, ts, specs, names, mesh, regularize: bool):
    """Per leaf: (region-form initial value, reference, labels, adjacent pairs)."""
    labels, vals, refs, pairs = [], [], [], []
    for v, t, spec, n in zip(leaves, ts, specs, names, strict=True):
        lab = _labels(spec, mesh, n)
        if lab is not None and not t.fitted and np.shape(v) != (int(lab.max()) + 1,):
            lab = None  # a held leaf keeps its own layout unless it is one value per region
        v0, ref = _leaf_init(v, t, lab, n)
        vals.append(v0)
        refs.append(ref)
        labels.append(None if lab is None else jnp.asarray(lab))
        fit_reg = lab is not None and t.fitted and regularize
        pairs.append(jnp.asarray(region_adjacency(mesh.cells, lab)) if fit_reg else None)
    if regularize and all(p is None for p in pairs):
        raise ValueError("regularization needs regions (or regions='cells')")
    return vals, refs, labels, pairs


def make_parametrization(
    init,
    transforms=None,
    *,
    regions=None,
    fields=None,
    mesh=None,
    regularization: float = 0.0,
    reg_kind: str = "tikhonov",
    to_psi: Callable | None = None,
) -> Parametrization:
    """Build a :class:`Parametrization` of the parameter pytree ``init``.

    Args:
        init: initial parameters, any pytree (e.g. ``MR(c10=1e5, c01=2e4, kappa=1e7)``);
            shared leaves scalars (or any shape), region leaves scalars or ``(R,)``.
        transforms: a :class:`~jaxelastic.fitting.transforms.Transform` for every leaf, or
            a tree with ``init``'s structure holding one per leaf (e.g.
            ``MR(Positive(), Positive(), Fixed())``); default ``Positive()`` everywhere.
        regions: layout of the fitted leaves: None (shared), ``(n_cells,)`` int labels
            ``0..R−1``, ``"cells"``, or a tree with ``init``'s structure of those (per leaf).
        fields: names of the leaves to fit (e.g. ``("c10", "c01")``; see
            :attr:`Parametrization.names`); the others become ``Fixed()``. Default: every
            leaf whose transform is not ``Fixed``.
        mesh: the mesh the labels refer to (needed for regions and regularisation).
        regularization: weight w ≥ 0 of the penalty over adjacent regions.
        reg_kind: ``"tikhonov"`` or ``"tv"``.
        to_psi: optional hashable callable, region-expanded parameters → ψ's pytree.

    Raises:
        ValueError: bad transforms, labels, shapes, or initial values outside a transform's
            range.
    """
    if reg_kind not in REG_KINDS:
        raise ValueError(f"reg_kind must be 'tikhonov' or 'tv', got {reg_kind!r}")
    if not regularization >= 0:
        raise ValueError(f"regularization must be >= 0, got {regularization!r}")
    leaves, treedef = jax.tree_util.tree_flatten(init)
    if not leaves:
        raise ValueError("the parameters have no leaves to fit")
    names = _leaf_names(init)
    if transforms is None:
        transforms = Positive()
    ts = [transforms] * len(leaves) if isinstance(transforms, Transform) else None
    if ts is None:
        ts = _per_leaf(treedef, transforms, "transforms")
    for n, t in zip(names, ts, strict=True):
        if not isinstance(t, Transform):
            raise ValueError(f"parameter {n}: transform must be a Transform, got {t!r}")
    if fields is not None:
        fields = (fields,) if isinstance(fields, str) else tuple(fields)
        unknown = [f for f in fields if f not in names]
        if unknown or not fields:
            raise ValueError(f"fields must name parameters among {names}, got {fields!r}")
        ts = [t if n in fields else Fixed() for n, t in zip(names, ts, strict=True)]
    if not any(t.fitted for t in ts):
        raise ValueError("every parameter is Fixed: nothing to fit")
    single = _is_single_layout(regions)
    specs = [regions] * len(leaves) if single else _per_leaf(treedef, regions, "regions")
    vals, refs, labels, pairs = _layout(leaves, ts, specs, names, mesh, regularization > 0)
    return Parametrization(
        init=jax.tree_util.tree_unflatten(treedef, vals),
        refs=tuple(refs),
        labels=tuple(labels),
        pairs=tuple(pairs),
        reg_weight=jnp.asarray(float(regularization)),
        transforms=tuple(ts),
        names=names,
        reg_kind=reg_kind,
        to_psi=to_psi,
    )
