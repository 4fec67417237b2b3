"""Material data per quadrature point: the :class:`AtQuadrature` parameter leaf.

A material parameter pytree has three kinds of leaves (:mod:`~jaxelastic.mechanics.checks`):

* shared: shape ``()`` (or a vector the material treats as shared, broadcast by the
  material's own helper, e.g. :func:`~jaxelastic.materials.per_cell_basis`);
* per cell: a leading axis of length ``n_cells``, constant over the cell;
* per quadrature point: ``AtQuadrature(values)`` with ``values`` of shape
  ``(n_cells, n_q, ...)``, one value at each quadrature point of each cell (``n_q`` =
  ``mesh.weights.shape[1]``, the points of
  :func:`~jaxelastic.mesh.geometry.quadrature_points`).

ψ never sees the wrapper: at a quadrature point it gets the plain ``values[c, q]`` (for a
fibre direction, a ``(3,)`` vector, exactly as a per-cell direction arrives). A per-point
field resolves what a per-cell one cannot: a fibre angle that turns by 180° through a wall
one to three cells thick (:func:`~jaxelastic.materials.per_quadrature_basis`). A parameter
pytree without the wrapper runs the per-cell code unchanged (nothing is added to it).

Gradients with respect to per-point values work as for per-cell ones (the wrapper is a
pytree node; its gradient is an ``AtQuadrature`` of the same shape).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax

__all__ = [
    "AtQuadrature",
    "is_at_quadrature",
    "has_quadrature_fields",
    "plain_params",
    "first_point_params",
    "quadrature_axes",
    "over_quadrature",
    "check_quadrature_fields",
]


class AtQuadrature(NamedTuple):
    """A material parameter given at every quadrature point.

    Attributes:
        values: ``(n_cells, n_q, ...)``: the value at quadrature point q of cell c is
            ``values[c, q]`` (what ψ receives there), in the order of the element's
            quadrature rule (``mesh.weights[c, q]``).
    """

    values: Any


def is_at_quadrature(node) -> bool:
    """Whether ``node`` is an :class:`AtQuadrature` (the ``is_leaf`` of tree maps here)."""
    return isinstance(node, AtQuadrature)


def has_quadrature_fields(params) -> bool:
    """Whether any node of ``params`` is an :class:`AtQuadrature` (static: pytree structure)."""
    nodes = jax.tree_util.tree_leaves(params, is_leaf=is_at_quadrature)
    return any(is_at_quadrature(n) for n in nodes)


def plain_params(params):
    """``params`` with each :class:`AtQuadrature` replaced by its values."""
    return jax.tree_util.tree_map(
        lambda n: n.values if is_at_quadrature(n) else n, params, is_leaf=is_at_quadrature
    )


def first_point_params(params):
    """Per-cell ``params``: each :class:`AtQuadrature` ``(n_cells, n_q, ...)`` replaced by
    its values at the cell's first quadrature point ``(n_cells, ...)`` (for per-cell probes
    of a material, not for the energy)."""
    return jax.tree_util.tree_map(
        lambda n: n.values[:, 0] if is_at_quadrature(n) else n, params, is_leaf=is_at_quadrature
    )


def quadrature_axes(params):
    """vmap ``in_axes`` of :func:`plain_params` over the quadrature axis: 0 where ``params``
    holds an :class:`AtQuadrature` (after the per-cell vmap its values are ``(n_q, ...)``),
    None (shared across the cell's points) elsewhere."""
    return jax.tree_util.tree_map(
        lambda n: 0 if is_at_quadrature(n) else None, params, is_leaf=is_at_quadrature
    )


def over_quadrature(fn: Callable) -> Callable:
    """``fn(F, params)`` of one point, mapped over one cell's points: ``(F (q, ...), params)
    ↦ fn`` at each point, per-point values taken at their point, the rest shared.

    ``fn`` is ψ or a derivative of it (``jax.grad(psi)``, ``jax.hessian(psi)``). Without
    per-point fields this is ``jax.vmap(fn, in_axes=(0, None))``, as before.
    """
    shared = jax.vmap(fn, in_axes=(0, None))

    def mapped(F, params):
        if not has_quadrature_fields(params):
            return shared(F, params)
        return jax.vmap(fn, in_axes=(0, quadrature_axes(params)))(F, plain_params(params))

    return mapped


def check_quadrature_fields(params, n_cells: int, n_q: int, *, where: str = "je.energy") -> None:
    """Raise unless every :class:`AtQuadrature` of ``params`` holds an array of shape
    ``(n_cells, n_q, ...)`` (static shapes only: free under jit).

    Raises:
        TypeError: the values are not an array (e.g. a tuple or a nested pytree).
        ValueError: the message names the leaf, its shape and the mesh's ``(n_cells, n_q)``.
    """
    flat = jax.tree_util.tree_flatten_with_path(params, is_leaf=is_at_quadrature)[0]
    for path, node in flat:
        if not is_at_quadrature(node):
            continue
        name = "params" + jax.tree_util.keystr(path)
        shape = getattr(node.values, "shape", None)
        if shape is None or not hasattr(node.values, "dtype"):
            raise TypeError(
                f"{where}: {name} is an AtQuadrature of {type(node.values).__name__}; its "
                "values must be one array of shape (n_cells, n_q, ...)"
            )
        shape = tuple(shape)
        if len(shape) < 2 or shape[:2] != (n_cells, n_q):
            raise ValueError(
                f"{where}: {name} is an AtQuadrature of shape {shape}; this mesh needs "
                f"(n_cells, n_q, ...) = ({n_cells}, {n_q}, ...) (n_q = mesh.weights.shape[1], "
                "the points of je.mesh.geometry.quadrature_points)"
            )
