"""Host factorisation back ends (NumPy/SciPy) of the device conjugate-gradient loop.

The device CG (:func:`jaxelastic.solvers.linear.cg`) runs every Krylov iteration; the host
only factorises the assembled Newton matrix and applies the result. Each back end has
``update(K)`` (factorise / build a hierarchy for an ``(n, n)`` sparse matrix) and one
application:

* :class:`DirectSolver`: sparse Cholesky (CHOLMOD through ``cholespy``), which also
  certifies positive definiteness, SciPy's SuperLU as a fallback; :meth:`DirectSolver.solve`
  is the exact solve ``K⁻¹b``.
* :class:`AMGSolver`: PyAMG smoothed aggregation with the rigid-body near-null space
  (:func:`~jaxelastic.solvers.pattern.rigid_body_modes`), optionally reusing the hierarchy;
  :meth:`AMGSolver.precondition` is one V-cycle ``M⁻¹r``, an SPD preconditioner.

Assembly and the sparsity pattern live in :mod:`~jaxelastic.solvers.pattern`; the matrices
handed to these back ends keep the full pattern, with Dirichlet dofs eliminated
symmetrically (identity rows/columns). Dof ordering is node-major: dof ``a*dim + i`` is
component ``i`` of node ``a``.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .pattern import SparsityPattern, rigid_body_modes

__all__ = ["DirectSolver", "AMGSolver", "make_backend", "BACKEND_KINDS"]

BACKEND_KINDS = ("direct", "amg")


def _as_csr(K) -> tuple[sp.csr_matrix, int]:
    """``K`` as CSR and its size n (checked square)."""
    if not sp.issparse(K):
        raise TypeError(f"expected a scipy.sparse matrix, got {type(K).__name__}")
    K = K.tocsr()
    n, m = K.shape
    if n != m:
        raise ValueError(f"matrix must be square, got {K.shape}")
    return K, int(n)


@contextlib.contextmanager
def _quiet_stdout():
    """Silence C-level writes to fd 1 (CHOLMOD prints 'not positive definite' there)."""
    try:
        fd = os.dup(1)
    except OSError:  # no usable stdout: nothing to silence
        yield
        return
    try:
        sys.stdout.flush()
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 1)
        os.close(devnull)
        yield
    finally:
        os.dup2(fd, 1)
        os.close(fd)


def _has_cholespy() -> bool:
    try:
        import cholespy  # noqa: F401
    except ImportError:
        return False
    return True


class DirectSolver:
    """Sparse direct solver: Cholesky (CHOLMOD via ``cholespy``) or SuperLU.

    Cholesky succeeds exactly when the matrix is positive definite, so a successful
    :meth:`update` certifies that the Newton system is SPD (``positive_definite``). The
    SuperLU path (used when ``cholespy`` is not installed, or with ``backend="splu"``)
    factorises with symmetric diagonal pivoting and reads the inertia off ``diag(U)``, so
    it detects indefinite matrices as well.

    Cost (scripts/bench_linear.py): cholespy runs CHOLMOD's *simplicial* factorisation
    with a bundled reference BLAS, so in 3D it is 1.5–2.5x slower than SuperLU but uses
    ~3x less memory (cantilever, 92k dofs: 151 s / 1.5 GB vs 68 s / 4.2 GB). Both are
    10–50x slower than :class:`AMGSolver` above ~20k dofs: prefer this solver for small
    systems, for certifying positive definiteness, or for many right-hand sides.

    Args:
        backend: ``"auto"`` (cholespy if importable, else SuperLU), ``"cholespy"`` or
            ``"splu"``.
        on_indefinite: ``"lu"``: when the matrix is not positive definite, factorise it by
            pivoted LU so that :meth:`solve` still works (``positive_definite`` stays
            False); ``"fail"``: keep no factorisation (:meth:`solve` returns NaNs).
        quiet: silence CHOLMOD's own "not positive definite" message on stdout.
    """

    def __init__(self, *, backend: str = "auto", on_indefinite: str = "lu", quiet: bool = True):
        if backend not in ("auto", "cholespy", "splu"):
            raise ValueError(f"backend must be 'auto', 'cholespy' or 'splu', got {backend!r}")
        if on_indefinite not in ("fail", "lu"):
            raise ValueError(f"on_indefinite must be 'fail' or 'lu', got {on_indefinite!r}")
        if backend == "cholespy" and not _has_cholespy():
            raise ImportError("backend='cholespy' needs the cholespy package")
        if backend == "auto":
            backend = "cholespy" if _has_cholespy() else "splu"
        self.backend = backend
        self.on_indefinite = on_indefinite
        self.quiet = quiet
        self._solve = None
        self.n = None
        self.method = None
        self.positive_definite = None
        self.setup_time = 0.0

    @property
    def ready(self) -> bool:
        """Whether a factorisation is available to :meth:`solve`."""
        return self._solve is not None

    def update(self, K) -> None:
        """Factorise ``K`` (``(n, n)`` symmetric sparse; Cholesky reads its lower triangle).

        Sets ``positive_definite`` (bool) and ``method`` (``"cholesky"`` / ``"lu"``).
        """
        t0 = time.perf_counter()
        K, self.n = _as_csr(K)
        self._solve = None
        self.positive_definite = None
        if self.backend == "cholespy":
            self._factor_cholespy(K)
        else:
            self._factor_splu(K, check_inertia=True)
        if not self.positive_definite and self.on_indefinite == "lu" and self._solve is None:
            self._factor_splu(K, check_inertia=False)
        self.setup_time = time.perf_counter() - t0

    def _factor_cholespy(self, K):
        # names made at import by the compiled cholespy._cholespy_core (no stubs)
        from cholespy import CholeskySolverD, MatrixType  # pyright: ignore[reportAttributeAccessIssue]

        n = K.shape[0]
        indptr = np.ascontiguousarray(K.indptr, dtype=np.int32)
        indices = np.ascontiguousarray(K.indices, dtype=np.int32)
        data = np.ascontiguousarray(K.data, dtype=np.float64)
        self.method = "cholesky"
        ctx = _quiet_stdout() if self.quiet else contextlib.nullcontext()
        try:
            with ctx:
                chol = CholeskySolverD(n, indptr, indices, data, MatrixType.CSR)
        except ValueError as e:  # "Matrix is not positive definite!"
            if "positive definite" not in str(e):
                raise
            self.positive_definite = False
            return

        def solve(b):
            b = np.ascontiguousarray(b, dtype=np.float64)
            x = np.zeros_like(b)
            chol.solve(b, x)
            return x

        self._solve = solve
        self.positive_definite = True

    def _factor_splu(self, K, *, check_inertia: bool):
        opts = {"SymmetricMode": True} if check_inertia else {}
        self.method = "lu"
        try:
            lu = spla.splu(
                K.tocsc(),
                permc_spec="MMD_AT_PLUS_A" if check_inertia else "COLAMD",
                diag_pivot_thresh=0.0 if check_inertia else 1.0,
                options=opts,
            )
        except RuntimeError:  # exactly singular
            self.positive_definite = False
            return
        if check_inertia:
            # with P A Pᵀ = L U and no off-diagonal pivoting, U = D Lᵀ: inertia = signs of D
            same_perm = np.array_equal(lu.perm_r, lu.perm_c)
            self.positive_definite = bool(same_perm and np.all(lu.U.diagonal() > 0))
            if not self.positive_definite:  # refactorise with pivoting if asked (update)
                return
        elif self.positive_definite is None:
            self.positive_definite = False
        self._solve = lu.solve

    def release(self) -> None:
        """Drop the factorisation (frees the compiled solver object now, not at exit)."""
        self._solve = None
        self.positive_definite = None

    def solve(self, b) -> np.ndarray:
        """Exact solve ``K x = b`` with the current factorisation.

        Args:
            b: ``(n,)`` or ``(n, m)`` right-hand side(s).

        Returns:
            ``x`` shaped like ``b`` (float64); all NaN when no factorisation is available
            (the matrix was singular, or not positive definite with ``on_indefinite="fail"``).
        """
        if self.n is None:
            raise RuntimeError("call update(K) before solve(b)")
        b = np.asarray(b, dtype=np.float64)
        if b.shape[0] != self.n:
            raise ValueError(f"right-hand side has {b.shape[0]} rows, the matrix {self.n}")
        if self._solve is None:
            return np.full_like(b, np.nan)
        return self._solve(b)


class AMGSolver:
    """Smoothed-aggregation AMG (PyAMG) with rigid-body modes: an SPD preconditioner.

    Args:
        points: ``(n_nodes, dim)`` node positions for
            :func:`~jaxelastic.solvers.pattern.rigid_body_modes`.
        fixed: ``(n_nodes*dim,)`` bool Dirichlet mask (rows of the modes zeroed).
        reuse: rebuild the hierarchy (aggregates, prolongators) every ``reuse`` calls to
            :meth:`update`; 1 rebuilds every time. Measured on the twist (5 matrices along a
            0→0.4 rad path, n = 29): rebuilding every time 8.7 s CPU, Galerkin refresh
            with ``reuse=5`` 5.8 s at unchanged iteration counts (13–14), hence the default.
        refresh: between rebuilds, ``"galerkin"`` keeps P and R but recomputes the
            coarse operators ``R A P`` and smoothers for the new matrix; ``"none"`` keeps
            the old hierarchy as is (a preconditioner for a nearby matrix).
        cycle: multigrid cycle of one :meth:`precondition` (``"V"``, ``"W"``, ``"F"``).
        sa_options: overrides for ``pyamg.smoothed_aggregation_solver``.
        block: hand PyAMG the matrix as BSR with ``(dim, dim)`` node blocks (node-wise
            aggregation and block Gauss–Seidel smoothing).
        pattern: optional :class:`~jaxelastic.solvers.pattern.SparsityPattern` of the
            matrices, for a fast CSR→BSR conversion.
    """

    def __init__(
        self,
        points,
        fixed=None,
        *,
        reuse: int = 5,
        refresh: str = "galerkin",
        cycle: str = "V",
        sa_options: dict | None = None,
        block: bool = True,
        pattern: SparsityPattern | None = None,
    ):
        if int(reuse) < 1:
            raise ValueError(f"reuse must be >= 1, got {reuse!r}")
        if refresh not in ("galerkin", "none"):
            raise ValueError(f"refresh must be 'galerkin' or 'none', got {refresh!r}")
        pts = np.asarray(points, dtype=np.float64)
        self.dim = pts.shape[1]
        self.B = rigid_body_modes(pts, fixed)
        self.reuse = int(reuse)
        self.refresh = refresh
        self.cycle = cycle
        self.block = block
        self.pattern = pattern
        self.sa_options: dict[str, Any] = dict(
            strength=("symmetric", {"theta": 0.0}),
            smooth=("jacobi", {"omega": 4.0 / 3.0}),
            presmoother=("block_gauss_seidel", {"sweep": "symmetric"}),
            postsmoother=("block_gauss_seidel", {"sweep": "symmetric"}),
            max_coarse=300,  # node blocks; the coarsest level is factorised by SuperLU
            coarse_solver="splu",
        )
        self.sa_options.update(sa_options or {})
        self.ml = None
        self._M = None
        self._updates_since_build = 0
        self.setup_time = 0.0
        self.rebuilt = False

    def _amg_matrix(self, K):
        if not self.block or self.dim == 1:
            return K
        if self.pattern is not None and self.pattern.has_pattern(K):
            return self.pattern.to_bsr(K)
        return K.tobsr(blocksize=(self.dim, self.dim))

    def update(self, K) -> None:
        """Set the matrix ``(n, n)`` SPD sparse and (re)build or refresh the hierarchy."""
        import pyamg

        t0 = time.perf_counter()
        K, n = _as_csr(K)
        if n != self.B.shape[0]:
            raise ValueError(f"matrix has {n} rows, the modes {self.B.shape[0]}")
        self._M = None
        A = self._amg_matrix(K)
        if self.ml is None or self._updates_since_build >= self.reuse:
            self.ml = None
            self.ml = pyamg.smoothed_aggregation_solver(A, B=self.B, **self.sa_options)
            self._updates_since_build = 1
            self.rebuilt = True
        else:
            if self.refresh == "galerkin":
                self._galerkin(A)
            self._updates_since_build += 1
            self.rebuilt = False
        self._M = self.ml.aspreconditioner(cycle=self.cycle).matvec
        self.setup_time = time.perf_counter() - t0

    def _galerkin(self, A):
        from pyamg.multilevel import coarse_grid_solver
        from pyamg.relaxation.smoothing import change_smoothers

        ml = self.ml
        assert ml is not None  # called by update between rebuilds only
        levels = ml.levels
        levels[0].A = A
        for lo, hi in zip(levels[:-1], levels[1:], strict=True):
            Ac = lo.R @ lo.A @ lo.P
            hi.A = Ac.tobsr(blocksize=hi.A.blocksize) if hi.A.format == "bsr" else Ac.tocsr()
        change_smoothers(ml, self.sa_options["presmoother"], self.sa_options["postsmoother"])
        ml.coarse_solver = coarse_grid_solver(self.sa_options["coarse_solver"])

    @property
    def ready(self) -> bool:
        """Whether a hierarchy is available to :meth:`precondition`."""
        return self._M is not None

    def precondition(self, r) -> np.ndarray:
        """One multigrid cycle from a zero guess: ``z = M⁻¹ r``.

        Args:
            r: ``(n,)`` or ``(n, m)`` residual(s).

        Returns:
            ``z`` shaped like ``r`` (float64); symmetric positive definite in ``r`` for an
            SPD matrix (symmetric smoothing, exact coarsest solve).
        """
        if self._M is None:
            raise RuntimeError("call update(K) before precondition(r)")
        r = np.asarray(r, dtype=np.float64)
        if r.ndim == 1:
            return np.asarray(self._M(r), dtype=np.float64).reshape(r.shape)
        return np.stack([self._M(np.ascontiguousarray(c)) for c in r.T], axis=1)

    def info(self) -> dict:
        """``levels``, ``operator_complexity``, ``rebuilt``, ``setup_time`` of the hierarchy."""
        if self.ml is None:
            return dict(levels=0, operator_complexity=0.0, rebuilt=False, setup_time=0.0)
        return dict(
            levels=len(self.ml.levels),
            operator_complexity=float(self.ml.operator_complexity()),
            rebuilt=self.rebuilt,
            setup_time=self.setup_time,
        )


def make_backend(kind: str, points=None, fixed=None, pattern=None, **opts):
    """Build a host factorisation back end by name.

    Args:
        kind: ``"direct"`` (:class:`DirectSolver`) or ``"amg"`` (:class:`AMGSolver`).
        points: ``(n_nodes, dim)`` node positions (needed by ``"amg"``).
        fixed: ``(n_nodes*dim,)`` bool Dirichlet mask (used by ``"amg"``).
        pattern: optional :class:`~jaxelastic.solvers.pattern.SparsityPattern` (``"amg"``).
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
