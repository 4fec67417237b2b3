"""Host factorise / apply services behind the device conjugate-gradient loop.

:class:`HostLinearSolver` is built once per (mesh, Dirichlet mask): it analyses the
sparsity pattern and keeps a :mod:`~jaxelastic.solvers.host` back end. The device CG
(:func:`jaxelastic.solvers.linear.krylov`) runs every Krylov iteration and reaches the host
through :func:`jax.pure_callback` only to

* :meth:`HostLinearSolver.factor_upper`: take the upper-triangle CSR data of the Newton
  matrix, which JAX assembled on the device from the element Hessians (a segment sum over
  the int32 :attr:`HostLinearSolver.element_map`, symmetrisation folded in: only the
  ``(nnz_upper,)`` vector crosses to the host), eliminate the Dirichlet dofs, and factorise
  (``"direct"``: sparse Cholesky, see :class:`~jaxelastic.solvers.host.DirectSolver`)
  or build / refresh an AMG hierarchy (``"amg"``), returning a status code
  (:meth:`HostLinearSolver.factor` does the same from element Hessians on the host); and
* :meth:`HostLinearSolver.apply`: ``K⁻¹r`` (direct, exact) or one V-cycle ``M⁻¹r`` (AMG).

The host runs no Krylov loop and never modifies the Hessian: when :meth:`factor` reports
:data:`NOT_POSITIVE_DEFINITE`, the caller projects the element Hessians
(:func:`jaxelastic.mechanics.psd.project_psd`) and factorises again. On CPU nothing is copied
across devices.

Status codes (members of :class:`jaxelastic.Status`): :data:`SUCCESS` = 0,
:data:`NONFINITE` = 4 (non-finite Hessian or mass entries: nothing factorised, apply
gives NaN), :data:`NOT_POSITIVE_DEFINITE` = 6 (direct: Cholesky failed, a pivoted LU
factorisation is used by apply, or NaN if the matrix is singular; AMG: a free diagonal
entry is ``≤ 0``, the hierarchy is built anyway).
"""

from __future__ import annotations

import atexit
import hashlib
import threading
import time
import weakref
from typing import Any

import numpy as np
import scipy.sparse as sp

from ..results import Status
from .amg import AMGSolver
from .direct import DirectSolver
from .pattern import SparsityPattern

__all__ = [
    "HostLinearSolver",
    "ContentCache",
    "content_key",
    "SUCCESS",
    "NONFINITE",
    "NOT_POSITIVE_DEFINITE",
    "make_backend",
    "BACKEND_KINDS",
]

# the statuses :meth:`HostLinearSolver.factor` returns (members of je.Status)
SUCCESS = Status.SUCCESS  # factorised (positive definite) / AMG hierarchy built
NONFINITE = Status.NONFINITE  # non-finite Hessian or mass entries: nothing factorised
NOT_POSITIVE_DEFINITE = Status.NOT_POSITIVE_DEFINITE  # the assembled matrix is not SPD

BACKEND_KINDS = ("direct", "amg")


def make_backend(kind: str, points=None, fixed=None, pattern=None, **opts):
    """Build a host factorisation back end by name.

    Args:
        kind: ``"direct"`` (:class:`DirectSolver`) or ``"amg"`` (:class:`AMGSolver`).
        points: ``(n_nodes, dim)`` node positions (needed by ``"amg"``).
        fixed: ``(n_nodes*dim,)`` bool Dirichlet mask (used by ``"amg"``).
        pattern: optional :class:`~jaxelastic.solvers.host.pattern.SparsityPattern` (``"amg"``).
        **opts: keyword options of the chosen class.

    Raises:
        ValueError: unknown ``kind`` (the message lists the valid ones).
    """
    if kind == "direct":
        return DirectSolver(**opts)
    if kind == "amg":
        if points is None:
            raise ValueError("make_backend('amg', ...) needs the node positions `points`")
        return AMGSolver(points, fixed, pattern=pattern, **opts)
    raise ValueError(f"unknown solver kind {kind!r}; valid kinds: {', '.join(BACKEND_KINDS)}")


def content_key(cells, points, fixed, kind: str, opts: dict) -> tuple:
    """Hashable identity of a host solver: kind, sizes, a SHA-1 of connectivity, rest
    positions and Dirichlet mask, and the options."""
    fixed = np.asarray(fixed, dtype=bool).reshape(-1)
    h = hashlib.sha1()
    for a in (np.ascontiguousarray(cells), np.ascontiguousarray(points), fixed):
        h.update(a.tobytes())
    n, d = np.shape(points)
    return (kind, n, d, h.hexdigest(), repr(sorted(opts.items())))


class ContentCache:
    """A thread-safe least-recently-used cache of host-built solver data by
    :func:`content_key`, keeping the last ``capacity`` entries."""

    def __init__(self, capacity: int):
        self.capacity = capacity
        self._items: dict = {}  # key -> value, least recently used first
        self._lock = threading.Lock()

    def get(self, key, build):
        """The entry of ``key``, built by ``build()`` on first use (or after eviction)."""
        with self._lock:
            value = self._items.pop(key, None)
            if value is None:
                value = build()
            self._items[key] = value  # most recently used last
            while len(self._items) > self.capacity:
                self._items.pop(next(iter(self._items)))
            return value

    def clear(self) -> None:
        with self._lock:
            self._items.clear()


def _release_all() -> None:
    """At interpreter exit, drop every live factorisation before the extension modules are
    torn down: cholespy objects still referenced from jit caches would otherwise be reported
    by nanobind as leaked ("leaked 1 instances … CholeskySolverD")."""
    _SHARED.clear()
    for inst in list(_LIVE):
        inst.release()


_LIVE: weakref.WeakSet = weakref.WeakSet()  # every HostLinearSolver, for _release_all
atexit.register(_release_all)

SHARED_CAPACITY = 8
"""How many distinct host solvers :meth:`HostLinearSolver.shared` keeps alive."""
_SHARED = ContentCache(SHARED_CAPACITY)


class HostLinearSolver:
    """Sparse factorisation (direct) or AMG hierarchy of the Newton matrix on the host.

    Args:
        cells: ``(n_cells, k)`` connectivity; points: ``(n_nodes, dim)`` rest positions.
        fixed: ``(n_nodes, dim)`` bool Dirichlet mask.
        kind: ``"direct"`` (sparse Cholesky: MKL PARDISO, CHOLMOD, cholespy or SuperLU,
            see :class:`~jaxelastic.solvers.host.DirectSolver`; :meth:`apply` is an
            exact solve) or ``"amg"`` (PyAMG smoothed aggregation with rigid-body
            modes; :meth:`apply` is one V-cycle, a preconditioner).
        **opts: options of the back end (:class:`~jaxelastic.solvers.host.DirectSolver`
            or :class:`~jaxelastic.solvers.host.AMGSolver`).

    Instances compare equal (and hash alike) when built for the same connectivity, rest
    positions, mask, kind and options, so jitted solvers taking one as a static argument
    compile once per scene even if the object is rebuilt; reuse one to also skip the
    pattern analysis.

    Counters: ``calls`` (factor + apply), ``factorizations``, ``applications``;
    ``last_info`` describes the last factorisation (``status``, ``assemble_time``,
    ``setup_time``, and ``backend``/``method``/``positive_definite`` (direct) or ``levels``,
    ``operator_complexity``, ``rebuilt``, ``rate`` (AMG: the CG's mean residual reduction
    per iteration since the previous factorisation, or None)).
    """

    def __init__(self, cells, points, fixed, kind: str = "direct", **opts):
        cells = np.asarray(cells)
        points = np.asarray(points)
        fixed = np.asarray(fixed, dtype=bool)
        n, d = points.shape
        if fixed.shape != (n, d):
            raise ValueError(f"fixed mask must have shape {(n, d)}, got {fixed.shape}")
        self._key = content_key(cells, points, fixed, kind, opts)
        self.kind = kind
        self.shape = (n, d)
        self.fixed = fixed.reshape(-1)
        self.pattern = SparsityPattern.build_cached(cells, n, d, self.fixed)
        self.backend = make_backend(
            kind, points=points, fixed=self.fixed, pattern=self.pattern, **opts
        )
        self._ready = False
        self.calls = 0
        self.factorizations = 0
        self.applications = 0
        self.last_info: dict = {}
        # XLA may run independent host callbacks concurrently (e.g. two load cases that
        # share this solver): one call at a time, since they share the factorisation
        self._lock = threading.Lock()
        _LIVE.add(self)

    def release(self) -> None:
        """Drop the factorisation / hierarchy (the next :meth:`apply` gives NaN until the
        next :meth:`factor`)."""
        with self._lock:
            self._ready = False
            if isinstance(self.backend, DirectSolver):
                self.backend.release()
            else:
                self.backend.ml = None  # AMG: the hierarchy

    @classmethod
    def for_problem(cls, mesh, bc, kind: str = "direct", **opts) -> HostLinearSolver:
        """Build from a :class:`~jaxelastic.mesh.Mesh` and :class:`~jaxelastic.loads.Dirichlet`."""
        return cls(mesh.cells, mesh.points, bc.mask, kind, **opts)

    @classmethod
    def shared(cls, mesh, bc, kind: str = "direct", **opts) -> HostLinearSolver:
        """The one instance for this (mesh, mask, kind, options), built on first use.

        Equal instances are interchangeable as static jit arguments, so a compiled solve
        keeps calling the instance it was traced with; sharing one instance per content
        makes its factorisation (and counters) the one every equal solver sees, and skips
        the pattern analysis on repeated solves. The last :data:`SHARED_CAPACITY` are kept.
        """
        cells, points = np.asarray(mesh.cells), np.asarray(mesh.points)
        fixed = np.asarray(bc.mask, dtype=bool)
        key = content_key(cells, points, fixed, kind, opts)
        return _SHARED.get(key, lambda: cls(cells, points, fixed, kind, **opts))

    @property
    def exact(self) -> bool:
        """True when :meth:`apply` is an exact solve (``"direct"``), False for AMG."""
        return isinstance(self.backend, DirectSolver)

    @property
    def element_map(self) -> np.ndarray:
        """``(n_cells * m(m+1)/2,)`` int32 upper-triangle slot of every local upper entry of
        every element Hessian
        (:attr:`~jaxelastic.solvers.host.pattern.SparsityPattern.element_map`), for assembling
        the upper data on the device."""
        return self.pattern.element_map

    @property
    def nnz_upper(self) -> int:
        """Length of the upper-triangle data vector that :meth:`factor_upper` takes."""
        return self.pattern.nnz_upper

    def _diag(self, mass_diag):
        if mass_diag is None or not np.any(mass_diag):
            return None
        diag = np.repeat(np.asarray(mass_diag, dtype=np.float64), self.shape[1])
        diag[self.fixed] = 0.0
        return diag

    def assemble(self, Ke, mass_diag=None) -> sp.csr_matrix:
        """Global matrix with Dirichlet elimination, ``(n_nodes*dim, n_nodes*dim)`` CSR.

        Args:
            Ke: ``(n_cells, k*dim, k*dim)`` element Hessians (symmetrised here).
            mass_diag: ``(n_nodes,)`` diagonal added to every free dof of the node (e.g. a
                lumped mass / h²), or ``None`` / zeros for none.

        Fixed dofs get identity rows and columns; the pattern is kept (AMG reuse).
        """
        return self.pattern.assemble(Ke, diag=self._diag(mass_diag))

    def factor(self, Ke, mass_diag, token=None) -> np.int32:
        """Assemble on the host and factorise (direct) or build / refresh the hierarchy
        (AMG). The solvers of the library assemble on the device and call
        :meth:`factor_upper`; this entry point is for host callers.

        Args:
            Ke: ``(n_cells, k*dim, k*dim)`` element Hessians (any float dtype).
            mass_diag: ``(n_nodes,)`` diagonal term per node (zeros for none).
            token: ignored; a data dependency that orders the callbacks.

        Returns:
            Status code, shape ``()`` int32: :data:`SUCCESS`, :data:`NONFINITE` or
            :data:`NOT_POSITIVE_DEFINITE` (see the module docstring).
        """
        with self._lock:
            self.calls += 1
            return np.int32(self._factor(self._host_upper(Ke), mass_diag))

    def factor_upper(self, data, mass_diag, token=None) -> np.int32:
        """:meth:`factor` from the assembled upper-triangle data.

        Args:
            data: ``(nnz_upper,)`` ``Σ_c ½(Ke_c + Ke_cᵀ)`` on the upper-triangle pattern,
                before elimination (a segment sum of the element Hessians over
                :attr:`element_map`); not modified.
            mass_diag: ``(n_nodes,)`` diagonal term per node (zeros for none).
            token: ignored; a data dependency that orders the callbacks.
        """
        with self._lock:
            self.calls += 1
            return np.int32(self._factor(data, mass_diag))

    def _host_upper(self, Ke):
        Ke = np.asarray(Ke, dtype=np.float64)
        if not np.all(np.isfinite(Ke)):
            return None
        return self.pattern.upper_data(Ke)

    def _factor(self, data, mass_diag, threads: bool = False) -> Status:
        t0 = time.perf_counter()
        md = None if mass_diag is None else np.asarray(mass_diag, dtype=np.float64)
        self._ready = False
        ok = data is not None and (md is None or bool(np.all(np.isfinite(md))))
        if data is not None:
            data = np.array(data, dtype=np.float64)  # own, writable (14 MB at 146k tets)
            if data.shape != (self.pattern.nnz_upper,):
                raise ValueError(
                    f"upper data must have shape ({self.pattern.nnz_upper},), got {data.shape}"
                )
            ok = ok and bool(np.all(np.isfinite(data)))
        if data is None or not ok:
            self.last_info = dict(status=NONFINITE, assemble_time=time.perf_counter() - t0)
            return NONFINITE
        P = self.pattern
        P.finish(data, diag=self._diag(md))
        t_asm = time.perf_counter() - t0
        self.factorizations += 1
        backend = self.backend
        if isinstance(backend, DirectSolver):
            if backend.wants_upper:
                backend.update_upper(P.upper_matrix(data))
            else:
                backend.update(P.matrix(P.full_data(data)))
            pd = bool(backend.positive_definite)
            info: dict[str, Any] = dict(
                method=backend.method, positive_definite=pd, backend=backend.backend
            )
            info["setup_time"] = backend.setup_time
        else:
            backend.update(P.matrix(P.full_data(data)), threads=threads)
            pd = bool(np.all(data[P.diag_slots][~self.fixed] > 0))
            info = backend.info()
        self._ready = backend.ready
        status = SUCCESS if pd else NOT_POSITIVE_DEFINITE
        self.last_info = dict(info, status=status, assemble_time=t_asm)
        return status

    def apply(self, r, token=None) -> np.ndarray:
        """``K⁻¹ r`` (direct) or one V-cycle ``M⁻¹ r`` (AMG) with the last factorisation.

        Args:
            r: ``(..., n_nodes, dim)`` residual(s); leading axes are independent
                right-hand sides (e.g. from a batched callback).
            token: ignored; a data dependency that orders the callbacks.

        Returns:
            Array shaped and typed like ``r`` (computed in float64), zero on fixed dofs;
            NaN on the free dofs when nothing is factorised (the last factorisation
            reported :data:`NONFINITE`, or a singular matrix).
        """
        with self._lock:
            self.calls += 1
            return self._apply(r)

    def factor_solve(self, Ke, mass_diag, r, token=None) -> tuple[np.ndarray, np.int32]:
        """:meth:`factor` then :meth:`apply` under one lock: ``(K⁻¹ r, status)``.

        Use this (not two callbacks) where the result must come from *this* matrix: two
        independent callback chains sharing one solver (e.g. two load cases in one jit)
        may otherwise interleave a factorisation between the other's factor and apply.
        """
        with self._lock:
            self.calls += 1
            status = np.int32(self._factor(self._host_upper(Ke), mass_diag))
            return self._apply(r), status

    def factor_solve_upper(self, data, mass_diag, r, token=None) -> tuple[np.ndarray, np.int32]:
        """:meth:`factor_upper` then :meth:`apply` under one lock: ``(K⁻¹ r, status)``."""
        with self._lock:
            self.calls += 1
            status = np.int32(self._factor(data, mass_diag))
            return self._apply(r), status

    def factor_cg_upper(
        self, data, mass_diag, r, tol, max_iter, token=None, threads: bool = False
    ) -> tuple[np.ndarray, np.int32, np.int32]:
        """AMG only: :meth:`factor_upper`, then the whole preconditioned CG on the host
        (:meth:`~jaxelastic.solvers.host.AMGSolver.solve`: the assembled matrix and one
        V-cycle per iteration), under one lock: ``(x, iterations, status)``.

        For a Newton operator that *is* the assembled matrix (no self-contact coupling,
        no matrix-free Hessian): one callback per Newton step instead of one per CG
        iteration.

        Args:
            data, mass_diag: as :meth:`factor_upper`.
            r: ``(n_nodes, dim)`` right-hand side (zero on fixed dofs).
            tol: absolute residual tolerance (``‖r‖``, as the device CG); max_iter: cap.
            token: ignored; a data dependency that orders the callbacks.
            threads: the hierarchy's Galerkin products and the CG's large matrix products
                split over the cores (for calls from Python only, see
                :meth:`~jaxelastic.solvers.host.AMGSolver.solve`).

        Returns:
            ``x`` shaped and typed like ``r`` (zero on fixed dofs), the iteration count
            and the status: :data:`NONFINITE` (nothing factorised, x NaN),
            :data:`NOT_POSITIVE_DEFINITE` (a free diagonal entry ≤ 0: the CG ran anyway),
            else the CG's (SUCCESS, MAX_STEPS or NEGATIVE_CURVATURE).
        """
        backend = self.backend
        if not isinstance(backend, AMGSolver):
            raise ValueError("factor_cg_upper is for kind='amg' (use factor_solve_upper)")
        with self._lock:
            self.calls += 1
            status = self._factor(data, mass_diag, threads=threads)
            r_in = np.asarray(r)
            n, d = self.shape
            if r_in.shape != (n, d):
                raise ValueError(f"r must have shape ({n}, {d}), got {r_in.shape}")
            if status == NONFINITE or not self._ready:
                x = np.full((n * d,), np.nan)
                x[self.fixed] = 0.0
                return x.reshape(n, d).astype(r_in.dtype), np.int32(0), np.int32(NONFINITE)
            b = np.array(r_in, dtype=np.float64).reshape(-1)
            b[self.fixed] = 0.0
            t0 = time.perf_counter()
            x, its, st = backend.solve(b, float(tol), int(max_iter), threads=threads)
            self.applications += its
            self.last_info.update(cg_time=time.perf_counter() - t0, cg_iterations=its)
            x[self.fixed] = 0.0
            if status == NOT_POSITIVE_DEFINITE:
                st = int(NOT_POSITIVE_DEFINITE)
            return x.reshape(n, d).astype(r_in.dtype), np.int32(its), np.int32(st)

    def _apply(self, r) -> np.ndarray:
        self.applications += 1
        r_in = np.asarray(r)
        n, d = self.shape
        if r_in.shape[-2:] != (n, d):
            raise ValueError(f"r must have shape (..., {n}, {d}), got {r_in.shape}")
        b = np.array(r_in, dtype=np.float64).reshape(-1, n * d).T  # (n_dofs, m)
        b[self.fixed] = 0.0
        if not self._ready:
            x = np.full_like(b, np.nan)
        elif isinstance(self.backend, AMGSolver):
            x = self.backend.precondition(b)
        else:
            x = self.backend.solve(np.ascontiguousarray(b))
        x[self.fixed] = 0.0
        return np.ascontiguousarray(x.T).reshape(r_in.shape).astype(r_in.dtype)

    def __eq__(self, other) -> bool:
        return isinstance(other, HostLinearSolver) and self._key == other._key

    def __hash__(self) -> int:
        return hash(self._key)

    def __repr__(self) -> str:
        return f"HostLinearSolver(kind={self.kind!r}, n_dofs={self.fixed.size})"
