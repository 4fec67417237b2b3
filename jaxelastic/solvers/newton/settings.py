"""Newton's settings: a frozen, hashable dataclass (static under ``jit``)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

__all__ = ["Newton", "HESSIANS", "TANGENTS", "XTOL_MAX"]

HESSIANS = ("element", "hvp", "projected")

TANGENTS = ("auto", "exact", "symmetric")
"""Newton's ``tangent`` choices (:func:`~jaxelastic.solvers.newton.iteration.exact_tangent`
decides ``"auto"``)."""


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
    """Newton's method with an inversion-aware backtracking line search and a
    Levenberg–Marquardt safeguard (frozen, hashable: a static argument under jit; changing
    a field recompiles).

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
        tangent: the Newton operator of a potential with a non-conservative follower load
            (:attr:`~jaxelastic.mechanics.pressure.Pressure.follower`), whose true tangent
            is not symmetric: ``"exact"`` (the true tangent, symmetric part plus the skew
            pressure stiffness as a matrix-free product, solved by GMRES preconditioned by
            the linear solver's symmetric preconditioner or factorisation: quadratic
            convergence), ``"symmetric"`` (its symmetric part, solved like any Hessian: a
            quasi-Newton, linear convergence, cheaper per step) or ``"auto"`` (``"exact"``
            wherever the tangent is not symmetric:
            :func:`~jaxelastic.solvers.newton.iteration.exact_tangent`). Conservative
            potentials have a symmetric tangent, and there the three are the same.
        linear: linear solver: ``"auto"``, ``"cg"``, ``"direct"``, ``"amg"`` or a
            :class:`~jaxelastic.solvers.linear.CG` / ``Direct`` / ``AMG`` object
            (settings only: the state they need, a factorisation or a hierarchy, is made by
            :func:`~jaxelastic.solvers.linear.init_linear` and passed explicitly).
        ls_max: maximum halvings in the line search.
        armijo: sufficient-decrease constant (of Π; with a follower load, which has no
            Π, of the residual norm, before the line search's natural monotonicity test:
            :data:`~jaxelastic.solvers.newton.iteration.NATURAL_MONOTONICITY`).
        require_positive_J: also reject trial steps where any element has J ≤ 0 (for user
            materials that return finite garbage there); the built-in neo-Hookean returns
            +inf, which the line search rejects anyway.
        kappa_max_factor: potential terms with an adaptive stiffness (the contact
            barrier's κ, :meth:`~jaxelastic.contact.Contact.adapt`) may raise it inside the
            solve to this multiple of its starting value: 1 (default) is off, IPC uses 100
            (:data:`~jaxelastic.contact.log_barrier.KAPPA_MAX_FACTOR`). Off by default because
            the adapted stiffness lives only in the solution (``stats["kappa"]``): forces
            computed from the original potential would use the old one (use
            :func:`~jaxelastic.solvers.newton.solved_potential`), and in dynamics every
            step adapts afresh.
        regularize: the Levenberg–Marquardt safeguard
            (:mod:`~jaxelastic.solvers.newton.levenberg`): where plain Newton misbehaves (a
            line search finds no acceptable step, or the residual sets no new minimum for
            several iterations: a flat, curved valley such as a nearly free rotation) the
            Hessian is shifted by λI, λ adapted by the ratio of actual to predicted
            decrease of Π, and back to 0 (plain Newton) once steps are predicted well.
            Solves where Newton behaves never shift; a non-conservative follower load
            (no Π to decrease) never does. ``stats["regularized"]``: the iterations
            solved with a shift.
    """

    rtol: float = 1e-8
    atol: float = 0.0
    max_steps: int = 50
    xtol: float = 1e-12
    hessian: str = "element"
    tangent: str = "auto"
    linear: Any = "auto"
    ls_max: int = 40
    armijo: float = 1e-4
    require_positive_J: bool = False
    kappa_max_factor: float = 1.0
    regularize: bool = True

    def __post_init__(self):
        if self.hessian not in HESSIANS:
            raise ValueError(f"hessian must be one of {HESSIANS}, got {self.hessian!r}")
        if self.tangent not in TANGENTS:
            raise ValueError(f"tangent must be one of {TANGENTS}, got {self.tangent!r}")
        for name in ("max_steps", "ls_max"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
        for name in ("require_positive_J", "regularize"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise TypeError(f"{name} must be True or False, got {getattr(self, name)!r}")
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
