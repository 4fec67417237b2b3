"""Host-side sparse assembly of element Hessians and linear solvers (NumPy/SciPy).

The global Hessian's sparsity depends only on the connectivity, so it is analysed once:
:meth:`SparsityPattern.build` precomputes the CSR structure and, for every entry of every
element Hessian, the CSR data slot it adds into. Assembling a new Hessian (every Newton
step) is then one weighted ``np.bincount`` over those slots, with no sorting and no
duplicate summation. Dirichlet dofs are eliminated *keeping the pattern* (their rows and
columns are zeroed, their diagonal set to 1), so the matrix stays symmetric and a
factorisation or AMG hierarchy can be reused across Newton steps.

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
import dataclasses
import os
import sys
import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

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
# sparsity pattern and assembly
# ----------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class SparsityPattern:
    """CSR structure of the global Hessian and the element→CSR scatter map.

    Built once per (mesh, Dirichlet mask) by :meth:`build`. All dofs are kept (fixed ones
    get an identity row/column after elimination), so ``n_dofs = n_nodes * dim``.

    Attributes:
        n_nodes, dim: mesh size and spatial dimension.
        indptr: ``(n_dofs + 1,)`` int32 CSR row pointers.
        indices: ``(nnz,)`` int32 CSR column indices, sorted within each row.
        scatter: ``(n_cells * (k*dim)**2,)`` intp; entry ``Ke.reshape(-1)[e]`` of the
            element Hessians ``Ke`` ``(n_cells, k*dim, k*dim)`` adds into ``data[scatter[e]]``.
        fixed: ``(n_dofs,)`` bool Dirichlet mask.
        transpose: ``(nnz,)`` intp; ``data[transpose]`` is the data of Kᵀ (same pattern).
        zeroed: CSR data slots in a fixed row or column (diagonals included).
        fixed_diag: CSR data slots of the diagonals of fixed dofs.
        diag_slots: ``(n_dofs,)`` intp CSR data slot of each diagonal entry ``(i, i)``.
        node_indptr, node_indices: the node-level (block) pattern; with ``bsr_perm`` it
            gives the same matrix as a BSR matrix with ``(dim, dim)`` blocks.
        bsr_perm: ``(nnz,)`` intp; ``data[bsr_perm].reshape(-1, dim, dim)`` is BSR data.
    """

    n_nodes: int
    dim: int
    indptr: np.ndarray
    indices: np.ndarray
    scatter: np.ndarray
    fixed: np.ndarray
    transpose: np.ndarray
    zeroed: np.ndarray
    fixed_diag: np.ndarray
    diag_slots: np.ndarray
    node_indptr: np.ndarray
    node_indices: np.ndarray
    bsr_perm: np.ndarray

    @property
    def n_dofs(self) -> int:
        return self.n_nodes * self.dim

    @property
    def nnz(self) -> int:
        return int(self.indices.size)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.n_dofs, self.n_dofs)

    @classmethod
    def build(
        cls, cells: np.ndarray, n_nodes: int, dim: int, fixed: np.ndarray | None = None
    ) -> SparsityPattern:
        """Analyse the connectivity once.

        Args:
            cells: ``(n_cells, k)`` node indices of each element.
            n_nodes: number of mesh nodes.
            dim: spatial dimension (dofs per node).
            fixed: ``(n_nodes*dim,)`` bool Dirichlet mask (node-major), or ``None``.

        Cost: one stable argsort of the ``n_cells*k²`` node pairs plus a few linear passes
        (about 4.5 s for 585k tets / 316k dofs on our 2-core machine, most of it first
        touching the 84M-entry ``scatter``); memory is dominated by ``scatter`` (8 bytes
        per element-Hessian entry, like the Hessians themselves).
        """
        cells = np.asarray(cells)
        if cells.ndim != 2:
            raise ValueError(f"cells must have shape (n_cells, k), got {cells.shape}")
        c, k = cells.shape
        d = int(dim)
        n = int(n_nodes)
        nd = n * d
        if fixed is None:
            fixed = np.zeros(nd, dtype=bool)
        fixed = np.asarray(fixed, dtype=bool).reshape(-1)
        if fixed.shape != (nd,):
            raise ValueError(f"fixed must have n_nodes*dim = {nd} entries, got {fixed.size}")

        # node-level pattern: unique (row node, col node) pairs in row-major order. A stable
        # argsort of int64 keys (radix/timsort) is ~5x faster than np.unique's quicksort.
        cl = cells.astype(np.int64)
        key = (cl[:, :, None] * n + cl[:, None, :]).reshape(-1)  # (c*k*k,)
        order = np.argsort(key, kind="stable")
        skey = key[order]
        new_block = np.empty(skey.size, dtype=bool)
        new_block[0] = True
        np.not_equal(skey[1:], skey[:-1], out=new_block[1:])
        ukey = skey[new_block]  # (n_blocks,)
        q = np.empty(key.size, dtype=np.int64)
        q[order] = np.cumsum(new_block) - 1  # block index of every (c, a, b)
        del key, order, skey, new_block
        q = q.reshape(c, k, k)
        brow = ukey // n
        bcol = ukey - brow * n
        deg = np.bincount(brow, minlength=n)  # blocks per node row
        node_indptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(deg, out=node_indptr[1:])

        # CSR slot of (row a*d+i, col b*d+j) where q is the index of block (a, b):
        #   d*d*node_indptr[a] + i*d*deg[a] + d*(q - node_indptr[a]) + j
        # (node a's d dof rows are consecutive, each holding d*deg[a] entries).
        ii = np.arange(d)
        row_part = (d * d - d) * node_indptr[cl][:, :, None] + (ii * d) * deg[cl][:, :, None]
        col_part = (d * q)[:, :, :, None] + ii  # (c, k, k, d)
        scatter = np.empty((c, k, d, k * d), dtype=np.intp)  # = Ke.reshape(c, k, d, k*d)
        np.add(row_part[..., None], col_part.reshape(c, k, 1, k * d), out=scatter)
        scatter = scatter.reshape(-1)
        del row_part, col_part, q

        row_len = np.repeat(d * deg, d)  # (nd,)
        indptr = np.zeros(nd + 1, dtype=np.int64)
        np.cumsum(row_len, out=indptr[1:])
        nnz = int(indptr[-1])
        if nnz >= np.iinfo(np.int32).max:
            raise ValueError(f"{nnz} nonzeros exceed int32 CSR indices")

        # work block by block (BSR order (block, i, j)), then permute into CSR order
        nb = ukey.size
        blk = np.arange(nb)
        bsr_perm = (
            (d * d * node_indptr[brow] + d * (blk - node_indptr[brow]))[:, None, None]
            + (ii * d)[None, :, None] * deg[brow][:, None, None]
            + ii[None, None, :]
        ).astype(np.intp)  # (nb, d, d): CSR slot of BSR entry (b, i, j)
        indices = np.empty(nnz, dtype=np.int32)
        indices[bsr_perm] = (bcol * d)[:, None, None] + ii[None, None, :]
        bt = np.searchsorted(ukey, bcol * n + brow)  # block index of the transposed block
        transpose = np.empty(nnz, dtype=np.intp)
        transpose[bsr_perm] = bsr_perm[bt].transpose(0, 2, 1)
        del bt
        fixed_n = fixed.reshape(n, d)
        fr = fixed_n[brow][:, :, None]  # (nb, d, 1): row dof fixed
        fc = fixed_n[bcol][:, None, :]  # (nb, 1, d): column dof fixed
        zeroed = np.sort(bsr_perm[fr | fc])
        diag = (brow == bcol)[:, None, None] & (ii[:, None] == ii[None, :])[None]
        fixed_diag = np.sort(bsr_perm[fr & diag])
        diag_slots = np.empty(nd, dtype=np.intp)  # diagonal blocks are (a, a), in row order
        diag_slots[(brow[brow == bcol] * d)[:, None] + ii] = bsr_perm[brow == bcol][:, ii, ii]
        bsr_perm = bsr_perm.reshape(-1)
        return cls(
            n_nodes=n,
            dim=d,
            indptr=indptr.astype(np.int32),
            indices=indices,
            scatter=scatter,
            fixed=fixed,
            transpose=transpose,
            zeroed=zeroed,
            fixed_diag=fixed_diag,
            diag_slots=diag_slots,
            node_indptr=node_indptr.astype(np.int32),
            node_indices=bcol.astype(np.int32),
            bsr_perm=bsr_perm,
        )

    # -- assembly --------------------------------------------------------------------

    def assemble_data(
        self, Ke, *, eliminate: bool = True, symmetrize: bool = True, diag=None
    ) -> np.ndarray:
        """CSR data ``(nnz,)`` of ``Σ_c Ke_c`` for element Hessians ``(n_cells, k*d, k*d)``.

        Args:
            eliminate: zero fixed rows/columns and put 1 on their diagonals.
            symmetrize: return ``(K + Kᵀ)/2`` (autodiff Hessians are symmetric only to
                round-off; Cholesky reads one triangle).
            diag: optional ``(n_dofs,)`` added to the diagonal before elimination (e.g. a
                lumped mass / dt² term); keeps the pattern, unlike ``K + sp.diags(m)``,
                which drops the explicit zeros of eliminated entries.
        """
        w = np.asarray(Ke, dtype=np.float64).reshape(-1)
        if w.size != self.scatter.size:
            raise ValueError(
                f"element Hessians have {w.size} entries, the pattern expects "
                f"{self.scatter.size} (n_cells*(k*dim)**2)"
            )
        # bincount with intp indices was the fastest of the variants we measured (585k tets,
        # 84M entries -> 13.7M slots: bincount 0.15 s; int32 indices 0.68 s (converted on
        # every call); CSR 0/1-matrix product 0.37 s; sort-once + add.reduceat 0.74 s;
        # block-wise sparse product 1.1 s; scipy COO->CSR 6.0 s)
        data = np.bincount(self.scatter, weights=w, minlength=self.nnz)
        if symmetrize:
            data += data[self.transpose]
            data *= 0.5
        if diag is not None:
            data[self.diag_slots] += np.asarray(diag, dtype=np.float64).reshape(-1)
        if eliminate:
            data[self.zeroed] = 0.0
            data[self.fixed_diag] = 1.0
        return data

    def matrix(self, data: np.ndarray) -> sp.csr_matrix:
        """Wrap CSR data ``(nnz,)`` in a ``scipy.sparse.csr_matrix`` (no copy)."""
        return sp.csr_matrix((data, self.indices, self.indptr), shape=self.shape, copy=False)

    def assemble(self, Ke, *, symmetrize: bool = True, diag=None) -> sp.csr_matrix:
        """Global Hessian with Dirichlet elimination, ``(n_dofs, n_dofs)`` CSR.

        ``Ke``: ``(n_cells, k*d, k*d)``; ``diag``: optional ``(n_dofs,)`` diagonal term.
        """
        data = self.assemble_data(Ke, eliminate=True, symmetrize=symmetrize, diag=diag)
        return self.matrix(data)

    def assemble_full(self, Ke, *, symmetrize: bool = True, diag=None) -> sp.csr_matrix:
        """Global Hessian without elimination (all dofs), ``(n_dofs, n_dofs)`` CSR."""
        data = self.assemble_data(Ke, eliminate=False, symmetrize=symmetrize, diag=diag)
        return self.matrix(data)

    def to_bsr(self, K: sp.csr_matrix) -> sp.bsr_matrix:
        """The same matrix as BSR with ``(dim, dim)`` node blocks (a gather, no search).

        ``K`` must have this pattern (e.g. come from :meth:`assemble`).
        """
        d = self.dim
        blocks = K.data[self.bsr_perm].reshape(-1, d, d)
        return sp.bsr_matrix(
            (blocks, self.node_indices, self.node_indptr), shape=self.shape, copy=False
        )

    def has_pattern(self, K) -> bool:
        """Whether CSR matrix ``K`` has exactly this structure (cheap identity test first)."""
        if not sp.issparse(K) or K.format != "csr" or K.shape != self.shape:
            return False
        if K.indices is self.indices and K.indptr is self.indptr:
            return True
        return (
            K.nnz == self.nnz
            and np.array_equal(K.indptr, self.indptr)
            and np.array_equal(K.indices, self.indices)
        )


# ----------------------------------------------------------------------------------------
# near-null space
# ----------------------------------------------------------------------------------------


def rigid_body_modes(points, fixed=None) -> np.ndarray:
    """Infinitesimal rigid-body motions of a node cloud, the elasticity near-null space.

    Args:
        points: ``(n_nodes, dim)`` positions (rest or current configuration).
        fixed: optional ``(n_nodes*dim,)`` bool Dirichlet mask; those rows are zeroed.

    Returns:
        ``(n_nodes*dim, 3)`` in 2D (2 translations, 1 rotation) or ``(n_nodes*dim, 6)``
        in 3D (3 translations, 3 rotations), node-major rows. Rotations are taken about
        the centroid and scaled by the cloud's size, so all columns have similar norms.
    """
    X = np.asarray(points, dtype=np.float64)
    n, d = X.shape
    if d not in (2, 3):
        raise ValueError(f"points must be (n_nodes, 2) or (n_nodes, 3), got {X.shape}")
    Y = X - X.mean(axis=0)
    scale = float(np.sqrt((Y**2).sum(axis=1).mean())) or 1.0
    Y = Y / scale
    if d == 2:
        B = np.zeros((n, 2, 3))
        B[:, 0, 0] = B[:, 1, 1] = 1.0
        B[:, 0, 2], B[:, 1, 2] = -Y[:, 1], Y[:, 0]
    else:
        B = np.zeros((n, 3, 6))
        B[:, 0, 0] = B[:, 1, 1] = B[:, 2, 2] = 1.0
        x, y, z = Y.T
        B[:, 1, 3], B[:, 2, 3] = -z, y  # rotation about x: e_x × Y
        B[:, 0, 4], B[:, 2, 4] = z, -x  # about y
        B[:, 0, 5], B[:, 1, 5] = -y, x  # about z
    B = B.reshape(n * d, -1)
    if fixed is not None:
        B[np.asarray(fixed, dtype=bool).reshape(-1)] = 0.0
    return B


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
