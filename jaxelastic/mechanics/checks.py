"""Input checks of the mechanics kernels, and the per-cell parameter axes.

Every public ``(psi, x, mesh, params)`` function checks, before anything is traced and at no
cost to a jitted computation (static shapes only, under jit/vmap/grad too): ``x`` (and
``v``) must have the mesh's shape ``(n_nodes, dim)`` (:func:`check_positions`), and ψ must
return a scalar float for one unbatched ``(d, d)`` F (:func:`check_psi`, evaluated
abstractly once per ψ, dimension, dtype and parameter structure, then cached). Outside any
transformation (no argument is a JAX tracer) they also refuse NaN/inf in ``x`` and the
float leaves of ``params`` (:func:`check_finite`); inside ``jax.jit`` (or under
``vmap``/``grad``) nothing is checked by value and non-finite input gives NaN results (the
solvers report it in their status).

``params`` is any pytree: a leaf of shape ``()`` is shared by all cells, a leaf with a
leading axis of length ``n_cells`` is a per-cell field (:func:`cell_params_axes`), and an
:class:`~jaxelastic.mechanics.quadrature_fields.AtQuadrature` of shape ``(n_cells, n_q, ...)``
a per-quadrature-point field (:func:`check_call` checks ``n_q`` against the mesh).
"""

from __future__ import annotations

import math
import weakref

import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer

from .quadrature_fields import check_quadrature_fields, is_at_quadrature

__all__ = [
    "cell_params_axes",
    "per_cell",
    "check_positions",
    "check_psi",
    "check_finite",
    "check_call",
    "psi_name",
]


def cell_params_axes(params, n_cells: int):
    """vmap ``in_axes`` for ``params``: 0 for per-cell leaves and per-point
    (:class:`~jaxelastic.mechanics.quadrature_fields.AtQuadrature`) nodes, None for shared
    scalars.

    Raises:
        ValueError: a non-scalar leaf whose leading axis is not ``n_cells``.
    """

    def axis(leaf):
        if is_at_quadrature(leaf):
            shape = tuple(getattr(leaf.values, "shape", ()))
            if len(shape) < 2 or shape[0] != n_cells:
                raise ValueError(
                    f"material parameter AtQuadrature of shape {shape} is not a per-point "
                    f"field of shape (n_cells, n_q, ...) with n_cells={n_cells}"
                )
            return 0
        shape = jnp.shape(leaf)
        if len(shape) == 0:
            return None
        if shape[0] != n_cells:
            raise ValueError(
                f"material parameter leaf of shape {shape} is neither a scalar nor a "
                f"per-cell field with leading axis n_cells={n_cells}"
            )
        return 0

    return jax.tree_util.tree_map(axis, params, is_leaf=is_at_quadrature)


def per_cell(fn, params, n_cells):
    """vmap ``fn(cell_data..., params)`` over cells, broadcasting shared parameters."""
    return jax.vmap(fn, in_axes=(0, 0, 0, cell_params_axes(params, n_cells)))


# ----------------------------------------------------------------------------- input checks


def psi_name(psi) -> str:
    """A readable name of ψ for error messages: its ``__qualname__`` (that of the wrapped
    function for ``functools.partial``), else its ``repr``."""
    func = getattr(psi, "func", None)  # functools.partial
    if func is not None and callable(func) and hasattr(psi, "args"):
        return f"functools.partial({psi_name(func)}, ...)"
    name = getattr(psi, "__qualname__", None) or getattr(psi, "__name__", None)
    return str(name) if name else repr(psi)


def check_positions(x, mesh, *, name: str = "x", where: str = "je.energy") -> None:
    """Raise unless ``x`` has the shape ``(n_nodes, dim)`` of ``mesh.points``.

    Static shapes only: free under jit, and under vmap it checks the per-example shape.

    Args:
        x: the array to check (positions, or a direction such as ``v`` of
            :func:`~jaxelastic.mechanics.kernels.hvp`).
        mesh: the :class:`~jaxelastic.mesh.Mesh` it belongs to.
        name, where: the argument's and the calling function's names, for the message.

    Raises:
        TypeError: ``mesh`` is not a mesh (e.g. arguments swapped).
        ValueError: the message names the argument, the expected and the given shape.
    """
    pts = getattr(mesh, "points", None)
    if pts is None or not hasattr(pts, "shape") or not hasattr(mesh, "cells"):
        raise TypeError(
            f"{where}: mesh must be a je.Mesh (e.g. je.rectangle(...), je.read_mesh(path).mesh),"
            f" got {type(mesh).__name__}; the signature is {where}(psi, x, mesh, params)"
        )
    shape, want = tuple(jnp.shape(x)), tuple(pts.shape)
    if shape != want:
        dim = want[1] if len(want) == 2 else "?"
        raise ValueError(
            f"{where}: {name} must have shape (n_nodes, dim) = {want} like mesh.points "
            f"(a {dim}D mesh of {want[0]} nodes), got {shape}"
        )


# ψ -> set of (dim, dtype, params structure) keys already checked
_PSI_CHECKED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


_NUMBERS = (bool, int, float, complex)


def _param_key(params, n_cells: int):
    """``(treedef, leaves, per_cell, key)`` of ``params``: ``per_cell[i]`` is the number of
    leading axes of leaf i that ψ does not see (0 shared, 1 per cell, 2 per quadrature point:
    an :class:`~jaxelastic.mechanics.quadrature_fields.AtQuadrature`, a leaf here); ``key``
    is a hashable summary of the structure ψ sees (None if a leaf is neither an array nor a
    Python number: nothing can be checked)."""
    leaves, treedef = jax.tree_util.tree_flatten(params, is_leaf=is_at_quadrature)
    per_cell, key = [], []
    for leaf in leaves:
        if is_at_quadrature(leaf):
            cell_params_axes(leaf, n_cells)  # raises on a bad shape
            v = leaf.values
            per_cell.append(2)
            key.append(("q", tuple(v.shape), v.dtype, bool(getattr(v, "weak_type", False))))
            continue
        if isinstance(leaf, _NUMBERS):
            per_cell.append(0)
            key.append(type(leaf))
            continue
        shape, dtype = getattr(leaf, "shape", None), getattr(leaf, "dtype", None)
        if shape is None or dtype is None:
            return treedef, leaves, per_cell, None
        shape = tuple(shape)
        if shape and shape[0] != n_cells:
            cell_params_axes(params, n_cells)  # raises the message naming the shape
        per_cell.append(int(bool(shape)))
        key.append((shape, dtype, bool(getattr(leaf, "weak_type", False))))
    return treedef, leaves, per_cell, (treedef, tuple(key))


def _param_spec(treedef, leaves, per_cell):
    """Parameters as ψ sees them at one point, as ShapeDtypeStructs (numbers kept,
    per-point wrappers removed)."""
    spec = []
    for leaf, pc in zip(leaves, per_cell, strict=True):
        if isinstance(leaf, _NUMBERS):
            spec.append(leaf)
            continue
        a = leaf.values if is_at_quadrature(leaf) else leaf
        spec.append(
            jax.ShapeDtypeStruct(
                tuple(a.shape)[pc:], a.dtype, weak_type=bool(getattr(a, "weak_type", False))
            )
        )
    return jax.tree_util.tree_unflatten(treedef, spec)


def _describe_return(out, raw) -> str | None:
    """What ψ returned, when it is not a scalar float (else None)."""
    if isinstance(raw, bool) or isinstance(raw, int):
        return f"the Python {type(raw).__name__} {raw!r}"
    if not isinstance(out, jax.ShapeDtypeStruct):
        return f"a {type(raw).__name__}" + (f" {raw!r}" if raw is None else "")
    if out.shape != () or not jnp.issubdtype(out.dtype, jnp.floating):
        return f"an array of shape {out.shape} and dtype {out.dtype}"
    return None


def check_psi(
    psi, dim: int, dtype, params, n_cells: int, *, where: str = "je.energy", own_errors=True
) -> None:
    """Raise unless ``psi(F, params)`` returns a scalar float for one ``(dim, dim)`` F.

    Evaluated abstractly (``jax.eval_shape`` at F = I with one cell's parameters), so it
    works under jit/vmap/grad too; the result is cached per ψ object, ``dim``, ``dtype`` and
    parameter structure, so repeated calls cost a dictionary lookup. Errors raised by ψ
    itself propagate unchanged (``own_errors=True``) or are ignored (``own_errors=False``,
    e.g. for a potential built with placeholder parameters: they surface when it is used).

    Args:
        psi: the strain-energy density ``psi(F, params)``.
        dim: 2 or 3.
        dtype: the float dtype of F (the mesh's).
        params: the parameter pytree as passed to the energy (shared or per-cell leaves).
        n_cells: number of cells (to recognise per-cell leaves).
        where: the calling function's name, for the message.

    Raises:
        TypeError: ψ is not callable, or returns anything but a scalar float (the message
            names ψ by its ``__qualname__``, what it returned and what is required).
        ValueError: a parameter leaf is neither a scalar nor a per-cell field.
    """
    if not callable(psi):
        raise TypeError(f"{where}: psi must be a function psi(F, params), got {psi!r}")
    treedef, leaves, per_cell, key = _param_key(params, n_cells)
    if key is None:
        return
    key = (int(dim), jnp.dtype(dtype), key)
    try:
        done = _PSI_CHECKED.get(psi)
    except TypeError:  # unhashable callable: check every time
        done = None
    if done is not None and key in done:
        return
    spec = _param_spec(treedef, leaves, per_cell)
    raw = []

    def at_identity(p):
        out = psi(jnp.eye(dim, dtype=dtype), p)
        raw.append(out)
        return out

    try:
        out = jax.eval_shape(at_identity, spec)
    except (AttributeError, KeyError) as e:  # ψ read a field its parameters do not have
        if not own_errors:
            return
        raise TypeError(
            f"{where}: ψ {psi_name(psi)!r} could not read its parameters "
            f"({type(e).__name__}: {e}); they were a {type(params).__name__}. The built-in "
            "models take je.Lame(mu, lam) (e.g. je.Lame.from_E_nu(E, nu)); a user ψ gets "
            "exactly the pytree given as params"
        ) from e
    except Exception:
        if own_errors:
            raise
        return
    what = _describe_return(out, raw[0] if raw else None)
    if what is not None:
        raise TypeError(
            f"{where}: ψ {psi_name(psi)!r} returned {what} at F = I ({dim}×{dim}); a "
            f"strain-energy density must return a scalar float for one unbatched F of shape "
            f"({dim}, {dim}) (reduce with jnp.sum, return floats: 0.0 not 0)"
        )
    try:
        _PSI_CHECKED.setdefault(psi, set()).add(key)
    except TypeError:
        pass  # not weak-referenceable or unhashable: nothing is cached


def _first_bad(leaf) -> str:
    """Where the first NaN/inf of a concrete array sits (for the message)."""
    a = np.asarray(leaf)
    bad = ~np.isfinite(a)
    n = int(bad.sum())
    if a.ndim == 0:
        return f"is {a.item()!r}"
    idx = np.unravel_index(int(np.flatnonzero(bad.ravel())[0]), a.shape)
    at = f"node {idx[0]}" if a.ndim == 2 else f"index {tuple(int(i) for i in idx)}"
    return f"has {n} NaN/inf value(s) of {a.size}, the first at {at} ({a[idx]!r})"


def _all_finite(a: jax.Array) -> bool:
    """``isfinite(a).all()`` of a concrete array: on the host for CPU arrays (a zero-copy
    view, ~5 µs), one reduction on the device otherwise (no copy of ``a``)."""
    if all(d.platform == "cpu" for d in a.devices()) and a.is_fully_addressable:
        return bool(np.isfinite(np.asarray(a)).all())
    return bool(jnp.isfinite(a).all())


def check_finite(where: str, **trees) -> None:
    """Outside any JAX transformation, raise if a float leaf of ``trees`` holds NaN/inf.

    Skipped entirely (free) when any leaf is a JAX tracer, i.e. under jit/vmap/grad, where
    NaN propagates to the results instead. One reduction per float array otherwise.

    Args:
        where: the calling function's name, for the message.
        trees: name → array or pytree (e.g. ``x=x, params=params``).

    Raises:
        ValueError: the message names the argument (and the leaf path of a pytree).
    """
    named = []
    for name, tree in trees.items():
        for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
            if isinstance(leaf, Tracer):
                return
            named.append((name + jax.tree_util.keystr(path), leaf))
    for name, leaf in named:
        if isinstance(leaf, float):
            ok = math.isfinite(leaf)
        elif isinstance(leaf, (np.ndarray, np.generic)):
            ok = not np.issubdtype(leaf.dtype, np.inexact) or bool(np.isfinite(leaf).all())
        elif isinstance(leaf, jax.Array):
            ok = not jnp.issubdtype(leaf.dtype, jnp.inexact) or _all_finite(leaf)
        else:
            continue
        if not ok:
            raise ValueError(
                f"{where}: {name} {_first_bad(leaf)}; refusing non-finite input (inside "
                "jax.jit nothing is checked and the result is NaN)"
            )


def check_call(where: str, psi, x, mesh, params, **more) -> None:
    """The checks of every public ``(psi, x, mesh, params)`` function."""
    check_positions(x, mesh, where=where)
    for name, v in more.items():
        check_positions(v, mesh, name=name, where=where)
    check_quadrature_fields(params, mesh.n_cells, int(mesh.weights.shape[1]), where=where)
    check_psi(psi, mesh.points.shape[1], mesh.points.dtype, params, mesh.n_cells, where=where)
    if not isinstance(mesh.points, Tracer):  # a traced mesh: inside a transformation
        check_finite(where, x=x, params=params, **more)
