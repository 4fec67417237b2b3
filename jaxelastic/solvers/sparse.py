"""Host-side sparse linear solvers (NumPy/SciPy) for the assembled Newton system.

Assembly and the sparsity pattern live in :mod:`~jaxelastic.solvers.pattern` (re-exported
here). The matrices handed to these solvers keep the full pattern, with Dirichlet dofs
eliminated symmetrically (identity rows/columns).

Three solvers share one interface, ``solver.update(K)`` then ``solver.solve(b, rtol)``:

* :class:`DirectSolver`: sparse Cholesky (CHOLMOD through ``cholespy``), which also
  certifies positive definiteness; SciPy's SuperLU as a fallback.
* :class:`AMGSolver`: CG preconditioned by PyAMG smoothed aggregation with the rigid-body
  near-null space (:func:`rigid_body_modes`), optionally reusing the hierarchy.
* :class:`ScipyCGSolver`: Jacobi-preconditioned CG, for comparison only (it needs
  hundreds of iterations on bending-dominated problems, see DESIGN §4).

Dof ordering is node-major everywhere: dof ``a*dim + i`` is component ``i`` of node ``a``.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .pattern import SparsityPattern, rigid_body_modes

__all__ = [
    "SparsityPattern",
    "rigid_body_modes",
    "DirectSolver",
    "AMGSolver",
    "ScipyCGSolver",
    "make_solver",
    "SOLVER_KINDS",
]

SOLVER_KINDS = ("direct", "amg", "cg-jacobi")


# ----------------------------------------------------------------------------------------
# linear solvers: update(K) then solve(b, rtol) -> (x, info)
# ----------------------------------------------------------------------------------------


def _rel_residual(K, x, b) -> float:
    nb = float(np.linalg.norm(b))
    r = float(np.linalg.norm(b - K @ x))
    return r / nb if nb > 0 else r


def _as_csr(K) -> sp.csr_matrix:
    if not sp.issparse(K):
        raise TypeError(f"expected a scipy.sparse matrix, got {type(K).__name__}")
    K = K.tocsr()
    if K.shape[0] != K.shape[1]:
        raise ValueError(f"matrix must be square, got {K.shape}")
    return K


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
    :meth:`update` certifies that the Newton system is SPD. The SuperLU path (used when
    ``cholespy`` is not installed, or with ``backend="splu"``) factorises with symmetric
    diagonal pivoting and reads the inertia off ``diag(U)``, so it detects indefinite
    matrices as well.

    Cost (scripts/bench_linear.py): cholespy runs CHOLMOD's *simplicial* factorisation
    with a bundled reference BLAS, so in 3D it is 1.5–2.5x slower than SuperLU but uses
    ~3x less memory (cantilever, 92k dofs: 151 s / 1.5 GB vs 68 s / 4.2 GB). Both are
    10–50x slower than :class:`AMGSolver` above ~20k dofs: prefer this solver for small
    systems, for certifying positive definiteness, or for many right-hand sides.

    Args:
        backend: ``"auto"`` (cholespy if importable, else SuperLU), ``"cholespy"`` or
            ``"splu"``.
        on_indefinite: ``"fail"``: :meth:`solve` returns NaNs with ``converged=False,
            reason="not positive definite"``; ``"lu"``: solve the indefinite system by
            LU anyway (``info["positive_definite"]`` stays ``False``).
        refine: at most this many steps of iterative refinement when the relative
            residual exceeds ``rtol``.
        quiet: silence CHOLMOD's own "not positive definite" message on stdout.
    """

    def __init__(
        self,
        *,
        backend: str = "auto",
        on_indefinite: str = "fail",
        refine: int = 2,
        quiet: bool = True,
    ):
        if backend not in ("auto", "cholespy", "splu"):
            raise ValueError(f"backend must be 'auto', 'cholespy' or 'splu', got {backend!r}")
        if on_indefinite not in ("fail", "lu"):
            raise ValueError(f"on_indefinite must be 'fail' or 'lu', got {on_indefinite!r}")
        if backend == "cholespy" and not _has_cholespy():
            raise ImportError("backend='cholespy' needs the cholespy package")
        self.backend = "cholespy" if backend == "auto" and _has_cholespy() else backend
        if self.backend == "auto":
            self.backend = "splu"
        self.on_indefinite = on_indefinite
        self.refine = int(refine)
        self.quiet = quiet
        self._K = None
        self._solve = None
        self.method = None
        self.positive_definite = None
        self.setup_time = 0.0

    def update(self, K) -> None:
        """Factorise ``K`` (``(n, n)`` symmetric sparse; Cholesky reads its lower triangle)."""
        t0 = time.perf_counter()
        K = _as_csr(K)
        self._K = K
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
        from cholespy import CholeskySolverD, MatrixType

        n = K.shape[0]
        indptr = np.ascontiguousarray(K.indptr, dtype=np.int32)
        indices = np.ascontiguousarray(K.indices, dtype=np.int32)
        data = np.ascontiguousarray(K.data, dtype=np.float64)
        ctx = _quiet_stdout() if self.quiet else contextlib.nullcontext()
        try:
            with ctx:
                chol = CholeskySolverD(n, indptr, indices, data, MatrixType.CSR)
        except ValueError as e:  # "Matrix is not positive definite!"
            if "positive definite" not in str(e):
                raise
            self.positive_definite = False
            self.method = "cholesky"
            return

        def solve(b):
            b = np.ascontiguousarray(b, dtype=np.float64)
            x = np.zeros_like(b)
            chol.solve(b, x)
            return x

        self._solve = solve
        self.method = "cholesky"
        self.positive_definite = True

    def _factor_splu(self, K, *, check_inertia: bool):
        opts = {"SymmetricMode": True} if check_inertia else {}
        try:
            lu = spla.splu(
                K.tocsc(),
                permc_spec="MMD_AT_PLUS_A" if check_inertia else "COLAMD",
                diag_pivot_thresh=0.0 if check_inertia else 1.0,
                options=opts,
            )
        except RuntimeError:  # exactly singular
            self.positive_definite = False
            self.method = "lu"
            return
        if check_inertia:
            # with P A Pᵀ = L U and no off-diagonal pivoting, U = D Lᵀ: inertia = signs of D
            same_perm = np.array_equal(lu.perm_r, lu.perm_c)
            self.positive_definite = bool(same_perm and np.all(lu.U.diagonal() > 0))
            if not self.positive_definite:  # refactorise with pivoting if asked (update)
                self.method = "lu"
                return
        elif self.positive_definite is None:
            self.positive_definite = False
        self._solve = lu.solve
        self.method = "lu"

    def solve(self, b, rtol: float = 1e-8) -> tuple[np.ndarray, dict]:
        """Solve ``K x = b`` for ``b`` ``(n,)``.

        Returns:
            ``x`` ``(n,)`` and ``info`` with ``iterations`` (1 + refinement steps),
            ``converged``, ``residual`` (relative, ``‖b − Kx‖/‖b‖``), ``reason``,
            ``method`` (``"cholesky"``/``"lu"``) and ``positive_definite``.
        """
        if self._K is None:
            raise RuntimeError("call update(K) before solve(b)")
        b = np.asarray(b, dtype=np.float64)
        info = dict(method=self.method, positive_definite=self.positive_definite)
        if self._solve is None:
            x = np.full_like(b, np.nan)
            info.update(iterations=0, converged=False, residual=np.inf)
            info["reason"] = "not positive definite"
            return x, info
        x = self._solve(b)
        res = _rel_residual(self._K, x, b)
        it = 1
        while res > rtol and it <= self.refine and np.isfinite(res):
            x = x + self._solve(b - self._K @ x)
            res = _rel_residual(self._K, x, b)
            it += 1
        ok = bool(np.isfinite(res) and res <= rtol)
        info.update(iterations=it, converged=ok, residual=res)
        if not ok:
            info["reason"] = "residual above tolerance" if np.isfinite(res) else "non-finite"
        elif not self.positive_definite:
            info["reason"] = "not positive definite (solved by LU)"
        else:
            info["reason"] = "converged"
        return x, info


def _pcg(K, b, M, rtol: float, maxiter: int, x0=None) -> tuple[np.ndarray, dict]:
    """Preconditioned CG on ``K x = b`` (``(n,)`` arrays), stopping at ``‖r‖ ≤ rtol·‖b‖``.

    ``M`` maps a residual to a preconditioned residual. Unlike SciPy's ``cg`` this stops
    at once on non-positive curvature ``pᵀKp ≤ 0`` (an indefinite Newton matrix) or a
    non-positive ``rᵀMr`` (a preconditioner that is not SPD) and says so in ``reason``.
    """
    b = np.asarray(b, dtype=np.float64)
    nb = float(np.linalg.norm(b))
    if nb == 0.0:
        info = dict(iterations=0, converged=True, residual=0.0, reason="zero right-hand side")
        return np.zeros_like(b), info
    x = np.zeros_like(b) if x0 is None else np.array(x0, dtype=np.float64).reshape(b.shape)
    r = b - K @ x if x0 is not None else b.copy()
    tol = rtol * nb
    reason = "max iterations"
    it = 0
    if np.linalg.norm(r) <= tol:
        reason = "converged"
    else:
        z = M(r)
        rz = float(r @ z)
        p = z.copy()
        while it < maxiter:
            if not rz > 0.0:
                reason = "preconditioner not positive definite"
                break
            Kp = K @ p
            pKp = float(p @ Kp)
            it += 1
            if not pKp > 0.0:
                reason = "negative curvature (matrix not positive definite)"
                break
            alpha = rz / pKp
            x += alpha * p
            r -= alpha * Kp
            if np.linalg.norm(r) <= tol:
                reason = "converged"
                break
            z = M(r)
            rz_new = float(r @ z)
            p *= rz_new / rz
            p += z
            rz = rz_new
    res = _rel_residual(K, x, b)  # the true residual, not the recurrence
    ok = bool(reason == "converged" and np.isfinite(res) and res <= 1.01 * rtol)
    if reason == "converged" and not ok:
        reason = "residual above tolerance (recurrence drifted)"
    return x, dict(iterations=it, converged=ok, residual=res, reason=reason)


class AMGSolver:
    """CG preconditioned by smoothed-aggregation AMG (PyAMG) with rigid-body modes.

    Args:
        points: ``(n_nodes, dim)`` node positions for :func:`rigid_body_modes`.
        fixed: ``(n_nodes*dim,)`` bool Dirichlet mask (rows of the modes zeroed).
        reuse: rebuild the hierarchy (aggregates, prolongators) every ``reuse`` calls to
            :meth:`update`; 1 rebuilds every time. Measured on the twist (5 matrices along a
            0→0.4 rad path, n = 29): rebuilding every time 8.7 s CPU, Galerkin refresh
            with ``reuse=5`` 5.8 s at unchanged iteration counts (13–14), hence the default.
        refresh: between rebuilds, ``"galerkin"`` keeps P and R but recomputes the
            coarse operators ``R A P`` and smoothers for the new matrix; ``"none"`` keeps
            the old preconditioner as is (CG still runs on the new matrix).
        maxiter: CG iteration cap.
        sa_options: overrides for ``pyamg.smoothed_aggregation_solver``.
        block: hand PyAMG the matrix as BSR with ``(dim, dim)`` node blocks (node-wise
            aggregation and block Gauss–Seidel smoothing).
        pattern: optional :class:`SparsityPattern` of the matrices, for a fast CSR→BSR
            conversion.
    """

    def __init__(
        self,
        points,
        fixed=None,
        *,
        reuse: int = 5,
        refresh: str = "galerkin",
        maxiter: int = 2000,
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
        self.maxiter = int(maxiter)
        self.block = block
        self.pattern = pattern
        self.sa_options = dict(
            strength=("symmetric", {"theta": 0.0}),
            smooth=("jacobi", {"omega": 4.0 / 3.0}),
            presmoother=("block_gauss_seidel", {"sweep": "symmetric"}),
            postsmoother=("block_gauss_seidel", {"sweep": "symmetric"}),
            max_coarse=300,  # node blocks; the coarsest level is factorised by SuperLU
            coarse_solver="splu",
        )
        self.sa_options.update(sa_options or {})
        self.ml = None
        self._K = None
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
        K = _as_csr(K)
        if K.shape[0] != self.B.shape[0]:
            raise ValueError(f"matrix has {K.shape[0]} rows, the modes {self.B.shape[0]}")
        self._K = K
        A = self._amg_matrix(K)
        if self.ml is None or self._updates_since_build >= self.reuse:
            self.ml = pyamg.smoothed_aggregation_solver(A, B=self.B, **self.sa_options)
            self._updates_since_build = 1
            self.rebuilt = True
        else:
            if self.refresh == "galerkin":
                self._galerkin(A)
            self._updates_since_build += 1
            self.rebuilt = False
        self.setup_time = time.perf_counter() - t0

    def _galerkin(self, A):
        from pyamg.multilevel import coarse_grid_solver
        from pyamg.relaxation.smoothing import change_smoothers

        levels = self.ml.levels
        levels[0].A = A
        for lo, hi in zip(levels[:-1], levels[1:], strict=True):
            Ac = lo.R @ lo.A @ lo.P
            hi.A = Ac.tobsr(blocksize=hi.A.blocksize) if hi.A.format == "bsr" else Ac.tocsr()
        change_smoothers(self.ml, self.sa_options["presmoother"], self.sa_options["postsmoother"])
        self.ml.coarse_solver = coarse_grid_solver(self.sa_options["coarse_solver"])

    def solve(self, b, rtol: float = 1e-8, x0=None) -> tuple[np.ndarray, dict]:
        """AMG-preconditioned CG on ``K x = b``, ``b`` ``(n,)``, stopping at
        ``‖b − Kx‖ ≤ rtol·‖b‖``.

        Returns:
            ``x`` ``(n,)`` and ``info`` (``iterations``, ``converged``, ``residual``,
            ``reason``, ``levels``, ``operator_complexity``, ``rebuilt``).
        """
        if self.ml is None:
            raise RuntimeError("call update(K) before solve(b)")
        M = self.ml.aspreconditioner(cycle="V").matvec
        x, info = _pcg(self._K, b, M, rtol, self.maxiter, x0)
        info.update(
            levels=len(self.ml.levels),
            operator_complexity=float(self.ml.operator_complexity()),
            rebuilt=self.rebuilt,
        )
        return x, info


class ScipyCGSolver:
    """Jacobi-preconditioned CG, a baseline: slow on bending (DESIGN §4).

    Args:
        maxiter: CG iteration cap.
    """

    def __init__(self, *, maxiter: int = 20000):
        self.maxiter = int(maxiter)
        self._K = None
        self._M = None
        self.setup_time = 0.0

    def update(self, K) -> None:
        """Set the matrix ``(n, n)`` SPD sparse and its inverse diagonal."""
        t0 = time.perf_counter()
        K = _as_csr(K)
        diag = K.diagonal()
        if np.any(diag <= 0):
            raise ValueError("Jacobi preconditioner needs a positive diagonal")
        inv = 1.0 / diag
        self._K = K
        self._M = lambda r: inv * r
        self.setup_time = time.perf_counter() - t0

    def solve(self, b, rtol: float = 1e-8, x0=None) -> tuple[np.ndarray, dict]:
        """Jacobi-CG on ``K x = b``; same return convention as :meth:`AMGSolver.solve`."""
        if self._K is None:
            raise RuntimeError("call update(K) before solve(b)")
        return _pcg(self._K, b, self._M, rtol, self.maxiter, x0)


def make_solver(kind: str, points=None, fixed=None, **opts):
    """Build a host linear solver by name.

    Args:
        kind: ``"direct"`` (:class:`DirectSolver`), ``"amg"`` (:class:`AMGSolver`) or
            ``"cg-jacobi"`` (:class:`ScipyCGSolver`).
        points: ``(n_nodes, dim)`` node positions (needed by ``"amg"``).
        fixed: ``(n_nodes*dim,)`` bool Dirichlet mask (used by ``"amg"``).
        **opts: keyword options of the chosen class.

    Raises:
        ValueError: unknown ``kind`` (the message lists the valid ones).
    """
    if kind == "direct":
        return DirectSolver(**opts)
    if kind == "amg":
        if points is None:
            raise ValueError("make_solver('amg', ...) needs the node positions `points`")
        return AMGSolver(points, fixed, **opts)
    if kind == "cg-jacobi":
        return ScipyCGSolver(**opts)
    raise ValueError(f"unknown solver kind {kind!r}; valid kinds: {', '.join(SOLVER_KINDS)}")
