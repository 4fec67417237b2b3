"""Host factorisation back ends (NumPy/SciPy) of the device conjugate-gradient loop.

The device CG (:func:`jaxelastic.solvers.linear.cg`) runs every Krylov iteration; the host
only factorises the assembled Newton matrix and applies the result. Each back end has
``update(K)`` (factorise / build a hierarchy for an ``(n, n)`` sparse matrix) and one
application:

* :class:`DirectSolver`: sparse Cholesky — MKL PARDISO (pypardiso) where it imports,
  else supernodal CHOLMOD (scikit-sparse), else cholespy or SciPy's SuperLU, with one
  warning — which also certifies positive definiteness; :meth:`DirectSolver.solve` is the
  exact solve ``K⁻¹b``. PARDISO takes the upper triangle (:meth:`DirectSolver.update_upper`),
  analysed once per sparsity pattern.
* :class:`AMGSolver`: PyAMG smoothed aggregation with the rigid-body near-null space
  (:func:`~jaxelastic.solvers.pattern.rigid_body_modes`), optionally reusing the hierarchy;
  :meth:`AMGSolver.precondition` is one V-cycle ``M⁻¹r``, an SPD preconditioner.

Host-only packages (pypardiso, scikit-sparse, cholespy, pyamg) are imported inside the
functions that use them, never at import time. Assembly and the sparsity pattern live in
:mod:`~jaxelastic.solvers.pattern`; the matrices handed to these back ends keep the pattern,
with Dirichlet dofs eliminated symmetrically (identity rows/columns). Dof ordering is
node-major: dof ``a*dim + i`` is component ``i`` of node ``a``.
"""

from __future__ import annotations

import contextlib
import functools
import os
import sys
import time
import warnings
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .pattern import SparsityPattern, rigid_body_modes
from .results import Status

__all__ = [
    "DirectSolver",
    "AMGSolver",
    "make_backend",
    "available_direct_backends",
    "BACKEND_KINDS",
    "DIRECT_BACKENDS",
]

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


_MKL: list = []  # [ctypes function] once loaded, [None] if it cannot be


def _mkl_rt_candidates() -> list[str]:
    """Paths of ``mkl_rt`` to try, cheapest lookups first: pypardiso's override variable
    ``PYPARDISO_MKL_RT``, then the library directories of this environment and of the user
    site, where pip's ``mkl`` wheel puts it (one directory listing each)."""
    import glob
    import site

    env = os.environ.get("PYPARDISO_MKL_RT")
    if env:
        return [env]
    found: list[str] = []
    bases = [sys.prefix]
    with contextlib.suppress(Exception):  # no user site in some embedded interpreters
        bases.append(site.getuserbase())
    for base in bases:
        for sub in ("lib", "Lib", os.path.join("Library", "bin")):
            found += sorted(glob.glob(os.path.join(base, sub, "*mkl_rt*")), key=len)
    return found


def _load_mkl_rt():
    """``mkl_rt`` as a ``ctypes.CDLL`` where pypardiso is installed, or None.

    Found without importing pypardiso, in the environment's own library directories
    first: pypardiso's locator (the last resort here) walks the whole ``lib`` tree
    recursively when ``ctypes.util.find_library`` fails, which took 1.0 s of a 6 s bracket
    command, and importing pypardiso 0.6 s more.
    """
    import ctypes
    import importlib.util

    try:  # PARDISO is offered with pypardiso installed (which brings the mkl wheel)
        if importlib.util.find_spec("pypardiso") is None:
            return None
    except (ImportError, ValueError):
        return None
    for path in _mkl_rt_candidates():
        try:
            return ctypes.CDLL(path)
        except OSError:
            continue
    try:
        from pypardiso.pardiso_wrapper import PyPardisoSolver  # pyright: ignore

        return PyPardisoSolver().libmkl
    except (ImportError, OSError, AttributeError):
        return None


def _pardiso_function():
    """The ``pardiso`` entry point of MKL (pip's ``mkl`` wheel, a pypardiso dependency), or
    None.

    Loaded lazily on first use and cached.
    """
    if _MKL:
        return _MKL[0]
    fn = None
    try:
        import ctypes

        lib = _load_mkl_rt()
        if lib is None:
            raise ImportError("mkl_rt not found")
        fn = lib.pardiso
        P = ctypes.POINTER
        i32 = P(ctypes.c_int32)
        fn.argtypes = [P(ctypes.c_int64), i32, i32, i32, i32, i32, ctypes.c_void_p, i32, i32]
        fn.argtypes += [i32, i32, i32, i32, ctypes.c_void_p, ctypes.c_void_p, i32]
        fn.restype = None
    except (ImportError, OSError, AttributeError):
        fn = None
    _MKL.append(fn)
    return fn


def available_direct_backends() -> tuple[str, ...]:
    """The direct back ends importable here, fastest first (``"splu"`` always is)."""
    out = []
    if _pardiso_function() is not None:
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


class _Pardiso:
    """MKL PARDISO in SPD mode (``mtype = 2``) on the upper triangle, phases driven here.

    The symbolic analysis (phase 11: METIS nested dissection, symbolic factor) runs once per
    sparsity pattern; each :meth:`factor` is a numeric factorisation (phase 22), which fails
    with error -4 (zero/negative pivot) exactly when the matrix is not positive definite;
    :meth:`solve` is phase 33. We drive the phases ourselves rather than through
    ``pypardiso.spsolve``, which hashes (SHA-1) the whole matrix on every solve to decide
    whether to refactorise, and repeats the analysis with every factorisation.
    """

    def __init__(self, mtype: int = 2):
        fn = _pardiso_function()
        if fn is None:
            raise ImportError("MKL PARDISO needs pypardiso (pip install pypardiso)")
        self._fn = fn
        self.mtype = mtype
        self.pt = np.zeros(64, dtype=np.int64)  # PARDISO's opaque handle
        self.iparm = np.zeros(64, dtype=np.int32)
        ip = self.iparm
        ip[0] = 1  # no defaults: use the values below
        ip[1] = 2  # METIS nested-dissection ordering
        ip[7] = 0  # iterative refinement only when pivots were perturbed
        ip[9] = 8  # pivot perturbation 1e-8 (symmetric indefinite mode only)
        ip[10] = 0  # no scaling (SPD)
        ip[12] = 0  # no weighted matching (SPD)
        ip[17] = -1  # report the factor's nonzeros in iparm[17]
        ip[20] = 1  # Bunch-Kaufman pivoting (symmetric indefinite mode only)
        ip[26] = 0  # no matrix checker
        ip[34] = 1  # zero-based ia/ja: our int32 CSR arrays are passed without copies
        self._structure: tuple | None = None  # (indptr, indices) of the analysed pattern
        self._data = None  # the factorised values (PARDISO may read them again in phase 33)
        self._n = 0
        self.analyses = 0

    def _call(self, phase: int, n: int, data, b=None, x=None, nrhs: int = 1) -> int:
        import ctypes

        err = ctypes.c_int32(0)
        c = lambda v: ctypes.byref(ctypes.c_int32(v))
        P = ctypes.POINTER
        ia, ja = self._structure if self._structure is not None else (_EMPTY_I, _EMPTY_I)
        dummy = np.zeros(1)
        self._fn(
            self.pt.ctypes.data_as(P(ctypes.c_int64)),
            c(1),  # maxfct
            c(1),  # mnum
            c(self.mtype),
            c(phase),
            c(n),
            (dummy if data is None else data).ctypes.data,
            ia.ctypes.data_as(P(ctypes.c_int32)),
            ja.ctypes.data_as(P(ctypes.c_int32)),
            _EMPTY_I.ctypes.data_as(P(ctypes.c_int32)),  # perm (unused)
            c(nrhs),
            self.iparm.ctypes.data_as(P(ctypes.c_int32)),
            c(0),  # msglvl: quiet
            (dummy if b is None else b).ctypes.data,
            (dummy if x is None else x).ctypes.data,
            ctypes.byref(err),
        )
        return int(err.value)

    def factor(self, U: sp.csr_matrix) -> bool:
        """Numeric factorisation of the upper-triangular CSR ``U`` (sorted, diagonal
        stored); the symbolic analysis is redone only when the pattern changed.

        Returns:
            True when ``U + Uᵀ − diag`` is positive definite (factorised), else False.
        """
        n = int(U.indptr.size - 1)
        indptr = np.ascontiguousarray(U.indptr, dtype=np.int32)
        indices = np.ascontiguousarray(U.indices, dtype=np.int32)
        data = np.ascontiguousarray(U.data, dtype=np.float64)
        st = self._structure
        same = st is not None and (
            (st[0] is indptr and st[1] is indices)
            or (np.array_equal(st[0], indptr) and np.array_equal(st[1], indices))
        )
        if not same:
            self.release()
            self._structure = (indptr, indices)
            self._n = n
            err = self._call(11, n, data)
            if err != 0:
                self._structure = None
                raise RuntimeError(f"PARDISO symbolic analysis failed (error {err})")
            self.analyses += 1
        self._data = data
        err = self._call(22, n, data)
        if err == -4:  # zero or negative pivot: not positive definite (or singular)
            self._data = None
            return False
        if err != 0:
            self._data = None
            raise RuntimeError(f"PARDISO numeric factorisation failed (error {err})")
        return True

    @property
    def factor_nnz(self) -> int:
        """Nonzeros of the Cholesky factor (after an analysis)."""
        return int(self.iparm[17])

    @property
    def perturbed(self) -> int:
        """Pivots perturbed by the last numeric factorisation (indefinite mode)."""
        return int(self.iparm[13])

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``x = A⁻¹ b`` for ``b`` ``(n,)`` or ``(n, m)`` (float64)."""
        nrhs = 1 if b.ndim == 1 else b.shape[1]
        bf = np.asfortranarray(b, dtype=np.float64)
        x = np.zeros_like(bf, order="F")
        err = self._call(33, self._n, self._data, bf, x, nrhs)
        if err != 0:
            raise RuntimeError(f"PARDISO solve failed (error {err})")
        return np.ascontiguousarray(x)

    def release(self) -> None:
        """Free PARDISO's memory for this handle (factor and analysis)."""
        if self._structure is not None:
            self._call(-1, self._n, None)
        self._structure = None
        self._data = None

    def __del__(self):
        try:
            self.release()
        except Exception:  # interpreter shutdown: nothing left to free safely
            pass


_EMPTY_I = np.zeros(1, dtype=np.int32)


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
        self._pardiso: _Pardiso | None = None
        self._pardiso_indef: _Pardiso | None = None
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
        K, n = _as_csr(K)
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
                :meth:`~jaxelastic.solvers.pattern.SparsityPattern.upper_matrix`).
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
            self._pardiso = _Pardiso(mtype=2)
        self.method = "cholesky"
        ok = self._pardiso.factor(U)
        self.positive_definite = ok
        if ok:
            self._solve = self._pardiso.solve
        elif self.on_indefinite == "lu":
            if self._pardiso_indef is None:
                self._pardiso_indef = _Pardiso(mtype=-2)
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


class AMGSolver:
    """Smoothed-aggregation AMG (PyAMG) with rigid-body modes: an SPD preconditioner.

    Args:
        points: ``(n_nodes, dim)`` node positions for
            :func:`~jaxelastic.solvers.pattern.rigid_body_modes`.
        fixed: ``(n_nodes*dim,)`` bool Dirichlet mask (rows of the modes zeroed).
        reuse: rebuild the hierarchy (aggregates, prolongators) at the latest every
            ``reuse`` calls to :meth:`update`; 1 rebuilds every time. In between,
            :meth:`update` rebuilds only when the CG that used the hierarchy since the
            previous update converged markedly slower than the first one after the last
            rebuild (fewer than :data:`REBUILD_DIGITS_RATIO` of its digits per iteration,
            from the residual norms :meth:`precondition` was given), and refreshes
            otherwise. Measured on the twist (5 matrices along a 0→0.4 rad path, n = 29):
            rebuilding every time 8.7 s CPU, Galerkin refresh 5.8 s at unchanged iteration
            counts (13–14); one rebuild costs about 15 refreshes (3.5–4 s against
            0.2–0.35 s CPU at n = 29).
        refresh: between rebuilds, ``"galerkin"`` keeps P and R but recomputes the
            coarse operators ``R A P`` and smoothers for the new matrix; ``"fine"`` sets
            the new matrix and its smoothers on the finest level only and keeps the coarse
            operators until the CG's convergence per iteration degrades (below
            :data:`REFRESH_DIGITS_RATIO` of the reference's digits per iteration: then a
            Galerkin refresh); ``"none"`` keeps the old hierarchy as is (a preconditioner
            for a nearby matrix). Default ``"fine"``: on warm twist solves at n = 29 with
            the host CG and Chebyshev smoothing, 4.87–5.38 s and 44 CG iterations against
            ``"galerkin"``'s 5.18–6.23 s and 40 (host setup 0.65–0.87 s against
            1.41–1.86 s per solve; the Galerkin products ``R A P`` are 0.2 s a step).
        cycle: multigrid cycle of one :meth:`precondition` (``"V"``, ``"W"``, ``"F"``).
        smoother: ``"chebyshev"`` (default): a degree-:data:`CHEBYSHEV_DEGREE` Chebyshev
            polynomial in the Jacobi-scaled matrix ``D⁻¹A`` before and after the coarse
            correction, with ``λ_max(D⁻¹A)`` from a few Lanczos steps warm-started at the
            previous estimate's Ritz vector (Adams, Brezina, Hu & Tuminaro, *Parallel
            multigrid smoothing: polynomial versus Gauss–Seidel*, J. Comput. Phys. 188,
            2003); ``"gauss_seidel"``: PyAMG's symmetric block Gauss–Seidel (the
            ``presmoother``/``postsmoother`` of ``sa_options``). Measured at twist n = 29
            (81k dofs, one V-cycle): Chebyshev 13 ms, block Gauss–Seidel 39 ms, at
            13 against 11 PCG iterations to 1e-6.
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
        reuse: int = 50,
        refresh: str = "fine",
        cycle: str = "V",
        smoother: str = "chebyshev",
        sa_options: dict | None = None,
        block: bool = True,
        pattern: SparsityPattern | None = None,
    ):
        if int(reuse) < 1:
            raise ValueError(f"reuse must be >= 1, got {reuse!r}")
        if refresh not in ("galerkin", "fine", "none"):
            raise ValueError(f"refresh must be 'galerkin', 'fine' or 'none', got {refresh!r}")
        if smoother not in ("chebyshev", "gauss_seidel"):
            raise ValueError(f"smoother must be 'chebyshev' or 'gauss_seidel', got {smoother!r}")
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
            # the rigid-body modes are the exact near-null space: PyAMG's default 4 block
            # Gauss–Seidel sweeps "improving" them took 0.48 of the 0.84 s hierarchy build
            # at twist n = 29, for the same iteration counts
            improve_candidates=None,
        )
        self.smoother = smoother
        if smoother == "chebyshev":  # the library's own (set_chebyshev), none by PyAMG
            self.sa_options.update(presmoother=None, postsmoother=None)
        self.sa_options.update(sa_options or {})
        self._cheb: list[tuple[np.ndarray, np.ndarray]] = []  # (D⁻¹, coefficients) per level
        self._ritz: list[np.ndarray] = []  # Lanczos warm starts per level
        self._cheb_of: list = []  # the level matrices _cheb was computed for
        self.ml = None
        self._M = None
        self._A = None  # the matrix of the last update (host CG operator)
        self._threaded = None  # (A's product, cycle) with split products, for solve
        self._updates_since_build = 0
        self.setup_time = 0.0
        self.rebuilt = False
        self._norms: list[float] = []  # ‖r‖ of every single-column precondition call
        self._rate_ref: float | None = None  # first measured CG rate after a rebuild
        self.rate: float | None = None  # CG rate of the uses since the previous update

    def _amg_matrix(self, K):
        if not self.block or self.dim == 1:
            return K
        if self.pattern is not None and self.pattern.has_pattern(K):
            return self.pattern.to_bsr(K)
        return K.tobsr(blocksize=(self.dim, self.dim))

    def update(self, K, threads: bool = False) -> None:
        """Set the matrix ``(n, n)`` SPD sparse and (re)build or refresh the hierarchy
        (``threads``: a Galerkin refresh's products split over the cores by
        :func:`galerkin_product`; for calls from Python only, as :meth:`solve`)."""
        import pyamg

        t0 = time.perf_counter()
        K, n = _as_csr(K)
        if n != self.B.shape[0]:
            raise ValueError(f"matrix has {n} rows, the modes {self.B.shape[0]}")
        self._M = None
        self._threaded = None
        A = self._amg_matrix(K)
        self._A = A
        self.rate = _convergence_factor(self._norms)
        self._norms = []
        if self._rate_ref is None:
            self._rate_ref = self.rate  # the first measured use after a rebuild
        if self.ml is None or self._updates_since_build >= self.reuse or self._degraded():
            self.ml = None
            self.ml = pyamg.smoothed_aggregation_solver(A, B=self.B, **self.sa_options)
            self._updates_since_build = 1
            self._rate_ref = None
            self._ritz = self._ritz[:1]  # the coarse bases are new: their estimates start cold
            self.rebuilt = True
        else:
            if self.refresh == "galerkin" or (self.refresh == "fine" and self._degraded(True)):
                self._galerkin(A, threads)
            elif self.refresh == "fine":
                self._fine(A)
            self._updates_since_build += 1
            self.rebuilt = False
        if self.smoother == "chebyshev":
            self._set_chebyshev()
        self._M = self._cycle_function()
        self.setup_time = time.perf_counter() - t0

    def _degraded(self, refresh: bool = False) -> bool:
        """Whether the uses since the previous update converged markedly slower than the
        first measured use after the last rebuild: below :data:`REBUILD_DIGITS_RATIO`
        (``refresh``: :data:`REFRESH_DIGITS_RATIO`) of its digits per iteration."""
        ref, rate = self._rate_ref, self.rate
        if ref is None or rate is None or rate <= ref:
            return False
        ratio = REFRESH_DIGITS_RATIO if refresh else REBUILD_DIGITS_RATIO
        return bool(np.log(rate) > ratio * np.log(ref))  # digits per iteration: −log ρ

    def _cycle_function(self, threads: bool = False):
        """``r ↦ M⁻¹r`` (one cycle from a zero guess) of the current hierarchy
        (``threads``: the Chebyshev V-cycle's level products by :func:`split_matvec`).

        V-cycles traverse the levels here, as PyAMG's ``MultilevelSolver.solve`` does with
        ``maxiter=1`` but without the residual norms and the two extra fine-level products
        it computes around the cycle: the same result bit for bit, 2.4× cheaper (n = 29:
        0.046 s against 0.11–0.12 s CPU per application).
        """
        ml = self.ml
        assert ml is not None
        if self.smoother == "chebyshev":
            if self.cycle != "V":
                raise ValueError("the Chebyshev smoother runs V-cycles only (cycle='V')")
            levels, coarse, cheb = ml.levels, ml.coarse_solver, self._cheb
            if len(levels) == 1:
                return lambda b: coarse(levels[0].A, b)
            mvs = [split_matvec(lv.A) if threads else lv.A.__matmul__ for lv in levels[:-1]]
            return lambda b: _cheb_v_cycle(levels, coarse, cheb, mvs, 0, b)
        if self.cycle != "V" or len(ml.levels) == 1:
            return ml.aspreconditioner(cycle=self.cycle).matvec
        levels, coarse = ml.levels, ml.coarse_solver

        def cycle(b):
            x = np.zeros_like(b)
            _v_cycle(levels, coarse, 0, x, b)
            return x

        return cycle

    def _galerkin(self, A, threads: bool = False):
        from pyamg.multilevel import coarse_grid_solver
        from pyamg.relaxation.smoothing import change_smoothers

        ml = self.ml
        assert ml is not None  # called by update between rebuilds only
        levels = ml.levels
        levels[0].A = A
        for lo, hi in zip(levels[:-1], levels[1:], strict=True):
            Ac = galerkin_product(lo.R, lo.A, lo.P) if threads else lo.R @ lo.A @ lo.P
            hi.A = Ac.tobsr(blocksize=hi.A.blocksize) if hi.A.format == "bsr" else Ac.tocsr()
        if self.smoother != "chebyshev":  # (Chebyshev: _set_chebyshev, after this)
            change_smoothers(ml, self.sa_options["presmoother"], self.sa_options["postsmoother"])
        ml.coarse_solver = coarse_grid_solver(self.sa_options["coarse_solver"])

    def _set_chebyshev(self) -> None:
        """``(D⁻¹, coefficients)`` of the Chebyshev smoother of every level but the
        coarsest, for the current level matrices: ``λ_max(D⁻¹A)`` by
        :data:`LANCZOS_STEPS` Lanczos steps (:data:`LANCZOS_WARM_STEPS` from the
        previous Ritz vector of the level, if any), the polynomial on ``[λ/30, 1.1 λ]``
        (PyAMG's interval)."""
        ml = self.ml
        assert ml is not None
        cheb, ritz = [], []
        for i, level in enumerate(ml.levels[:-1]):
            A = level.A
            warm = i < len(self._ritz)  # a Ritz vector of this level's basis (update)
            if warm and self._cheb_of[i] is A:  # unchanged (refresh="fine": the coarse
                cheb.append(self._cheb[i])  # levels; 20 ms of Lanczos each at n = 29)
                ritz.append(self._ritz[i])
                continue
            d = np.asarray(A.diagonal(), dtype=np.float64)
            dinv = np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 0.0)
            v0 = self._ritz[i] if warm else _lanczos_start(A.shape[0])
            steps = LANCZOS_WARM_STEPS if warm else LANCZOS_STEPS
            lam, v = _lanczos_max(A, np.sqrt(dinv), v0, steps)
            lo, hi = CHEBYSHEV_INTERVAL
            cheb.append((dinv, _chebyshev_coefficients(lo * lam, hi * lam, CHEBYSHEV_DEGREE)))
            ritz.append(v)
        self._cheb, self._ritz = cheb, ritz
        self._cheb_of = [level.A for level in ml.levels[:-1]]  # the matrices they are for

    def _fine(self, A):
        """The new matrix and its smoothers on the finest level; coarse operators kept."""
        from pyamg.relaxation.smoothing import change_smoothers

        assert self.ml is not None
        self.ml.levels[0].A = A
        if self.smoother != "chebyshev":  # (Chebyshev: _set_chebyshev, after this)
            opts = self.sa_options
            change_smoothers(self.ml, opts["presmoother"], opts["postsmoother"])

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
        if r.ndim == 2 and r.shape[1] == 1:  # one right-hand side: a CG iteration
            return self.precondition(r[:, 0])[:, None]
        if r.ndim == 1:
            return self._recorded_cycle(self._M, r)
        return np.stack([self._M(np.ascontiguousarray(c)) for c in r.T], axis=1)

    def solve(
        self, b, tol: float, max_iter: int, threads: bool = False
    ) -> tuple[np.ndarray, int, int]:
        """Preconditioned CG on the host with the fine-level matrix and one cycle per
        iteration (:func:`host_cg`): ``(x, iterations, status)``.

        The same iteration as the device :func:`~jaxelastic.solvers.linear.cg` with this
        preconditioner, without a device round trip per iteration: the product with the
        assembled matrix (BSR, 1.9 ms at 81k dofs) replaces the element-by-element product
        on the device (15 ms), and no cycle is spent after the last iterate (measured at
        twist n = 29).

        Args:
            b: ``(n,)`` right-hand side; tol: absolute residual tolerance; max_iter: cap.
            threads: split the products with the large level matrices by rows over the
                CPU's cores (:func:`split_matvec`). For calls from Python only: inside an
                XLA host callback XLA's own threads hold the cores.
        """
        if self._M is None or self._A is None:
            raise RuntimeError("call update(K) before solve(b, ...)")
        if not threads:
            A = self._A  # the current matrix (under refresh="none" not the hierarchy's)
            return host_cg(lambda v: A @ v, b, self.precondition, tol, max_iter)
        if self._threaded is None:
            self._threaded = (split_matvec(self._A), self._cycle_function(threads=True))
        A_mv, cycle = self._threaded
        return host_cg(A_mv, b, lambda r: self._recorded_cycle(cycle, r), tol, max_iter)

    def _recorded_cycle(self, cycle, r) -> np.ndarray:
        """``cycle(r)`` of one ``(n,)`` residual, its norm recorded for the CG's measured
        convergence rate (:func:`_convergence_factor`)."""
        r = np.ascontiguousarray(r, dtype=np.float64)
        self._norms.append(float(np.sqrt(_dot(r, r))))
        return np.asarray(cycle(r), dtype=np.float64).reshape(r.shape)

    def info(self) -> dict:
        """``levels``, ``operator_complexity``, ``rebuilt``, ``setup_time`` of the hierarchy
        and ``rate`` (the CG's mean residual reduction per iteration measured at the last
        :meth:`update`, or None)."""
        if self.ml is None:
            return dict(levels=0, operator_complexity=0.0, rebuilt=False, setup_time=0.0, rate=None)
        return dict(
            levels=len(self.ml.levels),
            operator_complexity=float(self.ml.operator_complexity()),
            rebuilt=self.rebuilt,
            setup_time=self.setup_time,
            rate=self.rate,
        )


REFRESH_DIGITS_RATIO = 0.85
"""With ``refresh="fine"``, :class:`AMGSolver` recomputes its coarse operators (Galerkin)
when the CG it preconditioned since the previous update gained fewer than this fraction of
the digits per iteration of the first measured CG after the last rebuild."""

REBUILD_DIGITS_RATIO = 2.0 / 3.0
""":class:`AMGSolver` rebuilds its hierarchy before ``reuse`` updates when the CG it
preconditioned since the previous update gained fewer than this fraction of the digits per
iteration of the first measured CG after the last rebuild (iterations per digit up 50 %)."""


RATE_MIN_RATIOS = 8
""":func:`_convergence_factor` measures a rate from at least this many consecutive residual
ratios, else none: a CG that an inexact Newton step stops after a few iterations shows its
first, pre-asymptotic reductions, not the hierarchy's rate. At twist n = 44 a 6-iteration
solve measured ρ = 0.66 against 0.49 for the 19-iteration reference and triggered a 3.2 s
rebuild that bought nothing (warm solve 26.6 → 23.2 s without it, 67 → 59 CG iterations);
a hierarchy that has really degraded shows itself in long CG runs, which are measured."""


def _convergence_factor(norms: list[float]) -> float | None:
    """Mean residual reduction per CG iteration ``ρ`` from the norms of the residuals
    handed to successive preconditioner calls: the geometric mean of the ratios of
    consecutive norms, where a rise above 2× marks the start of another solve and is
    skipped; None with fewer than :data:`RATE_MIN_RATIOS` ratios."""
    logs = [
        float(np.log(b / a))
        for a, b in zip(norms[:-1], norms[1:], strict=True)
        if a > 0 and 0 < b <= 2.0 * a
    ]
    if len(logs) < max(2, RATE_MIN_RATIOS):
        return None
    return float(np.exp(np.mean(logs)))


def host_cg(A, b, M, tol: float, max_iter: int) -> tuple[np.ndarray, int, int]:
    """Preconditioned CG in NumPy, the host twin of :func:`jaxelastic.solvers.linear.cg`.

    Same stopping rules and statuses: ``‖r‖ ≤ tol`` (recurrence residual) → SUCCESS;
    ``max_iter`` iterations → MAX_STEPS; non-positive curvature ``pᵀAp ≤ 0`` →
    NEGATIVE_CURVATURE with the last iterate, or the preconditioned residual
    ``M⁻¹b`` if it happens in the first iteration. Unlike the device loop it applies no
    preconditioner after the last iterate.

    Inner products go through ``einsum``, not BLAS: called from an XLA callback, a
    multithreaded BLAS ``ddot`` competes with XLA's spinning worker threads (measured at
    twist n = 29 on 2 cores: the host CG 2× slower with ``r @ r``).

    Args:
        A, M: ``v ↦ A v`` and ``r ↦ M⁻¹ r`` on ``(n,)`` float64 arrays.
        b: ``(n,)`` right-hand side; tol: absolute tolerance; max_iter: iteration cap.

    Returns:
        ``(x (n,), iterations, status)`` (status an ``int`` of :class:`Status`).
    """
    b = np.asarray(b, dtype=np.float64)
    x = np.zeros_like(b)
    r = b.copy()
    if np.sqrt(_dot(r, r)) <= tol:  # (NaN goes on, to NEGATIVE_CURVATURE, as on the device)
        return x, 0, int(Status.SUCCESS)
    z = M(r)
    z0 = z
    p = z.copy()
    rz = _dot(r, z)
    for k in range(max_iter):
        Ap = A(p)
        pAp = _dot(p, Ap)
        if not pAp > 0:  # also NaN
            return (z0.copy() if k == 0 else x), k + 1, int(Status.NEGATIVE_CURVATURE)
        alpha = rz / pAp
        x += alpha * p
        r -= alpha * Ap
        if np.sqrt(_dot(r, r)) <= tol:
            return x, k + 1, int(Status.SUCCESS)
        z = M(r)
        rz_new = _dot(r, z)
        p *= rz_new / (rz if rz != 0 else 1.0)
        p += z
        rz = rz_new
    return x, max_iter, int(Status.MAX_STEPS)


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """``aᵀb`` of two ``(n,)`` arrays without a BLAS call (see :func:`host_cg`)."""
    return float(np.einsum("i,i->", a, b))


CHEBYSHEV_DEGREE = 2
"""Degree of :class:`AMGSolver`'s Chebyshev smoother (one product with A per application
from a zero guess, two otherwise). Measured at twist n = 29 (PCG to 1e-6): degree 2
13 iterations at 13 ms per V-cycle, degree 3 11 at 18 ms."""

CHEBYSHEV_INTERVAL = (1.0 / 30.0, 1.1)
"""The part ``[lo·λ, hi·λ]`` of the spectrum of ``D⁻¹A`` the smoother damps, in units of
the Lanczos estimate λ of its largest eigenvalue (PyAMG's ``setup_chebyshev`` defaults;
the Lanczos Ritz value is a lower bound, the 10 % margin keeps the top inside)."""

LANCZOS_STEPS = 10
"""Lanczos steps of the ``λ_max(D⁻¹A)`` estimate per level and setup, from a fixed start."""

LANCZOS_WARM_STEPS = 4
"""Lanczos steps from the previous setup's Ritz vector of the same level. Measured on the
twist n = 29 tangents (fine level, the Ritz vector of the previous Newton step): 4 warm
steps reach 0.992 of λ_max (5: 0.996, 10: 0.9995), 10 cold steps 0.967; the Chebyshev
interval's upper end 1.1 λ absorbs either."""


def _lanczos_start(n: int) -> np.ndarray:
    """A fixed, dense start vector (no zero entries, not smooth)."""
    i = np.arange(n, dtype=np.float64)
    return np.sin(12.9898 * i + 0.5) + 1.5


def _lanczos_max(A, s: np.ndarray, v0: np.ndarray, steps: int) -> tuple[float, np.ndarray]:
    """Largest eigenvalue of ``S A S`` (``S = diag(s)``; SPD ``A``) and its Ritz vector, by
    ``steps`` Lanczos steps from ``v0`` (no reorthogonalisation: only the extreme Ritz
    value is used). The largest eigenvalue of ``SAS`` is that of ``S²A = D⁻¹A``."""
    v = np.asarray(v0, dtype=np.float64).copy()
    v /= np.sqrt(_dot(v, v))
    V, alphas, betas = [], [], []
    v_prev, beta = np.zeros_like(v), 0.0
    for _ in range(max(1, min(steps, v.size))):
        V.append(v)
        w = s * (A @ (s * v)) - beta * v_prev
        alpha = _dot(w, v)
        w -= alpha * v
        alphas.append(alpha)
        beta = np.sqrt(_dot(w, w))
        if not beta > 1e-14 * abs(alpha):  # an invariant subspace (or NaN): stop
            break
        betas.append(beta)
        v_prev, v = v, w / beta
    k = len(alphas)
    T = np.diag(alphas) + np.diag(betas[: k - 1], 1) + np.diag(betas[: k - 1], -1)
    evals, evecs = np.linalg.eigh(T)
    lam = float(evals[-1])
    ritz = np.stack(V, axis=1) @ evecs[:, -1]
    if not (np.isfinite(lam) and lam > 0):
        return 2.0, _lanczos_start(v.size)  # (D⁻¹A of an SPD matrix: λ_max ≤ #nonzeros/row)
    return lam, ritz


def _chebyshev_coefficients(a: float, b: float, degree: int) -> np.ndarray:
    """Coefficients (highest power first) of ``q`` with ``1 − t q(t)`` the Chebyshev
    polynomial of ``degree`` on ``[a, b]`` scaled to 1 at ``t = 0`` (the smoother
    ``x ← x + q(D⁻¹A) D⁻¹ r`` damps the error by ``1 − t q(t)`` on that interval)."""
    roots = 0.5 * (b - a) * (1.0 + np.cos(np.pi * (np.arange(degree) + 0.5) / degree)) + a
    c = np.poly(roots)  # monic, highest power first
    c = c / np.polyval(c, 0.0)  # C(0) = 1
    return -c[:-1]  # C(t) = 1 − t q(t): q's coefficients are −c without the constant


def _chebyshev_apply(A, dinv: np.ndarray, coeffs: np.ndarray, r: np.ndarray) -> np.ndarray:
    """``q(D⁻¹A) D⁻¹ r`` by Horner's rule (``len(coeffs) − 1`` products ``A(v)``)."""
    y = dinv * r
    h = coeffs[0] * y
    for c in coeffs[1:]:
        h = c * y + dinv * A(h)
    return h


def _cheb_v_cycle(levels, coarse_solver, cheb, mvs, lvl: int, b) -> np.ndarray:
    """One V-cycle from a zero guess with the Chebyshev smoother (the same polynomial
    before and after the coarse correction: a symmetric preconditioner); ``mvs[i]``:
    ``v ↦ A_i v`` of level i."""
    level = levels[lvl]
    A = mvs[lvl]
    dinv, coeffs = cheb[lvl]
    x = _chebyshev_apply(A, dinv, coeffs, b)
    coarse_b = level.R @ (b - A(x))
    if lvl == len(levels) - 2:
        coarse_x = np.asarray(coarse_solver(levels[-1].A, coarse_b)).reshape(coarse_b.shape)
    else:
        coarse_x = _cheb_v_cycle(levels, coarse_solver, cheb, mvs, lvl + 1, coarse_b)
    x += level.P @ coarse_x
    x += _chebyshev_apply(A, dinv, coeffs, b - A(x))
    return x


SPLIT_MIN_ENTRIES = 1 << 20
""":func:`split_matvec` splits the products with matrices of at least this many stored
entries (the finest level from about 40k dofs in 3D); below, a thread hand-off costs more
than half a product saves."""


def _cores() -> int:
    """The CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


@functools.cache
def _matvec_pool():
    """The worker threads of :func:`split_matvec` (made on first use, one fewer than the
    cores: the calling thread computes the first part)."""
    from concurrent.futures import ThreadPoolExecutor

    return ThreadPoolExecutor(max_workers=max(1, _cores() - 1), thread_name_prefix="jaxelastic")


def _row_parts(A, parts: int) -> list[tuple[int, int, Any]]:
    """``A`` (CSR or BSR) split by (block) rows into at most ``parts`` non-empty row
    ranges of about equal stored entries: ``[(first row, end row, sub-matrix), ...]``; the
    sub-matrices share ``A``'s arrays (views)."""
    rows = A.blocksize[0] if A.format == "bsr" else 1
    indptr = A.indptr
    nb = indptr.size - 1
    cuts = np.searchsorted(indptr, np.linspace(0, indptr[-1], parts + 1)[1:-1])
    bounds = np.unique(np.concatenate([[0], np.clip(cuts, 0, nb), [nb]]))
    pieces = []
    for r0, r1 in zip(bounds[:-1], bounds[1:], strict=True):
        s, e = indptr[r0], indptr[r1]
        sub = type(A)(
            (A.data[s:e], A.indices[s:e], indptr[r0 : r1 + 1] - s),
            shape=(int(r1 - r0) * rows, A.shape[1]),
        )
        pieces.append((int(r0) * rows, int(r1) * rows, sub))
    return pieces


def split_matvec(A):
    """``v ↦ A v`` for a CSR or BSR matrix, split by (block) rows into as many parts of
    about equal stored entries as there are cores, computed in threads.

    SciPy's sparse products release the GIL, so the parts run in parallel: on the
    81k-dof twist matrix (3.6M entries, 2 cores) 1.45 ms against 2.32 ms for one
    product. Matrices below :data:`SPLIT_MIN_ENTRIES` entries, other formats and a
    single core get the plain product.

    Args:
        A: ``scipy.sparse`` CSR or BSR ``(n, m)``.

    Returns:
        A function of ``v`` ``(m,)`` giving ``A v`` ``(n,)`` (float64 for float64 inputs).
    """
    parts = min(_cores(), 8)
    if parts < 2 or A.nnz < SPLIT_MIN_ENTRIES or A.format not in ("csr", "bsr"):
        return A.__matmul__
    pieces = _row_parts(A, parts)
    pool = _matvec_pool()
    first, rest = pieces[0], pieces[1:]

    def into(out, lo, hi, M, v):
        out[lo:hi] = M @ v

    def mv(v):
        out = np.empty(A.shape[0], dtype=np.result_type(A.dtype, v.dtype))
        futures = [pool.submit(into, out, lo, hi, M, v) for lo, hi, M in rest]
        into(out, first[0], first[1], first[2], v)
        for f in futures:
            f.result()
        return out

    return mv


def galerkin_product(R, A, P):
    """The coarse operator ``R A P`` with ``R``'s (block) rows split over the cores, each
    part's ``(R_i A) P`` computed in a thread (SciPy's sparse products release the GIL),
    the parts stacked without a format round trip.

    Every row of the result is computed by the same row-wise sparse product as in
    ``R @ A @ P``, so the values equal it bit for bit. On the twist n = 29 hierarchy
    (81k → 6.8k dofs, 3.5M entries in ``A``; 2 cores) 0.13 s against 0.19 s. Below
    :data:`SPLIT_MIN_ENTRIES` entries in ``A``, for other formats and on one core: the
    plain product.

    Args:
        R: ``(m, n)`` restriction, CSR or BSR; A: ``(n, n)``; P: ``(n, m)`` prolongation.

    Returns:
        ``(m, m)`` sparse matrix (the format ``R @ A @ P`` has).
    """
    parts = min(_cores(), 8)
    if parts < 2 or A.nnz < SPLIT_MIN_ENTRIES or R.format not in ("csr", "bsr"):
        return R @ A @ P
    pieces = _row_parts(R, parts)
    if len(pieces) < 2:
        return R @ A @ P
    pool = _matvec_pool()
    futures = [pool.submit(lambda M: (M @ A) @ P, M) for _, _, M in pieces[1:]]
    outs = [(pieces[0][2] @ A) @ P] + [f.result() for f in futures]
    return _stack_rows(outs)


def _stack_rows(parts: list) -> Any:
    """Row blocks of one CSR or BSR format (equal block sizes) stacked by concatenating
    their arrays (``scipy.sparse.vstack`` goes through COO for BSR: 0.1 s at n = 29);
    other mixtures by ``scipy.sparse.vstack``."""
    fmt = parts[0].format
    same = all(p.format == fmt for p in parts) and fmt in ("csr", "bsr")
    if same and fmt == "bsr":
        same = all(p.blocksize == parts[0].blocksize for p in parts)
    if not same:
        return sp.vstack(parts, format=fmt if fmt in ("csr", "bsr") else "csr")
    offsets = np.cumsum([0] + [int(p.indptr[-1]) for p in parts])
    itype = np.result_type(*(p.indices.dtype for p in parts), *(p.indptr.dtype for p in parts))
    if offsets[-1] > np.iinfo(itype).max:
        itype = np.int64
    indptr = np.concatenate(
        [parts[0].indptr[:1].astype(itype)]
        + [p.indptr[1:].astype(itype) + o for p, o in zip(parts, offsets[:-1], strict=True)]
    )
    indices = np.concatenate([p.indices.astype(itype, copy=False) for p in parts])
    data = np.concatenate([p.data for p in parts])
    shape = (sum(p.shape[0] for p in parts), parts[0].shape[1])
    if fmt == "bsr":
        return sp.bsr_matrix((data, indices, indptr), shape=shape, blocksize=parts[0].blocksize)
    return sp.csr_matrix((data, indices, indptr), shape=shape)


def _v_cycle(levels, coarse_solver, lvl: int, x, b) -> None:
    """One V-cycle on level ``lvl`` of a PyAMG hierarchy, updating ``x`` ``(n_lvl,)`` in
    place (the recursion of PyAMG's ``MultilevelSolver.solve(..., cycle="V")``)."""
    level = levels[lvl]
    A = level.A
    level.presmoother(A, x, b)
    coarse_b = level.R @ (b - A @ x)
    coarse_x = np.zeros_like(coarse_b)
    if lvl == len(levels) - 2:
        coarse_x[:] = coarse_solver(levels[-1].A, coarse_b)
    else:
        _v_cycle(levels, coarse_solver, lvl + 1, coarse_x, coarse_b)
    x += level.P @ coarse_x
    level.postsmoother(A, x, b)


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
