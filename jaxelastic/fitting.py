"""Material identification: fit E and ν (shared, per region or per cell) with optax.

A *case* is one experiment: a frozen pytree with a ``weight`` attribute and two methods,

* ``initial_warm() -> W``: a pytree of arrays, the first Newton initial guess(es);
* ``evaluate(params, warm, settings, adjoint) -> (loss, CaseAux)``: the unweighted scalar
  misfit for material parameters ``params`` (a :class:`~jaxelastic.materials.Lame` with
  scalar or ``(n_cells,)`` leaves), reverse-mode differentiable through
  :mod:`jaxelastic.implicit`, and a :class:`~jaxelastic.parametrization.CaseAux` (new warm
  start, ``ok``, Newton and linear iteration counts).

:class:`LoadCase` is the static case (a potential, Dirichlet data, observed positions of
all nodes or of marker nodes); :class:`~jaxelastic.trajectory.TrajectoryCase` (re-exported
here) observes a dynamic trajectory. :func:`fit`
minimises ``Σ_c w_c·loss_c + regulariser`` over the unconstrained variables of
:mod:`jaxelastic.parametrization` with optax (L-BFGS by default, or Adam), warm-starting
every forward solve from the previous iterate's solution; a failed solve raises
:class:`GradientError`. :func:`loss_landscape` and :func:`loss_hessian` probe
identifiability.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .implicit import (
    DEFAULT_ADJOINT,
    AdjointSettings,
    GradientError,
    equilibrium,
    equilibrium_result,
    value_and_grad,
)
from .loads import Dirichlet
from .materials import Lame, lame
from .objective import FIT_SETTINGS, Objective, _default_mesh, _forward, make_objective
from .parametrization import (
    CaseAux,
    Material,
    add_noise,
    from_unconstrained,
    observation_loss,
    to_unconstrained,
)
from .potential import Potential
from .solvers.newton import NewtonSettings, Status
from .trajectory import TrajectoryCase

__all__ = [
    # re-exported from jaxelastic.implicit / parametrization for convenience
    "AdjointSettings",
    "GradientError",
    "equilibrium",
    "equilibrium_result",
    "value_and_grad",
    "CaseAux",
    "Material",
    "add_noise",
    "observation_loss",
    "to_unconstrained",
    "from_unconstrained",
    # fitting
    "LoadCase",
    "TrajectoryCase",
    "Objective",
    "FitResult",
    "fit",
    "loss_landscape",
    "loss_hessian",
    "make_objective",
]


@dataclasses.dataclass(frozen=True)
class LoadCase:
    """One static experiment: a potential (its ``params`` are replaced by the fitted ones),
    the Dirichlet data, and observed positions.

    Attributes:
        pot: potential (mesh, ``f_ext``, ψ); ``params`` is ignored.
        bc: Dirichlet data.
        observed: ``(n_obs, dim)`` observed deformed positions of ``nodes``.
        nodes: ``(n_obs,)`` int marker-node indices, or None for all nodes.
        weight: weight of this case in the loss.
        linear: None (matrix-free PCG inside jit) or a host solver from
            :func:`~jaxelastic.solvers.newton.make_linear` (static; not a string).

    The loss is :func:`~jaxelastic.parametrization.observation_loss` (relative squared
    misfit; 1 at the rest shape).
    """

    pot: Potential
    bc: Dirichlet
    observed: Any
    nodes: Any = None
    weight: float = 1.0
    linear: Any = dataclasses.field(default=None, metadata=dict(static=True))

    def __post_init__(self):
        if isinstance(self.linear, str):
            raise ValueError(
                "LoadCase.linear must be None or a solver from make_linear(mesh, bc, name), "
                f"not the string {self.linear!r}"
            )

    def initial_warm(self):
        """Rest positions ``(n_nodes, dim)``."""
        return self.pot.mesh.points

    def evaluate(self, params, warm, settings: NewtonSettings, adjoint: AdjointSettings):
        """(unweighted loss, :class:`CaseAux`) at material parameters ``params``."""
        r = equilibrium_result(
            self.pot.replace(params=params), self.bc, warm, settings, self.linear, adjoint
        )
        loss = observation_loss(r.x, self.observed, self.pot.mesh.points, self.nodes)
        aux = CaseAux(r.x, r.status == Status.SUCCESS, r.steps, r.linear_iterations)
        return loss, aux


jax.tree_util.register_dataclass(
    LoadCase,
    data_fields=["pot", "bc", "observed", "nodes", "weight"],
    meta_fields=["linear"],
)


@functools.cache
def _named_optimizer(name: str, learning_rate: float):
    import optax

    if name == "lbfgs":
        return optax.lbfgs(linesearch=None)
    if name == "adam":
        return optax.adam(learning_rate)
    raise ValueError(f"optimizer must be 'lbfgs', 'adam' or an optax transformation, got {name!r}")


@functools.cache
def _update_fn(optimizer):
    return jax.jit(optimizer.update)


class FitResult(NamedTuple):
    """Result of :func:`fit`.

    Attributes:
        material: fitted :class:`Material` (floats, or ``(n_regions,)`` arrays).
        E, nu: the same values.
        loss: final loss.
        converged: a stopping criterion met (else ``max_iter`` reached or stalled).
        stop_reason: ``"gtol"``, ``"ftol"``, ``"xtol"``, ``"roundoff"`` (the line search's
            predicted decrease fell below 1e-12 × loss: no measurable progress is possible;
            counted as converged), ``"stalled"`` (line search or failed solves) or
            ``"max_iter"``.
        iterations: optimiser iterations k.
        loss_history: ``(k + 1,)`` loss at each iterate.
        param_history: ``(k + 1, 2)`` (E, ν) per iterate, or ``(k + 1, 2, n_regions)``.
        grad_norm_history: ``(k + 1,)`` gradient norm w.r.t. the unconstrained variables.
        newton_steps: ``(k + 1, n_cases)`` Newton iterations of each case's forward solve(s)
            per iteration (summed over its line-search trials; row 0: the initial guess).
        linear_iterations: ``(k + 1, n_cases)`` linear-solver iterations, likewise.
        solutions: final warm start (equilibrium positions) per case.
        z: final unconstrained vector.
        wall_time: seconds, including compilation.
    """

    material: Material
    E: Any
    nu: Any
    loss: float
    converged: bool
    stop_reason: str
    iterations: int
    loss_history: np.ndarray
    param_history: np.ndarray
    grad_norm_history: np.ndarray
    newton_steps: np.ndarray
    linear_iterations: np.ndarray
    solutions: list
    z: np.ndarray
    wall_time: float


def fit(
    cases: Sequence,
    init: Material,
    *,
    regions=None,
    fields: Sequence[str] = ("E", "nu"),
    plane: str = "strain",
    optimizer="lbfgs",
    learning_rate: float = 0.05,
    max_iter: int = 100,
    gtol: float = 1e-10,
    ftol: float = 1e-24,
    xtol: float = 1e-12,
    regularization: float = 0.0,
    reg_kind: str = "tikhonov",
    mesh=None,
    settings: NewtonSettings = FIT_SETTINGS,
    adjoint: AdjointSettings = DEFAULT_ADJOINT,
    progress: bool = False,
) -> FitResult:
    """Fit Young's modulus and Poisson's ratio to observations in one or several cases.

    Minimises ``Σ_c w_c·loss_c + regulariser`` over the unconstrained variables
    ``a = ln(E/E_init)``, ``b = logit((ν+1)/1.5)`` (so E > 0 and −1 < ν < 0.5 always);
    each forward solve starts from the previous iterate's solution of the same case.

    Args:
        cases: :class:`LoadCase` s (or any objects following the case protocol).
        init: initial :class:`Material` (scalars, or ``(n_regions,)`` arrays).
        regions: None (one shared E, ν), ``(n_cells,)`` int labels ``0..R−1``
            (piecewise-constant fields, e.g. a two-material bar), or ``"cells"``.
        fields: which of ``"E"``, ``"nu"`` to fit; the others stay at ``init``.
        plane: 2D only, ``"strain"`` or ``"stress"``.
        optimizer: ``"lbfgs"``: the optax L-BFGS direction (``optax.lbfgs(linesearch=None)``)
            with a backtracking Armijo line search run on the host (every trial point is one
            compiled value-and-gradient evaluation, reused as the next iterate, so the
            solver is compiled once); ``"adam"`` (``optax.adam(learning_rate)``) or any
            optax ``GradientTransformation``: updates applied as they come, halved only
            when a forward solve fails.
        learning_rate: Adam's step in the unconstrained variables.
        max_iter: maximum optimiser iterations.
        gtol: stop (converged) when ``‖∇_z loss‖ ≤ gtol``.
        ftol: stop (converged) when ``loss ≤ ftol``.
        xtol: stop (converged) when an update moves z by ``≤ xtol`` (max norm).
        regularization, reg_kind: weight and kind (``"tikhonov"``/``"tv"``) of the
            smoothness term over adjacent regions (see :meth:`ParamMap.penalty`).
        mesh: the mesh region labels refer to (default: the first case's ``pot.mesh``).
        settings, adjoint: Newton settings (keep ``rtol`` tight, ≤ 1e-10, for accurate
            gradients) and adjoint settings.
        progress: show a tqdm progress bar with the loss and parameters.

    Raises:
        GradientError: a forward solve at an accepted iterate failed.
    """
    t_start = time.perf_counter()
    obj = make_objective(
        cases,
        init,
        regions=regions,
        fields=fields,
        plane=plane,
        regularization=regularization,
        reg_kind=reg_kind,
        mesh=mesh,
        settings=settings,
        adjoint=adjoint,
    )
    line_search = optimizer == "lbfgs"
    if isinstance(optimizer, str):
        optimizer = _named_optimizer(optimizer, float(learning_rate))
    jit_update = _update_fn(optimizer)

    def update(g, state, z):
        try:
            return jit_update(g, state, z)
        except (TypeError, KeyError) as e:  # e.g. optax.lbfgs() with its zoom line search
            raise ValueError(
                "the optax optimizer needs extra arguments (value / value_fn of a line "
                f"search?); use optimizer='lbfgs' for L-BFGS ({e})"
            ) from e

    z = obj.z0
    state = optimizer.init(z)
    hist = dict(loss=[], p=[], g=[], nw=[], lin=[])
    counts = np.zeros((2, len(obj.cases)), int)  # Newton / linear iterations this iterate

    def evaluate(zz, warms):
        (f, auxs), g = obj.value_and_grad(zz, warms, check=False)
        counts[0] += [int(a.newton_steps) for a in auxs]
        counts[1] += [int(a.linear_iterations) for a in auxs]
        ok = all(bool(a.ok) for a in auxs) and bool(jnp.all(jnp.isfinite(g)))
        return float(f), auxs, g, ok and np.isfinite(float(f))

    def record(zz, f, g):
        mat = obj.material(zz)
        hist["loss"].append(f)
        hist["p"].append([np.asarray(mat.E), np.asarray(mat.nu)])
        hist["g"].append(float(jnp.linalg.norm(g)))
        hist["nw"].append(counts[0].tolist())
        hist["lin"].append(counts[1].tolist())
        counts[:] = 0

    f, auxs, g, ok = evaluate(z, obj.initial_warms())
    if not ok:
        bad = [i for i, a in enumerate(auxs) if not bool(a.ok)]
        raise GradientError(f"forward solve failed at the initial guess in case(s) {bad}")
    warms = tuple(a.warm for a in auxs)
    record(z, f, g)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=max_iter, desc="fit", unit="it")
    k, reason = 0, "max_iter"
    try:
        while True:
            if bar is not None:
                bar.set_postfix(loss=f"{f:.3e}", grad=f"{hist['g'][-1]:.1e}", refresh=False)
            if hist["g"][-1] <= gtol:
                reason = "gtol"
                break
            if f <= ftol:
                reason = "ftol"
                break
            if k >= max_iter:
                break
            d, state = update(g, state, z)
            slope = float(jnp.vdot(g, d))
            if line_search and not slope < 0:  # not a descent direction: restart L-BFGS
                state = optimizer.init(z)
                d, state = update(g, state, z)
                slope = float(jnp.vdot(g, d))
            t, accepted = 1.0, None
            for _ in range(40):  # backtracking (Armijo) / step halving on failed solves
                if line_search and -slope * t <= 1e-12 * abs(f):
                    break  # the predicted decrease is below the loss's round-off: done
                zt = z + t * d
                ft, auxs, gt, ok = evaluate(zt, warms)
                if ok and (not line_search or ft <= f + 1e-4 * t * slope):
                    accepted = (zt, ft, auxs, gt)
                    break
                if ok and line_search:  # minimiser of the quadratic through f, slope, ft
                    tq = -slope * t * t / (2.0 * (ft - f - slope * t))
                    t = float(np.clip(tq, 0.1 * t, 0.5 * t))
                else:
                    t *= 0.5
            if accepted is None:
                reason = "roundoff" if line_search and -slope * t <= 1e-12 * abs(f) else "stalled"
                break
            step = float(t * jnp.max(jnp.abs(d)))
            z, f, auxs, g = accepted
            warms = tuple(a.warm for a in auxs)
            k += 1
            record(z, f, g)
            if bar is not None:
                bar.update(1)
            if step <= xtol:
                reason = "xtol"
                break
    finally:
        if bar is not None:
            bar.close()
    mat = obj.material(z)
    if obj.pm.regions is None:
        mat = Material(float(mat.E), float(mat.nu))
    else:
        mat = Material(np.asarray(mat.E), np.asarray(mat.nu))
    return FitResult(
        material=mat,
        E=mat.E,
        nu=mat.nu,
        loss=hist["loss"][-1],
        converged=reason in ("gtol", "ftol", "xtol", "roundoff"),
        stop_reason=reason,
        iterations=k,
        loss_history=np.array(hist["loss"]),
        param_history=np.array(hist["p"], dtype=np.float64),
        grad_norm_history=np.array(hist["g"]),
        newton_steps=np.array(hist["nw"]),
        linear_iterations=np.array(hist["lin"]),
        solutions=list(warms),
        z=np.asarray(z),
        wall_time=time.perf_counter() - t_start,
    )


def loss_landscape(
    cases: Sequence,
    E_values,
    nu_values,
    *,
    plane: str = "strain",
    settings: NewtonSettings = FIT_SETTINGS,
    adjoint: AdjointSettings = DEFAULT_ADJOINT,
    progress: bool = False,
) -> np.ndarray:
    """The weighted loss ``Σ_c w_c·loss_c`` on an (E, ν) grid (shared parameters).

    Forward solves only, in a snake order (ν ascending, then descending on the next E),
    each warm-started from its grid neighbour's solutions. A failed solve gives NaN.

    Args:
        cases: cases; E_values: ``(n_E,)`` [Pa]; nu_values: ``(n_nu,)``.
    Returns:
        ``(n_E, n_nu)`` array of losses.
    """
    cases = tuple(cases)
    E_values, nu_values = np.asarray(E_values, float), np.asarray(nu_values, float)
    dim = _default_mesh(cases).dim
    out = np.full((E_values.size, nu_values.size), np.nan)
    init = tuple(c.initial_warm() for c in cases)
    warms = init
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=out.size, desc="landscape", unit="solve")
    for i, E in enumerate(E_values):
        js = range(nu_values.size) if i % 2 == 0 else range(nu_values.size - 1, -1, -1)
        for j in js:
            params = Lame(*lame(E, nu_values[j], dim=dim, plane=plane))
            params = Lame(jnp.asarray(params.mu), jnp.asarray(params.lam))
            loss, auxs = _forward(params, cases, warms, settings, adjoint)
            if all(bool(a.ok) for a in auxs):
                out[i, j] = float(loss)
                warms = tuple(a.warm for a in auxs)
            else:
                warms = init
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()
    return out


def loss_hessian(
    cases: Sequence,
    material: Material,
    *,
    plane: str = "strain",
    h: float = 1e-4,
    settings: NewtonSettings = FIT_SETTINGS,
    adjoint: AdjointSettings = DEFAULT_ADJOINT,
) -> np.ndarray:
    """Hessian of the weighted loss w.r.t. ``(ln E, ν)`` at a shared material, ``(2, 2)``.

    Central differences (step ``h``) of the implicit-adjoint gradient, symmetrised. At a
    noise-free optimum (loss 0) it equals the Gauss–Newton matrix ``2 JᵀJ``, whose
    conditioning measures identifiability: e.g. ``H_νν·(H⁻¹)_νν = 1/(1 − ρ²)`` is the
    inflation of ν's variance by its correlation ρ with E (Bard 1974, *Nonlinear Parameter
    Estimation*, §7-5).
    """
    obj = make_objective(cases, material, plane=plane, settings=settings, adjoint=adjoint)

    def grad_theta(theta):  # gradient w.r.t. (ln E, nu) by the chain rule through z
        s = (theta[1] + 1.0) / 1.5
        z = jnp.asarray([theta[0] - np.log(float(material.E)), np.log(s) - np.log1p(-s)])
        g = np.asarray(obj.value_and_grad(z)[1])
        return np.array([g[0], g[1] / (1.5 * s * (1.0 - s))])  # db/dnu = 1 / (1.5 s (1 - s))

    theta = np.array([np.log(float(material.E)), float(material.nu)])
    H = np.zeros((2, 2))
    for i in range(2):
        e = np.zeros(2)
        e[i] = h
        H[:, i] = (grad_theta(theta + e) - grad_theta(theta - e)) / (2 * h)
    return 0.5 * (H + H.T)
