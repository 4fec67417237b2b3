"""Homogeneous test curves without a mesh, their Levenberg–Marquardt fit, and Treloar's data.

The stresses of the autodiff path (:func:`jaxelastic.fitting.nominal_stress`) are checked
against the incompressible closed forms written out below (the principal-stretch formula
``P₁ = 2(λ₁ − λ₃²/λ₁)(W₁ + λ₂² W₂)`` of invariant laws and ``P₁ = Σ μ_p(λ₁^α_p −
λ₃^α_p)/λ₁`` of Ogden's, free direction 3; Treloar 1975, *The Physics of Rubber
Elasticity*, ch. 10), the compressible path against the neo-Hookean closed form of Bonet &
Wood (2008, §6.4), and the fits of Treloar's (1944) data against an independent SciPy
``least_squares`` fit of those closed forms.
"""

import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic.materials as M
from jaxelastic.fitting import (
    Fixed,
    Free,
    LMSettings,
    Positive,
    fit_curves,
    levenberg_marquardt,
    nominal_stress,
    stress_curve,
)
from jaxelastic.verification import TRELOAR, TRELOAR_UNIAXIAL

PRINCIPAL = ("uniaxial", "equibiaxial", "pure_shear")
AB = np.array([1 / 2, 1 / 20, 11 / 1050, 19 / 7000, 519 / 673750])  # Arruda & Boyce 1993


# ------------------------------------------------------------- closed forms (numpy, by hand)
def principal_stretches(test, lam):
    """(λ₁, λ₂, λ₃) of the incompressible test; direction 3 is traction-free."""
    return {
        "uniaxial": (lam, lam**-0.5, lam**-0.5),
        "equibiaxial": (lam, lam, lam**-2.0),
        "pure_shear": (lam, np.ones_like(lam), 1.0 / lam),
    }[test]


def invariant_stress(W1, W2, test, lam):
    l1, l2, l3 = principal_stretches(test, lam)
    return 2.0 * (l1 - l3**2 / l1) * (W1 + l2**2 * W2)


def closed_form(model, theta, test, lam):
    """Incompressible nominal stress P₁₁ of each model, written out (complex-step safe)."""
    l1, l2, l3 = principal_stretches(test, lam)
    x = l1**2 + l2**2 + l3**2 - 3.0  # I₁ − 3
    zero = 0.0 * x
    if model == "mooney_rivlin":
        c10, c01 = theta
        return invariant_stress(c10 + zero, c01 + zero, test, lam)
    if model == "yeoh":
        c10, c20, c30 = theta
        return invariant_stress(c10 + 2 * c20 * x + 3 * c30 * x**2, zero, test, lam)
    if model == "gent":
        mu, Jm = theta
        return invariant_stress(0.5 * mu / (1.0 - x / Jm), zero, test, lam)
    if model == "arruda_boyce":
        mu, lm = theta
        I1 = x + 3.0
        W1 = mu * sum(i * a * I1 ** (i - 1) / lm ** (2 * i - 2) for i, a in enumerate(AB, 1))
        return invariant_stress(W1, zero, test, lam)
    if model == "ogden":
        mu, alpha = theta[:3], theta[3:]
        return sum(m * (l1**a - l3**a) / l1 for m, a in zip(mu, alpha, strict=True))
    raise KeyError(model)


# library law, its default constants as the initial guess, the fitted names, the transforms
MODELS = {
    "mooney_rivlin": (
        M.mooney_rivlin,
        M.mooney_rivlin_params(),
        M.MooneyRivlin(Free(), Free(), Fixed()),
    ),
    "yeoh": (M.yeoh, M.yeoh_params(), M.Yeoh(Free(), Free(), Free(), Fixed())),
    "ogden": (M.ogden, M.ogden_params(), M.Ogden(*[Free()] * 6, Fixed())),
    "gent": (M.gent, M.gent_params(), M.Gent(Positive(), Positive(), Fixed())),
    "arruda_boyce": (
        M.arruda_boyce,
        M.arruda_boyce_params(),
        M.ArrudaBoyce(Positive(), Positive(), Fixed()),
    ),
}


def fitted_theta(params):
    return np.array([v for k, v in params._asdict().items() if k != "kappa"], dtype=float)


# ------------------------------------------------------------------------------ stresses
@pytest.mark.parametrize("model", list(MODELS))
def test_incompressible_stress_matches_the_closed_forms(model):
    psi, params, _ = MODELS[model]
    lam = np.linspace(1.02, 4.0, 9)
    theta = fitted_theta(params)
    for test in PRINCIPAL:
        r = nominal_stress(psi, params, test, lam)
        assert bool(np.all(r.ok))
        np.testing.assert_allclose(r.stress, closed_form(model, theta, test, lam), rtol=1e-11)
    # κ drops out of the exactly incompressible response
    r2 = nominal_stress(psi, params._replace(kappa=7.0 * params.kappa), "uniaxial", lam)
    np.testing.assert_allclose(r2.stress, nominal_stress(psi, params, "uniaxial", lam).stress)


def test_simple_shear_and_compression_closed_forms():
    p = M.mooney_rivlin_params(c10=0.2, c01=0.05)
    g = np.array([-0.8, -0.1, 0.0, 0.3, 1.5])
    r = nominal_stress(M.mooney_rivlin, p, "simple_shear", g)
    np.testing.assert_allclose(r.stress, 2 * g * (p.c10 + p.c01), atol=1e-14)
    assert bool(np.all(r.ok)) and np.all(r.lateral == 1.0)
    lam = np.array([0.4, 0.7, 0.95, 1.0, 1.3])  # compression (λ < 1) is the same formula
    r = nominal_stress(M.mooney_rivlin, p, "uniaxial", lam)
    np.testing.assert_allclose(
        r.stress, closed_form("mooney_rivlin", [0.2, 0.05], "uniaxial", lam), atol=1e-14
    )


def test_compressible_neo_hookean_matches_the_closed_form():
    from scipy.optimize import brentq

    mu, lam_ = M.lame(10.0, 0.3)
    params = M.Lame(mu, lam_)
    a = np.array([0.8, 1.2, 1.5, 2.0])
    r = nominal_stress(M.neo_hookean, params, "uniaxial", a, incompressible=False)

    def lateral(x):  # μ(b² − 1) + λ ln(x b²) = 0
        return brentq(lambda b: mu * (b * b - 1) + lam_ * np.log(x * b * b), 0.1, 2.0)

    b = np.array([lateral(x) for x in a])
    assert bool(np.all(r.ok))
    np.testing.assert_allclose(r.lateral, b, rtol=1e-12)
    np.testing.assert_allclose(r.stress, mu * (a - b * b / a), rtol=1e-11)


def test_compressible_tends_to_incompressible_as_kappa_grows():
    p = M.mooney_rivlin_params()
    lam = np.linspace(1.1, 5.0, 6)
    ref = {t: nominal_stress(M.mooney_rivlin, p, t, lam).stress for t in PRINCIPAL}
    for test in PRINCIPAL:
        errs = []
        for k in (1e3, 1e5, 1e7):
            r = nominal_stress(
                M.mooney_rivlin, p._replace(kappa=k), test, lam, incompressible=False
            )
            assert bool(np.all(r.ok))
            errs.append(np.max(np.abs(r.stress / ref[test] - 1)))
        assert errs[-1] < 1e-4, (test, errs)
        assert errs[0] / errs[1] > 50 and errs[1] / errs[2] > 50, (test, errs)  # O(1/κ)
    g = np.array([-0.8, 0.0, 0.3, 1.5, 2.0, 3.0])  # F is prescribed in simple shear
    r = nominal_stress(M.mooney_rivlin, p, "simple_shear", g, incompressible=False)
    np.testing.assert_allclose(r.stress, 2 * g * (p.c10 + p.c01), atol=1e-14)
    assert bool(np.all(r.ok)) and np.all(r.lateral == 1.0)


@pytest.mark.parametrize(
    ("incompressible", "tests"),
    [
        (True, ("uniaxial",)),
        pytest.param(True, PRINCIPAL, marks=pytest.mark.extended),
        pytest.param(False, PRINCIPAL, marks=pytest.mark.extended),
    ],
)
def test_parameter_derivatives_match_central_differences(incompressible, tests):
    lam = jnp.array([1.1, 2.0, 3.5])
    p0 = M.ogden_params(kappa=50.0)
    x0 = jnp.array([p0.mu1, p0.alpha1, p0.kappa])

    @jax.jit
    def stress(x):  # (n_tests × 3 stretches,)
        p = p0._replace(mu1=x[0], alpha1=x[1], kappa=x[2])
        out = [nominal_stress(M.ogden, p, t, lam, incompressible=incompressible) for t in tests]
        return jnp.concatenate([r.stress for r in out])

    J = jax.jit(jax.jacfwd(stress))(x0)
    for k in range(3):
        h = 1e-6 * max(abs(float(x0[k])), 1.0)
        e = jnp.zeros(3).at[k].set(h)
        fd = (stress(x0 + e) - stress(x0 - e)) / (2 * h)
        scale = float(jnp.max(jnp.abs(J))) * 1e-7
        np.testing.assert_allclose(J[:, k], fd, rtol=1e-6, atol=scale, err_msg=f"parameter {k}")
    if incompressible:  # κ has no effect on the incompressible stress
        assert float(jnp.max(jnp.abs(J[:, 2]))) <= 1e-25 * float(jnp.max(jnp.abs(J)))
    else:
        assert float(jnp.min(jnp.abs(J[:, 2]))) > 0.0


# --------------------------------------------------------------------- least squares
def test_levenberg_marquardt_solves_a_linear_problem_and_reports_uncertainty():
    x = np.linspace(0.0, 1.0, 20)
    A = np.stack([np.ones_like(x), x, x * x], axis=1)
    y = A @ np.array([1.0, -2.0, 0.5]) + 0.01 * np.sin(40 * x)

    def fun(z, A, y):
        return A @ z - y

    res = levenberg_marquardt(fun, jnp.zeros(3), (jnp.asarray(A), jnp.asarray(y)))
    assert res.converged and res.stop_reason == "converged"
    np.testing.assert_allclose(res.params, np.linalg.lstsq(A, y, rcond=None)[0], rtol=1e-8)
    np.testing.assert_allclose(res.uncertainty.covariance, np.linalg.inv(A.T @ A), rtol=1e-9)


def test_levenberg_marquardt_status_is_honest():
    t = jnp.linspace(0.0, 3.0, 30)
    y = 2.0 * jnp.exp(-1.3 * t)

    def decay(z, t, y):
        return z[0] * jnp.exp(-z[1] * t) - y

    ok = levenberg_marquardt(decay, jnp.array([1.0, 0.5]), (t, y))
    assert ok.converged and ok.cost < 1e-20
    np.testing.assert_allclose(ok.params, [2.0, 1.3], rtol=1e-9)
    short = levenberg_marquardt(
        decay, jnp.array([1.0, 0.5]), (t, y), settings=LMSettings(max_iterations=1)
    )
    assert not short.converged and short.stop_reason == "max_iterations"

    def refuses_to_move(z, z0):  # every trial point reports a failed prediction
        return z - 3.0, jnp.all(z == z0)

    z0 = jnp.array([1.0])
    stalled = levenberg_marquardt(refuses_to_move, z0, (z0,), settings=LMSettings(max_rejections=5))
    assert not stalled.converged and stalled.stop_reason == "stalled"
    nan = levenberg_marquardt(lambda z: jnp.sqrt(z - 2.0), jnp.array([1.0]))
    assert not nan.converged and nan.stop_reason == "nonfinite" and nan.uncertainty is None
    with pytest.raises(ValueError, match="finite, non-empty 1-D"):
        levenberg_marquardt(decay, jnp.array([jnp.nan, 1.0]), (t, y))


def test_the_fit_compiles_once_per_model():
    traces = []

    def psi(F, p):  # counts the traces of ψ (Python runs only while tracing)
        traces.append(1)
        return M.mooney_rivlin(F, p)

    init = M.mooney_rivlin_params()
    tr = M.MooneyRivlin(Free(), Free(), Fixed())
    curves = [stress_curve(c.test, c.stretch, c.stress) for c in TRELOAR]
    first = fit_curves(psi, init, curves, transforms=tr)
    n = len(traces)
    assert first.converged and first.result.iterations >= 2
    other = [stress_curve(c.test, c.stretch, 1.1 * c.stress) for c in TRELOAR]  # new data
    again = fit_curves(psi, init, other, transforms=tr)
    assert len(traces) == n and again.converged
    np.testing.assert_allclose(again.values["c10"], 1.1 * first.values["c10"], rtol=1e-8)


# --------------------------------------------------------------------------- Treloar
def scipy_fit(model, theta0, curves):
    """Independent reference: SciPy least squares on the closed forms, complex-step J."""
    from scipy.optimize import least_squares

    def resid(theta):
        return np.concatenate(
            [(closed_form(model, theta, c.test, c.stretch) - c.stress) / c.stress for c in curves]
        )

    sol = least_squares(
        resid, theta0, jac="cs", method="trf", x_scale="jac", xtol=1e-15, ftol=1e-15, gtol=1e-15
    )
    assert sol.status > 0, sol.message
    return sol.x


def treloar_fit_matches_scipy(model, curves):
    psi, init, tr = MODELS[model]
    curves = [stress_curve(c.test, c.stretch, c.stress) for c in curves]
    tic = time.perf_counter()
    fit = fit_curves(psi, init, curves, transforms=tr, settings=LMSettings(rtol=1e-14))
    assert fit.converged, fit.result.stop_reason
    assert time.perf_counter() - tic < 120.0
    ref = scipy_fit(model, fitted_theta(init), curves)
    np.testing.assert_allclose(np.asarray(fit.result.params), ref, rtol=1e-4)
    for c, pred, rms in zip(curves, fit.predicted, fit.rms_relative_error, strict=True):
        np.testing.assert_allclose(pred, closed_form(model, ref, c.test, c.stretch), rtol=1e-4)
        assert 0.0 < rms < 0.5
    se = fit.standard_errors
    assert all(np.isfinite(v) and v > 0 for v in se.values()), se
    return fit


def test_treloar_mooney_rivlin_joint_fit_matches_scipy():
    fit = treloar_fit_matches_scipy("mooney_rivlin", TRELOAR)
    assert fit.names == ("c10", "c01")


@pytest.mark.extended
@pytest.mark.parametrize("model", ["yeoh", "ogden", "gent", "arruda_boyce"])
def test_treloar_joint_fit_matches_scipy(model):
    treloar_fit_matches_scipy(model, TRELOAR)


@pytest.mark.extended
@pytest.mark.parametrize("model", list(MODELS))
def test_treloar_uniaxial_fit_matches_scipy(model):
    treloar_fit_matches_scipy(model, [TRELOAR_UNIAXIAL])


@pytest.mark.extended
def test_compressible_fit_at_large_kappa_approaches_the_incompressible_one():
    psi, init, tr = MODELS["mooney_rivlin"]
    curves = [stress_curve(c.test, c.stretch, c.stress) for c in TRELOAR]
    inc = fit_curves(psi, init, curves, transforms=tr)
    comp = fit_curves(psi, init._replace(kappa=1e5), curves, transforms=tr, incompressible=False)
    assert comp.converged and not comp.incompressible
    for k in ("c10", "c01"):
        np.testing.assert_allclose(comp.values[k], inc.values[k], rtol=1e-3)


@pytest.mark.extended
def test_compressible_fit_recovers_the_bulk_modulus_from_synthetic_data():
    true = M.mooney_rivlin_params(c10=0.2, c01=0.05, kappa=2.0)  # soft in bulk: κ informed
    lam, g = np.linspace(1.1, 3.0, 10), np.linspace(0.1, 1.0, 5)
    curves = [
        stress_curve(
            t, a, nominal_stress(M.mooney_rivlin, true, t, a, incompressible=False).stress, 1e-3
        )
        for t, a in (("uniaxial", lam), ("equibiaxial", lam), ("simple_shear", g))
    ]
    fit = fit_curves(
        M.mooney_rivlin,
        M.mooney_rivlin_params(kappa=5.0),
        curves,
        fields=("c10", "c01", "kappa"),
        incompressible=False,
        known_sigma=True,
    )
    assert fit.converged and fit.names == ("c10", "c01", "kappa")
    np.testing.assert_allclose([fit.values[k] for k in fit.names], [0.2, 0.05, 2.0], rtol=1e-8)
    assert 0 < fit.standard_errors["kappa"] < 0.1


# ------------------------------------------------------------------------- bad inputs
def test_bad_curves_are_refused_with_the_row():
    with pytest.raises(ValueError, match="unknown test 'biaxial'"):
        stress_curve("biaxial", [1.1], [1.0])
    with pytest.raises(ValueError, match="3 stretches but 2 stresses"):
        stress_curve("uniaxial", [1.1, 1.2, 1.3], [1.0, 2.0])
    with pytest.raises(ValueError, match="stress is not finite at row 1"):
        stress_curve("uniaxial", [1.1, 1.2], [1.0, np.nan])
    with pytest.raises(ValueError, match="stretch must be > 0, got 0.0 at row 0"):
        stress_curve("uniaxial", [0.0, 1.2], [1.0, 2.0])
    with pytest.raises(ValueError, match="sigma must be finite and > 0, got -1.0 at row 1"):
        stress_curve("equibiaxial", [1.1, 1.2], [1.0, 2.0], sigma=[1.0, -1.0])
    with pytest.raises(ValueError, match="sigma must be finite and > 0"):
        stress_curve("pure_shear", [1.1, 1.2], [1.0, 2.0], sigma=0.0)
    with pytest.raises(ValueError, match="relative weighting.*row 0"):
        stress_curve("simple_shear", [0.0, 0.2], [0.0, 2.0])
    with pytest.raises(ValueError, match="1-D"):
        stress_curve("uniaxial", [[1.1]], [[1.0]])
    with pytest.raises(ValueError, match="unknown test"):
        nominal_stress(M.mooney_rivlin, M.mooney_rivlin_params(), "torsion", jnp.ones(2))


def test_bad_fits_are_refused():
    psi, init, tr = MODELS["mooney_rivlin"]
    c = stress_curve("uniaxial", TRELOAR_UNIAXIAL.stretch, TRELOAR_UNIAXIAL.stress)
    with pytest.raises(ValueError, match="kappa has no effect"):
        fit_curves(psi, init, [c], fields=("c10", "kappa"))
    with pytest.raises(ValueError, match="fields must name parameters"):
        fit_curves(psi, init, [c], fields=("c11",))
    with pytest.raises(ValueError, match="non-empty sequence of StressCurve"):
        fit_curves(psi, init, [])
    with pytest.raises(ValueError, match="Positive\\(\\) needs an initial value > 0"):
        fit_curves(M.yeoh, M.yeoh_params(), [c])  # c20 < 0 needs Free()


@pytest.mark.extended
def test_a_model_undefined_at_the_initial_guess_is_refused():
    c = stress_curve("uniaxial", TRELOAR_UNIAXIAL.stretch, TRELOAR_UNIAXIAL.stress)
    with pytest.raises(ValueError, match="not finite at the initial parameters"):
        fit_curves(M.gent, M.gent_params(Jm=20.0), [c])  # Ī₁ − 3 reaches 55 > J_m


@pytest.mark.extended
def test_report_script_writes_its_table(tmp_path):
    import importlib
    import json
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
    report = importlib.import_module("report_treloar")
    out = tmp_path / "out"
    assert report.main(["--models", "mooney_rivlin", "--no-plot", "--out", str(out)]) == 0
    rows = json.loads((out / "report_treloar.json").read_text())["fits"]
    assert [r["fitted_on"] for r in rows] == ["joint", "uniaxial"]
    assert all(r["converged"] for r in rows)
    joint = rows[0]["rms_relative_error"]
    assert set(joint) == {"uniaxial", "equibiaxial", "pure_shear"}
    assert rows[1]["rms_relative_error"]["equibiaxial"] > 5 * joint["equibiaxial"]
    assert "| Mooney–Rivlin | all three |" in (out / "treloar_table.md").read_text()
