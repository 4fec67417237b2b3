"""The linear-solver protocol: immutable settings, explicit state.

In the shape of lineax: a linear solver is a small frozen dataclass of *settings*
(hashable, static under ``jit``; changing a field recompiles). What a solver builds for a
problem — a host factorisation with its sparsity analysis, an AMG or multigrid hierarchy —
is its *state*, made once outside ``jit`` by :meth:`LinearSolver.init` for a mesh and a
Dirichlet mask and passed explicitly to every solve (:func:`jaxelastic.solve`'s
``linear_state``, or made there when the mesh is concrete). States are kept in one bounded
cache per kind (:data:`~jaxelastic.solvers.host.SHARED_CAPACITY` entries, keyed by the
mesh's and mask's contents), so repeated solves of one scene reuse them and nothing keeps
more than a few factorisations alive.

A Newton step calls :meth:`LinearSolver.newton_step` (inside a trace) or, for host solvers
outside ``jit`` on an assembled operator, :meth:`LinearSolver.host_step`; the projected
retry around either is the Newton driver's (:mod:`~jaxelastic.solvers.newton.retry`).
A non-symmetric Newton operator (the true tangent of a follower load) is solved by
:meth:`LinearSolver.nonsymmetric_step`: GMRES (:func:`~.gmres.gmres`) preconditioned by
what the solver builds for the symmetric part (:meth:`LinearSolver.symmetric_preconditioner`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, ClassVar

import jax

from ..results import Solution
from .nonsymmetric import gmres
from .system import NewtonSystem

__all__ = ["LinearSolver", "LinearState", "NONSYMMETRIC_MAX_ITER"]

NONSYMMETRIC_MAX_ITER = 2000
"""GMRES iteration cap of :meth:`LinearSolver.nonsymmetric_step` for solvers without a
``max_iter`` of their own (:class:`~jaxelastic.solvers.linear.Direct`)."""


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class LinearState:
    """What a linear solver built for one mesh and Dirichlet mask (a pytree).

    Attributes:
        kind: the solver it belongs to (``"cg"``, ``"direct"``, ``"amg"``, ``"multilevel"``;
            static).
        host: the host back end (:class:`~jaxelastic.solvers.host.HostLinearSolver`,
            holding the sparsity analysis and the latest factorisation or hierarchy;
            static, compared by its content key), or None.
        hierarchy: a device multigrid hierarchy (arrays: travels as an argument of the
            compiled solve, never as a constant), or None.
    """

    kind: str = dataclasses.field(default="cg", metadata=dict(static=True))
    host: Any = dataclasses.field(default=None, metadata=dict(static=True))
    hierarchy: Any = None


class LinearSolver:
    """Base of the linear-solver settings (:class:`~jaxelastic.solvers.linear.CG`,
    :class:`~jaxelastic.solvers.linear.Direct`, :class:`~jaxelastic.solvers.linear.AMG`,
    :class:`~jaxelastic.solvers.linear.Multilevel`). Subclasses are frozen dataclasses."""

    kind: ClassVar[str] = ""
    on_host: ClassVar[bool] = False
    """The solve runs on the host: outside ``jit`` the Newton loop then runs in Python
    (:func:`~jaxelastic.solvers.newton.minimize`), inside it the solve is a callback."""

    shardable: ClassVar[bool] = False
    """Whether it solves a mesh sharded over several devices (:func:`jaxelastic.shard`)."""

    @property
    def needs_element_hessians(self) -> bool:
        return True

    def init(self, mesh, bc) -> LinearState:
        """The state for ``mesh`` and ``bc.mask`` (host work, outside ``jit``; cached)."""
        return LinearState(kind=self.kind)

    def newton_step(
        self, state: LinearState, system: NewtonSystem, A, Ke, rhs, tol, token
    ) -> Solution:
        """Solve ``A Δ = rhs`` to ``‖r‖ ≤ tol`` with the operator ``A`` built from the
        element Hessians ``Ke`` (the system's own, or their projection in the retry);
        ``token``: an int32 that orders host calls. Traceable. Status SUCCESS,
        MAX_STEPS, NEGATIVE_CURVATURE or NOT_POSITIVE_DEFINITE; stats ``iterations``,
        ``residual``."""
        raise NotImplementedError

    def symmetric_preconditioner(
        self, state: LinearState, system: NewtonSystem, Ke, token
    ) -> tuple[Callable | None, jax.Array]:
        """``(M, token)``: ``r ↦ M⁻¹ r`` built from the symmetric element Hessians ``Ke``
        (what the solver's symmetric solve is preconditioned or factorised with; None:
        none), zero on the Dirichlet dofs, and the token that orders later host calls.
        Traceable."""
        raise NotImplementedError(f"{type(self).__name__} has no preconditioner")

    def nonsymmetric_step(
        self, state: LinearState, system: NewtonSystem, A, Ke, rhs, tol, token
    ) -> Solution:
        """Solve a non-symmetric ``A Δ = rhs`` to ``‖r‖ ≤ tol`` by GMRES preconditioned by
        :meth:`symmetric_preconditioner` of the symmetric element Hessians ``Ke`` (a host
        factorisation of the symmetric part is an exact inverse of it, indefinite or not).
        Traceable. Status SUCCESS, MAX_STEPS (GMRES did not reach ``tol``: reported, the
        step is the best iterate) or NONFINITE; stats ``iterations``, ``residual``."""
        M, _ = self.symmetric_preconditioner(state, system, Ke, token)
        max_iter = int(getattr(self, "max_iter", NONSYMMETRIC_MAX_ITER))
        return gmres(A, rhs, M, tol=tol, max_iter=max_iter)

    def exact(self, state: LinearState, system: NewtonSystem, b, rtol, max_iter: int) -> Solution:
        """Solve with the exact operator to ``‖r‖ ≤ rtol·‖b‖`` (adjoint/tangent systems)."""
        raise NotImplementedError

    def host_step(self, state: LinearState, data, md, rhs, tol) -> tuple[Any, int, int]:
        """(host solvers, outside ``jit``) ``(Δ, iterations, status)`` of the assembled
        operator given by its upper-triangle data and mass diagonal."""
        raise NotImplementedError(f"{type(self).__name__} does not solve on the host")
