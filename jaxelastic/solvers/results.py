"""One result type and one status enum for every solver: Newton, linear solvers, host back ends.

A :class:`Solution` is a NamedTuple pytree ``(x, status, stats)`` usable under ``jit`` and
``vmap`` and outside: ``status`` is an int32 array holding a :class:`Status`, ``stats`` a
dict of arrays (iterations, residuals, histories, timings where known). Outside jit,
:meth:`Solution.raise_if_failed` (or ``throw=True`` in :func:`jaxelastic.solve`) raises
:class:`SolveError`, which names the status and what to try.
"""

from __future__ import annotations

import enum
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

__all__ = [
    "Status",
    "Solution",
    "SolveError",
    "SolveWarning",
    "REASONS",
    "ADVICE",
    "RUNNING",
    "solution_warnings",
    "warn_solution",
]


class Status(enum.IntEnum):
    """Outcome of a solve (``Solution.status``), shared by all solvers."""

    SUCCESS = 0
    MAX_STEPS = 1
    LINE_SEARCH_FAILED = 2
    INVERTED = 3
    NONFINITE = 4
    NEGATIVE_CURVATURE = 5
    NOT_POSITIVE_DEFINITE = 6


RUNNING = -1
"""Status of a loop that has not finished (never returned to users)."""

REASONS = {
    Status.SUCCESS: "converged",
    Status.MAX_STEPS: "no convergence within the iteration limit",
    Status.LINE_SEARCH_FAILED: "line search found no acceptable step (energy non-finite or "
    "not decreasing along the Newton direction)",
    Status.INVERTED: "the configuration has inverted elements (J ≤ 0) where the material "
    "is undefined",
    Status.NONFINITE: "non-finite energy or forces (NaN/inf)",
    Status.NEGATIVE_CURVATURE: "the linear operator has non-positive curvature (indefinite "
    "Hessian)",
    Status.NOT_POSITIVE_DEFINITE: "the assembled matrix is not positive definite",
}

ADVICE = {
    Status.SUCCESS: "",
    Status.MAX_STEPS: "raise max_steps, apply the load in steps (je.solve_incremental), or "
    "loosen rtol",
    Status.LINE_SEARCH_FAILED: "apply the load in steps (je.solve_incremental), use "
    "Newton(hessian='projected'), or check the material for J ≤ 0",
    Status.INVERTED: "start from an uninverted x0 or use an inversion-safe material "
    "(stable_neo_hookean, fixed_corotated)",
    Status.NONFINITE: "check inputs for NaN/inf; with float32 loosen rtol or enable x64",
    Status.NEGATIVE_CURVATURE: "use Newton(hessian='projected') or a direct linear solver",
    Status.NOT_POSITIVE_DEFINITE: "add Dirichlet conditions that remove rigid motions, or use "
    "Newton(hessian='projected')",
}


class Solution(NamedTuple):
    """Result of a solve.

    Attributes:
        x: the solution: ``(n_nodes, dim)`` positions for Newton, the solution vector for a
            linear solve.
        status: int32 array holding a :class:`Status` (batched under ``vmap``).
        stats: dict of arrays. Newton: ``steps``, ``linear_iterations``, ``residual``
            [force], ``energy``, ``residual_history`` ``(max_steps + 1,)`` (NaN-padded),
            ``linear_history`` ``(max_steps,)``, ``step_history`` ``(max_steps,)``
            (accepted step lengths, NaN-padded), ``line_search_cutbacks``,
            ``negative_curvature`` (Newton steps whose linear solve met it),
            ``linear_unconverged`` (Newton steps whose linear solve stopped short of its
            tolerance, e.g. a GMRES at its iteration cap: the step was its best iterate),
            ``projected`` (steps whose host matrix was PSD-projected),
            ``residual_floor`` (the round-off floor of the residual at the last iterate
            [force]: a residual at or below it counts as converged),
            ``residual_reference`` [force], ``tolerance`` (max(atol, rtol·reference)
            [force]), ``achieved_rtol`` (residual / reference), ``floor_limited``
            (SUCCESS at the round-off floor above ``tolerance``), ``min_J`` and
            ``min_J_cell`` (the smallest det F and its cell), ``max_strain`` and
            ``max_strain_cell`` (the largest principal strain max|λᵢ − 1| and its cell),
            ``wall_time`` [s] (NaN inside jit). Linear: ``iterations``, ``residual``.
    """

    x: Any
    status: jax.Array
    stats: dict

    @property
    def ok(self) -> jax.Array:
        """``status == SUCCESS`` as a bool array (usable under jit; ``bool()`` it outside)."""
        return jnp.asarray(self.status) == Status.SUCCESS

    @property
    def reason(self) -> str:
        """Human-readable status (outside jit, unbatched)."""
        return REASONS[Status(int(self.status))]

    def raise_if_failed(self, what: str = "solve") -> Solution:
        """Raise :class:`SolveError` unless SUCCESS (outside jit); return self otherwise."""
        if int(self.status) != Status.SUCCESS:
            raise SolveError(self, what)
        return self


class SolveError(RuntimeError):
    """A solve did not succeed (raised only outside jit, with ``throw=True``).

    Attributes:
        solution: the failed :class:`Solution`; status: its :class:`Status`.
    """

    def __init__(self, solution: Solution, what: str = "solve"):
        st = Status(int(solution.status))
        stats = solution.stats
        detail = []
        if "steps" in stats:
            detail.append(f"after {int(stats['steps'])} iterations")
        elif "iterations" in stats:
            detail.append(f"after {int(stats['iterations'])} iterations")
        if "residual" in stats:
            detail.append(f"residual {float(stats['residual']):.3e}")
        if st == Status.INVERTED and "min_J" in stats:
            detail.append(f"min J {float(stats['min_J']):.3g} in cell {int(stats['min_J_cell'])}")
        tail = f" ({', '.join(detail)})" if detail else ""
        advice = ADVICE[st]
        super().__init__(
            f"{what} failed: {st.name}: {REASONS[st]}{tail}"
            + (f"; try: {advice}" if advice else "")
        )
        self.solution = solution
        self.status = st


class SolveWarning(UserWarning):
    """A solve succeeded but its answer needs a look: an inverted cell of a ψ that is
    defined there, or a requested tolerance below the residual's round-off floor."""


def solution_warnings(sol: Solution) -> list[str]:
    """What is suspect about a successful, concrete, unbatched Newton solution: inverted
    cells (``stats["min_J"] ≤ 0``: only possible on a ψ defined there, else the status is
    INVERTED) and a SUCCESS at the round-off floor above the requested tolerance
    (``stats["floor_limited"]``). Plain sentences with the numbers; empty when nothing is.
    """
    st = sol.stats
    out = []
    if int(sol.status) != Status.SUCCESS:
        return out
    if "min_J" in st and not float(st["min_J"]) > 0:
        out.append(
            f"inverted cells: min J = {float(st['min_J']):.3g} in cell {int(st['min_J_cell'])} "
            f"(largest strain {100 * float(st['max_strain']):.3g} % in cell "
            f"{int(st['max_strain_cell'])}): the material is defined there, but an inverted "
            "cell is rarely physical: check the units of the material constants and loads, "
            "the supports and the load or time step size"
        )
    if "floor_limited" in st and bool(st["floor_limited"]):
        out.append(
            f"the requested tolerance {float(st['tolerance']):.3g} is below the residual's "
            f"round-off floor {float(st['residual_floor']):.3g}: converged to the floor, a "
            f"relative residual of {float(st['achieved_rtol']):.3g} (stats['achieved_rtol'])"
        )
    return out


_WARNING_TEXT = {
    "inverted": "the solution has inverted cells (J <= 0) on a material defined there: see "
    "stats['min_J'] and stats['min_J_cell']; check units, supports and load size",
    "floor": "the requested rtol/atol is below the residual's round-off floor: the solve "
    "stopped at the floor (SUCCESS), see stats['achieved_rtol'] and stats['residual_floor']",
}


def _concrete(v) -> float | None:
    """``v`` as a Python float, or None when absent or traced (an eager ``jax.jvp`` of a
    solve carries its statistics as tracers: nothing is warned there, as inside jit)."""
    if v is None:
        return None
    try:
        return float(v)
    except (jax.errors.ConcretizationTypeError, TypeError):
        return None


def warn_solution(sol: Solution, what: str = "je.solve", stacklevel: int = 3) -> None:
    """Emit a :class:`SolveWarning` for each of :func:`solution_warnings` (fixed texts, so
    Python shows each once per calling line; the numbers are in ``sol.stats``)."""
    import warnings

    st = sol.stats
    if int(sol.status) != Status.SUCCESS:
        return
    min_J, floor = _concrete(st.get("min_J")), _concrete(st.get("floor_limited"))
    if min_J is not None and not min_J > 0:
        warnings.warn(f"{what}: {_WARNING_TEXT['inverted']}", SolveWarning, stacklevel=stacklevel)
    if floor is not None and bool(floor):
        warnings.warn(f"{what}: {_WARNING_TEXT['floor']}", SolveWarning, stacklevel=stacklevel)
