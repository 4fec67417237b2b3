"""Control of XLA:CPU operator fusion: store an intermediate once instead of recomputing it.

XLA fuses a producer into every consumer loop that reads it and recomputes it per read.
For the element kernels that is the wrong trade: the autodiff ``∂²ψ/∂F²`` (hundreds of
operations per point) fused into the contraction was recomputed for each of the
``(k·d)²`` entries (measured 1.8× slower for tet4 than with it stored), and a per-cell
vector fused into a reduction over all cells made the reduction 16× slower than computing
the vector in one loop and summing it (the residual floor of the Newton loop at 146k tets:
0.163 s against 0.010 s). ``lax.optimization_barrier`` does not stop that fusion on CPU; a
conditional does: :func:`stored` returns its argument through a ``lax.cond`` whose
predicate (:func:`always`) is true for every valid mesh.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["always", "stored"]


def always(cells: jax.Array) -> jax.Array:
    """A traced predicate that is true for every valid mesh (cell indices are ≥ 0), for
    :func:`stored`. Compute it outside any per-cell ``vmap``, so that the conditional of
    :func:`stored` stays a conditional and does not become a select of both branches.

    Args:
        cells: ``(n_cells, k)`` integer cell table (``Mesh.cells``).
    """
    return jnp.min(cells[:1]) >= 0


def stored(a, pred: jax.Array):
    """``a`` (any pytree of arrays) unchanged, but computed once and stored before its
    consumers read it.

    Args:
        a: the intermediate(s) to store.
        pred: :func:`always` of the mesh. The other branch gives NaN, so it could never be
            taken silently.
    """
    return jax.lax.cond(
        pred,
        lambda t: t,
        lambda t: jax.tree_util.tree_map(lambda b: jnp.full_like(b, jnp.nan), t),
        a,
    )
