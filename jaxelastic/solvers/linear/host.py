"""Host linear solvers — :class:`Direct` (sparse Cholesky) and :class:`AMG` (smoothed
aggregation as CG's preconditioner) — and their bridge to traced code.

The host only *factorises* (the element Hessians are assembled into the upper triangle of
a CSR matrix on the device, :func:`assemble_upper`, and factorised or given an AMG
hierarchy) and *applies* (an exact solve, one V-cycle, or a whole host CG). Inside a trace
these are ``jax.pure_callback`` calls; outside ``jit`` the Newton driver calls
:meth:`HostSolver.host_step` directly, so no compiled program holds a callback and every
piece goes to the persistent compilation cache. They cannot run under ``vmap`` (one host
factorisation is shared state: a clear error says so) nor on traced meshes (the sparsity
analysis needs the connectivity on the host).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ..host.assembled import HostLinearSolver
from ..host.pattern import local_upper
from ..results import Solution, Status
from .krylov import cg
from .protocol import LinearSolver, LinearState
from .system import NewtonSystem, mass_or_zeros

__all__ = ["Direct", "AMG", "HostSolver", "assemble_upper", "UPPER_BLOCK_CELLS"]


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
    # a batch of right-hand sides (e.g. the tangents of jax.jacfwd) goes to the host as
    # one (batch, n_nodes, dim) array: one multi-right-hand-side solve of the shared
    # factorisation (HostLinearSolver.apply takes leading axes), not one call each
    return jax.pure_callback(backend.apply, out, r, token, vmap_method="expand_dims")


def _host_preconditioner(backend: HostLinearSolver, free, token):
    """``r ↦`` the host factorisation's (or AMG hierarchy's) solve of ``r``, zero on the
    Dirichlet dofs: the preconditioner of the device CG that ``token`` orders after the
    factorisation it names."""

    def M(r):
        return jnp.where(free, _host_apply(backend, r, token), 0.0)

    return M


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


class HostSolver(LinearSolver):
    """Shared logic of the host back ends (:class:`Direct`, :class:`AMG`): their state is
    a :class:`~jaxelastic.solvers.host.HostLinearSolver` (sparsity analysis, factorisation
    or hierarchy), reached from a trace through ``jax.pure_callback``."""

    kind = "direct"
    on_host = True

    def _options(self) -> dict:
        return {}

    def init(self, mesh, bc) -> LinearState:
        """The host back end for ``mesh`` and ``bc.mask`` (outside jit; cached by content)."""
        host = HostLinearSolver.shared(mesh, bc, self.kind, **self._options())
        return LinearState(kind=self.kind, host=host)

    def _factor_and_solve(self, backend, system: NewtonSystem, A, Ke, md, rhs, tol, token):
        """``(dx, iterations, status)`` with the host factorisation of ``Ke``."""
        raise NotImplementedError

    def symmetric_preconditioner(self, state, system: NewtonSystem, Ke, token):
        """The host factorisation (direct: an exact solve, pivoted where the matrix is
        indefinite) or AMG hierarchy (one V-cycle) of the assembled ``Ke``."""
        backend = _backend(state)
        token = _host_factor(backend, Ke, mass_or_zeros(system), token)
        return _host_preconditioner(backend, system.free, token), token

    def newton_step(self, state, system: NewtonSystem, A, Ke, rhs, tol, token) -> Solution:
        """Factorise ``Ke`` on the host and solve (status NOT_POSITIVE_DEFINITE when the
        assembled matrix is not positive definite)."""
        md = mass_or_zeros(system)
        dx, its, st = self._factor_and_solve(_backend(state), system, A, Ke, md, rhs, tol, token)
        stats = dict(iterations=its, residual=jnp.zeros((), rhs.dtype))
        return Solution(x=jnp.where(system.free, dx, 0.0), status=st.astype(jnp.int32), stats=stats)

    def exact(self, state, system: NewtonSystem, b, rtol, max_iter: int) -> Solution:
        """Device PCG on the exact operator, preconditioned by the host factorisation (or
        AMG hierarchy) the last Newton step left — the Hessian at the previous iterate,
        within ``O(‖x* − x_{k−1}‖)`` of K(x*) — for at most :attr:`reuse_iter` iterations;
        only if that stalls is K(x*) itself factorised and PCG continued."""
        backend = _backend(state)
        bn = jnp.sqrt(jnp.sum(b * b))
        tol = rtol * bn
        free = system.free

        M0 = _host_preconditioner(backend, free, jnp.asarray(0, jnp.int32))
        first = cg(system.A, b, M0, tol=tol, max_iter=min(self.reuse_iter, max_iter))
        y0 = jnp.where(jnp.all(jnp.isfinite(first.x)), first.x, 0.0)

        # refactorise K(x*) only if the reused preconditioner stalled; no lax.cond here: under
        # jacfwd/jacrev (vmap over right-hand sides) a cond would batch K(x*) too, while
        # _host_factor_if factorises once if any column needs it
        need = first.status != Status.SUCCESS
        token = _host_factor_if(backend, system.Ke, mass_or_zeros(system), need)

        M1 = _host_preconditioner(backend, free, token)
        res = cg(system.A, b, M1, tol=tol, max_iter=max_iter, x0=y0)  # 0 its if done
        its = res.stats["iterations"] + first.stats["iterations"]
        return res._replace(stats=dict(res.stats, iterations=its))

    reuse_iter = 25

    def host_exact(self, state, data, md, b, rtol: float, max_iter: int) -> tuple[np.ndarray, bool]:
        """(outside ``jit``) ``(y, converged)`` of the exact system ``K y = b`` given by its
        assembled upper-triangle data and mass diagonal (the adjoint solve of an eager
        gradient; ``b`` zero on fixed dofs)."""
        raise NotImplementedError


def _backend(state: LinearState) -> HostLinearSolver:
    if state is None or state.host is None:
        raise ValueError(
            "a host linear solver (Direct, AMG) needs its state: je.solve makes it when the "
            "mesh and the Dirichlet mask are concrete; under jit with traced ones make it "
            "first, outside jit, with state = je.solvers.init_linear(linear, mesh, bc) and "
            "pass je.solve(..., linear_state=state)"
        )
    return state.host


@dataclasses.dataclass(frozen=True)
class Direct(HostSolver):
    """Sparse Cholesky on the host: MKL PARDISO where pypardiso imports, else supernodal
    CHOLMOD (scikit-sparse), else cholespy / SciPy SuperLU with one warning
    (:class:`~jaxelastic.solvers.backends.DirectSolver`). The matrix is assembled on the
    device (upper triangle, int32 map); the symbolic analysis is done once per pattern,
    each Newton step is one numeric factorisation and one solve.
    """

    kind = "direct"

    def _factor_and_solve(self, backend, system, A, Ke, md, rhs, tol, token):
        if not system.assembled:
            # couplings outside the element pattern (self-contact) or a matrix-free
            # Hessian: the factorisation of the element part preconditions CG on A
            token = _host_factor(backend, Ke, md, token)

            M = _host_preconditioner(backend, system.free, token)

            res = cg(A, rhs, M, tol=tol, max_iter=2000)
            st = jnp.where(token == Status.NOT_POSITIVE_DEFINITE, token, res.status)
            return res.x, res.stats["iterations"], st
        # one callback: the step must come from this matrix's factorisation
        dx, st = _host_factor_solve(backend, Ke, md, rhs, token)
        return dx, jnp.asarray(1, jnp.int32), st

    def host_step(self, state, data, md, rhs, tol) -> tuple[np.ndarray, int, int]:
        dx, st = _backend(state).factor_solve_upper(data, md, rhs)
        return dx, 1, int(st)

    def host_exact(self, state, data, md, b, rtol: float, max_iter: int) -> tuple[np.ndarray, bool]:
        """The factorisation of K itself (its symbolic analysis is the Newton solve's)."""
        y, st = _backend(state).factor_solve_upper(data, md, b)
        return y, int(st) == Status.SUCCESS


@dataclasses.dataclass(frozen=True)
class AMG(HostSolver):
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
    """

    reuse: int = 50
    max_iter: int = 2000

    kind = "amg"

    def _options(self) -> dict:
        return dict(reuse=self.reuse)

    def _factor_and_solve(self, backend, system, A, Ke, md, rhs, tol, token):
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

        M = _host_preconditioner(backend, system.free, token)

        res = cg(A, rhs, M, tol=tol, max_iter=self.max_iter)
        st = jnp.where(token == Status.NOT_POSITIVE_DEFINITE, token, res.status)
        return res.x, res.stats["iterations"], st

    def host_step(self, state, data, md, rhs, tol) -> tuple[np.ndarray, int, int]:
        backend = _backend(state)
        dx, its, st = backend.factor_cg_upper(data, md, rhs, tol, self.max_iter, threads=True)
        return dx, int(its), int(st)

    def host_exact(self, state, data, md, b, rtol: float, max_iter: int) -> tuple[np.ndarray, bool]:
        """Host CG on K to ``rtol·‖b‖``, with the Newton solve's hierarchy where it still
        converges (:meth:`~jaxelastic.solvers.host.HostLinearSolver.factor_cg_upper`)."""
        tol = rtol * float(np.linalg.norm(np.asarray(b)))
        y, _, st = _backend(state).factor_cg_upper(data, md, b, tol, max_iter, threads=True)
        return y, int(st) == Status.SUCCESS
