"""Sparse direct solvers of the host back end: PARDISO, CHOLMOD, cholespy, SuperLU.

:class:`DirectSolver` factorises the assembled Newton matrix with sparse Cholesky — MKL
PARDISO (:mod:`~jaxelastic.solvers.host.pardiso`) where it imports, else supernodal CHOLMOD
(scikit-sparse), else cholespy or SciPy's SuperLU, with one warning — which also certifies
positive definiteness; :meth:`DirectSolver.solve` is the exact solve ``K⁻¹b``. PARDISO takes
the upper triangle (:meth:`DirectSolver.update_upper`), analysed once per sparsity pattern.

Host-only packages (pypardiso, scikit-sparse, cholespy) are imported inside the functions
that use them, never at import time. Dof ordering is node-major: dof ``a*dim + i`` is
component ``i`` of node ``a``.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
import warnings

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .pardiso import Pardiso, pardiso_function
from .products import as_csr

__all__ = ["DirectSolver", "available_direct_backends", "DIRECT_BACKENDS"]


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


DIRECT_BACKENDS = ("auto", "pardiso", "cholmod", "cholespy", "splu")
"""Names accepted by :class:`DirectSolver` (``"auto"``: the first importable of the rest,
in this order)."""

_FAST = ("pardiso", "cholmod")
_WARNED: set = set()  # fallback warnings already given in this process


def _has_cholespy() -> bool:
    try:
        import cholespy  # noqa: F401
    except ImportError:
        return False
    return True


def _has_cholmod() -> bool:
    try:
        import sksparse.cholmod  # noqa: F401  # pyright: ignore[reportMissingImports]
    except ImportError:
        return False
    return True


def available_direct_backends() -> tuple[str, ...]:
    """The direct back ends importable here, fastest first (``"splu"`` always is)."""
    out = []
    if pardiso_function() is not None:
        out.append("pardiso")
    if _has_cholmod():
        out.append("cholmod")
    if _has_cholespy():
        out.append("cholespy")
    return (*out, "splu")


def _auto_backend() -> str:
    """The first available direct back end; warns once when it is a slow fallback."""
    best = available_direct_backends()[0]
    if best not in _FAST and "fallback" not in _WARNED:
        _WARNED.add("fallback")
        warnings.warn(
            f"jaxelastic: neither MKL PARDISO (pip install pypardiso; x86-64 wheels) nor "
            f"CHOLMOD (scikit-sparse) is importable, so the sparse direct solver falls back "
            f"to {best!r}, which is 10-30x slower on 3D problems above ~20k dofs",
            RuntimeWarning,
            stacklevel=3,
        )
    return best


class DirectSolver:
    """Sparse direct solver: MKL PARDISO, CHOLMOD supernodal, cholespy or SuperLU.

    ``backend="auto"`` takes the first importable of

    1. ``"pardiso"``: MKL PARDISO (``pip install pypardiso``, x86-64 wheels) in SPD mode on
       the upper triangle; the symbolic analysis is done once per sparsity pattern, each
       :meth:`update` is a numeric factorisation.
    2. ``"cholmod"``: CHOLMOD supernodal through scikit-sparse (needs the SuiteSparse
       headers to build; analysis once per pattern, ``cholesky_inplace`` per update).
    3. ``"cholespy"``: CHOLMOD *simplicial* with a reference BLAS (10-30x slower in 3D).
    4. ``"splu"``: SciPy SuperLU with symmetric diagonal pivoting.

    and warns once per process when it has to use 3 or 4. Every back end detects a
    matrix that is not positive definite (``positive_definite`` False after
    :meth:`update`): Cholesky (1-3) fails exactly then, SuperLU reads the inertia off
    ``diag(U)``.

    Cost (twist tangents, 81k dofs, 2 cores; scripts/bench_linear.py): PARDISO and
    supernodal CHOLMOD 2.6-2.7 s per factorisation, cholespy 71 s, SuperLU 92 s.

    Args:
        backend: one of :data:`DIRECT_BACKENDS`.
        on_indefinite: ``"lu"``: when the matrix is not positive definite, factorise it
            anyway (PARDISO: symmetric indefinite mode, Bunch-Kaufman; others: pivoted LU)
            so that :meth:`solve` still works (``positive_definite`` stays False);
            ``"fail"``: keep no factorisation (:meth:`solve` returns NaNs).
        quiet: silence CHOLMOD's own "not positive definite" message on stdout.
    """

    def __init__(self, *, backend: str = "auto", on_indefinite: str = "lu", quiet: bool = True):
        if backend not in DIRECT_BACKENDS:
            raise ValueError(f"backend must be one of {DIRECT_BACKENDS}, got {backend!r}")
        if on_indefinite not in ("fail", "lu"):
            raise ValueError(f"on_indefinite must be 'fail' or 'lu', got {on_indefinite!r}")
        if backend != "auto" and backend not in available_direct_backends():
            need = dict(pardiso="pypardiso (and MKL)", cholmod="scikit-sparse")
            raise ImportError(
                f"backend={backend!r} needs the {need.get(backend, backend)} package; "
                f"available here: {available_direct_backends()}"
            )
        if backend == "auto":
            backend = _auto_backend()
        self.backend = backend
        self.on_indefinite = on_indefinite
        self.quiet = quiet
        self._solve = None
        self._pardiso: Pardiso | None = None
        self._pardiso_indef: Pardiso | None = None
        self._cholmod = None
        self._cholmod_structure: tuple | None = None
        self.n = None
        self.method = None
        self.positive_definite = None
        self.setup_time = 0.0

    @property
    def wants_upper(self) -> bool:
        """Whether :meth:`update_upper` (the upper triangle) is the natural input."""
        return self.backend == "pardiso"

    @property
    def ready(self) -> bool:
        """Whether a factorisation is available to :meth:`solve`."""
        return self._solve is not None

    def update(self, K) -> None:
        """Factorise ``K`` (``(n, n)`` symmetric sparse, both triangles stored).

        Sets ``positive_definite`` (bool) and ``method`` (``"cholesky"`` / ``"ldlt"`` /
        ``"lu"``).
        """
        K, n = as_csr(K)
        if self.backend == "pardiso":
            off = sp.triu(K, k=1, format="coo")
            i = np.arange(n)
            U = sp.coo_matrix(  # every diagonal stored, even a zero one (PARDISO needs it)
                (np.r_[K.diagonal(), off.data], (np.r_[i, off.row], np.r_[i, off.col])),
                shape=K.shape,
            ).tocsr()
            U.sort_indices()
            self.update_upper(U, full=K)
            return
        t0 = time.perf_counter()
        self.n = n
        self._solve = None
        self.positive_definite = None
        if self.backend == "cholmod":
            self._factor_cholmod(K)
        elif self.backend == "cholespy":
            self._factor_cholespy(K)
        else:
            self._factor_splu(K, check_inertia=True)
        if not self.positive_definite and self.on_indefinite == "lu" and self._solve is None:
            self._factor_splu(K, check_inertia=False)
        self.setup_time = time.perf_counter() - t0

    def update_upper(self, U, full=None) -> None:
        """Factorise the symmetric matrix given by its upper triangle ``U`` (CSR, sorted
        column indices, every diagonal entry stored).

        Args:
            U: ``(n, n)`` upper-triangular CSR (e.g.
                :meth:`~jaxelastic.solvers.host.pattern.SparsityPattern.upper_matrix`).
            full: the full symmetric matrix, or a callable returning it; used by the back
                ends other than PARDISO (built from ``U`` when omitted).
        """
        if self.backend != "pardiso":
            K = full() if callable(full) else full
            if K is None:
                U = sp.csr_matrix(U)
                K = (U + U.T - sp.diags(U.diagonal())).tocsr()
            self.update(K)
            return
        t0 = time.perf_counter()
        self.n = int(U.shape[0])
        self._solve = None
        self.positive_definite = None
        if self._pardiso is None:
            self._pardiso = Pardiso(mtype=2)
        self.method = "cholesky"
        ok = self._pardiso.factor(U)
        self.positive_definite = ok
        if ok:
            self._solve = self._pardiso.solve
        elif self.on_indefinite == "lu":
            if self._pardiso_indef is None:
                self._pardiso_indef = Pardiso(mtype=-2)
            self.method = "ldlt"
            # Bunch-Kaufman LDLᵀ; perturbed pivots mean (numerically) singular: no solve
            if self._pardiso_indef.factor(U) and self._pardiso_indef.perturbed == 0:
                self._solve = self._pardiso_indef.solve
        self.setup_time = time.perf_counter() - t0

    def _factor_cholmod(self, K):
        from sksparse.cholmod import (  # pyright: ignore[reportMissingImports]
            CholmodNotPositiveDefiniteError,
            analyze,
        )

        A = sp.csc_matrix((K.data, K.indices, K.indptr), shape=K.shape)  # K symmetric
        key = (K.indptr, K.indices)
        old = self._cholmod_structure
        same = old is not None and all(
            a is b or np.array_equal(a, b) for a, b in zip(key, old, strict=True)
        )
        if self._cholmod is None or not same:
            self._cholmod = analyze(A, mode="supernodal")
            self._cholmod_structure = key
        self.method = "cholesky"
        factor = self._cholmod
        try:
            factor.cholesky_inplace(A)
        except CholmodNotPositiveDefiniteError:
            self.positive_definite = False
            return
        self._solve = lambda b: np.asarray(factor(b), dtype=np.float64)
        self.positive_definite = True

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
        """Drop the factorisation (frees the solver objects and PARDISO's memory now)."""
        self._solve = None
        self.positive_definite = None
        self._cholmod = None
        self._cholmod_structure = None
        for h in (self._pardiso, self._pardiso_indef):
            if h is not None:
                h.release()

    @property
    def factor_nnz(self) -> int | None:
        """Nonzeros of the PARDISO factor (None for the other back ends)."""
        return None if self._pardiso is None else self._pardiso.factor_nnz

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
