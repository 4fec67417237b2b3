"""The accuracy and stability reports (``scripts/report_*.py``) on small settings: they
write their files, and their numbers are the physics the README promises.

The default run keeps to a few compilations (the Timoshenko error norms, a handful of
stability scenes); the quick accuracy report (Cook P1 with a direct solver, the patch
tests) is ``extended``; convergence rates, P2/F-bar, twist and the full stability table
are ``slow``.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from _common import load_script

import jaxelastic as je
from jaxelastic import verification as bm

rc = load_script("_report_common")
acc = load_script("report_accuracy")
stab = load_script("report_stability")


def _rows(result, case, element="P1", solver=None):
    rs = [r for r in result["rows"] if r["case"] == case and r["element"] == element]
    if solver is not None:
        rs = [r for r in rs if r["solver"] == solver]
    assert rs, (case, element, solver)
    assert all(r["status"] == "SUCCESS" for r in rs), [(r["level"], r["status"]) for r in rs]
    return sorted(rs, key=lambda r: r["h"], reverse=True)


# --------------------------------------------------------------------------------------
# helpers that the reports rely on
# --------------------------------------------------------------------------------------


def test_pareto_front_and_rate():
    t = [1.0, 2.0, 3.0, 0.5, 4.0]
    e = [1e-2, 1e-3, 5e-3, 1e-1, 1e-4]
    # (3, 5e-3) is dominated by (2, 1e-3)
    assert list(rc.pareto(t, e)) == [3, 0, 1, 4]
    h = np.array([1.0, 0.5, 0.25])
    assert rc.rate(h, 3 * h**2) == pytest.approx(2.0, abs=1e-12)


def test_timoshenko_exact_field_and_error_norms():
    """The exact field's gradient matches finite differences; its tip value is the
    REFERENCES value 0.0089; the error norm of the interpolant is small and that of a
    scaled field is the scaling."""
    X = np.array([[10.0, 2.0], [30.0, -4.0], [48.0, 0.0]])
    u, g = bm.timoshenko_exact(X)
    eps = 1e-6
    for j in range(2):
        dX = np.zeros_like(X)
        dX[:, j] = eps
        fd = (bm.timoshenko_exact(X + dX)[0] - bm.timoshenko_exact(X - dX)[0]) / (2 * eps)
        np.testing.assert_allclose(g[:, :, j], fd, rtol=1e-7, atol=1e-14)
    assert u[2, 1] == pytest.approx(0.0089, rel=2e-3)
    m = je.rectangle(16, 4, (48.0, 12.0), (0.0, -6.0))
    X = np.asarray(m.points)
    ue = bm.timoshenko_exact(X)[0]
    mu, lam = je.materials.lame(3e7, 0.3, dim=2, plane="stress")
    exact = (lambda Z: bm.timoshenko_exact(Z)[0], lambda Z: bm.timoshenko_exact(Z)[1])
    l2, en = acc.error_norms_2d(m, X + 0.5 * ue, *exact, mu, lam)
    # half the interpolant: errors near 1/2 (plus the interpolation error)
    assert 0.45 < l2 < 0.55 and 0.45 < en < 0.6
    l2i, eni = acc.error_norms_2d(m, X + ue, *exact, mu, lam)
    assert l2i < 0.01 and 0.2 < eni < 0.6
    # Galerkin optimality: the FE solution (same Dirichlet interpolant on x = 0, consistent
    # end load) is the best approximation in the energy norm, better than the interpolant
    prob = acc.build_timoshenko(4, "P1")
    assert prob.pot.mesh.n_nodes == m.n_nodes
    x = np.asarray(je.solve(prob.pot, prob.bc, solver=je.Newton(linear="direct")).x)
    fe = prob.evaluate(x)
    assert fe["error_energy"] < eni
    assert fe["error_energy"] == pytest.approx(acc.error_norms_2d(m, x, *exact, mu, lam)[1])


def test_edge_load_is_consistent():
    """The parabolic end shear integrates to P and, on P1 edges, matches ∫N_a t exactly
    for a quadratic t (5-point Gauss)."""
    from jaxelastic import loads

    m = je.rectangle(4, 3, (48.0, 12.0), (0.0, -6.0))
    facets = loads.facets_where(m, lambda X: np.abs(X[:, 0] - 48.0) < 1e-9)
    I = 12.0**3 / 12

    def t(X):
        return np.stack([0 * X[:, 1], 1000.0 / (2 * I) * (36.0 - X[:, 1] ** 2)], 1)

    f = bm.edge_load_2d(m, facets, t)
    assert f[:, 1].sum() == pytest.approx(1000.0, rel=1e-12)
    assert np.abs(f[:, 0]).max() == 0.0
    # top and bottom corner nodes: ∫ over the one edge of N t, by hand for t(y) quadratic
    y = np.linspace(-6, 6, 4)
    a, b = y[0], y[1]
    s = np.linspace(0, 1, 200001)
    tt = 1000.0 / (2 * I) * (36.0 - (a + s * (b - a)) ** 2)
    corner = np.trapezoid((1 - s) * tt, s) * (b - a)
    i = bm.node_at(m, (48.0, -6.0))
    assert f[i, 1] == pytest.approx(corner, rel=1e-8)


def test_twist_benchmark_setup():
    """bench_solvers times the benchmark's twist; its x = 0 face gets half of the 60°
    rotation about (y, z) = (0.5, 0.5) as displacement, x = 1 is clamped."""
    bench = load_script("bench_solvers")
    b = bm.twist(3)
    _, pot, bc = bench._twist_problem(3)
    assert pot.psi is b.psi and pot.mesh.n_nodes == b.mesh.n_nodes
    np.testing.assert_array_equal(np.asarray(bc.mask), np.asarray(b.bc.mask))
    X = np.asarray(b.mesh.points)
    turned, clamped = b.probes["turned"], b.probes["clamped"]
    c, s = np.cos(bm.TWIST_THETA), np.sin(bm.TWIST_THETA)
    R = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    Y = X[turned] - [0.0, 0.5, 0.5]
    expect = X[turned] + (Y @ R.T - Y) / 2  # Dirichlet values are positions
    np.testing.assert_allclose(np.asarray(b.bc.values)[turned], expect, atol=1e-15)
    np.testing.assert_array_equal(np.asarray(b.bc.values)[clamped], X[clamped])
    assert np.asarray(b.bc.mask)[np.r_[turned, clamped]].all()


# --------------------------------------------------------------------------------------
# accuracy report, extended tier
# --------------------------------------------------------------------------------------


@pytest.mark.extended
def test_accuracy_quick_cook_and_patch(tmp_path):
    res = acc.run(
        tmp_path,
        quick=True,
        case_names=["cook", "patch"],
        elements=["P1"],
        solvers=["direct"],
        verbose=False,
    )
    cook = _rows(res, "cook")
    err = [r["error"] for r in cook]
    # monotone convergence towards 23.96 from below; the finest quick level (n = 64) is
    # within 1 % (measured 0.78 %; n = 32 gives 23.28, 2.9 % off)
    assert all(r["value"] < 23.96 for r in cook)
    assert all(a > b for a, b in zip(err, err[1:], strict=False))
    assert cook[-1]["level"] == 64 and err[-1] < 0.01
    assert err[-2] > 0.01  # the coarser level does not: the test would notice a shortcut
    for r in cook:
        assert r["newton"] <= 2 and r["run_s"] > 0 and r["compile_s"] >= 0
    (patch,) = _rows(res, "patch")
    assert patch["error"] < 1e-9  # σx = σy = 1333.3, τ = 400 in every element
    for name in (
        "accuracy.json",
        "accuracy.csv",
        "error_vs_time_cook.png",
        "error_vs_time_summary.png",
    ):
        assert (tmp_path / name).stat().st_size > 100, name
    on_disk = json.loads((tmp_path / "accuracy.json").read_text())
    assert len(on_disk["rows"]) == len(res["rows"]) and "cores" in on_disk["machine"]
    csv_lines = (tmp_path / "accuracy.csv").read_text().splitlines()
    assert len(csv_lines) == 1 + len(res["rows"])


# --------------------------------------------------------------------------------------
# stability report, default run
# --------------------------------------------------------------------------------------
@pytest.mark.extended  # a study: the report script end to end
def test_stability_quick_subset(tmp_path):
    res = stab.run(
        tmp_path,
        quick=True,
        scenes=["relax"],
        models=("neo_hookean", "stvk"),
        starts=("crush", "reflect"),
        verbose=False,
    )
    out = {(r["scene"], r["material"]): r for r in res["rows"]}
    assert res["silent_nans"] == 0
    assert out["crush", "neo_hookean"]["outcome"] == "recovered"  # J = 1e-6 > 0: a barrier
    r = out["reflect", "neo_hookean"]
    assert r["outcome"] == "refused" and r["reason"].startswith("INVERTED")
    assert r["steps"] == 1 and r["newton_max"] == 0
    r = out["reflect", "stvk"]
    assert r["outcome"] == "at rest, not recovered" and "mirror image" in r["reason"]
    assert r["volume_error"] == pytest.approx(-2.0, abs=1e-9)  # every J = −1
    for key in [("crush", "neo_hookean"), ("crush", "stvk")]:
        assert out[key]["energy_monotone"] is True  # backward Euler dissipates
        assert abs(out[key]["volume_error"]) < 1e-6
    assert (tmp_path / "stability_shapes.png").stat().st_size > 1000
    assert len((tmp_path / "stability.csv").read_text().splitlines()) == 1 + len(res["rows"])


# --------------------------------------------------------------------------------------
# slow: rates, 3D locking, P2 / F-bar, twist, the full quick stability table
# --------------------------------------------------------------------------------------


@pytest.mark.slow
def test_timoshenko_rates_p1(tmp_path):
    res = acc.run(
        tmp_path, quick=True, case_names=["timoshenko"], elements=["P1"], verbose=False, plots=False
    )
    rs = _rows(res, "timoshenko")
    h = [r["h"] for r in rs]
    assert rc.rate(h[-2:], [r["error_L2"] for r in rs][-2:]) == pytest.approx(2.0, abs=0.2)
    assert rc.rate(h[-2:], [r["error_energy"] for r in rs][-2:]) == pytest.approx(1.0, abs=0.2)


@pytest.mark.slow
def test_timoshenko_rates_p2(tmp_path):
    res = acc.run(
        tmp_path, quick=True, case_names=["timoshenko"], elements=["P2"], verbose=False, plots=False
    )
    rs = _rows(res, "timoshenko", "P2")
    h = [r["h"] for r in rs]
    assert rc.rate(h[-2:], [r["error_L2"] for r in rs][-2:]) == pytest.approx(3.0, abs=0.2)
    assert rc.rate(h[-2:], [r["error_energy"] for r in rs][-2:]) == pytest.approx(2.0, abs=0.2)


@pytest.mark.slow
def test_cantilever3d_p1_locks_and_p2_does_not(tmp_path):
    res = acc.run(
        tmp_path,
        quick=True,
        case_names=["cantilever3d"],
        elements=["P1", "P2"],
        verbose=False,
        plots=False,
    )
    p1 = _rows(res, "cantilever3d")
    ratio = [r["ratio"] for r in p1]
    # shear locking: far below beam theory, improving with refinement (1, 2 elements)
    assert ratio[0] < 0.4 and 0.45 < ratio[1] < 0.7 and ratio[1] > ratio[0]
    two = [r for r in _rows(res, "cantilever3d", "P2") if r["level"] == 2][0]
    assert 0.98 <= two["ratio"] <= 1.02


@pytest.mark.slow
def test_homogeneous_cases_exact(tmp_path):
    res = acc.run(
        tmp_path,
        quick=True,
        case_names=["uniaxial", "shear", "patch_affine"],
        elements=["P1"],
        verbose=False,
        plots=False,
    )
    for case in ("uniaxial", "shear", "patch_affine"):
        for r in _rows(res, case):
            assert r["error"] < 1e-9, (case, r["level"], r["error"])


@pytest.mark.slow
def test_nearly_incompressible_cook_p2_and_fbar(tmp_path):
    res = acc.run(
        tmp_path,
        quick=True,
        case_names=["cook_nh", "cook_incompressible"],
        elements=["P1", "P2-Fbar", "P2-Bbar"],
        verbose=False,
        plots=False,
    )
    # P1 locks: far below the reference
    assert _rows(res, "cook_nh")[-1]["value"] < 0.6 * 6.91
    assert _rows(res, "cook_incompressible")[-1]["value"] < 0.6 * 16.43
    # F-bar (neo-Hookean) and B-bar (linear) reach 2 % at the finest quick level (n = 16
    # and 8: measured 1.2 % both)
    assert _rows(res, "cook_nh", "P2-Fbar")[-1]["error"] < 0.02
    assert _rows(res, "cook_incompressible", "P2-Bbar")[-1]["error"] < 0.02


@pytest.mark.slow
def test_twist_converges_towards_reference(tmp_path):
    res = acc.run(
        tmp_path,
        quick=True,
        case_names=["twist"],
        elements=["P1"],
        solvers=["direct"],
        verbose=False,
        plots=False,
    )
    err = [r["error"] for r in _rows(res, "twist")]
    assert err[-1] < err[0] < 0.2


@pytest.mark.slow
def test_stability_quick_full(tmp_path):
    res = stab.run(tmp_path, quick=True, verbose=False)
    assert res["silent_nans"] == 0
    rows = res["rows"]
    assert all(
        r["outcome"] in ("recovered", "completed", "at rest, not recovered", "refused")
        for r in rows
    )
    by = {(r["scene"], r["material"], r["integrator"]): r for r in rows}
    for start in ("crush", "inflate"):
        for m in ("stable_neo_hookean_log", "fixed_corotated"):
            assert by[start, m, "backward_euler"]["outcome"] == "recovered", (start, m)
    for start in ("reflect", "random"):
        r = by[start, "neo_hookean", "backward_euler"]
        assert r["outcome"] == "refused" and "INVERTED" in r["reason"]
    assert by["collapse to point", "neo_hookean", "backward_euler"]["outcome"] == "refused"
    assert by["twist 360°", "stable_neo_hookean_log", "static"]["outcome"] == "completed"
    for r in rows:
        if r["scene"].startswith("drop") or r["scene"].startswith("h="):
            assert r["outcome"] == "completed", (r["scene"], r["material"], r["reason"])
        if r["integrator"] == "backward_euler" and r["energy_monotone"] is not None:
            # backward Euler dissipates: kinetic + elastic + load potential never grows
            assert r["energy_monotone"], (r["scene"], r["material"])
    # the 2π twist really turned the bar: the mid-section is half-way round
    assert by["twist 360°", "stable_neo_hookean_log", "static"]["mid_angle_deg"] == pytest.approx(
        180.0, abs=5.0
    )
