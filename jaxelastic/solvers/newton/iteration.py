"""The pieces of one Newton iteration: right-hand side, direction, line search, the
residual's round-off floor and the status test (see :mod:`jaxelastic.solvers.newton`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from ...loads import Dirichlet
from ...mechanics import potential as pot_mod
from ...mechanics.fusion import always, computed
from ...mechanics.kernels import hvp
from ...mechanics.kinematics import deformation_gradients, det
from ...mechanics.potential import Potential
from ..linear.system import NewtonSystem, is_nonsymmetric
from ..results import RUNNING, Solution, Status
from .settings import Newton
from .terms import step_bound

__all__ = [
    "norm",
    "min_J",
    "value_and_grad",
    "energy_scale",
    "is_quadratic",
    "exact_tangent",
    "newton_rhs",
    "descent",
    "line_search",
    "Correction",
    "NATURAL_MONOTONICITY",
    "residual_floor",
    "status_of",
    "near_tol",
    "STALL",
    "NEAR_EPS",
    "FLOOR_FACTOR",
    "STRAIGHT_TRIAL_MIN_CELLS",
]


def norm(a):
    return jnp.sqrt(jnp.sum(a * a))


def min_J(pot: Potential, x):
    F = deformation_gradients(x, pot.mesh)
    return jnp.min(jax.vmap(jax.vmap(det))(F))


def value_and_grad(s: Newton, pot: Potential, x):
    v = pot_mod.value(pot, x)
    if s.require_positive_J:
        v = jnp.where(min_J(pot, x) > 0, v, jnp.inf)
    return jnp.where(jnp.isnan(v), jnp.inf, v), pot_mod.gradient(pot, x)


def _computed_once(fn, mesh, *args):
    """``fn(*args)`` stored once (:func:`~jaxelastic.fusion.computed`) for a mesh on one
    device; for a sharded mesh (``mesh.halo``) plainly: there the predicate and the
    branch's gathers are collectives, and collectives inside a conditional made the two
    processes of a multi-process solve issue them in different orders (Gloo: "collective
    mismatch", 2 of 3 runs of the two-process twist)."""
    if getattr(mesh, "halo", None) is not None:
        return fn(*args)
    return computed(fn, always(mesh.cells), *args)


def energy_scale(pot: Potential, x, Ke):
    """Σ_c |x_cᵀK_c x_c| + |f_extᵀx|: the round-off scale of Π (translation invariant)."""
    if Ke is None:
        xKx = jnp.abs(jnp.sum(x * hvp(pot.psi, x, x, pot.mesh, pot.params)))
    else:
        xe = x[pot.mesh.cells].reshape(pot.mesh.n_cells, -1)  # (n_cells, m)

        def products(Ke, xe):  # K_c x_c in one loop over the columns
            Kx = Ke[:, :, 0] * xe[:, 0:1]
            for j in range(1, xe.shape[1]):
                Kx = Kx + Ke[:, :, j] * xe[:, j : j + 1]
            return Kx

        # stored before the sum (see _residual_floor): the batched-matvec einsum took
        # 0.030 s at 146k tets
        Kx = _computed_once(products, pot.mesh, Ke, xe)
        xKx = jnp.sum(jnp.abs(jnp.sum(Kx * xe, axis=1)))
    if pot.f_ext is not None:
        xKx = xKx + jnp.abs(jnp.sum(pot.f_ext * x))
    if pot.pressure is not None:
        xKx = xKx + jnp.abs(pot.pressure.energy(x))
    return xKx


def is_quadratic(pot: Potential) -> bool:
    """Whether Π is quadratic in x, so one exact Newton step solves it (static).

    True when ψ is marked ``psi.is_quadratic = True`` (the built-in ``linear`` material;
    mark your own quadratic ψ likewise) and the kinematics are linear in x (not F-bar,
    whose F̄ = (J̄/J)^{1/d} F is nonlinear). Inertia, damping and external forces keep Π
    quadratic; a loop term such as contact (the log barrier) or a pressure (−p V, cubic in
    3D) does not.
    """
    quadratic_psi = getattr(pot.psi, "is_quadratic", False) is True
    linear_kin = pot.mesh.formulation != "fbar" and pot.pressure is None
    return quadratic_psi and linear_kin and not pot_mod.loop_terms(pot)


def exact_tangent(s: Newton, pot: Potential) -> bool:
    """Whether Newton's operator is the true, non-symmetric tangent (static): the one table
    of :attr:`Newton.tangent`.

    ======================  =====================  ==============================
    potential               ``"auto"``/``"exact"``  ``"symmetric"``
    ======================  =====================  ==============================
    follower pressure       true tangent, GMRES     symmetric part (quasi-Newton)
    conservative            symmetric Hessian       symmetric Hessian
    ======================  =====================  ==============================

    ``"auto"`` is ``"exact"``: measured on Land et al.'s problem 1 and a follower-loaded
    cantilever (``docs/guide/pressure.md``), the true tangent converges quadratically in
    a fraction of the quasi-Newton's iterations and solves loads at which the quasi-Newton
    stalls; each of its iterations costs a GMRES of a few preconditioned products instead
    of one solve.
    """
    return s.tangent != "symmetric" and is_nonsymmetric(pot)


def newton_rhs(s: Newton, system: NewtonSystem, g, dD, ref):
    """``(rhs, tol, ‖rhs‖)`` of the Newton step's linear solve ``K_ff Δ_f = rhs``."""
    fm = system.free.astype(g.dtype)
    tiny = jnp.finfo(g.dtype).tiny
    gf = g * fm
    rn, dn = norm(gf), norm(dD)
    # K_fD Δ_D: the force a Dirichlet motion induces on the free dofs
    KdD = lax.cond(dn > 0, lambda: fm * system.H(dD), lambda: jnp.zeros_like(g))
    rhs = -gf - KdD
    bn = norm(rhs)
    scale = jnp.maximum(jnp.maximum(ref, rn), bn)
    # inexact Newton (forcing η·‖rhs‖) only where the model is nonlinear: on a quadratic
    # potential one accurate solve is the answer, and a loose one only costs Newton steps
    eta = jnp.clip(rn / jnp.maximum(scale, tiny), 1e-6, 0.1)
    tight = 0.1 * s.rtol * scale
    tol = tight if is_quadratic(system.pot) else jnp.maximum(eta * bn, tight)
    return rhs, tol, bn


def descent(system: NewtonSystem, g, dD, res: Solution):
    """Newton direction (free part + Dirichlet motion) from the linear solve's ``res``."""
    fm = system.free.astype(g.dtype)
    gf = g * fm
    d_free = res.x * fm
    # not a descent direction (only possible without projection): steepest descent; a
    # non-symmetric tangent's Newton direction descends on ‖g‖², not on gᵀd
    bad = (norm(dD) == 0) & ~(jnp.sum(g * d_free) < 0) & system.symmetric
    d_free = jnp.where(bad, -gf, d_free)
    return d_free + dD


class Correction(NamedTuple):
    """The simplified Newton correction of a non-conservative load's line search:
    ``norm(r) = ‖K_k⁻¹ r‖`` [length] with the step's own tangent ``K_k`` (one linear
    solve), and ``eta``, the relative residual the step's linear solve reached (the
    inexact Newton direction's slope on ½‖r‖² is at most ``−(1 − η)‖r‖²``)."""

    norm: Callable[[jax.Array], jax.Array]
    eta: jax.Array


def line_search(s: Newton, pot, bc: Dirichlet, x, g, e0, step, near, floor, correction=None):
    """Backtracking from α = 1, or from the smaller bound of the potential's terms
    (:func:`~jaxelastic.solvers.newton.terms.step_bound`; contact: the CCD bound
    ``min(1, 0.8·τ*)``): ``(α, x_t, Π_t, g_t, accepted, halvings)``.

    ``correction``: ``None`` for a potential (Armijo on Π), or for a non-conservative
    load a :class:`Correction` (the simplified Newton correction with this step's
    tangent): a trial is then accepted by a sufficient decrease of the residual norm or
    else by the natural monotonicity test (:data:`NATURAL_MONOTONICITY`)."""
    mask, xD = bc.mask, bc.values
    fm = (~mask).astype(x.dtype)
    rn = norm(g * fm)
    dn = norm(jnp.where(mask, xD - x, 0.0))
    slope = jnp.sum(g * step)
    sn = norm(step * fm)

    def trial(alpha):
        xt = x + alpha * step
        xt = jnp.where(mask & (alpha == 1.0), xD, xt)
        et, gt = value_and_grad(s, pot, xt)
        rt = norm(gt * fm)
        if correction is None:
            armijo = et <= e0 + s.armijo * alpha * slope
            # near the solution Π's round-off hides the decrease; at the residual's
            # round-off floor its norm is noise, so a trial that stays below the floor is
            # accepted too
            residual_ok = near & (dn == 0) & (rt < jnp.maximum(rn, floor))
            accept = jnp.isfinite(et) & ((dn > 0) | armijo | residual_ok)
        else:  # ‖K_k⁻¹ r(x_t)‖ ≤ (1 − α/4)‖Δ‖, solved only where the residual's
            # sufficient decrease for an inexact Newton direction, ‖r_t‖ ≤ (1 − cα(1 − η))‖r‖
            # (Eisenstat & Walker 1994, SIAM J. Optim. 4:393), or its floor does not decide
            eta, simplified = correction.eta, correction.norm
            residual_ok = (rt <= floor) | (rt <= (1.0 - s.armijo * alpha * (1.0 - eta)) * rn)

            def natural():
                return simplified(gt * fm) <= (1.0 - NATURAL_MONOTONICITY * alpha) * sn

            finite = jnp.isfinite(et) & jnp.isfinite(rt)
            undecided = finite & (dn == 0) & ~residual_ok
            if getattr(pot.mesh, "halo", None) is not None:  # no collectives inside a
                monotone = undecided & natural()  # conditional (see _computed_once)
            else:
                monotone = lax.cond(undecided, natural, lambda: jnp.asarray(False))
            accept = finite & ((dn > 0) | monotone | residual_ok)
        return xt, et, gt, accept

    def cond(c):
        return (~c[4]) & (c[5] < s.ls_max)

    def body(c):
        alpha = 0.5 * c[0]
        return (alpha, *trial(alpha), c[5] + 1)

    # terms that bound the step (contact: every trial stays intersection-free)
    alpha0 = jnp.minimum(1.0, step_bound(pot, x, step)).astype(x.dtype)
    if pot.mesh.n_cells >= STRAIGHT_TRIAL_MIN_CELLS:  # the first trial before the loop
        start = (alpha0, *trial(alpha0), jnp.asarray(0, jnp.int32))
    else:  # the loop's first pass tries alpha0 (halvings 0): Π compiled once
        inf = jnp.asarray(jnp.inf, x.dtype)
        start = (2.0 * alpha0, x, inf, g, jnp.asarray(False), jnp.asarray(-1, jnp.int32))
    return lax.while_loop(cond, body, start)


NATURAL_MONOTONICITY = 0.25
"""A trial ``x + αΔ`` of a non-conservative (follower) Newton step is accepted when its
simplified Newton correction, solved with the step's own tangent, is shorter than the
step by this margin: ``‖K_k⁻¹ r(x + αΔ)‖ ≤ (1 − α/4)‖Δ‖`` (the restricted natural
monotonicity test of Deuflhard, *Newton Methods for Nonlinear Problems*, 2004, §3.3).
Without a potential to decrease, the residual's own norm is the obvious merit, but it is
not affine covariant: it is dominated by the stiff (axial, volumetric) modes, whose
residual grows quadratically along the linearised step of a rotating body, so a test on
it alone cut every step of the follower cantilever to α = 1/64–1/128 (125 steps at
p = 2 against 13 with this test; margins 0.5 and 0.75 took 23 and failed at p = 4, where
0.25 takes 20). A trial whose residual norm decreases sufficiently is accepted without
the extra solve: near the solution that decides, where the inexact corrections are
noise (Land et al.'s beam at twice its load stopped at 6.6e-4 of its first residual
on the natural test alone)."""


STRAIGHT_TRIAL_MIN_CELLS = 50_000
"""Meshes of at least this many cells run the line search's first trial (α = 1) outside
its while loop, which then only cuts back: XLA:CPU ran the solver's Π and ∇Π 1.6–3.9×
slower inside a while loop's body than outside (twist n = 29: 0.058 against 0.016 s per
Newton step; ``jax.grad`` of ``je.energy``, the HVP and the element Hessians showed no
such penalty, so it is not a property of every loop). Smaller meshes keep the single
trial inside the loop: compiling Π and its gradient twice cost 0.6 s of the default
scene's 10 s cold command (1,080 tets, measured), more than the loop costs it."""


STALL = 0.5
"""The residual's round-off floor counts as reached once a full Newton step reduces the
residual by less than this factor (``‖g_{k+1}‖ ≥ STALL·‖g_k‖``): above the floor Newton
still converges and one more step improves the answer (measured on the default scene in
float32: stopping at the floor without this test let the trajectory drift 8e-4 from
float64; with it 8e-7)."""

NEAR_EPS = 1e4
"""The line search switches from Armijo on Π to a decrease of the residual when the
predicted decrease ``|gᵀd|`` is below ``max(1e-10, NEAR_EPS·eps)`` times Π's round-off
scale (:func:`energy_scale`): 1e-10 in float64 (as before), 1.2e-3 in float32, where
Π's round-off (≈ 1e-7 of that scale) makes Armijo a coin flip well before 1e-10."""


def near_tol(dtype) -> float:
    """The relative predicted decrease below which Π is too noisy for Armijo."""
    return max(1e-10, NEAR_EPS * float(jnp.finfo(dtype).eps))


FLOOR_FACTOR = 2.0
"""The residual's round-off floor is taken as ``FLOOR_FACTOR · eps · ‖r̄‖`` (see
:func:`residual_floor`)."""


def residual_floor(pot: Potential, system: NewtonSystem, x, fm):
    """Round-off floor of the free force residual at x [force].

    The positions are stored as absolute coordinates, each rounded to about ``eps·|x_j|``,
    and every nodal force is a sum of terms computed in floating point, so the residual
    cannot be resolved below about ``eps`` times the root-sum-square of the terms that
    enter it: ``r̄² = Σ_a [Σ_c Σ_j (K_c,aj x_j)² +
    f_ext,a² + (w m_a)² (x_a² + x̃_a²)]`` over free dofs (mass-damping likewise), with the
    element Hessians ``K_c`` of this Newton step (no stiffness term in matrix-free
    ``hessian="hvp"`` + ``CG(preconditioner="none")``, which builds none). Measured on a
    steel block (E = 210 GPa, linear, one exact Newton step): the residual stagnates at
    5.5e-5 N, this estimate (factor 1) is 1.6e-4 N; the worst-case absolute sum would be
    1.0e-3 N. In float32, at the float64 solution rounded to float32 (README example):
    residual 1.44 N = rounding of the positions alone 1.01 N (F from displacements does
    not remove that part) ⊕ float32 arithmetic 0.89 N; Newton without a floor stagnates at
    1.26–1.64 N; this estimate (factor 1) is 1.81 N (twist n = 10: 3.25e-6 vs 5.66e-6;
    default scene time step: 1.2 vs 2.3). Newton stops with SUCCESS once the residual is
    below ``FLOOR_FACTOR`` times this (``stats["residual_floor"]``) and a full step has
    stalled (:data:`STALL`): below it no Newton step makes measurable progress.
    """
    eps = jnp.finfo(x.dtype).eps
    sq = jnp.zeros_like(x)
    total = jnp.zeros((), x.dtype)
    if system.Ke is not None:
        mesh = pot.mesh
        xe2 = (x[mesh.cells].reshape(mesh.n_cells, -1)) ** 2  # (n_cells, m)

        def squares(Ke, xe2):  # v_i = Σ_j K_ij² x_j², one fused loop per column: the
            # einsum of Ke**2 stored the squares and ran a batched matvec, 4.6× the time
            v = Ke[:, :, 0] ** 2 * xe2[:, 0:1]  # (n_cells, m)
            for j in range(1, xe2.shape[1]):
                v = v + Ke[:, :, j] ** 2 * xe2[:, j : j + 1]
            return v

        # Σ over free dofs of the assembled v is Σ over cells of v masked by the cells'
        # free dofs, no assembly; v stored first (fused into its consumer, the node gathers
        # of an assembly or a reduction, it cost 0.067 / 0.16 s per Newton step at 146k
        # tets, against 0.012 s)
        v = _computed_once(squares, mesh, system.Ke, xe2)
        total = jnp.sum(v * fm[mesh.cells].reshape(mesh.n_cells, -1))
    if pot.f_ext is not None:
        sq = sq + pot.f_ext**2
    if pot.pressure is not None:  # the follower forces, like f_ext
        sq = sq + pot.pressure.gradient(x) ** 2
    md = pot_mod.mass_diagonal(pot)
    if md is not None:
        ref = pot.x_tilde if pot.x_tilde is not None else x
        sq = sq + (md**2)[:, None] * (x**2 + ref**2)
    return FLOOR_FACTOR * eps * jnp.sqrt(total + jnp.sum(sq * fm))


def status_of(s: Newton, rn, dn, ref, k, floor: jax.Array | float = 0.0):
    tol = jnp.maximum(jnp.maximum(s.atol, s.rtol * ref), floor)
    st = jnp.where(~jnp.isfinite(rn), Status.NONFINITE, RUNNING)
    st = jnp.where((st == RUNNING) & (rn <= tol) & (dn == 0), Status.SUCCESS, st)
    return jnp.where((st == RUNNING) & (k >= s.max_steps), Status.MAX_STEPS, st)
