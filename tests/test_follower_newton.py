"""Newton with the true, non-symmetric tangent of a follower load (``Newton(tangent=...)``):
the GMRES that solves it, the tangent operator against the Jacobian of the residual,
quadratic convergence against the symmetric quasi-Newton, and honest statuses."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic as je
from jaxelastic import loads as L
from jaxelastic.mechanics import potential as pot_mod
from jaxelastic.solvers.linear import gmres, newton_system
from jaxelastic.solvers.newton import exact_tangent
from jaxelastic.solvers.results import Status


def _cantilever(p, n=4):
    """A neo-Hookean n × 1 × 1 cantilever clamped at x = 0, a follower pressure ``p`` on
    its bottom face (an open surface whose rim moves)."""
    m = je.box(n, 1, 1, size=(float(n), 1.0, 1.0))
    bottom = L.facets_where(m, lambda X: X[:, 2] < 1e-9)
    term = L.pressure_load(m, bottom, p, follower=True)
    bc = L.fix(m, L.nodes_on_plane(m, 0, 0.0))
    pot = je.Potential(m, je.Lame(100.0, 150.0), psi=je.neo_hookean, pressure=term)
    return m, bc, pot


def _history(res):
    k = int(res.stats["steps"])
    return np.asarray(res.stats["residual_history"])[: k + 1]


def test_gmres_solves_a_nonsymmetric_system_and_reports_failure():
    """GMRES on a dense non-symmetric matrix reaches the tolerance on the true residual;
    an iteration cap, a tolerance below round-off (stagnation) and a NaN operator are
    reported as MAX_STEPS, MAX_STEPS and NONFINITE, never as SUCCESS."""
    rng = np.random.default_rng(0)
    n = 60
    A = jnp.asarray(4.0 * np.eye(n) + rng.normal(size=(n, n)) / np.sqrt(n))
    assert float(jnp.abs(A - A.T).max()) > 0.1
    b = jnp.asarray(rng.normal(size=(n, 3)))  # any shape: (n, 3) like (n_nodes, dim)
    bn = float(jnp.linalg.norm(b))

    @jax.jit
    def run(b, tol):
        return (
            gmres(lambda v: A @ v, b, tol=tol, max_iter=200, restart=8),
            gmres(lambda v: A @ v, b, tol=tol, max_iter=3, restart=8),
            gmres(lambda v: A @ v * jnp.nan, b, tol=tol, max_iter=50, restart=8),
        )

    ok, capped, nan = run(b, 1e-10 * bn)
    assert int(ok.status) == Status.SUCCESS
    assert float(jnp.linalg.norm(A @ ok.x - b)) <= 1e-10 * bn
    assert 8 < int(ok.stats["iterations"]) <= 200  # restarted at least once
    assert int(capped.status) == Status.MAX_STEPS and int(capped.stats["iterations"]) == 3
    assert float(capped.stats["residual"]) > 1e-10 * bn
    assert int(nan.status) == Status.NONFINITE
    stuck = jax.jit(lambda b: gmres(lambda v: A @ v, b, tol=0.0, max_iter=10_000, restart=8))(b)
    assert int(stuck.status) == Status.MAX_STEPS
    assert int(stuck.stats["iterations"]) < 10_000  # stopped by stagnation, not the cap
    assert float(stuck.stats["residual"]) < 1e-12 * bn


def test_tangent_setting_and_its_table():
    """``tangent`` is validated; ``"auto"`` and ``"exact"`` use the true tangent wherever a
    follower load makes it non-symmetric, ``"symmetric"`` never; conservative potentials
    always solve with their symmetric Hessian."""
    with pytest.raises(ValueError, match="tangent must be one of"):
        je.Newton(tangent="gmres")
    m, bc, pot = _cantilever(1.0)
    closed = pot.replace(pressure=pot.pressure.replace(follower=False))
    for t, follower, conservative in (
        ("auto", True, False),
        ("exact", True, False),
        ("symmetric", False, False),
    ):
        s = je.Newton(tangent=t)
        assert exact_tangent(s, pot) is follower
        assert exact_tangent(s, closed) is conservative
        assert exact_tangent(s, pot.replace(pressure=None)) is False


def test_true_tangent_operator_is_the_jacobian_of_the_residual():
    """The Newton operator with ``exact_tangent`` is the Jacobian of the residual (its JVP)
    to round-off at a deformed state; the symmetric one is not; the element Hessians are
    the same symmetric ones in both."""
    m, bc, pot = _cantilever(1.0)
    x = m.points @ jnp.asarray([[1.0, 0.0, 0.1], [0.0, 1.02, 0.0], [-0.1, 0.0, 0.99]]).T
    v = jax.random.normal(jax.random.PRNGKey(0), x.shape, x.dtype)

    @jax.jit
    def products(pot, x, v):
        Jv = jax.jvp(lambda y: pot_mod.gradient(pot, y), (x,), (v,))[1]
        true = newton_system(pot, x, ~bc.mask, hessian="element", need_Ke=True, exact_tangent=True)
        sym = newton_system(pot, x, ~bc.mask, hessian="element", need_Ke=True)
        hvp = newton_system(pot, x, ~bc.mask, hessian="hvp", need_Ke=False, exact_tangent=True)
        return Jv, true.H(v), sym.H(v), hvp.H(v), jnp.abs(true.Ke - sym.Ke).max()

    Jv, true, sym, hvp, dK = products(pot, x, v)
    scale = float(jnp.abs(Jv).max())
    assert float(jnp.abs(true - Jv).max()) <= 1e-12 * scale
    assert float(jnp.abs(hvp - Jv).max()) <= 1e-12 * scale
    assert float(jnp.abs(sym - Jv).max()) > 1e-4 * scale
    assert float(dK) == 0.0


@pytest.mark.extended  # two follower solves, ~20 s cold on a loaded 2-core machine
def test_true_tangent_converges_quadratically_to_the_quasi_newton_solution():
    """On a small follower cantilever the true tangent converges quadratically
    (``r_{k+1} ≤ C r_k²`` over the last steps above round-off, relative residuals) in at
    most 8 Newton steps, where the symmetric quasi-Newton needs at least twice as many
    (linear convergence), and both reach the same equilibrium."""
    m, bc, pot = _cantilever(1.0)
    exact = je.solve(pot, bc, solver=je.Newton(rtol=1e-12, tangent="auto"))
    quasi = je.solve(pot, bc, solver=je.Newton(rtol=1e-12, tangent="symmetric", max_steps=100))
    he, hq = _history(exact), _history(quasi)
    assert len(he) - 1 <= 8 and len(hq) - 1 >= 2 * (len(he) - 1), (he, hq)

    def ratios(h):  # r_{k+1} / r_k² (relative residuals) above the round-off floor
        rel = h / h[0]
        return [
            rel[k + 1] / rel[k] ** 2
            for k in range(len(rel) - 1)
            if rel[k] < 0.1 < 1e11 * rel[k + 1]
        ]

    assert len(ratios(he)) >= 2 and max(ratios(he)) < 10.0, he
    assert max(ratios(hq)) > 100.0, hq  # the quasi-Newton: linear
    assert int(exact.stats["linear_unconverged"]) == 0
    assert int(exact.stats["linear_iterations"]) > len(he) - 1  # GMRES: > 1 per step
    x, y = np.asarray(exact.x), np.asarray(quasi.x)
    assert np.abs(x - y).max() <= 1e-8 * np.abs(x - np.asarray(m.points)).max()


@pytest.mark.extended  # two follower solves (~200 quasi-Newton steps), ~40 s loaded
def test_true_tangent_solves_a_load_where_the_quasi_newton_stalls():
    """p = 4 on the 6 × 1 × 1 follower cantilever: the quasi-Newton stalls (no convergence
    in 200 steps), the true tangent converges, ending quadratically."""
    m, bc, pot = _cantilever(4.0, n=6)
    quasi = je.solve(
        pot, bc, solver=je.Newton(rtol=1e-10, max_steps=200, tangent="symmetric"), throw=False
    )
    assert not quasi.ok
    exact = je.solve(pot, bc, solver=je.Newton(rtol=1e-10, max_steps=200))
    h = _history(exact)
    # (natural monotonicity line search: 20 steps; 40 with Armijo on a pseudo-energy)
    assert int(exact.stats["steps"]) <= 25
    rel = h / h[0]
    # (a last step that lands below 1e-8 is limited by the linear solve's tolerance,
    # 0.1·rtol·ref, not by Newton's convergence)
    last = [
        rel[k + 1] / rel[k] ** 2 for k in range(len(rel) - 1) if rel[k] < 1e-2 < 1e6 * rel[k + 1]
    ]
    assert last and max(last) < 10.0, rel
    assert float(exact.x[:, 2].max()) > 4.0


@pytest.mark.extended  # one capped follower solve (~10 s loaded)
def test_capped_gmres_is_reported_in_the_newton_statistics():
    """A GMRES capped at one iteration per Newton step (CG(max_iter=1)'s cap) stops short
    of its tolerance: every step counts it in ``stats["linear_unconverged"]``, and the
    solve does not report an unconverged state as SUCCESS."""
    m, bc, pot = _cantilever(1.0)
    s = je.Newton(rtol=1e-12, max_steps=5, linear=je.CG(max_iter=1))
    res = je.solve(pot, bc, solver=s, throw=False)
    steps = int(res.stats["steps"])
    assert int(res.stats["linear_unconverged"]) == steps > 0
    assert int(res.status) != Status.SUCCESS
    assert float(res.stats["residual"]) > float(res.stats["tolerance"])


@pytest.mark.extended  # three follower solves, ~13 s cold on a loaded 2-core machine
def test_follower_line_search_takes_full_steps_from_a_neighbouring_state():
    """A load step p = 1 → 2 of the 6 × 1 × 1 follower cantilever started from the
    converged p = 1 state converges in at most 10 Newton steps, nearly all full (the line
    search's natural monotonicity test on the simplified Newton correction; the Armijo test
    on a pseudo-energy took 78 steps at α = 1/64 here), to the same equilibrium as from
    rest, with SUCCESS only at the tolerance."""
    s = je.Newton(rtol=1e-10, max_steps=100)
    _, bc, pot1 = _cantilever(1.0, n=6)
    _, _, pot2 = _cantilever(2.0, n=6)
    start = je.solve(pot1, bc, solver=s)
    ramp = je.solve(pot2, bc, solver=s, x0=start.x)
    k = int(ramp.stats["steps"])
    alpha = np.asarray(ramp.stats["step_history"])[:k]
    assert int(ramp.status) == Status.SUCCESS and k <= 10, (k, alpha)
    assert np.sum(alpha == 1.0) >= k - 2, alpha
    assert float(ramp.stats["residual"]) <= float(ramp.stats["tolerance"])
    rest = je.solve(pot2, bc, solver=s)
    assert int(rest.stats["steps"]) <= 16
    scale = float(np.abs(np.asarray(rest.x) - np.asarray(pot2.mesh.points)).max())
    assert np.abs(np.asarray(ramp.x) - np.asarray(rest.x)).max() <= 1e-8 * scale


def test_follower_line_search_leaves_conservative_solves_unchanged():
    """A conservative solve (a tip load on the neo-Hookean cantilever, CG and direct) keeps
    its energy line search: the same 11 Newton steps, 4 cut-backs and residual history as
    with the energy line search alone (golden values)."""
    m = je.box(6, 1, 1, size=(6.0, 1.0, 1.0))
    bc = L.fix(m, L.nodes_on_plane(m, 0, 0.0))
    f = np.zeros(m.points.shape)
    f[np.asarray(m.points)[:, 0] > 5.9, 2] = 3.0
    pot = je.Potential(m, je.Lame(100.0, 150.0), psi=je.neo_hookean, f_ext=jnp.asarray(f))
    golden = [6.0, 60.881168770096075, 34.404510819442294, 65.18577242867187, 8.673436170729314]
    res = je.solve(pot, bc, solver=je.Newton(rtol=1e-10))
    assert int(res.stats["steps"]) == 11 and int(res.stats["line_search_cutbacks"]) == 4
    assert int(res.stats["regularized"]) == 0
    h = np.asarray(res.stats["residual_history"])[:5]
    np.testing.assert_allclose(h, golden, rtol=1e-9)
