"""MKL PARDISO through ctypes: the SPD and symmetric indefinite sparse direct solver.

:func:`pardiso_function` finds MKL's ``pardiso`` entry point (pip's ``mkl`` wheel, a
pypardiso dependency) without importing pypardiso; :class:`Pardiso` drives the analysis,
factorisation and solve phases itself, once per sparsity pattern.
"""

from __future__ import annotations

import contextlib
import os
import sys

import numpy as np
import scipy.sparse as sp

__all__ = ["Pardiso", "pardiso_function"]

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


def pardiso_function():
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


class Pardiso:
    """MKL PARDISO in SPD mode (``mtype = 2``) on the upper triangle, phases driven here.

    The symbolic analysis (phase 11: METIS nested dissection, symbolic factor) runs once per
    sparsity pattern; each :meth:`factor` is a numeric factorisation (phase 22), which fails
    with error -4 (zero/negative pivot) exactly when the matrix is not positive definite;
    :meth:`solve` is phase 33. We drive the phases ourselves rather than through
    ``pypardiso.spsolve``, which hashes (SHA-1) the whole matrix on every solve to decide
    whether to refactorise, and repeats the analysis with every factorisation.
    """

    def __init__(self, mtype: int = 2):
        fn = pardiso_function()
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
