"""The fitting objective ``Σ_c w_c·loss_c(z) + regulariser(z)`` in unconstrained variables.

One jit-compiled value-and-gradient function serves :func:`~jaxelastic.fitting.fit`, its
line search, :func:`~jaxelastic.fitting.loss_hessian` and user code (benchmarks): it is
compiled once per case structure, parametrisation structure and solver. Each case's linear
solver is bound once, outside jit (:meth:`Case.bind <jaxelastic.fitting.cases.Case.bind>`).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..solvers import GradientError, ImplicitAdjoint, Newton, check_finite_gradients
from .elastic import Material, material_parametrization
from .parameters import Parametrization, make_parametrization

__all__ = [
    "FIT_SOLVER",
    "Objective",
    "bind_solvers",
    "cases_loss",
    "make_objective",
    "parametrize",
]

FIT_SOLVER = Newton(rtol=1e-11)
"""Default Newton solver of fits: a tight rtol, so that gradients are accurate."""


def _cases_loss(params, cases, warms, solvers, adjoint):
    """Σ_cases w·loss at ψ parameters ``params`` and the cases' auxiliary data."""
    loss = 0.0
    auxs = []
    for c, w, s in zip(cases, warms, solvers, strict=True):
        val, aux = c.evaluate(params, w, s, adjoint)
        loss = loss + c.weight * val
        auxs.append(aux)
    return loss, tuple(auxs)


def _total(z, pz: Parametrization, cases, warms, solvers, adjoint):
    loss, auxs = _cases_loss(pz.psi_params(z), cases, warms, solvers, adjoint)
    return pz.penalty(z) + loss, auxs


@functools.partial(jax.jit, static_argnums=(5,))
def _value_and_grad(z, pz, cases, warms, solvers, adjoint):
    return jax.value_and_grad(_total, has_aux=True)(z, pz, cases, warms, solvers, adjoint)


_forward = jax.jit(_cases_loss, static_argnums=(4,))


def cases_loss(params, cases, warms, solvers, adjoint):
    """Jit-compiled ``(Σ_c w_c·loss_c, auxs)`` at ψ parameters ``params`` (forward only).

    Args:
        params: ψ parameter pytree; cases: tuple of cases; warms: tuple of warm starts;
        solvers: tuple of prepared solvers (one per case, :func:`bind_solvers`; a pytree
            argument: their linear-solver states are traced, their settings static);
        adjoint: :class:`~jaxelastic.solvers.ImplicitAdjoint`.
    """
    return _forward(params, tuple(cases), tuple(warms), tuple(solvers), adjoint)


def bind_solvers(cases, solver: Newton) -> tuple:
    """One :class:`~jaxelastic.solvers.PreparedSolver` per case: the Newton settings with
    the linear solver's state for the case's mesh and mask (outside jit)."""
    return tuple(c.bind(solver) for c in cases)


class Objective(NamedTuple):
    """The fitting objective in unconstrained variables (see :func:`make_objective`).

    Attributes:
        pz: the :class:`~jaxelastic.fitting.parameters.Parametrization`.
        cases: tuple of cases.
        z0: ``(n,)`` initial unconstrained vector.
        solvers: one bound Newton solver per case.
        adjoint: adjoint settings.
    """

    pz: Parametrization
    cases: tuple
    z0: jax.Array
    solvers: tuple
    adjoint: ImplicitAdjoint

    def initial_warms(self) -> tuple:
        return tuple(c.initial_warm() for c in self.cases)

    def value_and_grad(self, z, warms=None, check: bool = True):
        """``((loss, auxs), grad)`` at z (jit-compiled once per case structure).

        With ``check`` (default), raises :class:`~jaxelastic.solvers.GradientError` if a
        forward solve failed or the gradient is not finite; without it the caller inspects
        ``auxs[i].ok``.
        """
        warms = self.initial_warms() if warms is None else tuple(warms)
        (loss, auxs), g = _value_and_grad(
            jnp.asarray(z), self.pz, self.cases, warms, self.solvers, self.adjoint
        )
        if check:
            bad = [i for i, a in enumerate(auxs) if not bool(a.ok)]
            if bad:
                raise GradientError(f"forward solve failed in case(s) {bad}")
            check_finite_gradients(g)
        return (loss, auxs), g

    def params(self, z):
        """Region-form parameters at ``z`` (what a fit reports)."""
        return self.pz.from_unconstrained(jnp.asarray(z))


def parametrize(
    init,
    *,
    transforms=None,
    regions=None,
    fields=None,
    plane: str = "strain",
    regularization: float = 0.0,
    reg_kind: str = "tikhonov",
    mesh=None,
) -> Parametrization:
    """The :class:`~jaxelastic.fitting.parameters.Parametrization` of a fit's ``init``.

    Args:
        init: a :class:`~jaxelastic.fitting.Material` (E, ν; fitted as Lamé parameters with
            ``E`` positive and ν bounded, see :func:`material_parametrization`), any other ψ
            parameter pytree (see :func:`make_parametrization`), or a ready
            :class:`Parametrization` (then the other arguments must keep their defaults).
        transforms: per-leaf transforms (not for a Material).
        regions, fields, regularization, reg_kind: as in :func:`make_parametrization`;
            for a Material, ``fields`` defaults to ``("E", "nu")``.
        plane: 2D only (Material): ``"strain"`` or ``"stress"``.
        mesh: the mesh region labels refer to.
    """
    if isinstance(init, Parametrization):
        if transforms is not None or regions is not None or fields is not None:
            raise ValueError("with a Parametrization, pass no transforms, regions or fields")
        return init
    if isinstance(init, Material):
        if transforms is not None:
            raise ValueError("a Material is fitted with fixed transforms; pass fields=...")
        return material_parametrization(
            init,
            mesh,
            regions=regions,
            fields=("E", "nu") if fields is None else fields,
            plane=plane,
            regularization=regularization,
            reg_kind=reg_kind,
        )
    return make_parametrization(
        init,
        transforms,
        regions=regions,
        fields=fields,
        mesh=mesh,
        regularization=regularization,
        reg_kind=reg_kind,
    )


def make_objective(
    cases: Sequence,
    init,
    *,
    transforms=None,
    regions=None,
    fields=None,
    plane: str = "strain",
    regularization: float = 0.0,
    reg_kind: str = "tikhonov",
    mesh=None,
    solver: Newton = FIT_SOLVER,
    adjoint: ImplicitAdjoint = ImplicitAdjoint(),
) -> Objective:
    """The objective ``Σ_c w_c·loss_c(z) + penalty(z)`` of :func:`~jaxelastic.fitting.fit`
    as an :class:`Objective` (arguments as there; ``init`` as in :func:`parametrize`).

    The mesh defaults to the first case's ``mesh``; each case's linear solver is bound here,
    outside jit (keep ``solver.rtol`` tight, ≤ 1e-10, for accurate gradients).
    """
    cases = tuple(cases)
    if not cases:
        raise ValueError("fit needs at least one case")
    pz = parametrize(
        init,
        transforms=transforms,
        regions=regions,
        fields=fields,
        plane=plane,
        regularization=regularization,
        reg_kind=reg_kind,
        mesh=cases[0].mesh if mesh is None else mesh,
    )
    return Objective(pz, cases, pz.initial_z(), bind_solvers(cases, solver), adjoint)
