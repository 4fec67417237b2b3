"""Load stepping with automatic cut-back (jaxelastic.solvers.continuation)."""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic as je
from jaxelastic import loads, materials
from jaxelastic.solvers.continuation import scaled_dirichlet, solve_incremental


@pytest.fixture(scope="module")
def beam():
    mesh = je.rectangle(16, 2, size=(4.0, 0.5))
    params = je.Lame(*je.lame(1e4, 0.3, dim=2))
    clamp = loads.fix(mesh, loads.nodes_on_plane(mesh, 0, 0.0))
    tip = loads.facets_where(mesh, lambda X: np.isclose(X[:, 0], 4.0))
    f = jnp.asarray(loads.traction_load(mesh, tip, [0.0, -400.0]))  # large: tip folds down
    pot = je.Potential(mesh=mesh, params=params, f_ext=f, psi=materials.neo_hookean)
    return mesh, pot, clamp


def test_cut_back_reaches_full_load(beam):
    mesh, pot, clamp = beam
    tight = je.NewtonSettings(max_steps=4)
    one = je.solve(pot, clamp, settings=tight, linear="direct", throw=False)
    assert not one.ok  # too large for 4 Newton iterations in one go
    inc = solve_incremental(pot, clamp, steps=1, settings=tight, linear="direct")
    assert inc.ok and inc.load_factor == 1.0
    assert any(not h["accepted"] for h in inc.history)  # it did cut back
    ref = je.solve(pot, clamp, settings=je.NewtonSettings(max_steps=200), linear="direct")
    np.testing.assert_allclose(np.asarray(inc.x), np.asarray(ref.x), atol=1e-8)
    assert float(jnp.min(inc.x[:, 1])) < -1.0  # large deflection, not a small-strain answer


def test_stalls_loudly(beam):
    mesh, pot, clamp = beam

    def nan_psi(F, p):
        return jnp.nan * jnp.sum(F)

    bad = pot.replace(psi=nan_psi)
    with pytest.raises(je.SolveError, match="load stepping"):
        solve_incremental(bad, clamp, steps=2, min_increment=0.2, linear="direct")
    res = solve_incremental(bad, clamp, steps=2, min_increment=0.2, linear="direct", throw=False)
    assert not res.ok and res.load_factor == 0.0


def test_scaled_dirichlet_interpolates(beam):
    mesh, _, _ = beam
    bc = loads.fix(mesh, loads.nodes_on_plane(mesh, 0, 0.0), displacement=[0.1, -0.2])
    half = scaled_dirichlet(mesh, bc)(0.5)
    m = np.asarray(bc.mask)
    np.testing.assert_allclose(
        np.asarray(half.values - mesh.points)[m], 0.5 * np.asarray(bc.values - mesh.points)[m]
    )
