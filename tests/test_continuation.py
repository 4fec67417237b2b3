"""Load stepping with automatic cut-back (jaxelastic.solvers.continuation)."""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic as je
from jaxelastic import loads, materials
from jaxelastic.solvers.continuation import scaled_dirichlet, solve_incremental

DIRECT = je.Newton(linear="direct")


@pytest.fixture(scope="module")
def beam():
    mesh = je.rectangle(16, 2, size=(4.0, 0.5))
    params = je.Lame.from_E_nu(1e4, 0.3, dim=2)
    clamp = loads.fix(mesh, loads.nodes_on_plane(mesh, 0, 0.0))
    tip = loads.facets_where(mesh, lambda X: np.isclose(X[:, 0], 4.0))
    f = jnp.asarray(loads.traction_load(mesh, tip, [0.0, -400.0]))  # large: tip folds down
    pot = je.Potential(mesh=mesh, params=params, f_ext=f, psi=materials.neo_hookean)
    return mesh, pot, clamp


def test_cut_back_reaches_full_load(beam):
    mesh, pot, clamp = beam
    tight = je.Newton(max_steps=4, linear="direct")
    one = je.solve(pot, clamp, solver=tight, throw=False)
    assert not one.ok  # too large for 4 Newton iterations in one go
    inc = solve_incremental(pot, clamp, steps=1, solver=tight)
    assert inc.ok and inc.stats["load_factor"] == 1.0
    assert any(not h["accepted"] for h in inc.stats["increments"])  # it did cut back
    ref = je.solve(pot, clamp, solver=je.Newton(max_steps=200, linear="direct"))
    np.testing.assert_allclose(np.asarray(inc.x), np.asarray(ref.x), atol=1e-8)
    assert float(jnp.min(inc.x[:, 1])) < -1.0  # large deflection, not a small-strain answer


def test_stalls_loudly(beam):
    mesh, pot, clamp = beam

    def nan_psi(F, p):
        return jnp.nan * jnp.sum(F)

    bad = pot.replace(psi=nan_psi)
    with pytest.raises(je.SolveError, match="load stepping"):
        solve_incremental(bad, clamp, steps=2, min_increment=0.2, solver=DIRECT)
    res = solve_incremental(bad, clamp, steps=2, min_increment=0.2, solver=DIRECT, throw=False)
    assert not res.ok and res.stats["load_factor"] == 0.0
    assert int(res.status) == je.Status.NONFINITE


def test_scaled_dirichlet_interpolates(beam):
    mesh, _, _ = beam
    bc = loads.fix(mesh, loads.nodes_on_plane(mesh, 0, 0.0), displacement=[0.1, -0.2])
    half = scaled_dirichlet(mesh, bc)(0.5)
    m = np.asarray(bc.mask)
    np.testing.assert_allclose(
        np.asarray(half.values - mesh.points)[m], 0.5 * np.asarray(bc.values - mesh.points)[m]
    )


def test_path_rotates_instead_of_scaling(beam):
    """A custom path s -> Dirichlet (here a rigid rotation of the clamped edge by s·θ) is
    followed increment by increment, and the callback sees every converged load factor."""
    mesh, pot, clamp = beam
    X = mesh.points
    th = 0.3

    def path(s):
        c, sn = jnp.cos(s * th), jnp.sin(s * th)
        R = jnp.array([[c, -sn], [sn, c]])
        return je.Dirichlet(mask=clamp.mask, values=jnp.where(clamp.mask, X @ R.T, X))

    seen = []
    res = solve_incremental(
        pot.replace(f_ext=None),
        clamp,
        steps=3,
        solver=DIRECT,
        path=path,
        callback=lambda s, sol: seen.append(s),
    )
    np.testing.assert_allclose(seen, [1 / 3, 2 / 3, 1.0])
    # no load: the whole beam turns rigidly with its clamped edge
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    np.testing.assert_allclose(np.asarray(res.x), np.asarray(X) @ R.T, atol=1e-8)


def test_bad_arguments(beam):
    mesh, pot, clamp = beam
    with pytest.raises(ValueError, match="steps"):
        solve_incremental(pot, clamp, steps=0)
    with pytest.raises(ValueError, match="min_increment"):
        solve_incremental(pot, clamp, min_increment=0.0)
