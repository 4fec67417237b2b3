"""Smoothed-aggregation AMG (PyAMG) with rigid-body modes: the host SPD preconditioner.

:class:`AMGSolver` builds a PyAMG hierarchy with the rigid-body near-null space
(:func:`~jaxelastic.solvers.host.pattern.rigid_body_modes`), reuses it across Newton steps
(refreshing the coarse operators, rebuilding when the CG's measured convergence degrades)
and applies one V-cycle with a Chebyshev smoother (:meth:`AMGSolver.precondition`), or runs
the whole preconditioned CG on the host (:meth:`AMGSolver.solve`, :func:`host_cg`).

pyamg is imported inside the functions that use it, never at import time.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from .krylov import blas_free_dot, host_cg
from .pattern import SparsityPattern, rigid_body_modes
from .products import as_csr, galerkin_product, split_matvec

__all__ = [
    "AMGSolver",
    "REFRESH_DIGITS_RATIO",
    "REBUILD_DIGITS_RATIO",
    "RATE_MIN_RATIOS",
    "CHEBYSHEV_DEGREE",
    "CHEBYSHEV_INTERVAL",
    "LANCZOS_STEPS",
    "LANCZOS_WARM_STEPS",
    "lanczos_max",
    "chebyshev_coefficients",
]


class AMGSolver:
    """Smoothed-aggregation AMG (PyAMG) with rigid-body modes: an SPD preconditioner.

    Args:
        points: ``(n_nodes, dim)`` node positions for
            :func:`~jaxelastic.solvers.host.pattern.rigid_body_modes`.
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
        pattern: optional :class:`~jaxelastic.solvers.host.pattern.SparsityPattern` of the
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
        K, n = as_csr(K)
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
            lam, v = lanczos_max(A, np.sqrt(dinv), v0, steps)
            lo, hi = CHEBYSHEV_INTERVAL
            cheb.append((dinv, chebyshev_coefficients(lo * lam, hi * lam, CHEBYSHEV_DEGREE)))
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

        The same iteration as the device :func:`~jaxelastic.solvers.linear.krylov` with this
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
        self._norms.append(float(np.sqrt(blas_free_dot(r, r))))
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


def lanczos_max(A, s: np.ndarray, v0: np.ndarray, steps: int) -> tuple[float, np.ndarray]:
    """Largest eigenvalue of ``S A S`` (``S = diag(s)``; SPD ``A``) and its Ritz vector, by
    ``steps`` Lanczos steps from ``v0`` (no reorthogonalisation: only the extreme Ritz
    value is used). The largest eigenvalue of ``SAS`` is that of ``S²A = D⁻¹A``."""
    v = np.asarray(v0, dtype=np.float64).copy()
    v /= np.sqrt(blas_free_dot(v, v))
    V, alphas, betas = [], [], []
    v_prev, beta = np.zeros_like(v), 0.0
    for _ in range(max(1, min(steps, v.size))):
        V.append(v)
        w = s * (A @ (s * v)) - beta * v_prev
        alpha = blas_free_dot(w, v)
        w -= alpha * v
        alphas.append(alpha)
        beta = np.sqrt(blas_free_dot(w, w))
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


def chebyshev_coefficients(a: float, b: float, degree: int) -> np.ndarray:
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
