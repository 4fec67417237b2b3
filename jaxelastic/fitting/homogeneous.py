"""Homogeneous test curves of any ψ without a mesh, and fitting them: :func:`fit_curves`.

A material is ``psi(F, params) -> scalar`` for one ``(3, 3)`` F; the four classical
homogeneous tests of rubber are evaluated from it directly (Treloar 1975, *The Physics of
Rubber Elasticity*, ch. 10; Ogden 1997, *Non-linear Elastic Deformations*, §7.2), with
``G = ∂ψ/∂F`` by autodiff and the nominal (first Piola–Kirchhoff) stress ``P`` [stress] in
the loaded direction as output:

=============  =================================  ==========================
test           F                                  output
=============  =================================  ==========================
uniaxial       diag(λ, b, b)                      P₁₁ (P₂₂ = P₃₃ = 0)
equibiaxial    diag(λ, λ, b)                      P₁₁ = P₂₂ (P₃₃ = 0)
pure_shear     diag(λ, 1, b)                      P₁₁ (P₃₃ = 0; λ₂ = 1 held)
simple_shear   I + γ e₁⊗e₂                        P₁₂ (F fully prescribed)
=============  =================================  ==========================

The lateral stretch ``b`` is free (its face is traction-free):

* **incompressible** (``incompressible=True``, the default): ``b`` follows from det F = 1
  (λ^-½, λ⁻², λ⁻¹) and the stress is ``P = G − p F⁻ᵀ`` with the Lagrange multiplier p
  fixed in closed form by the free face P₃₃ = 0, ``p = b G₃₃``, so ``P₁₁ = G₁₁ − p/λ``.
  Any term of ψ that depends on J alone contributes a multiple of F⁻ᵀ at J = 1 and is
  absorbed by p: the volumetric term ``U(J)`` of the library's rubber laws
  (:mod:`jaxelastic.materials.rubber`, ``U′(1) = 0``) drops out, whatever κ is, and the
  result is the exactly incompressible response of the isochoric part. In simple
  shear ``(F⁻ᵀ)₁₂ = 0``, so ``P₁₂ = G₁₂``.
* **compressible** (``incompressible=False``): ``b`` minimises ψ along the free direction,
  ``∂ψ/∂b = 0`` (the free face's stress vanishes), found per stretch by a safeguarded
  Newton iteration in ``ln b`` from the incompressible value (:class:`FreeStretchNewton`),
  vmapped over the stretches and differentiable by the implicit function theorem
  (``lax.custom_root``); the response then depends on the bulk modulus κ in ``params``.
  Simple shear keeps F prescribed (no free stretch, det F = 1), and ``(F⁻ᵀ)₁₂ = 0``: both
  modes give the same P₁₂.

**The bulk modulus is part of the fitted model.** Constants fitted with
``incompressible=False`` hold for the κ they were fitted with (the default fields hold κ
fixed; pass it in ``fields`` to fit it, which these tests barely inform); with
``incompressible=True`` they are the κ → ∞ limit, and a finite-element model using them
with a finite κ is slightly softer in tension. The principal tests assume an isotropic
material (uniaxial tension: the two lateral directions are equivalent; the free face is
the one normal to e₃).

A fitting case is a :class:`StressCurve` (:func:`stress_curve` validates one);
:func:`fit_curves` fits any parameters of ψ to several curves jointly by
:func:`~jaxelastic.fitting.least_squares.levenberg_marquardt` and reports the parameters,
their Gauss–Newton standard errors and the RMS relative stress error of each curve.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .least_squares import LeastSquaresResult, LMSettings, levenberg_marquardt
from .parameters import Parametrization, make_parametrization
from .transforms import Free

__all__ = [
    "TESTS",
    "FreeStretchNewton",
    "HomogeneousResponse",
    "homogeneous_deformation",
    "nominal_stress",
    "StressCurve",
    "stress_curve",
    "CurveFit",
    "fit_curves",
]

TESTS = ("uniaxial", "equibiaxial", "pure_shear", "simple_shear")
"""The homogeneous tests, by name."""


class FreeStretchNewton(NamedTuple):
    """Settings of the free-stretch Newton iteration of the compressible tests.

    Attributes:
        xtol: converged when a Newton step changes ``ln b`` by at most ``xtol`` (a relative
            change of the free stretch; at least 64 ulps of the dtype) at a point where
            ``∂²ψ/∂(ln b)² > 0``.
        max_iterations: iterations before reporting failure.
        max_step: largest change of ``ln b`` per iteration (safeguard).
    """

    xtol: float = 1e-12
    max_iterations: int = 60
    max_step: float = 0.5


class HomogeneousResponse(NamedTuple):
    """Response of a homogeneous test at ``n`` amounts.

    Attributes:
        stress: ``(n,)`` nominal stress P₁₁ (P₁₂ in simple shear) [ψ's stress unit].
        lateral: ``(n,)`` the free stretch b (1 in simple shear).
        ok: ``(n,)`` bool: ψ and P finite and, if compressible, the free stretch converged.
    """

    stress: jax.Array
    lateral: jax.Array
    ok: jax.Array


def _check_test(test: str) -> None:
    if test not in TESTS:
        raise ValueError(f"unknown test {test!r}; expected one of {TESTS}")


def _code(test: str) -> int:
    _check_test(test)
    return TESTS.index(test)


def _deformation(code, amount, lateral):
    """F ``(3, 3)`` of test number ``code`` (index in :data:`TESTS`), traceable in code."""
    shear = code == 3
    one = jnp.ones_like(amount)
    d1 = jnp.where(shear, one, amount)
    d2 = jnp.where(code == 1, amount, jnp.where(code == 0, lateral, one))
    d3 = jnp.where(shear, one, lateral)
    F = jnp.diag(jnp.stack([d1, d2, d3]))
    return F.at[0, 1].set(jnp.where(shear, amount, 0.0))


def homogeneous_deformation(test: str, amount, lateral) -> jax.Array:
    """F ``(3, 3)`` of a test at one amount (λ, or γ in simple shear) and free stretch b."""
    amount = jnp.asarray(amount)
    return _deformation(_code(test), amount, jnp.asarray(lateral, amount.dtype))


def _incompressible_lateral(code, lam):
    """b with det F = 1 (1 in simple shear); ``lam`` is replaced by 1 there (γ may be ≤ 0)."""
    lam = jnp.where(code == 3, jnp.ones_like(lam), lam)
    return jnp.where(code == 0, lam**-0.5, jnp.where(code == 1, lam**-2.0, 1.0 / lam))


def _incompressible_point(psi, params, code, lam):
    """(P, b, ok) of one amount, exactly incompressible (module docstring)."""
    b = _incompressible_lateral(code, lam)
    w, G = jax.value_and_grad(psi)(_deformation(code, lam, b), params)
    p = b * G[2, 2]  # the Lagrange multiplier from the free face P₃₃ = 0
    lam_safe = jnp.where(code == 3, jnp.ones_like(lam), lam)
    P = jnp.where(code == 3, G[0, 1], G[0, 0] - p / lam_safe)
    return P, b, jnp.isfinite(w) & jnp.isfinite(P)


def _newton_solve(newton: FreeStretchNewton):
    """The ``solve`` of ``lax.custom_root``: a safeguarded scalar Newton iteration."""

    def solve(f, s0):
        def step(carry):
            s, _, k, _ = carry
            r, dr = jax.jvp(f, (s,), (jnp.ones_like(s),))
            newton_step = -r / jnp.where(dr > 0, dr, 1.0)
            h = jnp.where(dr > 0, newton_step, -0.25 * jnp.sign(r))  # descent if not convex
            h = jnp.clip(h, -newton.max_step, newton.max_step)
            good = jnp.isfinite(h)
            xtol = jnp.maximum(newton.xtol, 64.0 * jnp.finfo(s.dtype).eps)  # float32: 7.6e-6
            done = good & (dr > 0) & (jnp.abs(h) <= xtol)
            return jnp.where(good, s + h, s), done, k + 1, ~good

        def cond(carry):
            _, done, k, bad = carry
            return ~done & ~bad & (k < newton.max_iterations)

        init = (s0, jnp.asarray(False), jnp.zeros((), jnp.int32), jnp.asarray(False))
        s, done, _, _ = jax.lax.while_loop(cond, step, init)
        return s, jnp.where(done, 1.0, 0.0).astype(s.dtype)  # a float aux: custom_root's
        # JVP gives a boolean aux a boolean tangent, which JAX then refuses

    return solve


def _compressible_point(psi, params, code, lam, newton: FreeStretchNewton):
    """(P, b, ok) of one amount with the free stretch from ∂ψ/∂b = 0 (module docstring).

    Simple shear has no free stretch: its root function is ``s`` itself (root ``b = 1``).
    """
    shear = code == 3

    def energy(s):
        w = psi(_deformation(code, lam, jnp.exp(s)), params)
        return jnp.where(shear, 0.5 * s * s, w)

    s0 = jnp.log(_incompressible_lateral(code, lam))
    s, done = jax.lax.custom_root(
        jax.grad(energy),
        s0,
        _newton_solve(newton),
        lambda g, y: y / g(jnp.ones_like(y)),
        has_aux=True,
    )
    b = jnp.exp(s)
    w, G = jax.value_and_grad(psi)(_deformation(code, lam, b), params)
    P = jnp.where(shear, G[0, 1], G[0, 0])
    return P, b, (done > 0.5) & jnp.isfinite(w) & jnp.isfinite(P)


@functools.partial(jax.jit, static_argnames=("psi", "incompressible", "newton"))
def _stress(psi, params, codes, amount, incompressible, newton):
    """Vmapped over points: ``codes`` ``(n,)`` test numbers, ``amount`` ``(n,)``."""
    if incompressible:
        point = functools.partial(_incompressible_point, psi, params)
    else:
        point = functools.partial(_compressible_point, psi, params, newton=newton)
    P, b, ok = jax.vmap(point)(codes, amount)
    return HomogeneousResponse(P, b, ok)


def nominal_stress(
    psi: Callable,
    params,
    test: str,
    amount,
    *,
    incompressible: bool = True,
    newton: FreeStretchNewton | None = None,
) -> HomogeneousResponse:
    """Nominal stress of a homogeneous test of ``psi`` at each amount (module docstring).

    Args:
        psi: ``psi(F, params) -> scalar`` for a ``(3, 3)`` F (any law; hashable, static).
        params: its parameter pytree (κ is used only when ``incompressible=False``).
        test: one of :data:`TESTS`.
        amount: ``(n,)`` stretches λ > 0 in the loaded direction, or amounts of shear γ.
        incompressible: exactly incompressible by the Lagrange multiplier (default), or
            compressible with the free stretch found by Newton's method.
        newton: :class:`FreeStretchNewton` settings of the compressible case.
    Returns:
        :class:`HomogeneousResponse` (stress ``(n,)``, lateral ``(n,)``, ok ``(n,)``);
        differentiable in ``params`` and ``amount`` (jit-, vmap- and jacfwd-compatible).
    Raises:
        ValueError: unknown test, or ``amount`` not 1-D.
    """
    code = _code(test)
    amount = jnp.asarray(amount)
    if amount.ndim != 1:
        raise ValueError(f"amount must be a 1-D array of stretches, got shape {amount.shape}")
    newton = FreeStretchNewton() if newton is None else newton
    codes = jnp.full(amount.shape, code, jnp.int32)
    return _stress(psi, params, codes, amount, bool(incompressible), newton)


# ----------------------------------------------------------------------- fitting cases
class StressCurve(NamedTuple):
    """One measured test curve: a fitting case (build it with :func:`stress_curve`).

    Attributes:
        test: one of :data:`TESTS`.
        stretch: ``(n,)`` stretch λ in the loaded direction (γ in simple shear) [-].
        stress: ``(n,)`` measured nominal stress [stress, e.g. MPa].
        sigma: ``(n,)`` standard deviation (or relative weight) of each stress [same unit].
    """

    test: str
    stretch: np.ndarray
    stress: np.ndarray
    sigma: np.ndarray


def _vector(x, name: str, what: str) -> np.ndarray:
    v = np.asarray(x, dtype=np.float64)
    if v.ndim != 1 or v.size == 0:
        raise ValueError(f"{name}: {what} must be a non-empty 1-D array, got shape {v.shape}")
    bad = np.flatnonzero(~np.isfinite(v))
    if bad.size:
        raise ValueError(f"{name}: {what} is not finite at row {int(bad[0])} ({v[bad[0]]})")
    return v


def stress_curve(test: str, stretch, stress, sigma=None, *, name: str | None = None):
    """A validated :class:`StressCurve`.

    Args:
        test: one of :data:`TESTS`.
        stretch: ``(n,)`` stretches λ > 0 (amounts of shear γ for ``"simple_shear"``).
        stress: ``(n,)`` measured nominal stress.
        sigma: None (relative weighting, σ_i = |stress_i|: residuals are relative errors;
            every stress must then be non-zero), a positive scalar, or ``(n,)`` positive.
        name: label used in error messages (default: the test name).
    Raises:
        ValueError: unknown test, mismatched lengths, NaN/inf (naming the row),
            stretch ≤ 0, σ ≤ 0, or a zero stress with relative weighting.
    """
    name = name or f"{test} curve"
    _check_test(test)
    lam = _vector(stretch, name, "stretch")
    P = _vector(stress, name, "stress")
    if lam.shape != P.shape:
        raise ValueError(f"{name}: {lam.size} stretches but {P.size} stresses")
    if test != "simple_shear" and np.any(lam <= 0):
        row = int(np.flatnonzero(lam <= 0)[0])
        raise ValueError(f"{name}: stretch must be > 0, got {lam[row]} at row {row}")
    if sigma is None:
        if np.any(P == 0):
            row = int(np.flatnonzero(P == 0)[0])
            raise ValueError(
                f"{name}: relative weighting (sigma=None) needs non-zero stresses; row {row} "
                "is 0 (give sigma explicitly)"
            )
        sig = np.abs(P)
    else:
        sig = np.broadcast_to(np.asarray(sigma, dtype=np.float64), P.shape).copy()
        if not np.all(np.isfinite(sig)) or np.any(sig <= 0):
            row = int(np.flatnonzero(~(np.isfinite(sig) & (sig > 0)))[0])
            raise ValueError(f"{name}: sigma must be finite and > 0, got {sig[row]} at row {row}")
    return StressCurve(test, lam, P, sig)


class CurveFit(NamedTuple):
    """Result of :func:`fit_curves`.

    Attributes:
        params: the fitted parameters in ``init``'s structure (floats).
        names: names of the fitted parameters, in the order of ``result.params``.
        values: name → fitted value.
        standard_errors: name → Gauss–Newton standard error.
        predicted: per curve, ``(n,)`` the fitted model's stress.
        rms_relative_error: per curve, ``sqrt(mean(((pred − data)/data)²))`` over its
            rows of non-zero data.
        incompressible: whether the fitted model is the incompressible limit.
        result: the :class:`~jaxelastic.fitting.least_squares.LeastSquaresResult`.
    """

    params: Any
    names: tuple[str, ...]
    values: dict
    standard_errors: dict
    predicted: tuple
    rms_relative_error: tuple
    incompressible: bool
    result: LeastSquaresResult

    @property
    def converged(self) -> bool:
        """Whether the least-squares driver met its tolerance."""
        return self.result.converged


@dataclasses.dataclass(frozen=True)
class _CurveResiduals:
    """``(z, parametrisation, (codes, λ, P, σ)) -> (r, ok)`` of all points at once
    (hashable: one compilation per ψ and mode, whatever the tests)."""

    psi: Callable
    incompressible: bool
    newton: FreeStretchNewton

    def __call__(self, z, par: Parametrization, data):
        codes, lam, P, sig = data
        params = par.psi_params(z)
        resp = _stress(self.psi, params, codes, lam, self.incompressible, self.newton)
        return (resp.stress - P) / sig, jnp.all(resp.ok)


def _physical(z, par: Parametrization, data):
    """The fitted leaves' physical values, concatenated ``(p,)``."""
    leaves = jax.tree_util.tree_leaves(par.from_unconstrained(z))
    fitted = [jnp.ravel(v) for v, t in zip(leaves, par.transforms, strict=True) if t.fitted]
    return jnp.concatenate(fitted)


def _default_fields(init, fields, incompressible: bool):
    names = make_parametrization(init, Free()).names
    if fields is None:
        fields = tuple(n for n in names if n != "kappa")
    fields = (fields,) if isinstance(fields, str) else tuple(fields)
    unknown = [f for f in fields if f not in names]
    if unknown or not fields:
        raise ValueError(f"fields must name parameters among {names}, got {fields!r}")
    if incompressible and "kappa" in fields:
        raise ValueError(
            "kappa has no effect on an incompressible test (incompressible=True is the κ → ∞ "
            "limit); fit it with incompressible=False or leave it out of fields"
        )
    return fields


def fit_curves(
    psi: Callable,
    init,
    curves: Sequence[StressCurve],
    *,
    transforms=None,
    fields=None,
    incompressible: bool = True,
    known_sigma: bool = False,
    settings: LMSettings | None = None,
    newton: FreeStretchNewton | None = None,
) -> CurveFit:
    """Fit parameters of ``psi`` to homogeneous test curves by Levenberg–Marquardt.

    Minimises ``½ Σ_curves Σ_i ((P_model(λ_i) − P_i)/σ_i)²`` over the fitted leaves of
    ``init`` (compiled once per ``psi``, test sequence and mode; later fits of other data
    reuse it).

    Args:
        psi: ``psi(F, params) -> scalar`` (e.g. ``jaxelastic.materials.mooney_rivlin``).
        init: initial parameters (the law's NamedTuple; κ only matters when compressible).
        curves: :class:`StressCurve` cases (:func:`stress_curve`), fitted jointly.
        transforms: per-leaf transforms as in
            :func:`~jaxelastic.fitting.parameters.make_parametrization` (default
            ``Positive()``; use ``Free()`` for constants that may be ≤ 0, e.g. Ogden's
            μ_p, α_p or Yeoh's c20).
        fields: names of the leaves to fit; default every leaf except ``kappa`` (the bulk
            modulus is part of the model: fixed at ``init.kappa`` when compressible,
            irrelevant when incompressible).
        incompressible: fit the exactly incompressible response (the κ → ∞ limit;
            default) or the compressible one at the given κ.
        known_sigma: True when the curves' σ are measurement standard deviations; False
            (default) when they are weights only (relative weighting, or unknown scale):
            the covariance is then scaled by the reduced χ².
        settings: :class:`~jaxelastic.fitting.least_squares.LMSettings`; by default
            ``atol`` is the cost of residuals at 1000 ulps of the data (an exact fit
            counts as converged).
        newton: :class:`FreeStretchNewton` of the compressible case.
    Returns:
        :class:`CurveFit`; ``converged`` says whether the tolerance was met.
    Raises:
        ValueError: no curves, a curve that is not a :class:`StressCurve`, a bad field or
            transform, or residuals that are not finite at ``init``.
    """
    curves = tuple(curves)
    if not curves or not all(isinstance(c, StressCurve) for c in curves):
        raise ValueError("curves must be a non-empty sequence of StressCurve (stress_curve())")
    fields = _default_fields(init, fields, incompressible)
    par = make_parametrization(init, transforms, fields=fields)
    newton = FreeStretchNewton() if newton is None else newton
    fun = _CurveResiduals(psi, bool(incompressible), newton)
    codes = np.concatenate([np.full(c.stretch.shape, _code(c.test), np.int32) for c in curves])
    data = (jnp.asarray(codes),) + tuple(
        jnp.asarray(np.concatenate([getattr(c, k) for c in curves]))
        for k in ("stretch", "stress", "sigma")
    )
    if settings is None:
        eps = float(jnp.finfo(jnp.asarray(1.0).dtype).eps)
        scaled = np.concatenate([np.abs(c.stress) / c.sigma for c in curves])
        settings = LMSettings(atol=0.5 * float(np.sum((1e3 * eps * scaled) ** 2)))
    res = levenberg_marquardt(
        fun,
        par.initial_z(),
        (par, data),
        physical=_physical,
        known_sigma=known_sigma,
        settings=settings,
    )
    if res.stop_reason == "nonfinite":
        raise ValueError(
            "the model's stresses are not finite at the initial parameters (e.g. a Gent "
            "lock J_m below the data's Ī₁ − 3, or a failed free-stretch solve); change init"
        )
    return _report(par, curves, res, incompressible)


def _report(par: Parametrization, curves, res: LeastSquaresResult, incompressible) -> CurveFit:
    params = jax.tree_util.tree_map(
        lambda v: float(v) if np.ndim(v) == 0 else np.asarray(v),
        par.from_unconstrained(jnp.asarray(res.z)),
    )
    names = par.fitted
    unc = res.uncertainty
    se = unc.standard_errors if unc is not None else np.full(len(names), np.nan)
    predicted, rms, start = [], [], 0
    for c in curves:
        n = c.stress.size
        pred = c.stress + c.sigma * res.residuals[start : start + n]  # pred = data + σ r
        start += n
        predicted.append(pred)
        nz = c.stress != 0
        rel = (pred[nz] - c.stress[nz]) / c.stress[nz]
        rms.append(float(np.sqrt(np.mean(rel**2))) if rel.size else float("nan"))
    return CurveFit(
        params=params,
        names=names,
        values=dict(zip(names, (float(v) for v in res.params), strict=True)),
        standard_errors=dict(zip(names, (float(v) for v in se), strict=True)),
        predicted=tuple(predicted),
        rms_relative_error=tuple(rms),
        incompressible=bool(incompressible),
        result=res,
    )
