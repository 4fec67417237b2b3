"""Implicit dynamics: energy behaviour, convergence order in h, free fall, time-dependent
Dirichlet data, rollout vs simulate, Rayleigh damping.

Compilation budget: :class:`~jaxelastic.dynamics.Integrator` is a *static* argument of
``simulate``/``rollout`` (every distinct h compiles a new step), so the h-sweeps call
:func:`jaxelastic.dynamics.step` through a local jit that traces h (that path uses
matrix-free CG; ``simulate`` uses its default sparse direct solver). All potentials carry
an ``f_ext`` array (zeros when unloaded) so that they share one pytree structure.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic as je
from jaxelastic import Newton, Status
from jaxelastic import dynamics as D
from jaxelastic import loads as L
from jaxelastic import materials as M

MU, LAM = (float(v) for v in M.lame(1.0e4, 0.3))
PARAMS = M.Lame(MU, LAM)
RHO = 1.0e4  # heavy enough that h = 0.05 … 0.005 resolves the mesh modes (ωh < 1)
# atol: the round-off floor of the residual is ~eps·(m/h²)·|x| (3e-9 at h = 0.005), and
# steps that start from the inertial predictor have a tiny initial residual, so a purely
# relative tolerance could fall below it
SETTINGS = Newton(rtol=1e-10, atol=1e-7)
H0 = 0.05
BE = D.Integrator(H0)


@functools.partial(jax.jit, static_argnames=("method",))
def _step_h(base, state, bc, h, method):
    """One step with a *traced* time step (one compile for every h)."""
    return D.step(base, state, bc, D.Integrator(h, method), solver=SETTINGS)


def _run(base, state, bc, h, n, method):
    """n steps with `_step_h`; returns the list of states (including the initial one)."""
    states = [state]
    h = jnp.asarray(h)
    for _ in range(n):
        state, res = _step_h(base, state, bc, h, method)
        assert int(res.status) == Status.SUCCESS, Status(int(res.status)).name
        states.append(state)
    return states


@pytest.fixture(scope="module")
def mesh():
    return je.rectangle(4, 4)


@pytest.fixture(scope="module")
def base(mesh):
    return je.Potential(
        mesh=mesh,
        params=PARAMS,
        f_ext=jnp.zeros(mesh.points.shape),
        mass=jnp.asarray(L.lumped_mass(mesh, RHO)),
        psi=M.neo_hookean,
    )


@pytest.fixture(scope="module")
def clamp(mesh):
    return L.fix(mesh, L.nodes_on_plane(mesh, 0, 0.0))


def _prestretched(mesh):
    """Released from rest: a bent and stretched shape that keeps the left edge in place."""
    X = np.asarray(mesh.points)
    u = np.stack([0.15 * X[:, 0] ** 2, 0.2 * X[:, 0] ** 2 * (1.0 - 0.3 * X[:, 1])], axis=1)
    return jnp.asarray(X + u)


def _energies(base, states):
    return np.array([float(D.total_energy(base, s)) for s in states])


# --------------------------------------------------------------------------------------
# Energy behaviour without external work
# --------------------------------------------------------------------------------------


def test_energy_nonincreasing_backward_euler(mesh, base, clamp):
    st0 = D.init_state(_prestretched(mesh))
    states = [st0]
    final, stats = D.simulate(
        base,
        st0,
        clamp,
        BE,
        40,
        solver=SETTINGS,
        progress=False,
        callback=lambda s, r, rec: states.append(s),
    )
    assert len(stats) == 40 and all(s["status"] == "SUCCESS" for s in stats)
    E = _energies(base, states)
    assert E[0] > 1.0
    assert np.all(np.diff(E) <= 1e-10 * E[0]), np.diff(E).max()
    # it really moves and dissipates (numerical damping of backward Euler)
    assert E[-1] < 0.9 * E[0]
    assert float(D.kinetic_energy(base.mass, states[5].v)) > 0.05 * E[0]
    np.testing.assert_allclose(float(final.t), 40 * H0, rtol=1e-12)


@pytest.mark.extended
def test_energy_bdf2_nearly_conserved(mesh, base, clamp):
    st0 = D.init_state(_prestretched(mesh))
    states = _run(base, st0, clamp, H0, 40, "bdf2")
    E = _energies(base, states)
    # never grows beyond a small tolerance, and dissipates much less than backward Euler
    assert E.max() <= E[0] * (1 + 1e-3), E.max() / E[0]
    be = _energies(base, _run(base, st0, clamp, H0, 40, "backward_euler"))
    assert be[-1] < 0.5 * E[0]
    assert E[-1] > 0.7 * E[0]


# --------------------------------------------------------------------------------------
# Order of accuracy in h
# --------------------------------------------------------------------------------------


def _orders(base, clamp, mesh, method):
    X = np.asarray(mesh.points)
    v0 = jnp.asarray(np.stack([0 * X[:, 0], 0.4 * X[:, 0]], 1))  # clamped edge at rest
    T = 0.4
    finals = []
    for n in (10, 20, 40, 80):
        st = _run(base, D.init_state(mesh.points, v0), clamp, T / n, n, method)[-1]
        np.testing.assert_allclose(float(st.t), T, rtol=1e-12)
        finals.append(np.asarray(st.x))
    diffs = [np.abs(finals[k] - finals[k + 1]).max() for k in range(3)]
    return np.log2(np.array(diffs[:-1]) / np.array(diffs[1:])), diffs


def test_backward_euler_first_order(mesh, base, clamp):
    p, diffs = _orders(base, clamp, mesh, "backward_euler")
    assert diffs[-1] > 1e-6  # far above the Newton tolerance
    np.testing.assert_allclose(p, 1.0, atol=0.3, err_msg=str(diffs))


def test_bdf2_second_order(mesh, base, clamp):
    p, diffs = _orders(base, clamp, mesh, "bdf2")
    assert diffs[-1] > 1e-8
    np.testing.assert_allclose(p, 2.0, atol=0.3, err_msg=str(diffs))


# --------------------------------------------------------------------------------------
# Free fall
# --------------------------------------------------------------------------------------


def test_free_fall_centre_of_mass(mesh, base):
    g = np.array([0.0, -9.81])
    fall = base.replace(f_ext=jnp.asarray(L.gravity_load(mesh, RHO, g)))
    free = L.no_dirichlet(mesh)
    m = np.asarray(base.mass)
    v0 = np.array([1.0, 2.0])
    st0 = D.init_state(mesh.points, jnp.tile(jnp.asarray(v0), (mesh.n_nodes, 1)))
    c0 = (m[:, None] * np.asarray(mesh.points)).sum(0) / m.sum()
    errors = {}
    for method in ("backward_euler", "bdf2"):
        for h in (0.05, 0.025):
            n = int(round(0.5 / h))
            states = _run(fall, st0, free, h, n, method)
            t = np.array([float(s.t) for s in states])
            com = np.array([(m[:, None] * np.asarray(s.x)).sum(0) / m.sum() for s in states])
            exact = c0 + np.outer(t, v0) + 0.5 * np.outer(t * t, g)
            if method == "backward_euler":
                # backward Euler is *not* exact for constant acceleration: its discrete
                # solution is x0 + v0 t + ½ g t (t + h), an O(h) error, reproduced exactly
                np.testing.assert_allclose(com, exact + 0.5 * h * np.outer(t, g), atol=1e-9)
            errors[method, h] = np.abs(com - exact).max()
            # a uniform field moves the body rigidly: no elastic energy
            assert float(je.energy(M.neo_hookean, states[-1].x, mesh, PARAMS)) < 1e-12
    be = errors["backward_euler", 0.05] / errors["backward_euler", 0.025]
    b2 = errors["bdf2", 0.05] / errors["bdf2", 0.025]
    np.testing.assert_allclose(np.log2(be), 1.0, atol=0.05)
    np.testing.assert_allclose(np.log2(b2), 2.0, atol=0.3)
    assert errors["bdf2", 0.025] < 0.1 * errors["backward_euler", 0.025]


# --------------------------------------------------------------------------------------
# Time-dependent Dirichlet data; rollout vs simulate; damping
# --------------------------------------------------------------------------------------


def _moving_bc(mesh):
    left = L.fix(mesh, L.nodes_on_plane(mesh, 0, 0.0))
    right = L.nodes_on_plane(mesh, 0, 1.0)
    mask = left.mask.at[right].set(True)
    X = mesh.points

    def bc(t):
        # jnp only, so the same function serves simulate (float t) and rollout (traced t)
        u = jnp.stack([0.2 * jnp.sin(2.0 * t) * jnp.ones(right.size), 0.1 * t * t * X[right, 1]], 1)
        return je.Dirichlet(mask=mask, values=left.values.at[right].set(X[right] + u))

    return bc, right


def test_time_dependent_dirichlet_simulate(mesh, base):
    bc, right = _moving_bc(mesh)
    seen = []
    final, stats = D.simulate(
        base,
        D.init_state(mesh.points),
        bc,
        BE,
        12,
        solver=SETTINGS,
        progress=False,
        callback=lambda s, r, rec: seen.append(s),
    )
    assert [round(s["t"], 12) for s in stats] == [round((k + 1) * H0, 12) for k in range(12)]
    for s in seen:
        want = np.asarray(bc(float(s.t)).values)[right]
        np.testing.assert_allclose(np.asarray(s.x)[right], want, atol=1e-14)
    left = L.nodes_on_plane(mesh, 0, 0.0)
    np.testing.assert_allclose(np.asarray(final.x)[left], np.asarray(mesh.points)[left], atol=1e-14)
    # the interior follows the boundary motion
    mid = L.nodes_on_plane(mesh, 0, 0.5)
    assert np.abs(np.asarray(final.x)[mid, 0] - 0.5).max() > 0.01


def test_rollout_under_jit_matches_simulate(mesh, base):
    bc, _ = _moving_bc(mesh)
    st0 = D.init_state(mesh.points)
    xs = []
    D.simulate(
        base,
        st0,
        bc,
        BE,
        12,
        solver=SETTINGS,
        progress=False,
        callback=lambda s, r, rec: xs.append(np.asarray(s.x)),
    )
    # the same linear solver as simulate's default (sparse Cholesky through a callback),
    # its state made outside jit (the mesh is traced inside: base is a jit argument)
    prepared = je.solvers.prepare_solver(SETTINGS, mesh, bc(0.0))
    assert isinstance(prepared.linear, je.Direct) and prepared.linear_state.host is not None
    roll = jax.jit(D.rollout, static_argnames=("bc", "integ", "n_steps", "solver"))
    final, traj = roll(base, st0, bc, BE, 12, solver=prepared)
    assert (np.asarray(traj.status) == Status.SUCCESS).all()
    assert (np.asarray(traj.stats["steps"]) >= 1).all()
    np.testing.assert_allclose(np.asarray(traj.frames), np.stack(xs), rtol=0, atol=1e-12)
    np.testing.assert_allclose(float(final.t), 12 * H0, rtol=1e-12)


@pytest.mark.parametrize(
    "damping",
    [dict(alpha=2.0), pytest.param(dict(beta=0.2), marks=pytest.mark.extended)],
    ids=["mass", "stiffness"],
)
def test_rayleigh_damping_dissipates_faster(mesh, base, clamp, damping):
    st0 = D.init_state(_prestretched(mesh))
    plain, damped = [st0], [st0]
    D.simulate(
        base,
        st0,
        clamp,
        BE,
        20,
        solver=SETTINGS,
        progress=False,
        callback=lambda s, r, rec: plain.append(s),
    )
    D.simulate(
        base,
        st0,
        clamp,
        D.Integrator(H0, **damping),
        20,
        solver=SETTINGS,
        progress=False,
        callback=lambda s, r, rec: damped.append(s),
    )
    Ep, Ed = _energies(base, plain), _energies(base, damped)
    assert np.all(np.diff(Ed) <= 1e-10 * Ed[0])
    assert np.all(Ed[5:] < Ep[5:]), (Ed, Ep)
    assert Ed[-1] < 0.7 * Ep[-1]


def test_free_swing_bdf2_no_false_max_steps():
    """A linear P2 cantilever swinging freely under BDF2 converges (without the round-off
    floor in the stopping rule it stops with MAX_STEPS at residual 3.4e-8 after 50
    iterations with the default rtol). Linear material: one Newton step per time step."""
    mesh = je.rectangle(40, 4, size=(10.0, 1.0), origin=(0.0, -0.5), order=2)
    params = je.Lame.from_E_nu(1e6, 0.3, dim=2, plane="stress")
    clamp = L.fix(mesh, L.nodes_on_plane(mesh, 0, 0.0))
    tip = L.facets_where(mesh, lambda X: np.isclose(X[:, 0], 10.0))
    f = jnp.asarray(L.traction_load(mesh, tip, [0.0, -1.0]))
    static = je.solve(je.Potential(mesh=mesh, params=params, f_ext=f, psi=M.linear), clamp)
    assert int(static.stats["steps"]) == 1
    pot = je.Potential(
        mesh=mesh, params=params, mass=jnp.asarray(L.lumped_mass(mesh, 1000.0)), psi=M.linear
    )
    _, recs = D.simulate(
        pot, D.init_state(static.x), clamp, D.Integrator(0.164, "bdf2"), 25, progress=False
    )
    assert [r["status"] for r in recs] == ["SUCCESS"] * 25
    assert max(r["newton_steps"] for r in recs) == 1
