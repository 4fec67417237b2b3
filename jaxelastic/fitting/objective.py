"""The fitting objective ``Σ_c w_c·loss_c(z) + regulariser(z)`` in unconstrained variables.

One jit-compiled value-and-gradient function serves :func:`~jaxelastic.fitting.fit`, its
line search, :func:`~jaxelastic.fitting.loss_hessian` and user code (benchmarks): it is
compiled once per case structure, parametrisation structure and solver. Each case's linear
solver is bound once, outside jit (:meth:`Case.bind <jaxelastic.fitting.cases.Case.bind>`).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..solvers import GradientError, ImplicitAdjoint, Newton, check_finite_gradients
from ..solvers.linear.auto import missing_host_package
from .elastic import Material, material_parametrization
from .parameters import Parametrization, make_parametrization
from .uncertainty import Uncertainty, gauss_newton_uncertainty

__all__ = [
    "FIT_DEVICE_MAX_DOFS",
    "FIT_DIRECT_MAX_DOFS",
    "FIT_SOLVER",
    "Objective",
    "bind_solvers",
    "cases_loss",
    "check_cases",
    "fit_linear",
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


def _residual_vector(z, pz: Parametrization, cases, warms, solvers, adjoint):
    """``(√w_c · r_c)`` of every case concatenated (``Σ r² = Σ w_c loss_c``), auxs."""
    params = pz.psi_params(z)
    rs, auxs = [], []
    for c, w, s in zip(cases, warms, solvers, strict=True):
        r, aux = c.residuals(params, w, s, adjoint)
        rs.append(jnp.sqrt(jnp.asarray(c.weight, r.dtype)) * r)
        auxs.append(aux)
    return jnp.concatenate(rs), tuple(auxs)


@functools.partial(jax.jit, static_argnums=(5,))
def _residual_jacobian(z, pz, cases, warms, solvers, adjoint):
    """Residuals ``(m,)``, their Jacobian ``(m, n)`` with respect to z (forward mode, all
    n directions at once: one solve per level, its n tangents one multi-right-hand-side
    solve) and the cases' auxs."""

    def fun(z):
        r, auxs = _residual_vector(z, pz, cases, warms, solvers, adjoint)
        return r, (r, auxs)

    J, (r, auxs) = jax.jacfwd(fun, has_aux=True)(z)
    return r, J, auxs


def fitted_values(pz: Parametrization, z) -> tuple[jax.Array, tuple[str, ...]]:
    """The fitted parameters at ``z`` in their own units, ``(p,)`` (region leaves one value
    per region), and their names (``"c10"``, ``"E[1]"``, …)."""
    leaves = jax.tree_util.tree_structure(pz.init).flatten_up_to(pz.from_unconstrained(z))
    vals, names = [], []
    for v, n, t in zip(leaves, pz.names, pz.transforms, strict=True):
        if not t.fitted:
            continue
        a = jnp.ravel(jnp.asarray(v))
        vals.append(a)
        names += [n] if jnp.ndim(v) == 0 else [f"{n}[{i}]" for i in range(a.size)]
    return jnp.concatenate(vals), tuple(names)


def cases_loss(params, cases, warms, solvers, adjoint):
    """Jit-compiled ``(Σ_c w_c·loss_c, auxs)`` at ψ parameters ``params`` (forward only).

    Args:
        params: ψ parameter pytree; cases: tuple of cases; warms: tuple of warm starts;
        solvers: tuple of prepared solvers (one per case, :func:`bind_solvers`; a pytree
            argument: their linear-solver states are traced, their settings static);
        adjoint: :class:`~jaxelastic.solvers.ImplicitAdjoint`.
    """
    return _forward(params, tuple(cases), tuple(warms), tuple(solvers), adjoint)


def check_cases(cases) -> None:
    """Raise TypeError, saying what to do, for a case that is not a JAX pytree or lacks
    the case protocol's methods (JAX's own error names neither the case nor the fix)."""
    for i, c in enumerate(cases):
        missing = [m for m in ("evaluate", "initial_warm", "mesh") if not hasattr(c, m)]
        if missing:
            raise TypeError(
                f"case {i} ({type(c).__name__}) lacks {', '.join(missing)} of the case "
                "protocol (jaxelastic.fitting.Case)"
            )
        leaves = jax.tree_util.tree_leaves(c)
        if len(leaves) == 1 and leaves[0] is c:
            raise TypeError(
                f"case {i} ({type(c).__name__}) is not a registered JAX pytree, so the "
                "compiled objective cannot take it as an argument: make it a frozen "
                "dataclass and register it with jax.tree_util.register_dataclass(cls, "
                "data_fields=[...arrays...], meta_fields=[...static settings...]), as "
                "jaxelastic.fitting.LoadCase does"
            )


FIT_DEVICE_MAX_DOFS = 3_000
"""``linear="auto"`` in a fit: matrix-free device CG up to this many dofs. The compiled
objective then holds no host callback, so JAX's persistent cache keeps it and a fresh
process loads it instead of compiling it (a host solver's ``jax.pure_callback`` makes
every process recompile the whole objective: 28 s of the 42 s of the small Mooney–Rivlin
fit of ``scripts/bench_first_result.py``, loaded machine)."""

FIT_DIRECT_MAX_DOFS = {2: 200_000, 3: 20_000}
"""``linear="auto"`` in a fit: sparse Cholesky above :data:`FIT_DEVICE_MAX_DOFS` up to this
many dofs (per dimension), where a single solve takes AMG-CG above 10k dofs in 3D
(:data:`~jaxelastic.solvers.linear.auto.AUTO_DIRECT_MAX_DOFS`). A fit solves the same
specimen many times to ``rtol = 1e-11``, where the exact Newton steps of a factorisation
converge in fewer steps than AMG-CG's inexact ones, and preconditions every adjoint solve
with the last factorisation. On the 10k-dof plate with a hole
(``scripts/bench_identification.py``, loaded machine, noisy wall times): a loss and
gradient at a new point took 3 Newton steps per level with it against 5 with AMG-CG, and
2.0 s against 9.8–13 s for 4 levels (minutes apart); for 20 levels, beside the code with
AMG-CG and a second solve per level, 12.7 s against 10.6 s per evaluation but 189 s
against 279 s for the whole fit with its uncertainty (docs/guide/compilation.md). 20k in
3D is a cautious bound, twice the single-solve one, until the two are compared on an
idle machine."""


def fit_linear(solver: Newton, mesh) -> Newton:
    """``solver`` with ``linear="auto"`` made the fit's choice for ``mesh`` (device CG up to
    :data:`FIT_DEVICE_MAX_DOFS`, sparse Cholesky up to :data:`FIT_DIRECT_MAX_DOFS`, else
    :func:`jaxelastic.solve`'s own choice); any other setting unchanged."""
    if not isinstance(solver, Newton) or solver.linear not in ("auto", None) or mesh is None:
        return solver
    dim, n = int(mesh.dim), int(mesh.n_dofs)
    if getattr(mesh, "halo", None) is not None:  # sharded: the device multigrid
        return solver
    if n <= FIT_DEVICE_MAX_DOFS:
        return solver.replace(linear="cg")
    if n <= FIT_DIRECT_MAX_DOFS.get(dim, 0) and missing_host_package("direct") is None:
        return solver.replace(linear="direct")
    return solver


def bind_solvers(cases, solver: Newton) -> tuple:
    """One :class:`~jaxelastic.solvers.PreparedSolver` per case: the Newton settings (with
    ``linear="auto"`` resolved for a fit, :func:`fit_linear`) with the linear solver's state
    for the case's mesh and mask (outside jit)."""
    bound = tuple(c.bind(fit_linear(solver, getattr(c, "mesh", None))) for c in cases)
    for i, (c, b) in enumerate(zip(cases, bound, strict=True)):
        leaves = jax.tree_util.tree_leaves(b)
        if len(leaves) == 1 and leaves[0] is b and not hasattr(b, "dtype"):
            raise TypeError(
                f"case {i} ({type(c).__name__}).bind returned {type(b).__name__}, which the "
                "compiled objective cannot take: return jaxelastic.solvers.prepare_solver("
                "solver, mesh, bc) for a case that solves, or None for one that does not"
            )
    return bound


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

    @property
    def sigma_known(self) -> bool:
        """Whether every case weighs its residuals by measurement standard deviations."""
        return all(bool(getattr(c, "sigma_known", False)) for c in self.cases)

    def linearize(self, z, warms=None):
        """``(r (m,), J (m, n), auxs)`` at ``z``: the residuals and their Jacobian with
        respect to the unconstrained variables, by one forward-mode pass through the solves
        (:func:`jax.jacfwd`: each solve once, its n implicit tangents one linear solve with
        n right-hand sides). When a solve fails, r and J are None and ``auxs[i].ok`` says
        which case failed.

        Raises:
            NotImplementedError: a case has no residuals.
        """
        z = jnp.asarray(z)
        warms = self.initial_warms() if warms is None else tuple(warms)
        a = self.adjoint
        fwd = ImplicitAdjoint(rtol=a.rtol, max_iter=a.max_iter, mode="forward")
        r, J, auxs = _residual_jacobian(z, self.pz, self.cases, warms, self.solvers, fwd)
        if not all(bool(a.ok) for a in auxs):
            return None, None, auxs
        return np.asarray(r), np.asarray(J), auxs

    def residuals_and_jacobian(self, z, warms=None, linearization=None):
        """``(r (m,), J (m, p))`` at ``z``: the residuals and their Jacobian with respect to
        the fitted parameters in their own units (:func:`fitted_values`), by one
        forward-mode pass through the solves (:meth:`linearize`), or from
        ``linearization``, ``(r, ∂r/∂z)`` already computed at ``z`` (no solve).

        Raises:
            GradientError: a solve failed. NotImplementedError: a case has no residuals.
        """
        z = jnp.asarray(z)
        if linearization is None:
            r, Jz, auxs = self.linearize(z, warms)
            if r is None or Jz is None:
                bad = [i for i, a in enumerate(auxs) if not bool(a.ok)]
                raise GradientError(f"forward solve failed in case(s) {bad} at the optimum")
        else:
            r, Jz = (np.asarray(a) for a in linearization)
        D = np.asarray(jax.jacfwd(lambda z: fitted_values(self.pz, z)[0])(z))  # dθ/dz
        return r, np.linalg.solve(D.T, Jz.T).T

    def uncertainty(
        self, z, warms=None, linearization=None
    ) -> tuple[Uncertainty, tuple[str, ...], np.ndarray, Any]:
        """``(Uncertainty, names, values, residuals)`` of the fitted parameters at ``z``
        (the residual vector of :meth:`residuals_and_jacobian`, from ``linearization``
        ``(r, ∂r/∂z)`` at ``z`` where given; Gauss–Newton,
        :func:`~jaxelastic.fitting.gauss_newton_uncertainty`; scaled by the reduced χ²
        unless every case's σ are measurement standard deviations; the regulariser is
        not part of it)."""
        r, J = self.residuals_and_jacobian(z, warms, linearization)
        vals, names = fitted_values(self.pz, jnp.asarray(z))
        unc = gauss_newton_uncertainty(J, r, known_sigma=self.sigma_known)
        return unc, names, np.asarray(vals), r


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
    check_cases(cases)
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
