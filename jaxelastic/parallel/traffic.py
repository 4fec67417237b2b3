"""Communication volume of a sharded problem, counted in compiled HLO.

:func:`communication` compiles one HVP, one CG matvec and one block-Jacobi CG iteration of
a problem from :func:`jaxelastic.shard` in three layouts and sums the operand bytes of
their collectives (:func:`jaxelastic.parallel.sharding.collective_bytes`), with warm times:

* ``"halo"``: as :func:`~jaxelastic.shard` made it (shard_map, ghost nodes by ppermute);
* ``"xla"``: the same sharded arrays without the halo (XLA inserts the communication);
* ``"replicated"``: cell arrays sharded, node arrays replicated (one all-reduce per
  product).
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from ..loads import Dirichlet
from ..mechanics import potential as pm
from ..mechanics.hessians import element_hessians
from ..mechanics.kernels import hvp
from ..mechanics.potential import Potential
from ..solvers.linear import block_jacobi, cg
from .sharding import collective_bytes

__all__ = ["communication", "layout", "LAYOUTS"]

LAYOUTS = ("halo", "xla", "replicated")
_NODE_FIELDS = ("f_ext", "mass", "x_tilde", "x_prev")


def layout(pot_s: Potential, bc_s: Dirichlet, name: str):
    """``(pot, bc)`` of a sharded problem in one of the :data:`LAYOUTS` (module docstring).

    Raises:
        ValueError: an unknown layout name.
    """
    if name == "halo":
        return pot_s, bc_s
    mesh = dataclasses.replace(pot_s.mesh, halo=None)
    if name == "xla":
        return pot_s.replace(mesh=mesh), bc_s
    if name != "replicated":
        raise ValueError(f"layout must be 'halo', 'xla' or 'replicated', got {name!r}")
    rep = NamedSharding(pot_s.mesh.halo.device_mesh, P())
    put = lambda a: None if a is None else jax.device_put(a, rep)
    mesh = dataclasses.replace(mesh, points=put(mesh.points), incidence=put(mesh.incidence))
    fields = {k: put(getattr(pot_s, k)) for k in _NODE_FIELDS if getattr(pot_s, k) is not None}
    bc = Dirichlet(jax.device_put(bc_s.mask, rep), jax.device_put(bc_s.values, rep))
    return pot_s.replace(mesh=mesh, **fields), bc


def communication(pot_s: Potential, bc_s: Dirichlet, *, layouts=LAYOUTS, repeat: int = 3) -> dict:
    """Communication per HVP and per CG iteration of a sharded problem, from compiled HLO,
    and the warm time of each, for several layouts (see :func:`layout`).

    For each layout: ``hvp`` (one :func:`~jaxelastic.hvp`), ``matvec`` (one CG matvec
    from element Hessians, :func:`~jaxelastic.mechanics.potential.element_hessian_vp`) and
    ``cg_iteration`` (one iteration of block-Jacobi CG, the ``while`` body of
    :func:`~jaxelastic.solvers.linear.krylov`): :func:`collective_bytes` dicts (per device)
    plus ``time_s`` (min over ``repeat`` runs of 10 calls, divided by 10) for ``hvp`` and
    ``matvec``. ``halo_estimate_bytes``: the ghost traffic :class:`Halo` predicts for one
    3-vector gather.

    Args:
        pot_s, bc_s: from :func:`shard`.
        layouts: any of ``"halo"``, ``"xla"``, ``"replicated"``.
        repeat: timing repetitions.
    """
    halo = pot_s.mesh.halo
    if halo is None:
        raise ValueError("communication: pass a potential from je.shard (with a halo)")
    dim = pot_s.mesh.dim
    out: dict = dict(
        shards=halo.n_shards,
        halo_estimate_bytes=halo.exchange_bytes(dim, pot_s.mesh.points.dtype.itemsize),
    )

    def timed(f, *args):
        jax.block_until_ready(f(*args))
        best = np.inf
        for _ in range(repeat):
            t = time.perf_counter()
            for _ in range(10):
                r = f(*args)
            jax.block_until_ready(r)
            best = min(best, (time.perf_counter() - t) / 10)
        return best

    for name in layouts:
        pot, bc = layout(pot_s, bc_s, name)
        x = pot.mesh.points
        f_hvp = jax.jit(lambda pot, x, v: hvp(pot.psi, x, v, pot.mesh, pot.params))
        Ke = jax.jit(lambda pot, x: element_hessians(pot.psi, x, pot.mesh, pot.params))(pot, x)
        f_mv = jax.jit(pm.element_hessian_vp)

        def one_cg(pot, Ke, b, free):
            fm = free.astype(b.dtype)
            A = lambda v: fm * pm.element_hessian_vp(pot, Ke, fm * v) + (1 - fm) * v
            M = block_jacobi(pm.node_hessian_blocks(pot, Ke), free, lapack=False)
            return cg(A, b, M, tol=jnp.zeros((), b.dtype), max_iter=100).x

        f_cg = jax.jit(one_cg)
        rec = {}
        hlo = f_hvp.lower(pot, x, x).compile().as_text() or ""
        rec["hvp"] = dict(collective_bytes(hlo), time_s=timed(f_hvp, pot, x, x))
        hlo = f_mv.lower(pot, Ke, x).compile().as_text() or ""
        rec["matvec"] = dict(collective_bytes(hlo), time_s=timed(f_mv, pot, Ke, x))
        hlo = f_cg.lower(pot, Ke, x, ~bc.mask).compile().as_text() or ""
        rec["cg_iteration"] = collective_bytes(hlo, loop_body=True)
        out[name] = rec
    return out
