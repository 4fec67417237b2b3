"""The fitting objective ``Σ_c w_c·loss_c(z) + regulariser(z)`` in unconstrained variables.

One jit-compiled value-and-gradient function serves :func:`jaxelastic.fitting.fit`, its
line search, :func:`jaxelastic.fitting.loss_hessian` and user code (benchmarks): it is
compiled once per case structure and Newton/adjoint settings. Cases follow the protocol
described in :mod:`jaxelastic.fitting`.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp

from .implicit import DEFAULT_ADJOINT, AdjointSettings, GradientError, _check_finite_grads
from .parametrization import Material, ParamMap, make_param_map
from .solvers.newton import NewtonSettings

__all__ = ["FIT_SETTINGS", "Objective", "make_objective"]

FIT_SETTINGS = NewtonSettings(rtol=1e-11)


def _cases_loss(params, cases, warms, settings, adjoint):
    """Σ_cases w·loss at material ``params`` and the cases' auxiliary data."""
    loss = 0.0
    auxs = []
    for c, w in zip(cases, warms, strict=True):
        val, aux = c.evaluate(params, w, settings, adjoint)
        loss = loss + c.weight * val
        auxs.append(aux)
    return loss, tuple(auxs)


def _total(z, pm: ParamMap, cases, warms, settings, adjoint):
    loss, auxs = _cases_loss(pm.lame(z), cases, warms, settings, adjoint)
    return pm.penalty(z) + loss, auxs


@functools.partial(jax.jit, static_argnums=(4, 5))
def _value_and_grad(z, pm, cases, warms, settings, adjoint):
    return jax.value_and_grad(_total, has_aux=True)(z, pm, cases, warms, settings, adjoint)


_forward = jax.jit(_cases_loss, static_argnums=(3, 4))


class Objective(NamedTuple):
    """The fitting objective in unconstrained variables (see :func:`make_objective`).

    Attributes:
        pm: the :class:`~jaxelastic.parametrization.ParamMap`.
        cases: tuple of cases.
        z0: initial unconstrained vector.
        settings, adjoint: Newton and adjoint settings.
    """

    pm: ParamMap
    cases: tuple
    z0: jax.Array
    settings: NewtonSettings
    adjoint: AdjointSettings

    def initial_warms(self) -> tuple:
        return tuple(c.initial_warm() for c in self.cases)

    def value_and_grad(self, z, warms=None, check: bool = True):
        """``((loss, auxs), grad)`` at z (jit-compiled once per case structure).

        With ``check`` (default), raises :class:`GradientError` if a forward solve failed
        or the gradient is not finite; without it the caller inspects ``auxs[i].ok``.
        """
        warms = self.initial_warms() if warms is None else tuple(warms)
        (loss, auxs), g = _value_and_grad(
            jnp.asarray(z), self.pm, self.cases, warms, self.settings, self.adjoint
        )
        if check:
            bad = [i for i, a in enumerate(auxs) if not bool(a.ok)]
            if bad:
                raise GradientError(f"forward solve failed in case(s) {bad}")
            _check_finite_grads(g)
        return (loss, auxs), g

    def material(self, z) -> Material:
        return self.pm.material(jnp.asarray(z))


def _default_mesh(cases):
    for attr in ("pot", "base", "potential"):
        p = getattr(cases[0], attr, None)
        if p is not None:
            return p.mesh
    return getattr(cases[0], "mesh", None)


def make_objective(
    cases: Sequence,
    init: Material,
    *,
    regions=None,
    fields: Sequence[str] = ("E", "nu"),
    plane: str = "strain",
    regularization: float = 0.0,
    reg_kind: str = "tikhonov",
    mesh=None,
    settings: NewtonSettings = FIT_SETTINGS,
    adjoint: AdjointSettings = DEFAULT_ADJOINT,
) -> Objective:
    """The :func:`fit` objective ``Σ_c w_c·loss_c(z) + regulariser(z)`` as an
    :class:`Objective` (arguments as in :func:`fit`)."""
    cases = tuple(cases)
    if not cases:
        raise ValueError("fit needs at least one case")
    if mesh is None:
        mesh = _default_mesh(cases)
    pm = make_param_map(
        init,
        mesh,
        regions=regions,
        fields=fields,
        plane=plane,
        regularization=regularization,
        reg_kind=reg_kind,
    )
    return Objective(pm, cases, pm.initial_z(), settings, adjoint)
