"""Host-side linear algebra behind the Newton interface (sparse Cholesky, AMG-CG).

:class:`HostLinearSolver` is built once per (mesh, Dirichlet mask): it analyses the
sparsity pattern and keeps a :mod:`~jaxelastic.solvers.sparse` solver. Inside the jitted
Newton loop it is reached through :func:`jax.pure_callback`: the element Hessians computed
by JAX are assembled into CSR on the host (one ``bincount``), factorised or given an AMG
hierarchy, and the step comes back to the loop. On CPU nothing is copied across devices.

If the assembled Hessian is not positive definite (Cholesky fails, or AMG-CG meets
negative curvature), the element Hessians are PSD-projected on the host and the system is
solved again; the call reports it.
"""

from __future__ import annotations

import hashlib
import threading

import numpy as np

from .sparse import AMGSolver, DirectSolver, SparsityPattern, _pcg, make_solver

__all__ = ["HostLinearSolver"]


def _project_psd_np(Ke: np.ndarray) -> np.ndarray:
    Ke = 0.5 * (Ke + np.swapaxes(Ke, 1, 2))
    lam, Q = np.linalg.eigh(Ke)
    return np.einsum("cij,cj,ckj->cik", Q, np.maximum(lam, 0.0), Q)


class HostLinearSolver:
    """Sparse direct or AMG solve of the Newton system on the host.

    Args:
        cells: ``(n_cells, k)`` connectivity; points: ``(n_nodes, dim)`` rest positions.
        fixed: ``(n_nodes, dim)`` bool Dirichlet mask.
        kind: ``"direct"`` (CHOLMOD Cholesky via cholespy, SuperLU fallback) or ``"amg"``
            (PyAMG smoothed aggregation with rigid-body modes, as a CG preconditioner).
        **opts: options of the underlying solver class.

    Instances compare equal (and hash alike) when built for the same connectivity, mask,
    kind and options, so jitted solvers taking one as a static argument compile once per
    scene even if the object is rebuilt; reuse one to also skip the pattern analysis.
    """

    def __init__(self, cells, points, fixed, kind: str = "direct", **opts):
        cells = np.asarray(cells)
        points = np.asarray(points)
        fixed = np.asarray(fixed, dtype=bool)
        n, d = points.shape
        if fixed.shape != (n, d):
            raise ValueError(f"fixed mask must have shape {(n, d)}, got {fixed.shape}")
        self.kind = kind
        self.shape = (n, d)
        self.fixed = fixed.reshape(-1)
        self.pattern = SparsityPattern.build(cells, n, d, self.fixed)
        self.solver = make_solver(kind, points=points, fixed=self.fixed, **opts)
        h = hashlib.sha1()
        for a in (np.ascontiguousarray(cells), np.ascontiguousarray(points), self.fixed):
            h.update(a.tobytes())
        self._key = (kind, n, d, h.hexdigest(), repr(sorted(opts.items())))
        self.calls = 0
        self.projected_calls = 0
        self.adjoint_calls = 0
        self.adjoint_refactorizations = 0
        # XLA may run independent host callbacks concurrently (e.g. two load cases that
        # share this solver): one solve at a time, since they share the factorisation
        self._lock = threading.Lock()

    @classmethod
    def for_problem(cls, mesh, bc, kind: str = "direct", **opts) -> HostLinearSolver:
        """Build from a :class:`~jaxelastic.mesh.Mesh` and :class:`~jaxelastic.loads.Dirichlet`."""
        return cls(mesh.cells, mesh.points, bc.mask, kind, **opts)

    def _matrix(self, Ke, mass_diag):
        md = None
        if mass_diag is not None and np.any(mass_diag):
            md = np.repeat(np.asarray(mass_diag, dtype=np.float64), self.shape[1])
            md[self.fixed] = 0.0
        return self.pattern.assemble(Ke, diag=md)  # keeps the pattern (AMG reuse)

    def __call__(self, Ke, mass_diag, rhs, rtol):
        """Solve ``K Δ = rhs`` (``rhs`` ``(n_nodes, dim)``, zero on fixed dofs).

        Returns:
            ``(Δ (n_nodes, dim), iterations int32, projected bool)``.
        """
        with self._lock:
            return self._call(Ke, mass_diag, rhs, rtol)

    def _call(self, Ke, mass_diag, rhs, rtol):
        self.calls += 1
        Ke = np.array(Ke, dtype=np.float64)
        # autodiff Hessians are symmetric only to round-off (~1e-13); Cholesky reads one
        # triangle while the residual check uses the whole matrix, so symmetrise first
        Ke = 0.5 * (Ke + np.swapaxes(Ke, 1, 2))
        b = np.array(rhs, dtype=np.float64, order="C").reshape(-1)  # writable, contiguous
        K = self._matrix(Ke, mass_diag)
        self.solver.update(K)
        x, info = self.solver.solve(b, rtol=float(rtol))
        projected = False
        if not info.get("converged", True) or not np.all(np.isfinite(x)):
            projected = True
            self.projected_calls += 1
            K = self._matrix(_project_psd_np(Ke), mass_diag)
            self.solver.update(K)
            x, info = self.solver.solve(b, rtol=float(rtol))
        x = np.where(self.fixed, 0.0, x).reshape(self.shape).astype(np.asarray(rhs).dtype)
        return x, np.int32(info.get("iterations", 1)), np.bool_(projected)

    def _preconditioner(self):
        """``r ↦ M⁻¹r`` from the current factorisation / AMG hierarchy, or None."""
        sol = self.solver
        if isinstance(sol, DirectSolver):
            return sol._solve
        if isinstance(sol, AMGSolver):
            return None if sol.ml is None else sol.ml.aspreconditioner(cycle="V").matvec
        return sol._M

    def adjoint(self, Ke, mass_diag, rhs, rtol, reuse_iter=25):
        """Solve ``K y = rhs`` with the exact Hessian at a converged solution (the adjoint
        or tangent system of implicit differentiation); never PSD-projected.

        PCG on the assembled ``K(x*)``, preconditioned first by the factorisation (or AMG
        hierarchy) left by the last Newton step — the Hessian at the previous iterate,
        within ``O(‖x* − x_{k−1}‖)`` of ``K(x*)`` — for at most ``reuse_iter`` iterations;
        only if that leaves a residual above ``100·rtol`` is ``K(x*)`` itself factorised (or
        given a hierarchy) and PCG continued from the iterate reached.

        Args:
            Ke: ``(n_cells, k·d, k·d)`` element Hessians at x*; mass_diag: ``(n_nodes,)``;
            rhs: ``(n_nodes, dim)``, zero on fixed dofs; rtol: relative residual target.

        Returns:
            ``(y (n_nodes, dim), iterations int32, converged bool)``; y is the best iterate
            even when not converged (finite unless the matrix is not positive definite).
        """
        with self._lock:
            self.calls += 1
            self.adjoint_calls += 1
            Ke = np.array(Ke, dtype=np.float64)
            Ke = 0.5 * (Ke + np.swapaxes(Ke, 1, 2))
            b = np.array(rhs, dtype=np.float64, order="C").reshape(-1)
            K = self._matrix(Ke, mass_diag)
            rtol = float(rtol)
            M = self._preconditioner()
            y, info, its = None, dict(converged=False), 0
            if M is not None:
                y, info = _pcg(K, b, M, rtol, int(reuse_iter))
                its += info["iterations"]
                if not np.all(np.isfinite(y)):
                    y = None
            # refactorise only if the old preconditioner made poor progress: a true residual
            # a little above rtol is the round-off floor of K·y (~1e-12 here), which a new
            # factorisation would not lower (the caller's PCG certifies the final residual)
            if not info["converged"] and not info.get("residual", np.inf) <= 100.0 * rtol:
                self.adjoint_refactorizations += 1
                self.solver.update(K)
                M = self._preconditioner()
                if M is not None:
                    maxiter = getattr(self.solver, "maxiter", 200)
                    y2, info = _pcg(K, b, M, rtol, maxiter, y)
                    its += info["iterations"]
                    if np.all(np.isfinite(y2)):
                        y = y2
            ok = y is not None and bool(info.get("residual", np.inf) <= rtol)
            if y is None:
                y = np.full_like(b, np.nan)
            y = np.where(self.fixed, 0.0, y).reshape(self.shape).astype(np.asarray(rhs).dtype)
            return y, np.int32(its), np.bool_(ok)

    def __eq__(self, other) -> bool:
        return isinstance(other, HostLinearSolver) and self._key == other._key

    def __hash__(self) -> int:
        return hash(self._key)

    def __repr__(self) -> str:
        return f"HostLinearSolver(kind={self.kind!r}, n_dofs={self.fixed.size})"
