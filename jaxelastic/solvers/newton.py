"""Newton's method on the total potential Π, under ``jit`` (``lax.while_loop``).

Each iteration:

1. Dirichlet data enter the step: the prescribed part ``Δ_D = x_D − x`` is moved with the
   step and the free part solves ``K_ff Δ_f = −(g_f + K_fD Δ_D)``. The first iterate from
   the rest shape is therefore the linear-elastic predictor, and a boundary motion too
   large for one step is applied partially by the line search (no inverted initial guess).
2. The linear system is solved inexactly (forcing term ``η = min(½, √(‖g‖/‖g‖_ref))``,
   floored at 1e-4) by CG on the exact Hessian-vector product, or on PSD-projected element
   Hessians (``hessian="projected"``) for indefinite configurations; block-Jacobi or
   Jacobi preconditioning from element Hessians. Non-positive curvature is detected.
3. Backtracking line search treating non-finite Π as +∞ (an inverting step of a model that
   is undefined at J ≤ 0 is cut back until no element inverts): Armijo on Π far from the
   solution, decrease of the residual near it, where Π's round-off (~1e-16·Σ_c|x_cᵀK_c x_c|,
   far above 1e-16·|Π| near rest because ψ cancels large terms) exceeds
   the predicted decrease; steps that move Dirichlet dofs only need a finite Π.
4. Convergence: ``‖g_free‖ ≤ max(atol, rtol·‖g‖_ref)`` with all Dirichlet dofs in place
   (or a full step below ``xtol`` times the body's size, at the residual's round-off),
   where ``‖g‖_ref`` is the largest free residual seen, ‖f_ext‖, or the largest
   right-hand side ``‖g_f + K_fD Δ_D‖`` (the force induced by a Dirichlet motion).

Every solve returns a :class:`NewtonResult` with a :class:`Status`; :func:`solve` raises
:class:`SolveError` on failure when ``throw=True`` (outside jit).
"""

from __future__ import annotations

import enum
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from .. import potential as pot_mod
from ..energy import hvp
from ..kinematics import deformation_gradients, det
from ..loads import Dirichlet
from ..potential import Potential
from .host import HostLinearSolver
from .linear import CG_NEGATIVE_CURVATURE, CGResult, block_jacobi, cg, jacobi

__all__ = [
    "Status",
    "NewtonSettings",
    "NewtonResult",
    "SolveError",
    "newton",
    "solve",
    "make_linear",
    "LINEAR_SOLVERS",
    "AUTO_DIRECT_MAX_DOFS",
]

LINEAR_SOLVERS = ("auto", "cg", "direct", "amg")
AUTO_DIRECT_MAX_DOFS = {2: 100_000, 3: 10_000}
"""``linear="auto"``: sparse Cholesky up to this many dofs (per dimension), AMG-preconditioned
CG above. 3D: measured by ``scripts/bench_linear.py`` (AMG is 20–70× faster than a direct
factorisation from ~20k dofs on; the fill grows quickly in 3D). 2D: the fill of a nested-
dissection factorisation stays small (Cook P1 at 33k dofs: Cholesky 1.1 s vs AMG-CG 20 s,
``scripts/report_accuracy.py``)."""


class Status(enum.IntEnum):
    """Outcome of a solve (the ``status`` field of a result)."""

    SUCCESS = 0
    MAX_STEPS = 1
    LINE_SEARCH_FAILED = 2
    INVERTED = 3
    NONFINITE = 4


_RUNNING = -1

_REASONS = {
    Status.SUCCESS: "converged",
    Status.MAX_STEPS: "no convergence within max_steps Newton iterations",
    Status.LINE_SEARCH_FAILED: "line search found no acceptable step (energy non-finite or "
    "not decreasing along the Newton direction)",
    Status.INVERTED: "the configuration has inverted elements (J ≤ 0) where the material "
    "is undefined",
    Status.NONFINITE: "non-finite energy or forces (NaN/inf)",
}


class SolveError(RuntimeError):
    """A solve did not succeed (raised only with ``throw=True``, outside jit)."""

    def __init__(self, result, what: str = "Newton solve"):
        st = Status(int(result.status))
        super().__init__(
            f"{what} failed: {st.name}: {_REASONS[st]} (after {int(result.steps)} "
            f"iterations, residual {float(result.residual):.3e})"
        )
        self.result = result


class NewtonSettings(NamedTuple):
    """Static solver settings (hashable; changing one recompiles).

    Attributes:
        max_steps: maximum Newton iterations.
        rtol: relative tolerance on the free-dof force residual.
        atol: absolute tolerance [force].
        hessian: ``"hvp"`` (exact, matrix-free forward-over-reverse), ``"element"`` (exact
            element Hessians computed once per Newton step, then cheap matvecs), or
            ``"projected"`` (PSD-projected element Hessians: always a descent direction,
            but only linear convergence where the true Hessian is indefinite).
        preconditioner: ``"block_jacobi"``, ``"jacobi"`` or ``"none"``.
        cg_max_iter: CG iteration cap per Newton step.
        ls_max: maximum halvings in the line search.
        armijo: sufficient-decrease constant.
        require_positive_J: also reject trial steps where any element has J ≤ 0 (for user
            materials that return finite garbage there); the built-in neo-Hookean returns
            +inf, which the line search rejects anyway.
        xtol: also converged when a full Newton step moves no node by more than
            ``xtol × (rest bounding-box diagonal)`` with the Dirichlet dofs in place: the
            residual can stagnate at its round-off floor (e.g. ~eps·m/h²·|x| in dynamics)
            below ``rtol·‖g‖_ref`` for a body already at rest.
    """

    max_steps: int = 50
    rtol: float = 1e-8
    atol: float = 0.0
    hessian: str = "element"
    preconditioner: str = "block_jacobi"
    cg_max_iter: int = 2000
    ls_max: int = 40
    armijo: float = 1e-4
    require_positive_J: bool = False
    xtol: float = 1e-12


class NewtonResult(NamedTuple):
    """Result of a Newton solve.

    Attributes:
        x: ``(n_nodes, dim)`` final positions.
        status: :class:`Status` code (int array).
        steps: Newton iterations taken.
        linear_iterations: total CG iterations.
        residual: final free-dof residual norm [force].
        energy: final Π.
        residual_history: ``(max_steps + 1,)`` residual per iteration (NaN-padded).
        linear_history: ``(max_steps,)`` CG iterations per Newton step (0-padded).
        step_history: ``(max_steps,)`` accepted line-search step lengths (NaN-padded).
        line_search_cutbacks: total step halvings.
        negative_curvature: Newton steps whose CG met non-positive curvature.
        wall_time: seconds (filled by :func:`solve` outside jit, NaN inside).
    """

    x: jax.Array
    status: jax.Array
    steps: jax.Array
    linear_iterations: jax.Array
    residual: jax.Array
    energy: jax.Array
    residual_history: jax.Array
    linear_history: jax.Array
    step_history: jax.Array
    line_search_cutbacks: jax.Array
    negative_curvature: jax.Array
    wall_time: float | jax.Array = float("nan")

    @property
    def ok(self) -> bool:
        return int(self.status) == Status.SUCCESS

    @property
    def reason(self) -> str:
        return _REASONS[Status(int(self.status))]


def _min_J(pot: Potential, x):
    F = deformation_gradients(x, pot.mesh)
    return jnp.min(jax.vmap(jax.vmap(det))(F))


def _norm(a):
    return jnp.sqrt(jnp.sum(a * a))


def newton(
    pot: Potential,
    x0: jax.Array,
    bc: Dirichlet,
    settings: NewtonSettings = NewtonSettings(),
    linear=None,
) -> NewtonResult:
    """Minimise Π(x) subject to ``x[bc.mask] = bc.values[bc.mask]`` (pure, jit-compatible).

    Args:
        pot: the potential (elastic energy, loads, inertia).
        x0: ``(n_nodes, dim)`` initial positions (Dirichlet dofs need not be in place).
        bc: Dirichlet data.
        settings: static :class:`NewtonSettings`.
        linear: None for matrix-free CG under jit, or a
            :class:`~jaxelastic.solvers.host.HostLinearSolver` (sparse Cholesky / AMG on
            the host, reached through ``jax.pure_callback``); static.
    """
    s = settings
    if s.hessian not in ("hvp", "element", "projected"):
        raise ValueError(f"hessian must be 'hvp', 'element' or 'projected', got {s.hessian!r}")
    if s.preconditioner not in ("block_jacobi", "jacobi", "none"):
        raise ValueError(
            f"preconditioner must be 'block_jacobi', 'jacobi' or 'none', got {s.preconditioner!r}"
        )
    mask = bc.mask
    free = ~mask
    fm = free.astype(x0.dtype)
    xD = bc.values
    dtype = x0.dtype
    tiny = jnp.finfo(dtype).tiny
    need_Ke = s.hessian != "hvp" or s.preconditioner != "none" or linear is not None

    def value_and_grad(x):
        v = pot_mod.value(pot, x)
        if s.require_positive_J:
            v = jnp.where(_min_J(pot, x) > 0, v, jnp.inf)
        return jnp.where(jnp.isnan(v), jnp.inf, v), pot_mod.gradient(pot, x)

    def _energy_scale(x, Ke):
        if Ke is None:
            xKx = jnp.abs(jnp.sum(x * hvp(pot.psi, x, x, pot.mesh, pot.params)))
        else:
            xe = x[pot.mesh.cells].reshape(pot.mesh.n_cells, -1)
            xKx = jnp.sum(jnp.abs(jnp.einsum("ci,cij,cj->c", xe, Ke, xe)))
        if pot.f_ext is not None:
            xKx = xKx + jnp.abs(jnp.sum(pot.f_ext * x))
        return xKx

    ref0 = _norm(pot.f_ext * fm) if pot.f_ext is not None else jnp.zeros((), dtype)
    X = pot.mesh.points
    length = jnp.sqrt(jnp.sum((jnp.max(X, axis=0) - jnp.min(X, axis=0)) ** 2))

    def status_of(rn, dn, ref, k):
        tol = jnp.maximum(s.atol, s.rtol * ref)
        st = jnp.where(~jnp.isfinite(rn), Status.NONFINITE, _RUNNING)
        st = jnp.where((st == _RUNNING) & (rn <= tol) & (dn == 0), Status.SUCCESS, st)
        st = jnp.where((st == _RUNNING) & (k >= s.max_steps), Status.MAX_STEPS, st)
        return st

    def newton_step(x, g, energy0, ref):
        gf = g * fm
        rn = _norm(gf)
        dD = jnp.where(mask, xD - x, 0.0)
        dn = _norm(dD)

        if need_Ke:
            Ke = pot_mod.elastic_element_hessians(pot, x, project=s.hessian == "projected")
        if s.hessian in ("projected", "element"):

            def H(v):
                return pot_mod.element_hessian_vp(pot, Ke, v)
        else:

            def H(v):
                return pot_mod.hessian_vp(pot, x, v)

        def A(v):
            return fm * H(fm * v) + (1.0 - fm) * v

        if s.preconditioner == "none" or linear is not None:
            M = None
        else:
            blocks = pot_mod.node_hessian_blocks(pot, Ke)
            M = (block_jacobi if s.preconditioner == "block_jacobi" else jacobi)(blocks, free)

        rhs = -gf - lax.cond(dn > 0, lambda: fm * H(dD), lambda: jnp.zeros_like(x))
        bn = _norm(rhs)
        scale = jnp.maximum(jnp.maximum(ref, rn), bn)
        eta = jnp.clip(rn / jnp.maximum(scale, tiny), 1e-6, 0.1)
        tol_cg = jnp.maximum(eta * bn, 0.1 * s.rtol * scale)
        if linear is None:
            res = cg(A, rhs, M, tol=tol_cg, max_iter=s.cg_max_iter)
        else:
            md = pot_mod._mass_diag(pot)
            md = jnp.zeros(x.shape[:1], dtype) if md is None else md
            shapes = (
                jax.ShapeDtypeStruct(x.shape, dtype),
                jax.ShapeDtypeStruct((), jnp.int32),
                jax.ShapeDtypeStruct((), jnp.bool_),
            )
            dx, its, proj = jax.pure_callback(
                linear, shapes, Ke, md, rhs, tol_cg / jnp.maximum(bn, tiny)
            )
            res = CGResult(
                x=dx,
                iterations=its,
                status=jnp.where(proj, CG_NEGATIVE_CURVATURE, 0),
                residual=jnp.zeros((), dtype),
            )
        d_free = res.x * fm
        slope_free = jnp.sum(g * d_free)
        # not a descent direction (only possible without projection): steepest descent
        bad = (dn == 0) & ~(slope_free < 0)
        d_free = jnp.where(bad, fm * (M(-gf) if M is not None else -gf), d_free)
        step = d_free + dD
        slope = jnp.sum(g * step)
        # Round-off in Π is not ~eps·|Π|: ψ cancels terms of size ~F:C:F inside each
        # element (e.g. μ(I_C − 2 tr S + d) near rest, where Π → 0), so the scale is
        # Σ_c |x_cᵀK_c x_c| = Σ_c w|F:C:F| (translation invariant) plus |f_extᵀx|.
        escale = jnp.maximum(jnp.abs(energy0), _energy_scale(x, Ke if need_Ke else None))
        near = jnp.abs(slope) <= 1e-10 * jnp.maximum(escale, tiny)

        def trial(alpha):
            xt = x + alpha * step
            xt = jnp.where(mask & (alpha == 1.0), xD, xt)
            et, gt = value_and_grad(xt)
            finite = jnp.isfinite(et)
            armijo = et <= energy0 + s.armijo * alpha * slope
            residual_ok = near & (dn == 0) & (_norm(gt * fm) < rn)
            accept = finite & ((dn > 0) | armijo | residual_ok)
            return xt, et, gt, accept

        def ls_cond(c):
            alpha, xt, et, gt, acc, j = c
            return (~acc) & (j < s.ls_max)

        def ls_body(c):
            alpha, xt, et, gt, acc, j = c
            alpha = 0.5 * alpha
            xt, et, gt, acc = trial(alpha)
            return alpha, xt, et, gt, acc, j + 1

        one = jnp.asarray(1.0, dtype)
        alpha, xt, et, gt, acc, cuts = lax.while_loop(
            ls_cond, ls_body, (one, *trial(one), jnp.asarray(0, jnp.int32))
        )
        neg = res.status == CG_NEGATIVE_CURVATURE
        step_inf = jnp.max(jnp.abs(step))
        return xt, et, gt, acc, alpha, cuts, res.iterations, neg, bn, step_inf

    def cond(c):
        return c["status"] == _RUNNING

    def body(c):
        x, g, k = c["x"], c["g"], c["k"]
        xt, et, gt, acc, alpha, cuts, lin, neg, bn, step_inf = newton_step(
            x, g, c["energy"], c["ref"]
        )
        x_new = jnp.where(acc, xt, x)
        e_new = jnp.where(acc, et, c["energy"])
        g_new = jnp.where(acc, gt, g)
        rn = _norm(g_new * fm)
        dn = _norm(jnp.where(mask, xD - x_new, 0.0))
        # bn = ‖g_f + K_fD Δ_D‖ is the force a Dirichlet motion induces: the reference of a
        # purely displacement-driven solve (whose free residual is 0 at the rest shape)
        ref = jnp.maximum(jnp.maximum(c["ref"], rn), bn)
        st = status_of(rn, dn, ref, k + 1)
        tiny_step = acc & (alpha == 1.0) & (dn == 0) & (step_inf <= s.xtol * length)
        st = jnp.where((st == _RUNNING) & tiny_step & jnp.isfinite(rn), Status.SUCCESS, st)
        st = jnp.where(acc, st, Status.LINE_SEARCH_FAILED)
        return dict(
            x=x_new,
            g=g_new,
            energy=e_new,
            k=k + 1,
            status=st.astype(jnp.int32),
            ref=ref,
            hist=c["hist"].at[k + 1].set(rn),
            lin_hist=c["lin_hist"].at[k].set(lin.astype(jnp.int32)),
            alpha_hist=c["alpha_hist"].at[k].set(jnp.where(acc, alpha, jnp.nan)),
            cuts=c["cuts"] + cuts.astype(jnp.int32),
            neg=c["neg"] + neg.astype(jnp.int32),
        )

    e0, g0 = value_and_grad(x0)
    rn0 = _norm(g0 * fm)
    dn0 = _norm(jnp.where(mask, xD - x0, 0.0))
    ref = jnp.maximum(ref0, rn0)
    st0 = status_of(rn0, dn0, ref, 0)
    st0 = jnp.where(
        jnp.isfinite(e0), st0, jnp.where(_min_J(pot, x0) <= 0, Status.INVERTED, Status.NONFINITE)
    )
    nan = jnp.full((s.max_steps,), jnp.nan, dtype)
    c0 = dict(
        x=x0,
        g=g0,
        energy=e0,
        k=jnp.asarray(0, jnp.int32),
        status=st0.astype(jnp.int32),
        ref=ref,
        hist=jnp.full((s.max_steps + 1,), jnp.nan, dtype).at[0].set(rn0),
        lin_hist=jnp.zeros((s.max_steps,), jnp.int32),
        alpha_hist=nan,
        cuts=jnp.asarray(0, jnp.int32),
        neg=jnp.asarray(0, jnp.int32),
    )
    c = lax.while_loop(cond, body, c0)
    return NewtonResult(
        x=c["x"],
        status=c["status"],
        steps=c["k"],
        linear_iterations=jnp.sum(c["lin_hist"]),
        residual=c["hist"][c["k"]],
        energy=c["energy"],
        residual_history=c["hist"],
        linear_history=c["lin_hist"],
        step_history=c["alpha_hist"],
        line_search_cutbacks=c["cuts"],
        negative_curvature=c["neg"],
    )


_newton_jit = jax.jit(newton, static_argnames=("settings", "linear"))


def make_linear(mesh, bc: Dirichlet, kind: str = "auto"):
    """The linear-solver argument of :func:`newton` for a scene: None (matrix-free CG under
    jit) for ``"cg"``, else a :class:`HostLinearSolver` (``"direct"``, ``"amg"``, or
    ``"auto"``: direct up to :data:`AUTO_DIRECT_MAX_DOFS` dofs, AMG above)."""
    if kind not in LINEAR_SOLVERS:
        raise ValueError(f"linear solver must be one of {LINEAR_SOLVERS}, got {kind!r}")
    if kind == "cg":
        return None
    if kind == "auto":
        kind = "direct" if mesh.n_dofs <= AUTO_DIRECT_MAX_DOFS[mesh.dim] else "amg"
    return HostLinearSolver.for_problem(mesh, bc, kind)


def solve(
    pot: Potential,
    bc: Dirichlet,
    x0: jax.Array | None = None,
    *,
    settings: NewtonSettings = NewtonSettings(),
    linear: HostLinearSolver | str | None = "auto",
    throw: bool = True,
) -> NewtonResult:
    """Jitted :func:`newton` with wall-clock timing and loud failures.

    Args:
        pot: the potential; bc: Dirichlet data; x0: initial positions (default: rest).
        settings: :class:`NewtonSettings`.
        linear: ``"auto"`` (default: sparse Cholesky for small problems, AMG-CG for
            large, see :func:`make_linear`), ``"cg"`` or None (matrix-free PCG under jit),
            ``"direct"``, ``"amg"``, or a prebuilt :class:`HostLinearSolver` (reuse it
            across solves of the same scene to skip the pattern analysis).
        throw: raise :class:`SolveError` unless the status is SUCCESS.
    """
    if x0 is None:
        x0 = pot.mesh.points
    x0 = jnp.asarray(x0, pot.mesh.points.dtype)
    if x0.shape != pot.mesh.points.shape:
        raise ValueError(f"x0 must have shape {pot.mesh.points.shape}, got {x0.shape}")
    if isinstance(linear, str):
        linear = make_linear(pot.mesh, bc, linear)
    t0 = time.perf_counter()
    res = jax.block_until_ready(_newton_jit(pot, x0, bc, settings=settings, linear=linear))
    res = res._replace(wall_time=time.perf_counter() - t0)
    if throw and int(res.status) != Status.SUCCESS:
        raise SolveError(res)
    return res
