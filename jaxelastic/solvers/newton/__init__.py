"""Newton's method on the total potential Π: settings, state, one loop.

Each iteration:

1. Dirichlet data enter the step: the prescribed part ``Δ_D = x_D − x`` is moved with the
   step and the free part solves ``K_ff Δ_f = −(g_f + K_fD Δ_D)``. The first iterate from
   the rest shape is therefore the linear-elastic predictor, and a boundary motion too
   large for one step is applied partially by the line search (no inverted initial guess).
2. The linear system is solved inexactly (forcing term ``η = clip(‖g‖/‖g‖_ref, 1e-6, 0.1)``)
   by the linear solver (:mod:`~jaxelastic.solvers.linear`) on the exact Hessian (element
   Hessians or HVP), or on PSD-projected element Hessians (``hessian="projected"``); a
   follower load's true, non-symmetric tangent (``tangent="auto"``,
   :func:`~jaxelastic.solvers.newton.iteration.exact_tangent`) by GMRES preconditioned by
   the linear solver's preconditioner or factorisation of the symmetric part; a
   solve that finds the Hessian indefinite is retried once on projected element Hessians
   (:mod:`~jaxelastic.solvers.newton.retry`). Where plain Newton misbehaves (a failed
   line search, or no new smallest residual for several iterations) the Hessian is
   shifted by λI, λ adapted by the ratio of actual to predicted decrease
   (:mod:`~jaxelastic.solvers.newton.levenberg`, ``Newton(regularize=True)``).
3. Backtracking line search treating non-finite Π as +∞ (an inverting step of a model that
   is undefined at J ≤ 0 is cut back until no element inverts), starting from the bound
   of the potential's terms (contact: the CCD bound): Armijo on Π far from the solution,
   decrease of the residual near it, where Π's round-off (~eps·Σ_c|x_cᵀK_c x_c|, far
   above eps·|Π| near rest because ψ cancels large terms) exceeds the predicted decrease
   (below ``max(1e-10, 1e4·eps)`` of that scale:
   :data:`~jaxelastic.solvers.newton.iteration.NEAR_EPS`), or, there, a residual that
   stays below its round-off floor; steps that move Dirichlet dofs only need a finite Π.
4. Convergence: ``‖g_free‖ ≤ max(atol, rtol·‖g‖_ref)`` with all Dirichlet dofs in place,
   or the residual's round-off floor reached
   (:func:`~jaxelastic.solvers.newton.iteration.residual_floor`, reported as
   ``stats["residual_floor"]``) once a full step reduces the residual by less than half
   (at once for a quadratic Π), or a full step below ``xtol`` times the body's size;
   where ``‖g‖_ref`` is the largest free residual seen, ‖f_ext‖, the reaction on the
   prescribed dofs at the start (the load a warm start from a nearby solution carries),
   or the largest right-hand side ``‖g_f + K_fD Δ_D‖`` (the force induced by a
   Dirichlet motion).
5. Terms with an adaptive stiffness (contact's barrier κ, opt-in by
   ``kappa_max_factor > 1``) adapt after each accepted iterate
   (:mod:`~jaxelastic.solvers.newton.terms`); the solve then continues on the stiffer
   potential, reported in ``stats`` (``kappa``) and used by the implicit derivatives
   (:func:`solved_potential`).

``settings`` (:class:`Newton`) → ``terms`` → ``iteration`` (the pieces) → ``state``
(:class:`NewtonState`, :func:`init`, :func:`terminate`) → ``retry``, ``levenberg`` →
``driver``
(:func:`step`, :func:`minimize`: the one loop).
"""

from .driver import minimize as minimize
from .driver import runs_on_host as runs_on_host
from .driver import step as step
from .iteration import exact_tangent as exact_tangent
from .iteration import is_quadratic as is_quadratic
from .settings import HESSIANS as HESSIANS
from .settings import TANGENTS as TANGENTS
from .settings import XTOL_MAX as XTOL_MAX
from .settings import Newton as Newton
from .state import NewtonState as NewtonState
from .state import init as init
from .state import solution as solution
from .state import terminate as terminate
from .terms import solved_potential as solved_potential

__all__ = [
    "Newton",
    "NewtonState",
    "HESSIANS",
    "TANGENTS",
    "XTOL_MAX",
    "init",
    "step",
    "terminate",
    "solution",
    "minimize",
    "runs_on_host",
    "is_quadratic",
    "exact_tangent",
    "solved_potential",
]
