"""Linear solvers of the Newton system: one device CG, and host back ends as its servants.

* :func:`cg` is the one conjugate-gradient loop of the library (``lax.while_loop``, under
  ``jit``/``vmap``). It stops on the residual (``‖r‖ ≤ tol``), at ``max_iter``, or on
  non-positive curvature ``pᵀAp ≤ 0`` (an indefinite Hessian far from equilibrium): then it
  returns the last iterate, or the preconditioned steepest-descent direction if that
  happens in the first iteration, and says so in its status.
* Linear-solver objects are small frozen (hashable, static under jit) dataclasses:
  :class:`CG` (matrix-free, block-Jacobi/Jacobi preconditioned), :class:`Direct` (sparse
  Cholesky on the host), :class:`AMG` (PyAMG smoothed aggregation on the host as the
  preconditioner of :func:`cg`) and :class:`Multilevel` (aggregation multigrid built once
  on the host, applied on the device inside ``jit``: :mod:`~jaxelastic.solvers.multilevel`).
  String shortcuts ``"cg"``, ``"direct"``, ``"amg"``, ``"multilevel"`` and ``"auto"`` are
  resolved by :func:`bind_linear`.
* Host back ends are reached through ``jax.pure_callback``: the host only *factorises*
  (assembles the element Hessians into CSR and factorises / builds a hierarchy) and
  *applies* (an exact solve or one V-cycle); the iterations and the PSD projection of an
  indefinite Hessian (:func:`jaxelastic.energy.project_psd`) stay in JAX. They cannot run
  under ``vmap`` (one host factorisation is shared state: a clear error says so) nor on
  traced meshes (the sparsity analysis needs the connectivity on the host).
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable
from typing import Any, NamedTuple, Self

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.core import Tracer

from ..mechanics.potential import (
    Potential,
    mass_diagonal,
    node_hessian_blocks,
    projected_element_hessians,
)
from ..parallel.distributed import host_array
from ..parallel.sharding import is_sharded
from .blocks import block_inverse_or_diagonal
from .host import (
    ContentCache,
    HostLinearSolver,
    available_direct_backends,
    content_key,
    local_upper,
)
from .multilevel import (
    Hierarchy,
    ShardedHierarchy,
    build_hierarchy,
    build_sharded_hierarchy,
    preconditioner,
    sharded_preconditioner,
)
from .results import Solution, Status

__all__ = [
    "cg",
    "block_jacobi",
    "jacobi",
    "CG",
    "Direct",
    "AMG",
    "Multilevel",
    "LinearSolver",
    "NewtonSystem",
    "bind_linear",
    "LINEAR_SOLVERS",
    "AUTO_DIRECT_MAX_DOFS",
    "AUTO_DIRECT_MAX_DOFS_P2",
    "AUTO_DIRECT_MAX_DOFS_QUADRATIC",
    "assemble_upper",
]

LINEAR_SOLVERS = ("auto", "cg", "direct", "amg", "multilevel")
AUTO_DIRECT_MAX_DOFS = {2: 100_000, 3: 10_000}
"""``"auto"``: sparse Cholesky up to this many dofs (per dimension), AMG-preconditioned CG
above. 3D: whole twist solves (5 Newton steps, warm, ``scripts/bench_solvers.py --sizes
14,19 --solvers direct,amg --skip-extras``) with the host AMG-CG of session 7: direct /
AMG 0.44 / 0.43 s at 10k dofs, 1.53 / 0.83 s at 24k (before it, with a host callback per
CG iteration, the crossover was near 27k). 2D: the fill of a nested-dissection
factorisation stays small (Cook P1 at 33k dofs: Cholesky 1.1 s vs AMG-CG 20 s,
``scripts/report_accuracy.py``)."""

AUTO_DIRECT_MAX_DOFS_P2 = {2: 100_000, 3: 80_000}
"""The same for elements on the P2 node set (tri6, tet10 and the composite tri3x4, tet4x8):
their matrices couple more dofs per row and smoothed aggregation needs more CG iterations.
Measured on the neo-Hookean P2 steel bracket (31k dofs, 5 load steps,
``scripts/bench_bracket.py``): warm solve direct 58 s / 20 Newton steps / 1.1 GB against
AMG 311 s / 26 steps / 2.5 GB (loaded machine). 80k is an extrapolation of that 5× lead
with the P1 slope of the direct/AMG ratio (∝ n^0.7), kept conservative."""

AUTO_DIRECT_MAX_DOFS_QUADRATIC = {2: 200_000, 3: 120_000}
"""The same for a quadratic potential (``bind_linear(..., quadratic=True)``, which
:func:`jaxelastic.solve` passes for :func:`~jaxelastic.solvers.newton.is_quadratic`
potentials, e.g. the ``linear`` material): Newton takes one step, so one factorisation
against one tight AMG-CG solve (no reuse of a hierarchy across steps to amortise).
Measured on the linear P1 steel bracket (84k dofs, ``scripts/bench_bracket.py``, loaded
machine): warm direct 4.4 s against AMG 14.8 s. 120k in 3D is a conservative
extrapolation of that 3.4× lead (the direct/AMG ratio grows like n^0.7, see
:data:`AUTO_DIRECT_MAX_DOFS`) that also bounds the factor's memory (1.7 GB peak at 81k dofs
on the twist)."""

_P2_NODES = ("tri6", "tet10", "tri3x4", "tet4x8")


def _dot(a, b):
    return jnp.sum(a * b)


def cg(A: Callable, b: jax.Array, M: Callable | None = None, *, tol, max_iter: int, x0=None):
    """Solve ``A x = b`` for SPD ``A`` by preconditioned CG (jit- and vmap-compatible).

    Args:
        A: linear operator ``v ↦ A v`` on arrays shaped like ``b``.
        b: right-hand side (any shape, e.g. ``(n_nodes, dim)``).
        M: preconditioner ``r ↦ M⁻¹ r`` (identity if None).
        tol: absolute residual tolerance (scalar, may be traced).
        max_iter: maximum iterations (static).
        x0: initial guess (default zero).

    Returns:
        :class:`~jaxelastic.solvers.results.Solution` with ``status`` SUCCESS, MAX_STEPS or
        NEGATIVE_CURVATURE and ``stats`` ``iterations``, ``residual`` (recurrence norm).
    """
    if M is None:
        M = lambda r: r
    if x0 is None:
        x0, r0 = jnp.zeros_like(b), b
    else:
        r0 = b - A(x0)
    rn0 = jnp.sqrt(_dot(r0, r0))
    # already converged (e.g. the certifying PCG of a host adjoint): skip the
    # preconditioner, which for host back ends is a callback and a solve
    z0 = lax.cond(rn0 <= tol, jnp.zeros_like, M, r0)
    running = jnp.asarray(-1, jnp.int32)

    def cond(s):
        return (s[-1] < 0) & (s[-2] < max_iter)

    def body(s):
        x, r, z, p, rz, rn, k, status = s
        Ap = A(p)
        pAp = _dot(p, Ap)
        neg = ~(pAp > 0)
        alpha = rz / jnp.where(neg, 1.0, pAp)
        x_new = x + alpha * p
        r_new = r - alpha * Ap
        rn_new = jnp.sqrt(_dot(r_new, r_new))
        z_new = M(r_new)
        rz_new = _dot(r_new, z_new)
        p_new = z_new + rz_new / jnp.where(rz == 0, 1.0, rz) * p
        # on negative curvature keep the previous iterate (or z0 at k == 0)
        x_out = jnp.where(neg, jnp.where(k == 0, x0 + z0, x), x_new)
        st = jnp.where(neg, Status.NEGATIVE_CURVATURE, jnp.where(rn_new <= tol, 0, -1))
        return (
            x_out,
            jnp.where(neg, r, r_new),
            z_new,
            p_new,
            rz_new,
            jnp.where(neg, rn, rn_new),
            k + 1,
            st.astype(jnp.int32),
        )

    status0 = jnp.where(rn0 <= tol, jnp.int32(Status.SUCCESS), running)
    s0 = (x0, r0, z0, z0, _dot(r0, z0), rn0, jnp.asarray(0, jnp.int32), status0)
    x, _, _, _, _, rn, k, status = lax.while_loop(cond, body, s0)
    status = jnp.where(status < 0, jnp.int32(Status.MAX_STEPS), status)
    return Solution(x=x, status=status, stats=dict(iterations=k, residual=rn))


def block_jacobi(blocks: jax.Array, free: jax.Array, *, lapack: bool = True):
    """Node-block Jacobi preconditioner from ``(n, d, d)`` diagonal blocks.

    Prescribed dofs (``free == False``, shape ``(n, d)``) are decoupled (identity rows and
    columns). Blocks that are not positive definite fall back to ``|diag|`` (or 1).
    ``lapack=False`` inverts them with an unrolled Cholesky
    (:func:`~jaxelastic.solvers.blocks.spd_block_inverse`) instead of LAPACK, as a sharded
    program on several XLA:CPU devices must (jaxlib 0.10's batched LAPACK can deadlock
    there); the two agree to round-off, but only LAPACK gives bit-identical blocks in
    every compiled program.
    """
    d = blocks.shape[-1]
    eye = jnp.eye(d, dtype=blocks.dtype)[None]  # (1, d, d)
    fm = free.astype(blocks.dtype)
    B = blocks * fm[:, :, None] * fm[:, None, :] + eye * (1.0 - fm)[:, :, None]
    Binv = block_inverse_or_diagonal(B, lapack)

    def apply(r):
        return jnp.einsum("nij,nj->ni", Binv, r)

    return apply


def jacobi(blocks: jax.Array, free: jax.Array):
    """Point Jacobi preconditioner from the diagonals of the ``(n, d, d)`` node blocks."""
    diag = jnp.diagonal(blocks, axis1=1, axis2=2)
    diag = jnp.where(free & (diag > 0), diag, 1.0)
    inv = 1.0 / diag

    def apply(r):
        return inv * r

    return apply


class NewtonSystem(NamedTuple):
    """The linear system of one Newton step (built inside the trace; not a user type).

    Attributes:
        pot: the potential; x: ``(n_nodes, dim)`` current positions.
        free: ``(n_nodes, dim)`` bool, the free dofs.
        Ke: ``(n_cells, k·d, k·d)`` elastic element Hessians at x (exact or projected, as
            Newton's ``hessian`` setting asks), or None when nothing needs them.
        H: the Hessian operator ``v ↦ (∂²Π/∂x²) v`` (unmasked).
        A: the Dirichlet-masked operator ``v ↦ P_f H P_f v + P_D v``.
        operator: ``Ke ↦ A`` built from given element Hessians (for the projected retry).
        assembled: ``A`` (and ``operator(K)``) is exactly the assembled matrix of the
            element Hessians (plus the mass diagonal, Dirichlet rows and columns replaced by
            identity): no matrix-free Hessian, no self-contact coupling. Host back ends
            may then run the whole Krylov loop on the host.
    """

    pot: Potential
    x: jax.Array
    free: jax.Array
    Ke: Any
    H: Callable
    A: Callable
    operator: Callable
    assembled: bool = False


def _masked_diag(system: NewtonSystem):
    md = mass_diagonal(system.pot)
    return jnp.zeros(system.x.shape[:1], system.x.dtype) if md is None else md


@dataclasses.dataclass(frozen=True)
class CG:
    """Matrix-free preconditioned CG under jit (vmap- and sharding-friendly).

    Attributes:
        preconditioner: ``"block_jacobi"`` (node blocks of the element Hessians),
            ``"jacobi"`` or ``"none"`` (then Newton with ``hessian="hvp"`` builds no element
            Hessian at all).
        max_iter: iteration cap per linear solve.
    """

    preconditioner: str = "block_jacobi"
    max_iter: int = 2000

    def __post_init__(self):
        if self.preconditioner not in ("block_jacobi", "jacobi", "none"):
            raise ValueError(
                "CG preconditioner must be 'block_jacobi', 'jacobi' or 'none', got "
                f"{self.preconditioner!r}"
            )
        if int(self.max_iter) < 1:
            raise ValueError(f"CG max_iter must be >= 1, got {self.max_iter!r}")

    @property
    def needs_element_hessians(self) -> bool:
        return self.preconditioner != "none"

    is_bound = True

    def _M(self, system: NewtonSystem, kind: str):
        if kind == "none" or system.Ke is None:
            return None
        blocks = node_hessian_blocks(system.pot, system.Ke)
        if kind == "jacobi":
            return jacobi(blocks, system.free)
        return block_jacobi(blocks, system.free, lapack=not is_sharded(system.pot.mesh))

    def newton_step(self, system: NewtonSystem, rhs, tol) -> Solution:
        """Inexact solve of the Newton system to ``‖r‖ ≤ tol``."""
        M = self._M(system, self.preconditioner)
        res = cg(system.A, rhs, M, tol=tol, max_iter=self.max_iter)
        return res._replace(stats=dict(res.stats, projected=jnp.asarray(False)))

    def exact(self, system: NewtonSystem, b, rtol, max_iter: int) -> Solution:
        """Solve with the exact operator to ``‖r‖ ≤ rtol·‖b‖`` (adjoint/tangent systems):
        block-Jacobi PCG."""
        bn = jnp.sqrt(_dot(b, b))
        M = self._M(system, "block_jacobi")
        return cg(system.A, b, M, tol=rtol * bn, max_iter=max_iter)


def _element_map(backend: HostLinearSolver):
    """The int32 element→upper-CSR map ``(n_cells·m(m+1)/2,)`` of the bound pattern, handed
    to XLA by a callback (a copy per call, 4 bytes per entry: 46 MB at 146k tets) rather
    than closed over, which would make it an XLA constant (DESIGN §4)."""
    emap = backend.element_map
    out = jax.ShapeDtypeStruct(emap.shape, jnp.int32)
    return jax.pure_callback(lambda: backend.element_map, out, vmap_method="sequential")


def assemble_upper(Ke, element_map, nnz_upper: int):
    """Upper-triangle CSR data ``(nnz_upper,)`` of ``Σ_c ½(Ke_c + Ke_cᵀ)``, assembled in XLA
    (a scatter-add over the int32 map, see
    :attr:`~jaxelastic.solvers.host.HostLinearSolver.element_map`): only this vector goes to
    the host, never the ``(n_cells, m, m)`` element Hessians ``Ke``. Traceable.

    Cells are summed in blocks of :data:`UPPER_BLOCK_CELLS`: the symmetrised values of one
    block at a time (never of all cells) and in cache; measured at 146k tet4: 0.025 s
    against 0.072 s for all cells at once, 90 MB less at the peak.
    """
    c, m = Ke.shape[0], Ke.shape[-1]
    iu, ju = local_upper(m)
    emap = element_map.reshape(c, len(iu))  # the local upper entries' order

    def add(acc, K, e):
        v = 0.5 * (K[:, iu, ju] + K[:, ju, iu])  # (cells, m(m+1)/2)
        return acc.at[e.reshape(-1)].add(v.reshape(-1))

    B = UPPER_BLOCK_CELLS
    nb = c // B
    acc = jnp.zeros((nnz_upper,), Ke.dtype)
    if nb > 0:

        def body(i, acc):
            K = lax.dynamic_slice_in_dim(Ke, i * B, B)
            return add(acc, K, lax.dynamic_slice_in_dim(emap, i * B, B))

        acc = lax.fori_loop(0, nb, body, acc)
    if nb * B < c:
        acc = add(acc, Ke[nb * B :], emap[nb * B :])
    return acc


def _upper_data(backend: HostLinearSolver, Ke):
    """:func:`assemble_upper` with the bound pattern's map (handed over by a callback)."""
    return assemble_upper(Ke, _element_map(backend), backend.nnz_upper)


UPPER_BLOCK_CELLS = 16384
"""Cells per block of the device assembly of the upper-triangle data (:func:`_upper_data`)."""


def _host_factor(backend: HostLinearSolver, Ke, md, token):
    out = jax.ShapeDtypeStruct((), jnp.int32)
    return _no_vmap_callback(backend.factor_upper, out, _upper_data(backend, Ke), md, token)


def _host_apply(backend: HostLinearSolver, r, token):
    out = jax.ShapeDtypeStruct(r.shape, r.dtype)
    # the factorisation is not batched: a batch of right-hand sides is applied one by one
    return jax.pure_callback(backend.apply, out, r, token, vmap_method="sequential")


def _host_factor_solve(backend: HostLinearSolver, Ke, md, r, token):
    out = (jax.ShapeDtypeStruct(r.shape, r.dtype), jax.ShapeDtypeStruct((), jnp.int32))
    data = _upper_data(backend, Ke)
    return _no_vmap_callback(backend.factor_solve_upper, out, data, md, r, token)


def _host_factor_if(backend: HostLinearSolver, Ke, md, need):
    """Factorise ``Ke`` on the host if ``need``; returns the status token (0 if skipped).
    Under vmap with only ``need`` batched it factorises once, if any element needs it; the
    device assembly runs only when needed."""
    out = jax.ShapeDtypeStruct((), jnp.int32)

    def host(data, md, need):
        return backend.factor_upper(data, md) if bool(need) else np.int32(0)

    @jax.custom_batching.custom_vmap
    def call(Ke, md, need):
        nnz = backend.nnz_upper
        data = lax.cond(need, lambda: _upper_data(backend, Ke), lambda: jnp.zeros((nnz,), Ke.dtype))
        return jax.pure_callback(host, out, data, md, need)

    @call.def_vmap
    def _rule(axis_size, in_batched, Ke, md, need):
        if in_batched[0] or in_batched[1]:
            raise ValueError(_VMAP_MESSAGE)
        need = jnp.any(need) if in_batched[2] else need
        return call(Ke, md, need), False

    return call(Ke, md, need)


_VMAP_MESSAGE = (
    "host linear solvers (Direct, AMG) cannot run under jax.vmap: one host factorisation "
    "is shared by the whole batch; use linear='multilevel' (je.Multilevel(), the device "
    "multigrid) or linear='cg' (je.CG()) to vmap over scenes"
)


def _no_vmap_callback(fn, out, *args):
    @jax.custom_batching.custom_vmap
    def call(*a):
        return jax.pure_callback(fn, out, *a)

    @call.def_vmap
    def _rule(axis_size, in_batched, *a):
        if not any(jax.tree_util.tree_leaves(in_batched)):
            return call(*a), False
        raise ValueError(_VMAP_MESSAGE)

    return call(*args)


@dataclasses.dataclass(frozen=True)
class _Host:
    """Shared logic of the host back ends (:class:`Direct`, :class:`AMG`)."""

    backend: HostLinearSolver | None = None

    kind = "direct"
    needs_element_hessians = True

    @property
    def is_bound(self) -> bool:
        """Whether the host back end is built (:func:`bind_linear`)."""
        return self.backend is not None

    def _options(self) -> dict:
        return {}

    def bind(self, mesh, bc) -> Self:
        """This solver with its host back end built for ``mesh`` and ``bc.mask``."""
        host = HostLinearSolver.shared(mesh, bc, self.kind, **self._options())
        return dataclasses.replace(self, backend=host)

    def _require(self) -> HostLinearSolver:
        if self.backend is None:
            raise ValueError(
                f"{type(self).__name__}() is not bound to a mesh: call "
                "je.solvers.bind_linear(solver, mesh, bc) outside jit (je.solve does it "
                "when the mesh is concrete)"
            )
        return self.backend

    def _factor_and_solve(self, system: NewtonSystem, A, Ke, md, rhs, tol, token):
        """``(dx, iterations, status)`` with the host factorisation of ``Ke``."""
        raise NotImplementedError

    def newton_step(self, system: NewtonSystem, rhs, tol) -> Solution:
        """Factorise the element Hessians on the host and solve; if the matrix is not
        positive definite (or the solve meets negative curvature), PSD-project the element
        Hessians in JAX (:func:`~jaxelastic.potential.projected_element_hessians`) and solve
        again."""
        md = _masked_diag(system)
        zero = jnp.asarray(0, jnp.int32)
        dx, its, st = self._factor_and_solve(system, system.A, system.Ke, md, rhs, tol, zero)
        bad = (st == Status.NOT_POSITIVE_DEFINITE) | (st == Status.NEGATIVE_CURVATURE)
        bad = bad | ~jnp.all(jnp.isfinite(dx))

        def retry(_):
            Kp = projected_element_hessians(system.pot, system.Ke)
            A = system.operator(Kp)
            dx2, its2, st2 = self._factor_and_solve(system, A, Kp, md, rhs, tol, st)
            return dx2, its + its2, st2

        dx, its, st = lax.cond(bad, retry, lambda _: (dx, its, st), None)
        st = jnp.where(st == Status.NOT_POSITIVE_DEFINITE, jnp.int32(Status.SUCCESS), st)
        stats = dict(iterations=its, residual=jnp.zeros((), rhs.dtype), projected=bad)
        return Solution(x=dx * system.free, status=st.astype(jnp.int32), stats=stats)

    def assembled_step(self, data, md, rhs, tol) -> tuple[np.ndarray, int, int]:
        """One factorise-and-solve of :meth:`newton_step` on the host, outside jit, for a
        Newton operator that is the assembled matrix (``NewtonSystem.assembled``): ``(dx,
        iterations, status)`` from the upper data (:func:`assemble_upper`) and the mass
        diagonal; the caller makes the projected retry. No XLA program holds the host
        call, so every compiled piece of the host Newton loop goes to the persistent
        compilation cache (the one with the callback took 0.46 s to compile in every
        process at twist n = 29)."""
        raise NotImplementedError

    def exact(self, system: NewtonSystem, b, rtol, max_iter: int) -> Solution:
        """Device PCG on the exact operator, preconditioned by the host factorisation (or
        AMG hierarchy) the last Newton step left — the Hessian at the previous iterate,
        within ``O(‖x* − x_{k−1}‖)`` of K(x*) — for at most :attr:`reuse_iter` iterations;
        only if that stalls is K(x*) itself factorised and PCG continued."""
        backend = self._require()
        bn = jnp.sqrt(_dot(b, b))
        tol = rtol * bn
        free = system.free

        def M0(r):
            return free * _host_apply(backend, r, jnp.asarray(0, jnp.int32))

        first = cg(system.A, b, M0, tol=tol, max_iter=min(self.reuse_iter, max_iter))
        y0 = jnp.where(jnp.all(jnp.isfinite(first.x)), first.x, 0.0)

        # refactorise K(x*) only if the reused preconditioner stalled; no lax.cond here: under
        # jacfwd/jacrev (vmap over right-hand sides) a cond would batch K(x*) too, while
        # _host_factor_if factorises once if any column needs it
        need = first.status != Status.SUCCESS
        token = _host_factor_if(backend, system.Ke, _masked_diag(system), need)

        def M1(r):
            return free * _host_apply(backend, r, token)

        res = cg(system.A, b, M1, tol=tol, max_iter=max_iter, x0=y0)  # 0 its if done
        its = res.stats["iterations"] + first.stats["iterations"]
        return res._replace(stats=dict(res.stats, iterations=its))

    reuse_iter = 25


@dataclasses.dataclass(frozen=True)
class Direct(_Host):
    """Sparse Cholesky on the host: MKL PARDISO where pypardiso imports, else supernodal
    CHOLMOD (scikit-sparse), else cholespy / SciPy SuperLU with one warning
    (:class:`~jaxelastic.solvers.backends.DirectSolver`). The matrix is assembled on the
    device (upper triangle, int32 map); the symbolic analysis is done once per pattern,
    each Newton step is one numeric factorisation and one solve.

    Attributes:
        backend: the bound :class:`~jaxelastic.solvers.host.HostLinearSolver` (set by
            :func:`bind_linear`; leave None).
    """

    kind = "direct"

    def _factor_and_solve(self, system, A, Ke, md, rhs, tol, token):
        if getattr(system.pot.contact, "self_contact", None) is not None:
            # self-contact couples nodes outside the element pattern: the factorisation
            # of the element part preconditions CG on the whole operator A
            backend = self._require()
            token = _host_factor(backend, Ke, md, token)

            def M(r):
                return system.free * _host_apply(backend, r, token)

            res = cg(A, rhs, M, tol=tol, max_iter=2000)
            st = jnp.where(token == Status.NOT_POSITIVE_DEFINITE, token, res.status)
            return res.x, res.stats["iterations"], st
        # one callback: the step must come from this matrix's factorisation
        dx, st = _host_factor_solve(self._require(), Ke, md, rhs, token)
        return dx, jnp.asarray(1, jnp.int32), st

    def assembled_step(self, data, md, rhs, tol) -> tuple[np.ndarray, int, int]:
        dx, st = self._require().factor_solve_upper(data, md, rhs)
        return dx, 1, int(st)


@dataclasses.dataclass(frozen=True)
class AMG(_Host):
    """CG preconditioned by PyAMG smoothed aggregation (rigid-body modes, Chebyshev-smoothed
    V-cycles, :class:`~jaxelastic.solvers.backends.AMGSolver`).

    Where the Newton operator is the assembled matrix (``NewtonSystem.assembled``) the
    whole CG runs on the host (one call per Newton step:
    :meth:`~jaxelastic.solvers.host.HostLinearSolver.factor_cg_upper`); with self-contact
    coupling or a matrix-free Hessian the CG runs on the device with one V-cycle per
    iteration through a callback.

    Attributes:
        reuse: rebuild the hierarchy at the latest every ``reuse`` factorisations, and
            before that only when the CG's convergence per iteration has degraded
            (:class:`~jaxelastic.solvers.backends.AMGSolver`); in between the new matrix
            goes to the finest level, and the coarse operators get a Galerkin refresh
            when the convergence degrades less.
        max_iter: CG iteration cap.
        backend: the bound host back end (set by :func:`bind_linear`).
    """

    reuse: int = 50
    max_iter: int = 2000

    kind = "amg"

    def _options(self) -> dict:
        return dict(reuse=self.reuse)

    def _factor_and_solve(self, system, A, Ke, md, rhs, tol, token):
        backend = self._require()
        if system.assembled:  # A is the host's matrix: the whole PCG in one callback
            out = (
                jax.ShapeDtypeStruct(rhs.shape, rhs.dtype),
                jax.ShapeDtypeStruct((), jnp.int32),
                jax.ShapeDtypeStruct((), jnp.int32),
            )
            data = _upper_data(backend, Ke)
            max_iter = np.int32(self.max_iter)
            fn = backend.factor_cg_upper
            return _no_vmap_callback(fn, out, data, md, rhs, tol, max_iter, token)
        token = _host_factor(backend, Ke, md, token)

        def M(r):
            return system.free * _host_apply(backend, r, token)

        res = cg(A, rhs, M, tol=tol, max_iter=self.max_iter)
        st = jnp.where(token == Status.NOT_POSITIVE_DEFINITE, token, res.status)
        return res.x, res.stats["iterations"], st

    def assembled_step(self, data, md, rhs, tol) -> tuple[np.ndarray, int, int]:
        backend = self._require()
        dx, its, st = backend.factor_cg_upper(data, md, rhs, tol, self.max_iter, threads=True)
        return dx, int(its), int(st)


_HIERARCHIES = ContentCache(8)  # the last 8 (mesh, mask, options) hierarchies


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
class Multilevel:
    """CG preconditioned by aggregation multigrid applied on the device, inside ``jit``.

    The hierarchy (aggregates, rigid-body tentative prolongators, index maps) is built once
    per (mesh, Dirichlet mask) on the host by :meth:`bind`; every Newton step recomputes the
    level operators from the element Hessians on the device (exact Galerkin products) and
    runs :func:`cg` with one V-cycle per iteration (:mod:`~jaxelastic.solvers.multilevel`).
    No host callback: it works under ``jax.vmap`` (e.g. over material parameters), in
    float32 and float64, and on a sharded mesh (:func:`jaxelastic.shard`: level 0 per
    shard with halo exchanges, the coarse levels replicated, the same hierarchy and
    iterates as on one device; plain aggregation only). :func:`jaxelastic.solve` passes the
    hierarchy to its compiled function as an argument (no large XLA constants); inside a
    user's ``jit``/``vmap``/``grad`` a bound solver's arrays are constants of that trace.

    Attributes:
        degree: Chebyshev smoothing degree (pre and post).
        cycle: ``"V"`` or ``"W"``.
        coarse_scale: factor of the coarse-grid correction (in (0, 2)).
        smooth: smoothed aggregation (fewer iterations, but its Galerkin product costs
            ~14x the plain one on CPU) instead of plain aggregation.
        max_coarse: dofs of the coarsest level (dense Cholesky every Newton step).
        max_iter: CG iteration cap per linear solve.
        hierarchy: the bound :class:`~jaxelastic.solvers.multilevel.Hierarchy`, or
            :class:`~jaxelastic.solvers.multilevel.ShardedHierarchy` on a sharded mesh
            (set by :func:`bind_linear`; leave None). Compared by identity.
    """

    degree: int = 4
    cycle: str = "V"
    coarse_scale: float = 1.3
    smooth: bool = False
    max_coarse: int = 1500
    max_iter: int = 2000
    hierarchy: Hierarchy | ShardedHierarchy | None = None

    needs_element_hessians = True

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

    @property
    def is_bound(self) -> bool:
        """Whether the hierarchy is built (:func:`bind_linear`)."""
        return self.hierarchy is not None

    def bind(self, mesh, bc) -> Self:
        """This solver with the hierarchy of ``mesh`` and ``bc.mask`` (host, cached; per
        shard when the mesh is sharded)."""
        sharded = getattr(mesh, "halo", None) is not None
        shared = _shared_sharded_hierarchy if sharded else _shared_hierarchy
        return dataclasses.replace(
            self, hierarchy=shared(mesh, bc, int(self.max_coarse), bool(self.smooth))
        )

    def _require(self) -> Hierarchy | ShardedHierarchy:
        if self.hierarchy is None:
            raise ValueError(
                "Multilevel() is not bound to a mesh: call je.solvers.bind_linear(solver, "
                "mesh, bc) outside jit (je.solve does it when the mesh is concrete)"
            )
        return self.hierarchy

    def _M(self, system: NewtonSystem, Ke):
        h = self._require()
        halo = getattr(system.pot.mesh, "halo", None)
        if (halo is not None) != isinstance(h, ShardedHierarchy):
            raise ValueError(
                "this Multilevel() was bound to a "
                + ("one-device" if halo is not None else "sharded")
                + " mesh but solves a "
                + ("sharded" if halo is not None else "one-device")
                + " one: bind it to the mesh it solves (je.solvers.bind_linear(solver, "
                "mesh, bc)), or pass je.Multilevel() unbound and let je.solve bind it"
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
            return free * M(r)

        return apply

    def newton_step(self, system: NewtonSystem, rhs, tol) -> Solution:
        """Multigrid-preconditioned CG to ``‖r‖ ≤ tol``; on negative curvature (or a failed
        coarsest factorisation) PSD-project the element Hessians
        (:func:`~jaxelastic.potential.projected_element_hessians`) and solve again.

        Both attempts are one ``lax.while_loop`` body (at most two trips), so the cycle is
        compiled once, not once per branch of a ``cond``."""
        if system.Ke is None:
            raise ValueError("Multilevel needs the element Hessians (NewtonSystem.Ke)")
        Ke = system.Ke
        exact_is_elementwise = system.pot.stiffness_damping is None

        def attempt(c):
            k = c[0]
            K = lax.cond(k == 0, lambda: Ke, lambda: projected_element_hessians(system.pot, Ke))
            if exact_is_elementwise:  # system.A is the element-Hessian operator of Ke
                A = system.operator(K)
            else:

                def A(v):
                    return lax.cond(k == 0, system.A, system.operator(K), v)

            r = cg(A, rhs, self._M(system, K), tol=tol, max_iter=self.max_iter)
            bad = (r.status == Status.NEGATIVE_CURVATURE) | ~jnp.all(jnp.isfinite(r.x))
            its = c[2] + r.stats["iterations"]
            return (k + 1, r.x, its, r.status, r.stats["residual"], c[5] | bad, bad)

        def again(c):
            return (c[0] == 0) | ((c[0] == 1) & c[6])

        i32 = jnp.int32
        zero, no = jnp.asarray(0, i32), jnp.asarray(False)
        c0 = (zero, jnp.zeros_like(rhs), zero, zero, jnp.zeros((), rhs.dtype), no, no)
        _, dx, its, st, rn, projected, _ = lax.while_loop(again, attempt, c0)
        stats = dict(iterations=its, residual=rn, projected=projected)
        return Solution(x=dx * system.free, status=st, stats=stats)

    def exact(self, system: NewtonSystem, b, rtol, max_iter: int) -> Solution:
        """Multigrid-preconditioned CG on the exact operator to ``‖r‖ ≤ rtol·‖b‖``
        (adjoint / tangent solves of implicit differentiation)."""
        if system.Ke is None:
            raise ValueError("Multilevel needs the element Hessians (NewtonSystem.Ke)")
        bn = jnp.sqrt(_dot(b, b))
        return cg(system.A, b, self._M(system, system.Ke), tol=rtol * bn, max_iter=max_iter)


LinearSolver = CG | Direct | AMG | Multilevel


def _is_traced(tree) -> bool:
    return any(isinstance(a, Tracer) for a in jax.tree_util.tree_leaves(tree))


def _missing_host_package(kind: str) -> str | None:
    """The package a host back end of ``kind`` (``"direct"``/``"amg"``) needs and cannot
    import here (None when it can): ``pyamg`` for AMG; for direct, a sparse Cholesky
    package (SciPy's SuperLU alone is a slow fallback that ``"auto"`` does not pick)."""
    if kind == "amg":
        try:
            import pyamg  # noqa: F401
        except ImportError:
            return "pyamg"
        return None
    return "pypardiso" if available_direct_backends() == ("splu",) else None


def bind_linear(
    linear: str | LinearSolver | None, mesh, bc, *, quadratic: bool = False
) -> LinearSolver:
    """Resolve a linear-solver choice for one scene (outside jit).

    Long because: one dispatch over names and solver objects, each with its own refusal
    (traced meshes, sharded meshes) next to the choice it refuses.

    Args:
        linear: ``"auto"`` (:class:`Direct` up to :data:`AUTO_DIRECT_MAX_DOFS` dofs
            (:data:`AUTO_DIRECT_MAX_DOFS_P2` on P2 node sets), :class:`AMG` above;
            :class:`CG` when the mesh is traced, e.g. passed as a jit argument;
            :class:`Multilevel`, with a warning, when the host package that
            choice needs, pyamg or a sparse Cholesky, is not installed), ``"cg"``,
            ``"direct"``, ``"amg"``, ``"multilevel"``, None
            (= ``"auto"``) or a solver object (host ones and :class:`Multilevel` are bound
            to ``mesh`` and ``bc.mask`` unless already bound).
        mesh: the :class:`~jaxelastic.mesh.Mesh`; bc: the
            :class:`~jaxelastic.loads.Dirichlet` data (its mask fixes the pattern).
        quadratic: the potential is quadratic (one Newton step,
            :func:`~jaxelastic.solvers.newton.is_quadratic`): ``"auto"`` keeps the direct
            solver up to :data:`AUTO_DIRECT_MAX_DOFS_QUADRATIC` dofs.

    Raises:
        ValueError: unknown name, a host solver / an unbound :class:`Multilevel` on a
            traced mesh, or a host solver on a sharded mesh (:func:`jaxelastic.shard`;
            ``"auto"`` picks a device solver there).
    """
    if linear is None:
        linear = "auto"
    if isinstance(linear, str):
        if linear not in LINEAR_SOLVERS:
            raise ValueError(f"linear solver must be one of {LINEAR_SOLVERS}, got {linear!r}")
        if linear == "auto":
            if _is_traced((mesh.cells, mesh.points, bc.mask)):
                return CG()
            if is_sharded(mesh):  # the sharded multilevel once it can, else matrix-free CG
                return bind_linear(
                    "multilevel" if getattr(Multilevel, "supports_sharding", False) else "cg",
                    mesh,
                    bc,
                )
            limits = AUTO_DIRECT_MAX_DOFS_P2 if mesh.element in _P2_NODES else AUTO_DIRECT_MAX_DOFS
            if quadratic:
                limits = AUTO_DIRECT_MAX_DOFS_QUADRATIC
            small = mesh.n_dofs <= limits.get(mesh.dim, 10_000)
            linear = "direct" if small else "amg"
            missing = _missing_host_package(linear)
            if missing:  # a lean install (e.g. a GPU image): the device solver instead
                warnings.warn(
                    f"jaxelastic: linear='auto' would use the host {linear!r} solver but "
                    f"{missing} is not installed; using the device solver "
                    f"linear='multilevel' instead (pip install {missing} for the host one)",
                    RuntimeWarning,
                    stacklevel=1,  # one location: the default filter shows it once
                )
                linear = "multilevel"
        by_name: dict[str, type[LinearSolver]] = {
            "cg": CG,
            "direct": Direct,
            "amg": AMG,
            "multilevel": Multilevel,
        }
        linear = by_name[linear]()
    if isinstance(linear, CG):
        return linear
    if isinstance(linear, Multilevel):
        if linear.hierarchy is not None:
            return linear
        if _is_traced((mesh.cells, mesh.points, bc.mask)):
            raise ValueError(
                "Multilevel() builds its hierarchy from the mesh and the Dirichlet mask on "
                "the host, but they are traced here (passed as jit arguments): bind it "
                "first, outside jit, with je.solvers.bind_linear(solver, mesh, bc), or use "
                "linear='cg'"
            )
        return linear.bind(mesh, bc)
    if isinstance(linear, _Host):
        if is_sharded(mesh):
            raise ValueError(
                f"linear solver {type(linear).__name__}() runs on the host and cannot take a "
                "mesh sharded over several devices (je.shard); use linear='multilevel' (the "
                "device multigrid) or linear='cg' (matrix-free, block-Jacobi preconditioned)"
            )
        if linear.backend is not None:
            return linear
        if _is_traced((mesh.cells, mesh.points, bc.mask)):
            raise ValueError(
                f"{type(linear).__name__}() needs the mesh and the Dirichlet mask on the "
                "host, but they are traced here (passed as jit arguments): bind it first, "
                "outside jit, with je.solvers.bind_linear(solver, mesh, bc), or use "
                "linear='cg'"
            )
        return linear.bind(mesh, bc)
    raise TypeError(
        f"linear solver must be a name {LINEAR_SOLVERS} or je.CG/je.Direct/je.AMG/"
        f"je.Multilevel, got "
        f"{type(linear).__name__}"
    )
