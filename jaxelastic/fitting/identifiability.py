"""Identifiability probes: the loss on a 2-D parameter grid and its Hessian at a point."""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..solvers import ImplicitAdjoint, Newton
from .elastic import LameOf, Material
from .objective import FIT_SOLVER, bind_solvers, cases_loss, make_objective

__all__ = ["loss_landscape", "loss_hessian"]


def _with(params, names, values):
    """``params`` (NamedTuple or dict) with the leaves ``names`` set to ``values``."""
    upd = dict(zip(names, values, strict=True))
    if isinstance(params, dict):
        return {**params, **upd}
    return params._replace(**upd)


def loss_landscape(
    cases: Sequence,
    a_values,
    b_values,
    *,
    params=None,
    fields: tuple[str, str] = ("E", "nu"),
    plane: str = "strain",
    solver: Newton = FIT_SOLVER,
    adjoint: ImplicitAdjoint = ImplicitAdjoint(),
    progress: bool = False,
) -> np.ndarray:
    """The weighted loss ``Σ_c w_c·loss_c`` on a grid of two shared parameters.

    Forward solves only, in a snake order (b ascending, then descending on the next a),
    each warm-started from its grid neighbour's solutions. A failed solve gives NaN.

    Args:
        cases: cases (:mod:`jaxelastic.fitting.cases`).
        a_values: ``(n_a,)`` values of ``fields[0]`` (default E [Pa]).
        b_values: ``(n_b,)`` values of ``fields[1]`` (default ν).
        params: the other parameters: a NamedTuple or dict (ψ's own pytree), or None /
            a :class:`Material` (then (E, ν) are mapped to Lamé, ``plane`` in 2D).
        fields: the two leaves on the grid.
        plane: 2D Material only.
        solver, adjoint: Newton and adjoint settings.
        progress: tqdm progress bar.
    Returns:
        ``(n_a, n_b)`` array of losses.
    """
    cases = tuple(cases)
    a_values, b_values = np.asarray(a_values, float), np.asarray(b_values, float)
    params = Material(1.0, 0.0) if params is None else params
    to_psi = LameOf(cases[0].mesh.dim, plane) if isinstance(params, Material) else None
    solvers = bind_solvers(cases, solver)
    out = np.full((a_values.size, b_values.size), np.nan)
    init = tuple(c.initial_warm() for c in cases)
    warms = init
    bar = None
    if progress:
        try:
            from tqdm.auto import tqdm

            bar = tqdm(total=out.size, desc="landscape", unit="solve")
        except ImportError:  # a lean install without tqdm: no bar
            bar = None
    for i, a in enumerate(a_values):
        js = range(b_values.size) if i % 2 == 0 else range(b_values.size - 1, -1, -1)
        for j in js:
            p = _with(params, fields, (a, b_values[j]))
            p = jax.tree_util.tree_map(jnp.asarray, p if to_psi is None else to_psi(p))
            loss, auxs = cases_loss(p, cases, warms, solvers, adjoint)
            if all(bool(x.ok) for x in auxs):
                out[i, j] = float(loss)
                warms = tuple(x.warm for x in auxs)
            else:
                warms = init
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()
    return out


def loss_hessian(
    cases: Sequence,
    params,
    *,
    transforms=None,
    fields=None,
    plane: str = "strain",
    h: float = 1e-4,
    solver: Newton = FIT_SOLVER,
    adjoint: ImplicitAdjoint = ImplicitAdjoint(),
) -> np.ndarray:
    """Hessian of the weighted loss w.r.t. the natural coordinates of the fitted parameters.

    The coordinates θ are ``ln p`` for ``Positive`` leaves and ``p`` otherwise, in leaf order
    (``(ln E, ν)`` for a :class:`Material`), at shared ``params``; ``(n, n)``. Central
    differences (step ``h``) of the implicit-adjoint gradient, symmetrised. At a noise-free
    optimum (loss 0) it equals the Gauss–Newton matrix ``2 JᵀJ``, whose conditioning
    measures identifiability: e.g. ``H_νν·(H⁻¹)_νν = 1/(1 − ρ²)`` is the inflation of ν's
    variance by its correlation ρ with E (Bard 1974, *Nonlinear Parameter Estimation*, §7-5).

    Args:
        cases: cases; params: the point (a Material or any ψ pytree, as in
            :func:`~jaxelastic.fitting.fit`); transforms, fields, plane: as in ``fit``;
        h: difference step in θ; solver, adjoint: Newton and adjoint settings.
    """
    obj = make_objective(
        cases,
        params,
        transforms=transforms,
        fields=fields,
        plane=plane,
        solver=solver,
        adjoint=adjoint,
    )
    pz = obj.pz
    leaves, treedef = jax.tree_util.tree_flatten(pz.init)
    fitted = [i for i, t in enumerate(pz.transforms) if t.fitted]
    sizes = pz.sizes()

    def params_of(theta):
        vals, off = list(leaves), 0
        for i in fitted:
            th = theta[off : off + sizes[i]].reshape(jnp.shape(leaves[i]))
            vals[i] = jnp.exp(th) if pz.transforms[i].log_scale else th
            off += sizes[i]
        return jax.tree_util.tree_unflatten(treedef, vals)

    def grad_theta(theta):  # chain rule through z(θ)
        z, vjp = jax.vjp(lambda th: pz.to_unconstrained(params_of(th)), jnp.asarray(theta))
        return np.asarray(vjp(obj.value_and_grad(z)[1])[0])

    theta = np.concatenate(
        [np.ravel(np.log(leaves[i]) if pz.transforms[i].log_scale else leaves[i]) for i in fitted]
    )
    n = theta.size
    H = np.zeros((n, n))
    for i in range(n):
        e = np.zeros(n)
        e[i] = h
        H[:, i] = (grad_theta(theta + e) - grad_theta(theta - e)) / (2 * h)
    return 0.5 * (H + H.T)
