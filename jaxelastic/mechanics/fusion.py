"""Control of XLA:CPU operator fusion: compute an intermediate once and store it, instead of
recomputing it in every loop that reads it.

XLA fuses a producer into every consumer loop that reads it and recomputes it per read.
For the element kernels that is the wrong trade: the autodiff ``∂²ψ/∂F²`` (hundreds of
operations per point) fused into the contraction was recomputed for each of the
``(k·d)²`` entries (measured 1.8× slower for tet4 than with it stored), and a per-cell
vector fused into a reduction over all cells made the reduction 16× slower than computing
the vector in one loop and summing it (the residual floor of the Newton loop at 146k tets:
0.163 s against 0.010 s). ``lax.optimization_barrier`` does not stop that fusion on CPU; a
conditional does: :func:`computed` evaluates ``fn`` inside the taken branch of a
``lax.cond`` whose predicate (:func:`always`) is true for every valid mesh, so its result
is written once, where the branch leaves it.

Computing inside the branch, not passing a finished value through it: a value passed
through a conditional is copied to the conditional's output (the 68 MB of ``∂²ψ/∂F²`` at
105k tets: 0.026 s of a 0.116 s element-Hessian call; 0.083 s computed in the branch).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

__all__ = ["always", "computed"]


def always(cells: jax.Array) -> jax.Array:
    """A traced predicate that is true for every valid mesh (cell indices are ≥ 0), for
    :func:`computed`. Compute it outside any per-cell ``vmap``, so that the conditional
    of :func:`computed` stays a conditional and does not become a select of both branches.

    Args:
        cells: ``(n_cells, k)`` integer cell table (``Mesh.cells``).
    """
    return jnp.min(cells[:1]) >= 0


def computed(fn: Callable[..., Any], pred: jax.Array, *args) -> Any:
    """``fn(*args)``, computed once and stored before its consumers read it (the true
    branch of ``lax.cond(pred, …)``; the other branch gives NaN of the same structure, so
    it could never be taken silently).

    Args:
        fn: a function of arrays returning a pytree of arrays.
        pred: :func:`always` of the mesh.
        args: ``fn``'s arguments (arrays or pytrees of arrays).
    """

    def nan(*a):
        return jax.tree_util.tree_map(_nan_like, jax.eval_shape(fn, *a))

    return jax.lax.cond(pred, fn, nan, *args)


def _nan_like(s: jax.ShapeDtypeStruct) -> jax.Array:
    """NaN of ``s``'s shape and dtype, varying over the same manual mesh axes as the
    value it stands for (inside ``shard_map`` the branches of a conditional must agree)."""
    out = jnp.full(s.shape, jnp.nan, s.dtype)
    axis_type = getattr(s, "manual_axis_type", None)
    varying = tuple(sorted(getattr(axis_type, "varying", ()) or ()))
    return jax.lax.pcast(out, varying, to="varying") if varying else out
