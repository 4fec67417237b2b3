"""Newton's method on the total potential Π, under ``jit`` (``lax.while_loop``).

Each iteration:

1. Dirichlet data enter the step: the prescribed part ``Δ_D = x_D − x`` is moved with the
   step and the free part solves ``K_ff Δ_f = −(g_f + K_fD Δ_D)``. The first iterate from
   the rest shape is therefore the linear-elastic predictor, and a boundary motion too
   large for one step is applied partially by the line search (no inverted initial guess).
2. The linear system is solved inexactly (forcing term ``η = clip(‖g‖/‖g‖_ref, 1e-6, 0.1)``)
   by the :class:`Newton` object's linear solver (:mod:`~jaxelastic.solvers.linear`) on
   the exact Hessian (element Hessians or HVP), or on PSD-projected element Hessians
   (``hessian="projected"``) for indefinite configurations.
3. Backtracking line search treating non-finite Π as +∞ (an inverting step of a model that
   is undefined at J ≤ 0 is cut back until no element inverts): Armijo on Π far from the
   solution, decrease of the residual near it, where Π's round-off (~eps·Σ_c|x_cᵀK_c x_c|,
   far above eps·|Π| near rest because ψ cancels large terms) exceeds the predicted
   decrease (below ``max(1e-10, 1e4·eps)`` of that scale: :data:`NEAR_EPS`), or, there,
   a residual that stays below its round-off floor; steps that move Dirichlet dofs only
   need a finite Π.
4. Convergence: ``‖g_free‖ ≤ max(atol, rtol·‖g‖_ref)`` with all Dirichlet dofs in place,
   or the residual's round-off floor reached: ``‖g_free‖ ≤ floor`` (:func:`_residual_floor`:
   ``2·eps`` times the root-sum-square of the terms of the forces; reported as
   ``stats["residual_floor"]``) once a full step reduces the residual by less than half
   (:data:`STALL`; at once for a quadratic Π), or a full step below ``xtol`` times the
   body's size;
   where ``‖g‖_ref`` is the largest free residual seen, ‖f_ext‖, or the largest
   right-hand side ``‖g_f + K_fD Δ_D‖`` (the force induced by a Dirichlet motion).
5. With a contact term and ``kappa_max_factor > 1`` (opt-in), IPC's adaptive barrier
   stiffness: κ is doubled (up to ``kappa_max_factor`` × its starting value) while the
   smallest gap is below 1e-2·d̂ and still shrinking between iterates
   (:func:`~jaxelastic.contact.barrier.kappa_update`); the solve then continues on the
   stiffer potential, reported as ``stats["kappa"]`` and used by the implicit derivatives.
   Contact forces of such a solution need that κ: :func:`contact_potential`.

Users call :func:`jaxelastic.solve`; :meth:`Newton.minimize` is the non-differentiated loop
it runs.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ..contact.log_barrier import kappa_update
from ..loads import Dirichlet
from ..mechanics import potential as pot_mod
from ..mechanics.fusion import always, computed
from ..mechanics.kernels import hvp
from ..mechanics.kinematics import deformation_gradients, det
from ..mechanics.potential import Potential
from ..mechanics.psd import project_element_psd, project_psd
from .host import release_free_memory
from .linear import NewtonSystem, assemble_upper
from .results import RUNNING, Solution, Status

__all__ = ["Newton", "HESSIANS", "host_minimize", "contact_potential"]

HESSIANS = ("element", "hvp", "projected")


XTOL_MAX = 1e-3
"""The largest :attr:`Newton.xtol` accepted: a step-size criterion above it would declare
convergence while nodes still move by more than 0.1 % of the body's diagonal."""


def _real(v, name: str) -> float:
    """``v`` as a finite float, or a ValueError naming the field."""
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {v!r}") from None
    if not np.isfinite(f):
        raise ValueError(f"{name} must be finite, got {v!r}")
    return f


@dataclasses.dataclass(frozen=True)
class Newton:
    """Newton's method with an inversion-aware backtracking line search (frozen, hashable:
    a static argument under jit; changing a field recompiles).

    Attributes:
        rtol: relative tolerance on the free-dof force residual.
        atol: absolute tolerance [force].
        max_steps: maximum Newton iterations.
        xtol: also converged when a full Newton step moves no node by more than
            ``xtol × (rest bounding-box diagonal)`` with the Dirichlet dofs in place: the
            residual can stagnate at its round-off floor (e.g. ~eps·m/h²·|x| in dynamics)
            below ``rtol·‖g‖_ref`` for a body already at rest.
        hessian: ``"element"`` (exact element Hessians computed once per Newton step, then
            cheap matvecs), ``"hvp"`` (exact, matrix-free forward-over-reverse) or
            ``"projected"`` (PSD-projected element Hessians: always a descent direction,
            but only linear convergence where the true Hessian is indefinite).
        linear: linear solver: ``"auto"``, ``"cg"``, ``"direct"``, ``"amg"`` or a
            :class:`~jaxelastic.solvers.linear.CG` / ``Direct`` / ``AMG`` object
            (resolved by :func:`~jaxelastic.solvers.linear.bind_linear`).
        ls_max: maximum halvings in the line search.
        armijo: sufficient-decrease constant.
        require_positive_J: also reject trial steps where any element has J ≤ 0 (for user
            materials that return finite garbage there); the built-in neo-Hookean returns
            +inf, which the line search rejects anyway.
        kappa_max_factor: with a contact term, the in-solve κ adaptation may raise the
            barrier stiffness to this multiple of ``pot.contact.kappa``: 1 (default) is
            off, IPC uses 100 (:data:`~jaxelastic.contact.barrier.KAPPA_MAX_FACTOR`).
            Off by default because the adapted κ lives only in the solution
            (``stats["kappa"]``): forces computed from ``pot.contact`` would use the old
            one (use :func:`contact_potential`), and in dynamics every step adapts afresh
            from ``pot.contact.kappa``.
    """

    rtol: float = 1e-8
    atol: float = 0.0
    max_steps: int = 50
    xtol: float = 1e-12
    hessian: str = "element"
    linear: Any = "auto"
    ls_max: int = 40
    armijo: float = 1e-4
    require_positive_J: bool = False
    kappa_max_factor: float = 1.0

    def __post_init__(self):
        if self.hessian not in HESSIANS:
            raise ValueError(f"hessian must be one of {HESSIANS}, got {self.hessian!r}")
        for name in ("max_steps", "ls_max"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
        if not isinstance(self.require_positive_J, (bool, np.bool_)):
            raise TypeError(
                f"require_positive_J must be True or False, got {self.require_positive_J!r}"
            )
        if not 0.0 <= _real(self.armijo, "armijo") < 1.0:
            raise ValueError(
                f"armijo (the line search's sufficient-decrease constant) must be in [0, 1), "
                f"got {self.armijo!r}; 1e-4 is usual"
            )
        if not 0.0 <= _real(self.xtol, "xtol") <= XTOL_MAX:
            raise ValueError(
                f"xtol must be in [0, {XTOL_MAX:g}], got {self.xtol!r}: a Newton step that "
                "moves no node by more than xtol x the body's diagonal counts as converged, "
                "so a larger xtol reports SUCCESS for an unconverged solve (the default "
                "1e-12 only catches a residual stuck at its round-off floor)"
            )
        for name in ("rtol", "atol", "kappa_max_factor"):
            _real(getattr(self, name), name)
        if not self.kappa_max_factor >= 1:
            raise ValueError(f"kappa_max_factor must be >= 1, got {self.kappa_max_factor!r}")
        if not (self.rtol >= 0 and self.atol >= 0) or (self.rtol == 0 and self.atol == 0):
            raise ValueError(
                f"need rtol >= 0 and atol >= 0, not both 0; got rtol={self.rtol!r}, "
                f"atol={self.atol!r}"
            )

    def replace(self, **kw) -> Newton:
        return dataclasses.replace(self, **kw)

    def minimize(self, pot: Potential, bc: Dirichlet, x0: jax.Array) -> Solution:
        """Minimise Π(x) subject to ``x[bc.mask] = bc.values[bc.mask]`` (pure, jit-able,
        not differentiated: :func:`jaxelastic.solve` adds the implicit derivatives).
        ``self.linear`` must be bound (:func:`~jaxelastic.solvers.linear.bind_linear`)."""
        if isinstance(self.linear, str) or not self.linear.is_bound:
            raise ValueError("Newton.minimize needs a bound linear solver (use je.solve)")
        return _run(self, pot, bc, x0)


def _norm(a):
    return jnp.sqrt(jnp.sum(a * a))


def _min_J(pot: Potential, x):
    F = deformation_gradients(x, pot.mesh)
    return jnp.min(jax.vmap(jax.vmap(det))(F))


def _value_and_grad(s: Newton, pot: Potential, x):
    v = pot_mod.value(pot, x)
    if s.require_positive_J:
        v = jnp.where(_min_J(pot, x) > 0, v, jnp.inf)
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


def _energy_scale(pot: Potential, x, Ke):
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
    return xKx


def _system(s: Newton, pot: Potential, x, free, Ke=None, pair_h=None) -> NewtonSystem:
    """The Dirichlet-masked Newton operator at x (and the element Hessians it needs;
    ``Ke``: those already computed at x; ``pair_h``: the self-contact pair Hessians at x,
    :meth:`~jaxelastic.contact.Contact.pair_hessians`, if already computed)."""
    fm = free.astype(x.dtype)
    if pair_h is None and pot.contact is not None:  # once, for Ke's blocks and the coupling
        pair_h = pot.contact.pair_hessians(x)
    need_Ke = s.hessian != "hvp" or s.linear.needs_element_hessians
    if Ke is None and need_Ke:
        Ke = pot_mod.elastic_element_hessians(
            pot, x, project=s.hessian == "projected", pair_hessians=pair_h
        )

    def masked(H):
        def A(v):
            return fm * H(fm * v) + (1.0 - fm) * v

        return A

    # self-contact pairs couple nodes of different elements: that part of the Hessian is
    # an operator added to the element one (the node-diagonal part is inside Ke)
    cpl = None if pot.contact is None else pot.contact.coupling(x, pair_hessians=pair_h)

    def KV(K, v) -> jax.Array:
        Kv = pot_mod.element_hessian_vp(pot, K, v)
        return Kv if cpl is None else Kv + cpl(v)

    def operator(K):
        return masked(lambda v: KV(K, v))

    if s.hessian == "hvp":

        def H(v):
            return pot_mod.hessian_vp(pot, x, v)
    else:
        Ke_el = Ke
        assert Ke_el is not None  # need_Ke holds for every hessian but "hvp"

        def H(v):
            return KV(Ke_el, v)

    assembled = _operator_is_assembled(s, pot)
    assert not assembled or cpl is None
    return NewtonSystem(
        pot=pot, x=x, free=free, Ke=Ke, H=H, A=masked(H), operator=operator, assembled=assembled
    )


def _operator_is_assembled(s: Newton, pot: Potential) -> bool:
    """Whether the Newton operator is the assembled element matrix
    (``NewtonSystem.assembled``): element Hessians (not ``hessian="hvp"``) and no
    self-contact coupling. Decided by structure only, so also outside a trace."""
    no_coupling = pot.contact is None or getattr(pot.contact, "self_contact", None) is None
    return s.hessian != "hvp" and no_coupling


def is_quadratic(pot: Potential) -> bool:
    """Whether Π is quadratic in x, so one exact Newton step solves it (static).

    True when ψ is marked ``psi.is_quadratic = True`` (the built-in ``linear`` material;
    mark your own quadratic ψ likewise) and the kinematics are linear in x (not F-bar,
    whose F̄ = (J̄/J)^{1/d} F is nonlinear). Inertia, damping and external forces keep Π
    quadratic; a contact term (the log barrier) does not.
    """
    quadratic_psi = getattr(pot.psi, "is_quadratic", False) is True
    return quadratic_psi and pot.mesh.formulation != "fbar" and pot.contact is None


def _newton_rhs(s: Newton, system: NewtonSystem, g, dD, ref):
    """``(rhs, tol, ‖rhs‖)`` of the Newton step's linear solve ``K_ff Δ_f = rhs``."""
    fm = system.free.astype(g.dtype)
    tiny = jnp.finfo(g.dtype).tiny
    gf = g * fm
    rn, dn = _norm(gf), _norm(dD)
    # K_fD Δ_D: the force a Dirichlet motion induces on the free dofs
    KdD = lax.cond(dn > 0, lambda: fm * system.H(dD), lambda: jnp.zeros_like(g))
    rhs = -gf - KdD
    bn = _norm(rhs)
    scale = jnp.maximum(jnp.maximum(ref, rn), bn)
    # inexact Newton (forcing η·‖rhs‖) only where the model is nonlinear: on a quadratic
    # potential one accurate solve is the answer, and a loose one only costs Newton steps
    eta = jnp.clip(rn / jnp.maximum(scale, tiny), 1e-6, 0.1)
    tight = 0.1 * s.rtol * scale
    tol = tight if is_quadratic(system.pot) else jnp.maximum(eta * bn, tight)
    return rhs, tol, bn


def _descent(system: NewtonSystem, g, dD, res: Solution):
    """Newton direction (free part + Dirichlet motion) from the linear solve's ``res``."""
    fm = system.free.astype(g.dtype)
    gf = g * fm
    d_free = res.x * fm
    # not a descent direction (only possible without projection): steepest descent
    bad = (_norm(dD) == 0) & ~(jnp.sum(g * d_free) < 0)
    d_free = jnp.where(bad, -gf, d_free)
    return d_free + dD


def _linear_system(s: Newton, pot, bc: Dirichlet, c: dict, Ke=None, pair_h=None):
    """``(system, Δ_D, rhs, tol, ‖rhs‖)`` of the Newton step from the carry ``c``."""
    x = c["x"]
    system = _system(s, pot, x, ~bc.mask, Ke, pair_h)
    dD = jnp.where(bc.mask, bc.values - x, 0.0)
    rhs, tol, bn = _newton_rhs(s, system, c["g"], dD, c["ref"])
    return system, dD, rhs, tol, bn


def _line_search(s: Newton, pot, bc: Dirichlet, x, g, e0, step, near, floor):
    """Backtracking from α = 1 (with contact: from the CCD bound ``min(1, 0.8·τ*)``,
    :meth:`~jaxelastic.contact.Contact.ccd_step`): ``(α, x_t, Π_t, g_t, accepted, halvings)``."""
    mask, xD = bc.mask, bc.values
    fm = (~mask).astype(x.dtype)
    rn = _norm(g * fm)
    dn = _norm(jnp.where(mask, xD - x, 0.0))
    slope = jnp.sum(g * step)

    def trial(alpha):
        xt = x + alpha * step
        xt = jnp.where(mask & (alpha == 1.0), xD, xt)
        et, gt = _value_and_grad(s, pot, xt)
        armijo = et <= e0 + s.armijo * alpha * slope
        # near the solution Π's round-off hides the decrease; at the residual's round-off
        # floor its norm is noise, so a trial that stays below the floor is accepted too
        residual_ok = near & (dn == 0) & (_norm(gt * fm) < jnp.maximum(rn, floor))
        accept = jnp.isfinite(et) & ((dn > 0) | armijo | residual_ok)
        return xt, et, gt, accept

    def cond(c):
        return (~c[4]) & (c[5] < s.ls_max)

    def body(c):
        alpha = 0.5 * c[0]
        return (alpha, *trial(alpha), c[5] + 1)

    alpha0 = jnp.asarray(1.0, x.dtype)
    if pot.contact is not None:  # every trial stays intersection-free
        alpha0 = alpha0 * jnp.minimum(1.0, pot.contact.ccd_step(x, step)).astype(x.dtype)
    if pot.mesh.n_cells >= STRAIGHT_TRIAL_MIN_CELLS:  # the first trial before the loop
        start = (alpha0, *trial(alpha0), jnp.asarray(0, jnp.int32))
    else:  # the loop's first pass tries alpha0 (halvings 0): Π compiled once
        inf = jnp.asarray(jnp.inf, x.dtype)
        start = (2.0 * alpha0, x, inf, g, jnp.asarray(False), jnp.asarray(-1, jnp.int32))
    return lax.while_loop(cond, body, start)


STRAIGHT_TRIAL_MIN_CELLS = 50_000
"""Meshes of at least this many cells run the line search's first trial (α = 1) outside
its while loop, which then only cuts back: XLA:CPU ran the solver's Π and ∇Π 1.6–3.9×
slower inside a while loop's body than outside (twist n = 29: 0.058 against 0.016 s per
Newton step; ``jax.grad`` of ``je.energy``, the HVP and the element Hessians showed no
such penalty, so it is not a property of every loop). Smaller meshes keep the single
trial inside the loop: compiling Π and its gradient twice cost 0.6 s of the default
scene's 10 s cold command (1,080 tets, measured), more than the loop costs it."""


def _with_kappa(pot: Potential, c: dict) -> Potential:
    """``pot`` with the contact stiffness of the carry (unchanged without contact)."""
    if "kappa" not in c:
        return pot
    return pot.replace(contact=pot.contact.replace(kappa=c["kappa"]))


def contact_potential(pot: Potential, res: Solution) -> Potential:
    """The potential a solve ``res`` of ``pot`` converged on: ``pot`` with its contact κ
    scaled to ``res.stats["kappa"]`` (the in-solve adaptation; the ratio is a constant,
    so derivatives with respect to κ pass through). Unchanged without contact."""
    if pot.contact is None or "kappa" not in res.stats:
        return pot
    k = pot.contact.kappa
    ratio = lax.stop_gradient(res.stats["kappa"] / k)
    return pot.replace(contact=pot.contact.replace(kappa=k * ratio))


def _adapt_kappa(s: Newton, pot, c: dict) -> dict:
    """The carry ``c`` after IPC's κ update (:func:`~jaxelastic.contact.barrier.kappa_update`):
    a new κ re-evaluates Π and its gradient at the accepted iterate and keeps the solve
    running (a status reached with the old κ does not hold for the new one)."""
    if "kappa" not in c:
        return c
    contact = pot.contact
    gap = contact.min_distance(c["x"])
    kappa = kappa_update(c["kappa"], c["kappa_max"], gap, c["gap"], contact.dhat)
    changed = kappa != c["kappa"]

    def refresh():
        e, g = _value_and_grad(s, pot.replace(contact=contact.replace(kappa=kappa)), c["x"])
        return e, g

    energy, g = lax.cond(changed, refresh, lambda: (c["energy"], c["g"]))
    st = c["status"]
    fine = (st == RUNNING) | (st == Status.SUCCESS)
    more = changed & fine & (c["k"] < s.max_steps)
    st = jnp.where(more, RUNNING, st).astype(jnp.int32)
    return dict(c, kappa=kappa, gap=gap, energy=energy, g=g, status=st)


def _iteration(s: Newton, pot, bc: Dirichlet, c: dict, length) -> dict:
    """One Newton iteration on the loop carry ``c``."""
    pot = _with_kappa(pot, c)
    system, dD, rhs, tol, bn = _linear_system(s, pot, bc, c)
    lin = s.linear.newton_step(system, rhs, tol)
    return _iteration_end(s, pot, bc, c, length, system, dD, bn, lin)


def _iteration_end(s: Newton, pot, bc: Dirichlet, c: dict, length, system, dD, bn, lin) -> dict:
    """The rest of a Newton iteration once the linear solve ``lin`` is done: direction,
    line search, new carry and status."""
    x, g, k = c["x"], c["g"], c["k"]
    mask, xD = bc.mask, bc.values
    fm = (~mask).astype(x.dtype)
    step = _descent(system, g, dD, lin)
    escale = jnp.maximum(jnp.abs(c["energy"]), _energy_scale(pot, x, system.Ke))
    near = jnp.abs(jnp.sum(g * step)) <= _near_tol(x.dtype) * jnp.maximum(
        escale, jnp.finfo(x.dtype).tiny
    )
    floor = _residual_floor(pot, system, x, fm)
    alpha, xt, et, gt, acc, cuts = _line_search(s, pot, bc, x, g, c["energy"], step, near, floor)
    x_new = jnp.where(acc, xt, x)
    g_new = jnp.where(acc, gt, g)
    rn = _norm(g_new * fm)
    dn = _norm(jnp.where(mask, xD - x_new, 0.0))
    # bn = ‖g_f + K_fD Δ_D‖ is the force a Dirichlet motion induces: the reference of a
    # purely displacement-driven solve (whose free residual is 0 at the rest shape)
    ref = jnp.maximum(jnp.maximum(c["ref"], rn), bn)
    # the floor only counts once a full step no longer reduces the residual (or the
    # potential is quadratic, where one exact step is the answer)
    stalled = ((alpha == 1.0) & (rn >= STALL * c["hist"][k])) | is_quadratic(pot)
    st = _status(s, rn, dn, ref, k + 1, jnp.where(stalled, floor, 0.0))
    tiny_step = acc & (alpha == 1.0) & (dn == 0) & (jnp.max(jnp.abs(step)) <= s.xtol * length)
    st = jnp.where((st == RUNNING) & tiny_step & jnp.isfinite(rn), Status.SUCCESS, st)
    st = jnp.where(acc, st, Status.LINE_SEARCH_FAILED)
    its = lin.stats["iterations"].astype(jnp.int32)
    neg = lin.status == Status.NEGATIVE_CURVATURE
    new = dict(
        c,
        x=x_new,
        g=g_new,
        energy=jnp.where(acc, et, c["energy"]),
        k=k + 1,
        status=st.astype(jnp.int32),
        ref=ref,
        hist=c["hist"].at[k + 1].set(rn),
        lin_hist=c["lin_hist"].at[k].set(its),
        alpha_hist=c["alpha_hist"].at[k].set(jnp.where(acc, alpha, jnp.nan)),
        cuts=c["cuts"] + cuts.astype(jnp.int32),
        neg=c["neg"] + neg.astype(jnp.int32),
        proj=c["proj"] + lin.stats["projected"].astype(jnp.int32),
        floor=floor,
    )
    return _adapt_kappa(s, pot, new)


STALL = 0.5
"""The residual's round-off floor counts as reached once a full Newton step reduces the
residual by less than this factor (``‖g_{k+1}‖ ≥ STALL·‖g_k‖``): above the floor Newton
still converges and one more step improves the answer (measured on the default scene in
float32: stopping at the floor without this test let the trajectory drift 8e-4 from
float64; with it 8e-7)."""

NEAR_EPS = 1e4
"""The line search switches from Armijo on Π to a decrease of the residual when the
predicted decrease ``|gᵀd|`` is below ``max(1e-10, NEAR_EPS·eps)`` times Π's round-off
scale (:func:`_energy_scale`): 1e-10 in float64 (as before), 1.2e-3 in float32, where
Π's round-off (≈ 1e-7 of that scale) makes Armijo a coin flip well before 1e-10."""


def _near_tol(dtype) -> float:
    """The relative predicted decrease below which Π is too noisy for Armijo."""
    return max(1e-10, NEAR_EPS * float(jnp.finfo(dtype).eps))


FLOOR_FACTOR = 2.0
"""The residual's round-off floor is taken as ``FLOOR_FACTOR · eps · ‖r̄‖`` (see
:func:`_residual_floor`)."""


def _residual_floor(pot: Potential, system: NewtonSystem, x, fm):
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
    md = pot_mod.mass_diagonal(pot)
    if md is not None:
        ref = pot.x_tilde if pot.x_tilde is not None else x
        sq = sq + (md**2)[:, None] * (x**2 + ref**2)
    return FLOOR_FACTOR * eps * jnp.sqrt(total + jnp.sum(sq * fm))


def _status(s: Newton, rn, dn, ref, k, floor: jax.Array | float = 0.0):
    tol = jnp.maximum(jnp.maximum(s.atol, s.rtol * ref), floor)
    st = jnp.where(~jnp.isfinite(rn), Status.NONFINITE, RUNNING)
    st = jnp.where((st == RUNNING) & (rn <= tol) & (dn == 0), Status.SUCCESS, st)
    return jnp.where((st == RUNNING) & (k >= s.max_steps), Status.MAX_STEPS, st)


def _initial_carry(s: Newton, pot, bc: Dirichlet, x0) -> dict:
    mask, dtype = bc.mask, x0.dtype
    fm = (~mask).astype(dtype)
    e0, g0 = _value_and_grad(s, pot, x0)
    rn0 = _norm(g0 * fm)
    dn0 = _norm(jnp.where(mask, bc.values - x0, 0.0))
    ref0 = _norm(pot.f_ext * fm) if pot.f_ext is not None else jnp.zeros((), dtype)
    ref = jnp.maximum(ref0, rn0)
    st0 = _status(s, rn0, dn0, ref, 0)
    inverted = jnp.where(_min_J(pot, x0) <= 0, Status.INVERTED, Status.NONFINITE)
    st0 = jnp.where(jnp.isfinite(e0), st0, inverted)
    zero = jnp.asarray(0, jnp.int32)
    extra = {}
    if pot.contact is not None and s.kappa_max_factor > 1:  # in-solve κ adaptation (IPC)
        k0 = jnp.asarray(pot.contact.kappa, dtype)
        extra = dict(
            kappa=k0,
            kappa_max=k0 * s.kappa_max_factor,
            gap=pot.contact.min_distance(x0).astype(dtype),
        )
    return dict(
        **extra,
        x=x0,
        g=g0,
        energy=e0,
        k=zero,
        status=st0.astype(jnp.int32),
        ref=ref,
        hist=jnp.full((s.max_steps + 1,), jnp.nan, dtype).at[0].set(rn0),
        lin_hist=jnp.zeros((s.max_steps,), jnp.int32),
        alpha_hist=jnp.full((s.max_steps,), jnp.nan, dtype),
        cuts=zero,
        neg=zero,
        proj=zero,
        floor=jnp.zeros((), dtype),
    )


def _length(pot: Potential):
    """Diagonal of the rest bounding box [length] (the scale of ``xtol``)."""
    X = pot.mesh.points
    return jnp.sqrt(jnp.sum((jnp.max(X, axis=0) - jnp.min(X, axis=0)) ** 2))


def _run(s: Newton, pot: Potential, bc: Dirichlet, x0) -> Solution:
    length = _length(pot)
    c = lax.while_loop(
        lambda c: c["status"] == RUNNING,
        lambda c: _iteration(s, pot, bc, c, length),
        _initial_carry(s, pot, bc, x0),
    )
    return _solution(c)


def _solution(c: dict) -> Solution:
    """The :class:`Solution` of a finished loop carry."""
    stats = dict(
        steps=c["k"],
        linear_iterations=jnp.sum(c["lin_hist"]),
        residual=c["hist"][c["k"]],
        energy=c["energy"],
        residual_history=c["hist"],
        linear_history=c["lin_hist"],
        step_history=c["alpha_hist"],
        line_search_cutbacks=c["cuts"],
        negative_curvature=c["neg"],
        projected=c["proj"],
        residual_floor=c["floor"],
        wall_time=jnp.asarray(jnp.nan, c["x"].dtype),
    )
    if "kappa" in c:
        stats["kappa"] = c["kappa"]
    return Solution(x=c["x"], status=c["status"], stats=stats)


# ----------------------------------------------------------------------------------------
# the same loop driven from the host (host linear solvers outside jit)
# ----------------------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnames="s")
def _host_start(s: Newton, pot: Potential, bc: Dirichlet, x0):
    return _initial_carry(s, pot, bc, x0), _length(pot)


@functools.partial(jax.jit, static_argnames="s")
def _host_system(s: Newton, pot: Potential, bc: Dirichlet, c: dict):
    # self-contact pair Hessians: computed (and compiled) here only, handed to the others
    ph = None if pot.contact is None else pot.contact.pair_hessians(c["x"])
    system, _, rhs, tol, bn = _linear_system(s, pot, bc, c, pair_h=ph)
    return system.Ke, rhs, tol, bn, ph


@functools.partial(jax.jit, static_argnames="s")
def _host_linear(s: Newton, pot: Potential, bc: Dirichlet, x, Ke, rhs, tol, ph) -> Solution:
    return s.linear.newton_step(_system(s, pot, x, ~bc.mask, Ke, ph), rhs, tol)


@functools.partial(jax.jit, static_argnames="s")
def _host_update(s: Newton, pot: Potential, bc: Dirichlet, c: dict, length, Ke, bn, lin, ph):
    x = c["x"]
    # no new element Hessians, nor rhs; the operator is not applied here (``ph``: the pair
    # Hessians of the buffer before the refresh, only so that none are traced again)
    system = _system(s, pot, x, ~bc.mask, Ke, ph)
    dD = jnp.where(bc.mask, bc.values - x, 0.0)
    return _iteration_end(s, pot, bc, c, length, system, dD, bn, lin)


_host_solution = jax.jit(_solution)


@functools.partial(jax.jit, static_argnames="nnz_upper")
def _host_upper(pot: Potential, Ke, element_map, nnz_upper: int):
    """The assembled upper data of Ke (:func:`~jaxelastic.solvers.linear.assemble_upper`,
    the map an argument: no callback, so the persistent cache keeps it) and the mass
    diagonal ``(n_nodes,)`` (zeros for none)."""
    md = pot_mod.mass_diagonal(pot)
    if md is None:
        md = jnp.zeros(pot.mesh.points.shape[:1], Ke.dtype)
    return assemble_upper(Ke, element_map, nnz_upper), md


@functools.partial(jax.jit, static_argnames="size")
def _not_psd(Ke, start, size: int):
    """``(size,)`` bool: the element Hessians of cells ``start … start + size`` that are not
    positive semidefinite to :data:`PSD_SHIFT` (a Cholesky factorisation of
    ``K + PSD_SHIFT·max|diag K|·I`` fails: NaN)."""
    K = lax.dynamic_slice_in_dim(Ke, start, size)
    d = jnp.max(jnp.abs(jnp.diagonal(K, axis1=1, axis2=2)), axis=1)
    shift = PSD_SHIFT * jnp.where(d > 0, d, 1.0)
    eye = jnp.eye(K.shape[-1], dtype=K.dtype)[None]
    L = jnp.linalg.cholesky(K + shift[:, None, None] * eye)
    return ~jnp.all(jnp.isfinite(L), axis=(1, 2))


@functools.partial(jax.jit, static_argnames=("nnz_upper", "dim"), donate_argnums=0)
def _add_projection(acc, Ke, element_map, idx, valid, nnz_upper: int, dim: int):
    """``acc`` plus the upper data of ``project(K) − K`` over the cells ``idx``
    (``valid``: 0 on the padding); ``dim``: :func:`~jaxelastic.potential.projection_dim`
    (:func:`~jaxelastic.energy.project_element_psd`; 0: ``project_psd``)."""
    u = element_map.shape[0] // Ke.shape[0]
    K = Ke[idx]
    P = project_element_psd(K, dim) if dim else project_psd(K)
    D = (P - K) * valid[:, None, None]
    return acc + assemble_upper(D, element_map.reshape(-1, u)[idx].reshape(-1), nnz_upper)


PSD_SHIFT = 1e-12
"""An element Hessian whose smallest eigenvalue is above ``−PSD_SHIFT·max|diag K|``
counts as positive semidefinite in the host Newton loop's projected retry and is not
projected (its projection would change it by less than that)."""

PROJECT_BLOCK_CELLS = 65536
"""Cells per compiled call of the PSD test in the host Newton loop's retry, from a Python
loop: a ``lax`` loop around the batched LAPACK eigensolver deadlocked XLA:CPU at 511k tets
(jaxlib 0.10), and no copy of all cells' Hessians is made."""


PROJECT_ALL_FRACTION = 0.9
"""When more than this fraction of the first :data:`PROJECT_BLOCK_CELLS` cells fail the PSD
test, the host retry projects every cell without testing the rest (twist n = 44: 507k of
511k tets fail; the tests took 0.7 s of the 5.7 s retry)."""


def _projected_upper(data, Ke, element_map, nnz_upper: int, dim: int):
    """The upper data of the PSD-projected element Hessians from ``data``, that of the
    unprojected ones: only the cells whose Hessian is not positive semidefinite
    (:func:`_not_psd`) are projected and their change added. ``dim``: the element
    Hessians are elasticity's alone, projected through the 9×9 matrices without the
    translations (:func:`~jaxelastic.energy.project_element_psd`; twist n = 44, where 507k
    of 511k tets fail the test: 8.0 s with 12×12 ``eigh``); 0: ``project_psd``."""
    c = Ke.shape[0]
    tests = []
    for start in range(0, c, PROJECT_BLOCK_CELLS):
        tests.append(np.asarray(_not_psd(Ke, start, min(PROJECT_BLOCK_CELLS, c - start))))
        if start == 0 and c > PROJECT_BLOCK_CELLS and tests[0].mean() > PROJECT_ALL_FRACTION:
            tests = [np.ones(c, bool)]  # most fail: project all, the tests cost more
            break
    idx = np.flatnonzero(np.concatenate(tests)).astype(np.int32)
    for lo in range(0, idx.size, PROJECT_BLOCK_CELLS):
        part = idx[lo : lo + PROJECT_BLOCK_CELLS]
        size = max(256, 1 << int(np.ceil(np.log2(part.size))))  # few compiled sizes
        valid = np.zeros(size, Ke.dtype)
        valid[: part.size] = 1.0
        padded = np.zeros(size, np.int32)
        padded[: part.size] = part
        data = _add_projection(data, Ke, element_map, padded, valid, nnz_upper, dim)
    return data


def _assembled_on_host(s: Newton, pot: Potential) -> bool:
    """Whether a host Newton step can make its first linear solve outside jit
    (:meth:`~jaxelastic.solvers.linear.Direct.assembled_step`): a host back end and an
    operator that is the assembled element matrix (``NewtonSystem.assembled``)."""
    return hasattr(s.linear, "assembled_step") and _operator_is_assembled(s, pot)


def _host_assembled_step(s: Newton, pot: Potential, bc: Dirichlet, Ke, rhs, tol) -> Solution:
    """The linear solve of a host Newton step without an XLA callback: the upper data
    assembled in XLA, the factorisation (and AMG's CG) called from Python; if the matrix is
    not positive definite (or the CG meets negative curvature, or the step is not finite),
    the same with the PSD-projected element Hessians, as
    :meth:`~jaxelastic.solvers.linear.Direct.newton_step` does."""
    host = s.linear.backend
    nnz = host.nnz_upper
    data, md = _host_upper(pot, Ke, host.element_map, nnz)
    dx, its, st = s.linear.assembled_step(data, md, rhs, tol)
    bad = _bad_step(dx, st)
    if bad:
        dim = pot_mod.projection_dim(pot)
        data = _projected_upper(data, Ke, host.element_map, nnz, dim)
        dx, its2, st = s.linear.assembled_step(data, md, rhs, tol)
        its += its2
    if st == Status.NOT_POSITIVE_DEFINITE:
        st = int(Status.SUCCESS)  # (as newton_step: a projected matrix that is singular)
    free = np.asarray(~bc.mask)
    stats = dict(
        iterations=jnp.asarray(its, jnp.int32),
        residual=jnp.zeros((), rhs.dtype),
        projected=jnp.asarray(bad),
    )
    return Solution(x=jnp.asarray(dx * free, rhs.dtype), status=jnp.int32(st), stats=stats)


def _bad_step(dx, st) -> bool:
    """Whether a host linear solve calls for the projected retry."""
    bad_status = st in (Status.NOT_POSITIVE_DEFINITE, Status.NEGATIVE_CURVATURE)
    return bad_status or not bool(np.all(np.isfinite(dx)))


def host_minimize(s: Newton, pot: Potential, bc: Dirichlet, x0) -> Solution:
    """:meth:`Newton.minimize` with the Newton loop in Python (same iterations, same
    result), for concrete inputs outside jit.

    Each iteration runs three compiled pieces: the element Hessians and right-hand side,
    the linear solve and the line search + status update. JAX never writes an executable
    with a host callback to the persistent compilation cache, so with the loop under
    ``lax.while_loop`` (:meth:`Newton.minimize`) a solve with ``Direct``/``AMG`` was
    recompiled by every process. Where the Newton operator is the assembled matrix
    (:func:`_assembled_on_host`) the linear solve is called from Python on data assembled
    by a compiled piece without callbacks (:func:`_host_assembled_step`), so every piece
    is cached; otherwise (self-contact coupling, ``hessian="hvp"``) the linear-solve
    piece (``s.linear.newton_step``) holds the callbacks and is compiled in every
    process. Used by :func:`jaxelastic.solve` for host linear solvers outside jit.

    Args: as :meth:`Newton.minimize` (``x0`` ``(n_nodes, dim)``); not traceable.
    """
    if isinstance(s.linear, str) or not s.linear.is_bound:
        raise ValueError("host_minimize needs a bound linear solver (use je.solve)")
    c, length = _host_start(s, pot, bc, x0)
    outside = _assembled_on_host(s, pot)
    while int(c["status"]) == RUNNING:
        p = _with_kappa(pot, c)  # the adapted contact stiffness, if any
        Ke, rhs, tol, bn, ph = _host_system(s, p, bc, c)
        if outside:
            lin = _host_assembled_step(s, p, bc, Ke, rhs, tol)
        else:
            lin = _host_linear(s, p, bc, c["x"], Ke, rhs, tol, ph)
        if pot.contact is not None:  # self-contact: broad phase over the coming step
            step = jnp.where(bc.mask, bc.values - c["x"], lin.x)
            pot = pot.replace(contact=pot.contact.refreshed(c["x"], step))
            p = _with_kappa(pot, c)
        c = _host_update(s, p, bc, c, length, Ke, bn, lin, ph)
        # drop this step's element Hessians (and pair Hessians, linear result) before the
        # next _host_system makes new ones: otherwise two (n_cells, m, m) arrays are live
        # at its peak (168 MB each at 146k tets)
        big = Ke is not None and Ke.nbytes >= TRIM_BYTES
        del Ke, lin, ph
        if big:
            release_free_memory()  # the freed host heap back to the OS (solvers/heap.py)
    return _host_solution(c)


TRIM_BYTES = 32 << 20
""":func:`host_minimize` returns the freed heap to the OS after a Newton step whose element
Hessians took at least this many bytes (glibc keeps freed blocks below 32 MB in its
arenas). Smaller problems skip it: on the default scene (1,080 tets, 365 Newton steps)
trimming every step cost 0.5 s of a 3.2 s run."""
