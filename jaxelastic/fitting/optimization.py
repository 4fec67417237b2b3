"""Material identification: :func:`fit` and its :class:`FitResult`.

:func:`fit` minimises ``Σ_c w_c·loss_c + regulariser`` over the unconstrained variables of
a :class:`~jaxelastic.fitting.parameters.Parametrization` (any ψ parameter pytree, or
(E, ν) through :class:`~jaxelastic.fitting.Material`) with optax — L-BFGS directions with a
host backtracking line search by default, or any optax transformation — or, for a sum of
squared residuals, by Levenberg–Marquardt (``optimizer="lm"``: the Gauss–Newton model from
forward-mode Jacobians through the solves, the iteration of
:mod:`jaxelastic.fitting.least_squares`), warm-starting every forward solve from the
previous iterate's solution of the same case.
"""

from __future__ import annotations

import functools
import time
import warnings
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..solvers import GradientError, ImplicitAdjoint, Newton, Status
from .cases import Case
from .elastic import Material
from .least_squares import STOP_REASONS, LMSettings, LMState, lm_iterate
from .objective import FIT_SOLVER, Objective, fitted_values, make_objective
from .uncertainty import Uncertainty

__all__ = ["FitResult", "fit", "describe_failure"]

_CONVERGED = ("gtol", "ftol", "xtol", "roundoff", "predicted_decrease")
_ARMIJO = 1e-4
_ROUNDOFF = 1e-12  # predicted decrease below this × loss: no measurable progress possible


@functools.lru_cache(maxsize=16)  # bounded: keyed by learning rates
def _named_optimizer(name: str, learning_rate: float):
    import optax

    if name == "lbfgs":
        return optax.lbfgs(linesearch=None)
    if name == "adam":
        return optax.adam(learning_rate)
    raise ValueError(f"optimizer must be 'lbfgs', 'adam' or an optax transformation, got {name!r}")


@functools.lru_cache(maxsize=16)
def _update_fn(optimizer):
    """The optimiser's update, compiled; traced under JAX's standard dtype promotion (optax's
    own arithmetic, e.g. Adam's bias correction, mixes Python floats with int32 counters,
    which a session running ``jax_numpy_dtype_promotion="strict"`` would refuse)."""
    compiled = jax.jit(optimizer.update)

    def update(*args):
        with jax.numpy_dtype_promotion("standard"):
            return compiled(*args)

    return update


class FitResult(NamedTuple):
    """Result of :func:`fit`.

    Attributes:
        material: the fitted parameters in ``init``'s structure (region form: floats for
            shared scalars, ``(n_regions,)`` arrays per region), e.g. a :class:`Material`.
        E, nu: the fitted (E, ν) when ``init`` is a :class:`Material`, else None.
        loss: final loss.
        converged: a stopping criterion met (else ``max_iter`` reached, stalled or failed
            solves).
        stop_reason: ``"gtol"``, ``"ftol"``, ``"xtol"``, ``"roundoff"`` (the line search's
            predicted decrease fell below 1e-12 × loss with every trial solved: no
            measurable progress is possible; counted as converged),
            ``"predicted_decrease"`` (Levenberg–Marquardt: at an accepted point the
            undamped Gauss–Newton step predicts a decrease ≤ ``rtol``·cost + ``atol``;
            converged), ``"solve_failed"`` (the last line search, or the rejected
            Levenberg–Marquardt steps since the last two accepted points, ran into
            trial points whose solves failed: not converged, see ``failures``),
            ``"stalled"`` (no acceptable step), ``"max_iter"`` or ``"callback"`` (the
            callback asked to stop).
        iterations: optimiser iterations k (Levenberg–Marquardt: accepted steps).
        loss_history: ``(k + 1,)`` loss at each iterate.
        param_history: every leaf per iterate, in leaf order: ``(k + 1, n_leaves)`` for
            scalars (``(k + 1, 2)`` for (E, ν)), ``(k + 1, n_leaves, n_regions)`` with
            regions, or ``(k + 1, n_values)`` (leaves raveled) when shapes differ.
        grad_norm_history: ``(k + 1,)`` gradient norm w.r.t. the unconstrained variables.
        newton_steps: ``(k + 1, n_cases)`` Newton iterations of each case's forward solve(s)
            per iteration (summed over its line-search trials; row 0: the initial guess).
        linear_iterations: ``(k + 1, n_cases)`` linear-solver iterations, likewise.
        solutions: final warm start (equilibrium positions) per case.
        z: final unconstrained vector.
        wall_time: seconds, including compilation.
        failures: one dict per trial point whose solves failed: ``iteration``, ``case``
            (index), ``status`` (a :class:`~jaxelastic.solvers.Status` name), ``level``
            (load level of a :class:`~jaxelastic.fitting.LoadPathCase`, else None) and
            ``params`` (name → value of the fitted parameters there).
        names: names of the fitted parameters (``"E"``, ``"c10"``, ``"E[1]"``, …).
        uncertainty: the Gauss–Newton :class:`~jaxelastic.fitting.Uncertainty` at the
            optimum in the order of ``names`` (None when not computed).
        residuals: ``(m,)`` the cases' residual vectors at the optimum, concatenated in
            case order (``√w·(pred − data)/σ`` for measurements), with the uncertainty.
        evaluations: trial points evaluated (each a pass through every case's solves: a
            loss and gradient, or a Levenberg–Marquardt linearisation), line-search and
            rejected trials included; the uncertainty's pass, if any, not.
    """

    material: Any
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
    failures: tuple = ()
    names: tuple = ()
    uncertainty: Uncertainty | None = None
    residuals: np.ndarray | None = None
    evaluations: int = 0

    @property
    def params(self):
        """Alias of :attr:`material` (the fitted parameter pytree)."""
        return self.material

    @property
    def standard_errors(self) -> dict:
        """Fitted parameter name → standard error (empty without an uncertainty)."""
        if self.uncertainty is None:
            return {}
        return dict(zip(self.names, self.uncertainty.standard_errors.tolist(), strict=True))


def describe_failure(f: dict) -> str:
    """One line naming a failed trial: case, status, load level and parameters."""
    level = "" if f["level"] is None else f" at load level {f['level']}"
    at = ", ".join(f"{k} = {v:.6g}" for k, v in f["params"].items())
    return f"case {f['case']}: {f['status']}{level} (iteration {f['iteration']}, at {at})"


def _param_row(params) -> np.ndarray:
    leaves = [np.asarray(v, dtype=np.float64) for v in jax.tree_util.tree_leaves(params)]
    try:
        return np.stack(np.broadcast_arrays(*leaves))
    except ValueError:
        return np.concatenate([v.ravel() for v in leaves])


def _reported(params):
    """Region-form parameters as host values: floats for scalars, NumPy arrays otherwise."""
    return jax.tree_util.tree_map(lambda v: float(v) if np.ndim(v) == 0 else np.asarray(v), params)


class _Tracker:
    """Evaluations of the objective at trial points, with per-iterate counters and history."""

    def __init__(self, obj: Objective):
        self.obj = obj
        self.counts = np.zeros((2, len(obj.cases)), int)  # Newton / linear its this iterate
        self.evaluations = 0  # trial points evaluated
        self.hist = dict(loss=[], p=[], g=[], nw=[], lin=[])
        self.failures: list[dict] = []
        # (z, r, ∂r/∂z) at the last accepted Levenberg–Marquardt point: the uncertainty's
        # Jacobian at the optimum, without another pass through the solves
        self.linearization: tuple | None = None

    def evaluate(self, z, warms):
        """``(loss, auxs, grad, ok)`` at z; ok: every solve converged, all finite."""
        (f, auxs), g = self.obj.value_and_grad(z, warms, check=False)
        self.evaluations += 1
        self.counts[0] += [int(a.newton_steps) for a in auxs]
        self.counts[1] += [int(a.linear_iterations) for a in auxs]
        solved = [bool(a.ok) for a in auxs]
        if not all(solved):
            self._failed(z, auxs, solved)
        ok = all(solved) and bool(jnp.all(jnp.isfinite(g)))
        return float(f), auxs, g, ok and np.isfinite(float(f))

    def linearize(self, z, warms):
        """``(r, J, auxs, ok)`` at z (:meth:`Objective.linearize`); ok: every solve
        converged (r and J are None otherwise)."""
        r, J, auxs = self.obj.linearize(z, warms)
        self.evaluations += 1
        self.counts[0] += [int(a.newton_steps) for a in auxs]
        self.counts[1] += [int(a.linear_iterations) for a in auxs]
        solved = [bool(a.ok) for a in auxs]
        if not all(solved):
            self._failed(z, auxs, solved)
        return r, J, auxs, r is not None

    def _failed(self, z, auxs, solved) -> None:
        vals, names = fitted_values(self.obj.pz, jnp.asarray(z))
        params = dict(zip(names, np.asarray(vals).tolist(), strict=True))
        for i, (a, ok) in enumerate(zip(auxs, solved, strict=True)):
            if ok:
                continue
            st = getattr(a, "status", None)
            level = getattr(a, "level", None)
            name = "failed" if st is None else Status(int(st)).name
            lv = None if level is None or int(level) < 0 else int(level)
            it = len(self.hist["loss"])
            self.failures.append(dict(iteration=it, case=i, status=name, level=lv, params=params))

    def record(self, z, f, g):
        h = self.hist
        h["loss"].append(f)
        h["p"].append(_param_row(self.obj.params(z)))
        h["g"].append(float(jnp.linalg.norm(g)))
        h["nw"].append(self.counts[0].tolist())
        h["lin"].append(self.counts[1].tolist())
        self.counts[:] = 0


def _direction(update, optimizer, g, state, z, line_search: bool):
    """Optimiser update ``d`` and slope ``gᵀd``; L-BFGS restarts if d is not descending."""
    d, state = update(g, state, z)
    slope = float(jnp.vdot(g, d))
    if line_search and not slope < 0:
        state = optimizer.init(z)
        d, state = update(g, state, z)
        slope = float(jnp.vdot(g, d))
    return d, state, slope


def _step(tr: _Tracker, z, f, d, slope, warms, line_search: bool):
    """Backtracking Armijo line search (L-BFGS) or step halving on failed solves (others).

    Returns ``(accepted, t)``: accepted is ``(z, f, auxs, g)`` or None (no acceptable
    step), t the last step length tried; ``tr.failures`` records every failed trial.
    """
    t = 1.0
    for _ in range(40):
        if line_search and -slope * t <= _ROUNDOFF * abs(f):
            return None, t  # the predicted decrease is below the loss's round-off: done
        zt = z + t * d
        ft, auxs, gt, ok = tr.evaluate(zt, warms)
        if ok and (not line_search or ft <= f + _ARMIJO * t * slope):
            return (zt, ft, auxs, gt), t
        if ok and line_search:  # minimiser of the quadratic through f, slope, ft
            tq = -slope * t * t / (2.0 * (ft - f - slope * t))
            t = float(np.clip(tq, 0.1 * t, 0.5 * t))
        else:
            t *= 0.5
    return None, t


def _optimize(tr: _Tracker, optimizer, line_search, z, tol, callback, max_iter, bar):
    """The optimiser loop from z; returns ``(z, iterations, stop reason, warm starts)``."""
    update_jit = _update_fn(optimizer)

    def update(g, state, z):
        try:
            return update_jit(g, state, z)
        except (TypeError, KeyError) as e:  # e.g. optax.lbfgs() with its zoom line search
            raise ValueError(
                "the optax optimizer needs extra arguments (value / value_fn of a line "
                f"search?); use optimizer='lbfgs' for L-BFGS ({e})"
            ) from e

    gtol, ftol, xtol = tol
    f, auxs, g, ok = tr.evaluate(z, tr.obj.initial_warms())
    if not ok:
        what = "; ".join(describe_failure(x) for x in tr.failures) or "non-finite loss/gradient"
        raise GradientError(
            f"forward solve failed at the initial guess: {what}. Start closer to the data "
            "(initial parameters), or apply the load in more levels"
        )
    warms = tuple(a.warm for a in auxs)
    tr.record(z, f, g)
    state = optimizer.init(z)
    k = 0
    while True:
        if bar is not None:
            bar.set_postfix(loss=f"{f:.3e}", grad=f"{tr.hist['g'][-1]:.1e}", refresh=False)
        if tr.hist["g"][-1] <= gtol:
            return z, k, "gtol", warms
        if f <= ftol:
            return z, k, "ftol", warms
        if k >= max_iter:
            return z, k, "max_iter", warms
        d, state, slope = _direction(update, optimizer, g, state, z, line_search)
        n_failed = len(tr.failures)
        accepted, t = _step(tr, z, f, d, slope, warms, line_search)
        if accepted is None:
            if len(tr.failures) > n_failed:  # the trials failed: never convergence
                return z, k, "solve_failed", warms
            small = line_search and -slope * t <= _ROUNDOFF * abs(f)
            return z, k, "roundoff" if small else "stalled", warms
        z, f, auxs, g = accepted
        warms = tuple(a.warm for a in auxs)
        k += 1
        tr.record(z, f, g)
        if bar is not None:
            bar.update(1)
        if float(t * jnp.max(jnp.abs(d))) <= xtol:
            return z, k, "xtol", warms
        if callback is not None and callback(k, tr.obj.params(z), f):
            return z, k, "callback", warms


def _levenberg_marquardt(tr: _Tracker, settings: LMSettings, z0, callback, max_iter, bar):
    """Levenberg–Marquardt from z0 (:func:`~jaxelastic.fitting.least_squares.lm_iterate`);
    returns ``(z, accepted iterations, stop reason, warm starts)``."""
    warms: tuple = tr.obj.initial_warms()
    trial_warms: tuple = warms
    # failed trials since the last accepted point and in the window before it; accepted steps
    failed = before = k = 0

    def linearize(z):
        nonlocal trial_warms, failed
        r, J, auxs, ok = tr.linearize(z, warms)
        trial_warms = tuple(a.warm for a in auxs)
        failed += 0 if ok else 1
        return r, J, ok

    def accepted(s: LMState) -> bool:
        nonlocal warms, failed, before, k
        warms, failed, before = trial_warms, 0, failed
        r, J = np.asarray(s.r), np.asarray(s.J)
        tr.linearization = (np.asarray(s.z), r, J)
        f = float(r @ r)  # the loss Σ w_c·loss_c = ‖r‖²
        first = int(s.iteration) == 0
        if not first:
            k += 1
            if bar is not None:
                bar.update(1)
        tr.record(s.z, f, 2.0 * J.T @ r)
        if bar is not None:
            bar.set_postfix(loss=f"{f:.3e}", grad=f"{tr.hist['g'][-1]:.1e}", refresh=False)
        if first or callback is None:
            return False
        return bool(callback(k, tr.obj.params(s.z), f))

    s, stopped = lm_iterate(linearize, z0, settings._replace(max_iterations=max_iter), accepted)
    reason = STOP_REASONS[int(s.status)]
    if reason == "nonfinite":
        what = "; ".join(describe_failure(x) for x in tr.failures) or "non-finite residuals"
        raise GradientError(
            f"forward solve failed at the initial guess: {what}. Start closer to the data "
            "(initial parameters), or apply the load in more levels"
        )
    if stopped:
        reason = "callback"
    elif reason == "converged":
        reason = "predicted_decrease"
    elif reason == "max_iterations":
        reason = "max_iter"
    elif reason == "stalled" and failed + before:  # the last steps ran into failed solves
        reason = "solve_failed"
    return jnp.asarray(s.z), k, reason, warms


def _lm_settings(optimizer, regularization: float, cases) -> LMSettings | None:
    """The :class:`LMSettings` of ``optimizer`` (None: not Levenberg–Marquardt); refuses
    what a sum of squared residuals cannot express."""
    if isinstance(optimizer, LMSettings):
        settings = optimizer
    elif isinstance(optimizer, str) and optimizer == "lm":
        settings = LMSettings()
    else:
        return None
    if regularization:
        raise ValueError(
            "optimizer='lm' minimises a sum of squared residuals, which the regulariser is "
            "not: use optimizer='lbfgs' with regularization > 0"
        )
    for i, c in enumerate(cases):
        method = getattr(type(c), "residuals", None)
        if method is None or method is Case.residuals:
            raise ValueError(
                f"optimizer='lm' needs residuals of every case; case {i} "
                f"({type(c).__name__}) defines no residuals(): use optimizer='lbfgs'"
            )
    return settings


def fit(
    cases: Sequence,
    init,
    *,
    transforms=None,
    regions=None,
    fields: Sequence[str] | None = None,
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
    solver: Newton = FIT_SOLVER,
    adjoint: ImplicitAdjoint = ImplicitAdjoint(),
    progress: bool = False,
    callback=None,
    uncertainty: bool | None = None,
) -> FitResult:
    """Fit material parameters (any ψ pytree, or E and ν) to observations in several cases.

    Minimises ``Σ_c w_c·loss_c + regulariser`` over unconstrained variables (E = E₀·exp(a),
    ν = −1 + 1.5·sigmoid(b) for a :class:`Material`; the leaves' transforms otherwise); each
    forward solve starts from the previous iterate's solution of the same case.

    Args:
        cases: :class:`~jaxelastic.fitting.LoadCase` s, ``TrajectoryCase`` s or any objects
            following the case protocol (:mod:`jaxelastic.fitting.cases`).
        init: initial parameters: a :class:`Material` (scalars, or ``(n_regions,)``
            arrays), any ψ parameter pytree (e.g. a user ``NamedTuple``), or a
            :class:`~jaxelastic.fitting.Parametrization`.
        transforms: for a pytree ``init``: one transform or a tree of them (``Positive()``,
            ``Bounded(lo, hi)``, ``Free()``, ``Fixed()``); default ``Positive()``.
        regions: None (shared values), ``(n_cells,)`` int labels ``0..R−1``
            (piecewise-constant fields, e.g. a two-material bar), ``"cells"``, or a tree of
            those per leaf.
        fields: names of the leaves to fit (default: ``("E", "nu")`` for a Material, every
            non-Fixed leaf otherwise); the others stay at ``init``.
        plane: 2D Material only, ``"strain"`` or ``"stress"``.
        optimizer: ``"lbfgs"``: the optax L-BFGS direction (``optax.lbfgs(linesearch=None)``)
            with a backtracking Armijo line search on the host (every trial point is one
            compiled value-and-gradient evaluation, reused as the next iterate, so the
            solver is compiled once); ``"adam"`` (``optax.adam(learning_rate)``) or any
            optax ``GradientTransformation``: updates applied as they come, halved only
            when a forward solve fails; ``"lm"`` or an
            :class:`~jaxelastic.fitting.LMSettings`: Levenberg–Marquardt on the cases'
            residuals (every case needs ``residuals()``; no regulariser), each trial point
            linearised by one forward-mode pass through the solves (every fitted
            value's tangent at once, :meth:`Objective.linearize`), stopped by the
            settings' tests (``rtol``, ``atol``, ``max_rejections``;
            :mod:`jaxelastic.fitting.least_squares`), not by ``gtol``/``ftol``/``xtol``.
            Few parameters, a least-squares χ²: it converges quadratically near a
            well-fitting optimum where L-BFGS crawls on a flat one, and its Jacobian at
            the optimum is the uncertainty's.
        learning_rate: Adam's step in the unconstrained variables.
        max_iter: maximum optimiser iterations (Levenberg–Marquardt: accepted and
            rejected steps together).
        gtol: stop (converged) when ``‖∇_z loss‖ ≤ gtol``.
        ftol: stop (converged) when ``loss ≤ ftol``.
        xtol: stop (converged) when an update moves z by ``≤ xtol`` (max norm).
        regularization, reg_kind: weight and kind (``"tikhonov"``/``"tv"``) of the
            smoothness term over adjacent regions (:mod:`jaxelastic.fitting.parameters`).
        mesh: the mesh region labels refer to (default: the first case's ``mesh``).
        solver: :class:`~jaxelastic.solvers.Newton` settings (keep ``rtol`` tight, ≤ 1e-10,
            for accurate gradients; its linear solver is bound to each case once).
        adjoint: :class:`~jaxelastic.solvers.ImplicitAdjoint` settings.
        progress: show a tqdm progress bar with the loss and gradient norm.
        callback: called after every accepted iteration with ``(k, params, loss)``
            (params in ``init``'s structure); return True to stop there (stop reason
            ``"callback"``, e.g. on Ctrl-C, keeping every iterate so far).
        uncertainty: compute the Gauss–Newton uncertainty at the optimum
            (:attr:`FitResult.uncertainty`; one forward-mode pass through the solves, or
            none after Levenberg–Marquardt, whose Jacobian at the optimum it reuses);
            default None: when every case weighs its residuals by
            measurement σ (e.g. :class:`~jaxelastic.fitting.LoadPathCase`).

    Long because: the docstring documents 19 arguments; the body is ten lines.

    Raises:
        GradientError: a forward solve at the initial guess failed.
    """
    t_start = time.perf_counter()
    kw: dict[str, Any] = dict(transforms=transforms, regions=regions, fields=fields, mesh=mesh)
    kw.update(plane=plane, regularization=regularization, reg_kind=reg_kind)
    obj = make_objective(cases, init, solver=solver, adjoint=adjoint, **kw)
    tr = _Tracker(obj)
    lm = _lm_settings(optimizer, regularization, obj.cases)
    if lm is not None:
        run = functools.partial(_levenberg_marquardt, tr, lm, obj.z0, callback)
    else:
        line_search = optimizer == "lbfgs"
        if isinstance(optimizer, str):
            optimizer = _named_optimizer(optimizer, float(learning_rate))
        tols = (gtol, ftol, xtol)
        run = functools.partial(_optimize, tr, optimizer, line_search, obj.z0, tols, callback)
    z, k, reason, warms = _with_progress(run, max_iter, progress)
    if reason == "solve_failed":
        last = [describe_failure(f) for f in tr.failures[-len(obj.cases) :]]
        warnings.warn(
            "fit stopped without converging: the solves of its last trial steps "
            f"failed ({'; '.join(last)}); the material may be unstable there: bound the "
            "parameters (transforms), start elsewhere or use more load levels",
            RuntimeWarning,
            stacklevel=2,
        )
    unc = r = None
    if uncertainty or (uncertainty is None and obj.sigma_known):
        lin = tr.linearization
        same = lin is not None and np.array_equal(lin[0], np.asarray(z))
        unc, _, _, r = obj.uncertainty(z, warms, lin[1:] if same and lin is not None else None)
    res = _result(tr, z, k, reason, warms, time.perf_counter() - t_start)
    return res._replace(uncertainty=unc, residuals=r)


def _with_progress(run, max_iter: int, progress: bool):
    """``run(max_iter, bar)`` with a tqdm bar (or None), closed whatever happens."""
    bar = None
    if progress:
        try:
            from tqdm.auto import tqdm

            bar = tqdm(total=max_iter, desc="fit", unit="it")
        except ImportError:  # a lean install without tqdm: no bar
            bar = None
    try:
        return run(max_iter, bar)
    finally:
        if bar is not None:
            bar.close()


def _result(tr: _Tracker, z, k: int, reason: str, warms, wall: float) -> FitResult:
    h = tr.hist
    params = _reported(tr.obj.params(z))
    is_mat = isinstance(params, Material)
    return FitResult(
        material=params,
        E=params.E if is_mat else None,
        nu=params.nu if is_mat else None,
        loss=h["loss"][-1],
        converged=reason in _CONVERGED,
        stop_reason=reason,
        iterations=k,
        loss_history=np.array(h["loss"]),
        param_history=np.array(h["p"], dtype=np.float64),
        grad_norm_history=np.array(h["g"]),
        newton_steps=np.array(h["nw"]),
        linear_iterations=np.array(h["lin"]),
        solutions=list(warms),
        z=np.asarray(z),
        wall_time=wall,
        failures=tuple(tr.failures),
        names=fitted_values(tr.obj.pz, jnp.asarray(z))[1],
        evaluations=tr.evaluations,
    )
