"""Pressures in dynamics: ``simulate(..., pressure_at=...)`` ramps a cavity pressure in
time and a damped body settles at the static inflation of the same pressure; bad
schedules are refused."""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic as je
from jaxelastic import dynamics as D
from jaxelastic import loads as L
from jaxelastic.mesh import annulus


def _ring():
    m = annulus(1.0, 2.0, 6, 2)
    inner = L.facets_where(m, lambda X: np.linalg.norm(X, axis=1) < 1.0 + 1e-9)
    term = L.pressure_load(m, inner, 0.3, origin=np.zeros(2))
    bc = L.combine(*[L.fix(m, L.nodes_on_plane(m, i, 0.0), components=(i,)) for i in range(2)])
    pot = je.Potential(
        m,
        je.Lame(1.0, 10.0),
        psi=je.neo_hookean,
        pressure=term,
        mass=jnp.asarray(L.lumped_mass(m, 1.0)),
    )
    return m, term, bc, pot


def test_a_ramped_pressure_settles_at_the_static_inflation():
    m, term, bc, pot = _ring()
    ramp = 0.5  # [s]: the pressure grows linearly to 0.3, then stays
    integ = D.Integrator(0.05, alpha=1.5)
    seen = []

    def at(t):
        seen.append(t)
        return 0.3 * min(t / ramp, 1.0)

    state, rec = D.simulate(
        pot, D.init_state(m.points), bc, integ, 200, progress=False, pressure_at=at
    )
    assert all(r["status"] == "SUCCESS" for r in rec)
    assert seen[0] == pytest.approx(0.05) and seen[-1] == pytest.approx(200 * 0.05)
    # the cavity grows with the ramp: smaller volumes at the first steps than at the end
    V = [float(term.volumes(x)[0]) for x in (m.points, state.x)]
    static = je.solve_incremental(D.static_potential(pot, integ), bc, steps=2)
    assert static.ok
    assert float(jnp.max(jnp.abs(state.x - static.x))) < 1e-4 * float(np.ptp(m.points))
    assert V[1] > 1.2 * V[0]
    # without the schedule the term's own pressure acts from the first step (a step load)
    _, rec0 = D.simulate(pot, D.init_state(m.points), bc, integ, 2, progress=False)
    _, rec1 = D.simulate(pot, D.init_state(m.points), bc, integ, 2, progress=False, pressure_at=at)
    assert rec0[0]["kinetic"] > 10 * rec1[0]["kinetic"]


def test_bad_pressure_schedules_are_refused():
    m, term, bc, pot = _ring()
    integ = D.Integrator(0.05)
    with pytest.raises(ValueError, match="no pressure term"):
        D.simulate(
            pot.replace(pressure=None),
            D.init_state(m.points),
            bc,
            integ,
            1,
            progress=False,
            pressure_at=lambda t: 1.0,
        )
    with pytest.raises(ValueError, match="not finite"):
        D.simulate(
            pot,
            D.init_state(m.points),
            bc,
            integ,
            1,
            progress=False,
            pressure_at=lambda t: float("nan"),
        )
    with pytest.raises(TypeError, match="pressure_at must be a function"):
        D.simulate(pot, D.init_state(m.points), bc, integ, 1, progress=False, pressure_at=0.3)
