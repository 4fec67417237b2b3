"""The linear system of a Newton step or of an implicit-derivative solve.

:class:`NewtonSystem` bundles the Hessian operator at one iterate, its Dirichlet-masked
form and the element Hessians it was built from; :func:`newton_system` builds it for a
Newton step and :func:`exact_system` for the adjoint/tangent solves at a solution (exact
contact Hessians, stiffness damping through the HVP).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from ...mechanics import potential as pot_mod
from ...mechanics.potential import Potential

__all__ = [
    "NewtonSystem",
    "newton_system",
    "exact_system",
    "operator_is_assembled",
    "is_nonsymmetric",
    "mass_or_zeros",
]


class NewtonSystem(NamedTuple):
    """The linear system of one Newton step (built inside the trace; not a user type).

    Attributes:
        pot: the potential; x: ``(n_nodes, dim)`` current positions.
        free: ``(n_nodes, dim)`` bool, the free dofs.
        Ke: ``(n_cells, k·d, k·d)`` elastic element Hessians at x (exact or projected, as
            Newton's ``hessian`` setting asks), or None when nothing needs them.
        H: the Hessian operator ``v ↦ (∂²Π/∂x²) v`` (unmasked).
        A: the Dirichlet-masked operator ``v ↦ P_f H P_f v + P_D v``.
        operator: ``Ke ↦ A`` built from given element Hessians (for the projected retry).
        assembled: ``A`` (and ``operator(K)``) is exactly the assembled matrix of the
            element Hessians (plus the mass diagonal, Dirichlet rows and columns replaced by
            identity): no matrix-free Hessian, no self-contact coupling. Host back ends
            may then run the whole Krylov loop on the host.
        symmetric: ``H`` is symmetric. False for the true tangent of a follower load
            (``Ke`` then holds the symmetric part only, ``H`` adds the skew part
            :meth:`~jaxelastic.mechanics.pressure.Pressure.skew_vp`): solved by GMRES
            (:meth:`~jaxelastic.solvers.linear.LinearSolver.nonsymmetric_step`).
    """

    pot: Potential
    x: jax.Array
    free: jax.Array
    Ke: Any
    H: Callable
    A: Callable
    operator: Callable
    assembled: bool = False
    symmetric: bool = True


def _masked(fm: jax.Array, H: Callable) -> Callable:
    def A(v):
        return fm * H(fm * v) + (1.0 - fm) * v

    return A


def operator_is_assembled(hessian: str, pot: Potential) -> bool:
    """Whether the Newton operator is the assembled element matrix
    (``NewtonSystem.assembled``): element Hessians (not ``hessian="hvp"``) and no
    coupling between the nodes of different elements (self-contact pairs). Decided by
    structure only, so also outside a trace."""
    return hessian != "hvp" and not pot_mod.has_coupling(pot)


def _with_skew(pot: Potential, x, H: Callable) -> Callable:
    """``v ↦ H v + ½(J − Jᵀ) v`` with the pressure term's skew part (the true tangent)."""
    term = pot.pressure
    assert term is not None

    def J(v):
        return H(v) + term.skew_vp(x, v)

    return J


def is_nonsymmetric(pot: Potential) -> bool:
    """Whether the true tangent of ``pot`` is not symmetric (a follower pressure; static)."""
    return pot.pressure is not None and pot.pressure.follower


def newton_system(
    pot: Potential,
    x,
    free,
    *,
    hessian: str,
    need_Ke: bool,
    Ke=None,
    pair_h=None,
    exact_tangent: bool = False,
) -> NewtonSystem:
    """The Dirichlet-masked Newton operator at ``x`` ``(n_nodes, dim)``.

    Args:
        hessian: Newton's ``hessian`` setting (``"element"``, ``"hvp"``, ``"projected"``).
        need_Ke: build element Hessians even for ``hessian="hvp"`` (the linear solver's
            preconditioner needs them).
        Ke: element Hessians already computed at ``x`` (else computed here if needed).
        pair_h: coupling data of the potential's terms at ``x`` if already computed
            (:func:`~jaxelastic.potential.coupling_data`).
        exact_tangent: the operator is the true, non-symmetric tangent where the
            potential has a follower load (:func:`is_nonsymmetric`); else (and always for
            conservative potentials) the symmetric Hessian. ``Ke`` stays symmetric.
    """
    fm = free.astype(x.dtype)
    if pair_h is None:  # once, for Ke's blocks and the coupling
        pair_h = pot_mod.coupling_data(pot, x)
    if Ke is None and (hessian != "hvp" or need_Ke):
        Ke = pot_mod.elastic_element_hessians(
            pot, x, project=hessian == "projected", pair_hessians=pair_h
        )
    # couplings between nodes of different elements (self-contact pairs): an operator
    # added to the element one (the node-diagonal part is inside Ke)
    cpl = pot_mod.coupling(pot, x, pair_h)

    def KV(K, v) -> jax.Array:
        Kv = pot_mod.element_hessian_vp(pot, K, v)
        return Kv if cpl is None else Kv + cpl(v)

    def sym_operator(K):
        return _masked(fm, lambda v: KV(K, v))

    def true_operator(K):
        return _masked(fm, _with_skew(pot, x, lambda v: KV(K, v)))

    if hessian == "hvp":

        def H(v):
            return pot_mod.hessian_vp(pot, x, v)
    else:
        Ke_el = Ke
        assert Ke_el is not None  # built above for every hessian but "hvp"

        def H(v):
            return KV(Ke_el, v)

    assembled = operator_is_assembled(hessian, pot)
    symmetric = not (exact_tangent and is_nonsymmetric(pot))
    if not symmetric:  # the true tangent: not the assembled (symmetric) element matrix
        H = _with_skew(pot, x, H)
        assembled = False
    return NewtonSystem(
        pot=pot,
        x=x,
        free=free,
        Ke=Ke,
        H=H,
        A=_masked(fm, H),
        operator=sym_operator if symmetric else true_operator,
        assembled=assembled,
        symmetric=symmetric,
    )


def exact_system(pot: Potential, x, mask, *, exact_tangent: bool = False) -> NewtonSystem:
    """The exact Hessian at ``x``: element Hessians + lumped mass, exact contact blocks
    (through the HVP if there is stiffness damping): the operator of the adjoint and
    tangent solves of implicit differentiation. ``exact_tangent``: with a follower load
    (:func:`is_nonsymmetric`) ``H`` is the true, non-symmetric tangent (``Ke`` its
    symmetric part)."""
    free = ~mask
    fm = free.astype(x.dtype)
    Ke = pot_mod.elastic_element_hessians(pot, x, project=False, exact_contact=True)
    cpl = pot_mod.coupling(pot, x, pot_mod.coupling_data(pot, x, exact=True), exact=True)

    def KV(K, v) -> jax.Array:
        Kv = pot_mod.element_hessian_vp(pot, K, v)
        return Kv if cpl is None else Kv + cpl(v)

    def operator(K):
        return _masked(fm, lambda v: KV(K, v))

    if pot.stiffness_damping is not None:

        def H(v):
            return pot_mod.hessian_vp(pot, x, v, exact_contact=True)
    else:

        def H(v):
            return KV(Ke, v)

    symmetric = not (exact_tangent and is_nonsymmetric(pot))
    if not symmetric:
        H = _with_skew(pot, x, H)
    return NewtonSystem(
        pot=pot,
        x=x,
        free=free,
        Ke=Ke,
        H=H,
        A=_masked(fm, H),
        operator=operator,
        symmetric=symmetric,
    )


def mass_or_zeros(system: NewtonSystem) -> jax.Array:
    """The lumped mass diagonal ``(n_nodes,)`` of the system's potential (zeros for none)."""
    md = pot_mod.mass_diagonal(system.pot)
    return jnp.zeros(system.x.shape[:1], system.x.dtype) if md is None else md
