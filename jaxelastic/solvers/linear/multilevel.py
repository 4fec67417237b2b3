"""The device multigrid solver :class:`Multilevel`: aggregation multigrid built once on the
host, applied on the device inside ``jit`` as the preconditioner of :func:`~.krylov.cg`."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from ...mechanics.potential import mass_diagonal
from ...parallel.distributed import host_array
from ..host.assembled import ContentCache, content_key
from ..multilevel import (
    Hierarchy,
    ShardedHierarchy,
    build_hierarchy,
    build_sharded_hierarchy,
    preconditioner,
    sharded_preconditioner,
)
from ..results import Solution
from .krylov import cg
from .protocol import LinearSolver, LinearState
from .system import NewtonSystem

__all__ = ["Multilevel", "HIERARCHY_CAPACITY"]

HIERARCHY_CAPACITY = 8
"""Device hierarchies kept (the last ones by mesh, mask and options)."""

_HIERARCHIES = ContentCache(HIERARCHY_CAPACITY)


def _shared_hierarchy(mesh, bc, max_coarse: int, smooth: bool) -> Hierarchy:
    """The (cached) :func:`~jaxelastic.solvers.multilevel.build_hierarchy` of a mesh and
    mask: repeated solves of one scene reuse the setup (and the compiled code)."""
    opts = dict(max_coarse=max_coarse, smooth=smooth)
    key = content_key(mesh.cells, mesh.points, bc.mask, "multilevel", opts)
    return _HIERARCHIES.get(
        key,
        lambda: build_hierarchy(
            mesh.cells, mesh.points, bc.mask, max_coarse=max_coarse, smooth=smooth
        ),
    )


def _shared_sharded_hierarchy(mesh, bc, max_coarse: int, smooth: bool) -> ShardedHierarchy:
    """The (cached) hierarchy of a sharded mesh (``mesh.halo`` set, global padded layout):
    :func:`~jaxelastic.solvers.multilevel.build_hierarchy` of its real cells, whose
    aggregation follows the rest geometry (the coarse levels of the one-device mesh), then
    the per-shard level-0 tables (:func:`~jaxelastic.solvers.multilevel.build_sharded_hierarchy`).
    Keyed by the padded mesh and mask (which fix the partition) and the halo's sizes."""
    if smooth:
        raise ValueError(
            "je.Multilevel(smooth=True) is not supported on a sharded mesh (its smoothed "
            "prolongator needs whole level-0 rows); use the default smooth=False"
        )
    halo = mesh.halo
    cells, points, mask = (host_array(a) for a in (mesh.cells, mesh.points, bc.mask))
    shape = (halo.n_shards, halo.n_own, halo.n_ghost, halo.c_loc, halo.shifts)
    opts = dict(max_coarse=max_coarse, smooth=smooth, halo=shape, devices=str(halo.device_mesh))
    key = content_key(cells, points, mask, "multilevel-sharded", opts)

    def build():
        real = ~(cells == cells[:, :1]).all(axis=1)  # a padded cell repeats one node
        h = build_hierarchy(cells[real], points, mask, max_coarse=max_coarse, smooth=False)
        host_halo = jax.tree_util.tree_map(host_array, halo)
        return build_sharded_hierarchy(h, host_halo, cells)

    return _HIERARCHIES.get(key, build)


@dataclasses.dataclass(frozen=True)
class Multilevel(LinearSolver):
    """CG preconditioned by aggregation multigrid applied on the device, inside ``jit``.

    The hierarchy (aggregates, rigid-body tentative prolongators, index maps) is built once
    per (mesh, Dirichlet mask) on the host by :meth:`init`; every Newton step recomputes the
    level operators from the element Hessians on the device (exact Galerkin products) and
    runs :func:`cg` with one V-cycle per iteration (:mod:`~jaxelastic.solvers.multilevel`).
    No host callback: it works under ``jax.vmap`` (e.g. over material parameters), in
    float32 and float64, and on a sharded mesh (:func:`jaxelastic.shard`: level 0 per
    shard with halo exchanges, the coarse levels replicated, the same hierarchy and
    iterates as on one device; plain aggregation only). The hierarchy travels in the
    solver's state, an argument of the compiled solve (no large XLA constants).

    Attributes:
        degree: Chebyshev smoothing degree (pre and post).
        cycle: ``"V"`` or ``"W"``.
        coarse_scale: factor of the coarse-grid correction (in (0, 2)).
        smooth: smoothed aggregation (fewer iterations, but its Galerkin product costs
            ~14x the plain one on CPU) instead of plain aggregation.
        max_coarse: dofs of the coarsest level (dense Cholesky every Newton step).
        max_iter: CG iteration cap per linear solve.

    Its state (:meth:`init`) holds the :class:`~jaxelastic.solvers.multilevel.Hierarchy`,
    or a :class:`~jaxelastic.solvers.multilevel.ShardedHierarchy` on a sharded mesh.
    """

    degree: int = 4
    cycle: str = "V"
    coarse_scale: float = 1.3
    smooth: bool = False
    max_coarse: int = 1500
    max_iter: int = 2000

    kind = "multilevel"
    shardable = True

    def __post_init__(self):
        if int(self.degree) < 1:
            raise ValueError(f"Multilevel degree must be >= 1, got {self.degree!r}")
        if self.cycle not in ("V", "W"):
            raise ValueError(f"Multilevel cycle must be 'V' or 'W', got {self.cycle!r}")
        if not 0 < float(self.coarse_scale) < 2:
            raise ValueError(
                f"Multilevel coarse_scale must be in (0, 2) (else the preconditioner is not "
                f"positive definite), got {self.coarse_scale!r}"
            )
        if int(self.max_coarse) < 1 or int(self.max_iter) < 1:
            raise ValueError("Multilevel max_coarse and max_iter must be >= 1")

    def init(self, mesh, bc) -> LinearState:
        """The hierarchy of ``mesh`` and ``bc.mask`` (host, cached; per shard when the mesh
        is sharded)."""
        sharded = getattr(mesh, "halo", None) is not None
        shared = _shared_sharded_hierarchy if sharded else _shared_hierarchy
        h = shared(mesh, bc, int(self.max_coarse), bool(self.smooth))
        return LinearState(kind="multilevel", hierarchy=h)

    def _M(self, state, system: NewtonSystem, Ke):
        h = state.hierarchy
        halo = getattr(system.pot.mesh, "halo", None)
        if (halo is not None) != isinstance(h, ShardedHierarchy):
            raise ValueError(
                "this Multilevel() was bound to a "
                + ("one-device" if halo is not None else "sharded")
                + " mesh but solves a "
                + ("sharded" if halo is not None else "one-device")
                + " one: make its state for the mesh it solves "
                "(je.solvers.init_linear(linear, mesh, bc)), or let je.solve make it"
            )
        deg, cyc, scale = int(self.degree), self.cycle, float(self.coarse_scale)
        md = mass_diagonal(system.pot)
        if isinstance(h, ShardedHierarchy):
            M = sharded_preconditioner(
                h, halo, Ke, md, system.free, degree=deg, cycle=cyc, coarse_scale=scale
            )
        else:
            M = preconditioner(h, Ke, md, system.free, degree=deg, cycle=cyc, coarse_scale=scale)
        free = system.free

        def apply(r):
            return jnp.where(free, M(r), 0.0)

        return apply

    def symmetric_preconditioner(self, state, system: NewtonSystem, Ke, token):
        """One multigrid cycle of the level operators built from ``Ke``."""
        if Ke is None:
            raise ValueError("Multilevel needs the element Hessians (NewtonSystem.Ke)")
        return self._M(state, system, Ke), token

    def newton_step(self, state, system: NewtonSystem, A, Ke, rhs, tol, token) -> Solution:
        """Multigrid-preconditioned CG to ``‖r‖ ≤ tol`` (the level operators from ``Ke``)."""
        if Ke is None:
            raise ValueError("Multilevel needs the element Hessians (NewtonSystem.Ke)")
        return cg(A, rhs, self._M(state, system, Ke), tol=tol, max_iter=self.max_iter)

    def exact(self, state, system: NewtonSystem, b, rtol, max_iter: int) -> Solution:
        """Multigrid-preconditioned CG on the exact operator to ``‖r‖ ≤ rtol·‖b‖``
        (adjoint / tangent solves of implicit differentiation)."""
        if system.Ke is None:
            raise ValueError("Multilevel needs the element Hessians (NewtonSystem.Ke)")
        bn = jnp.sqrt(jnp.sum(b * b))
        M = self._M(state, system, system.Ke)
        return cg(system.A, b, M, tol=rtol * bn, max_iter=max_iter)
