"""Implicit differentiation through :func:`jaxelastic.solve` and dynamics rollouts: forward
mode (jvp/jacfwd) against central finite differences and against reverse mode
(⟨ẋ, x̄⟩ = ⟨θ̇, θ̄⟩), NaN derivatives and GradientError on a failed solve, the host adjoint
(Direct/AMG) that reuses the last Newton factorisation, linear-solver resolution under
jit/vmap, gradients through implicit dynamics rollouts (backward Euler, BDF2) against
finite differences, checkpointing (same gradient, bounded residuals), and E identified from
a released cantilever's motion.

The matrix-free CG (``linear="cg"``) is used unless a test is about the host back ends;
those use their own mesh (:func:`host_beam`) and one bound solver per kind, so that their
counters are not shared with equal solvers bound elsewhere.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic as je
from jaxelastic import dynamics as D
from jaxelastic import loads as L
from jaxelastic import materials as M
from jaxelastic.solvers import GradientError

Status = je.Status
E_MOD, NU = 100.0, 0.3
TIGHT = je.Newton(rtol=1e-12, linear="cg")
# dynamics: the residual's round-off floor is ~eps·(m/h²)·|x|, so add a tiny atol
DYN = je.Newton(rtol=1e-12, atol=1e-13, linear="cg")
REVERSE = je.ImplicitAdjoint()
FORWARD = je.ImplicitAdjoint(mode="forward")


def _fd(f, x, direction, h):
    """Fourth-order central difference of f at x along direction."""
    fp1, fm1 = f(x + h * direction), f(x - h * direction)
    fp2, fm2 = f(x + 2 * h * direction), f(x - 2 * h * direction)
    return (8.0 * (fp1 - fm1) - (fp2 - fm2)) / (12.0 * h)


def _rel(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-300))


def _xs(pot, bc, solver=TIGHT, adjoint=REVERSE):
    """The differentiable equilibrium positions x* ``(n_nodes, dim)``."""
    return je.solve(pot, bc, solver=solver, adjoint=adjoint).x


class Beam:
    """2D neo-Hookean cantilever (nx×2 cells, length × 0.5), clamped at x = 0, end traction."""

    def __init__(self, nx=8, length=4.0):
        self.mesh = je.rectangle(nx, 2, size=(length, 0.5))
        self.X = np.asarray(self.mesh.points)
        self.bc = L.fix(self.mesh, L.nodes_on_plane(self.mesh, 0, 0.0))
        facets = L.facets_where(self.mesh, lambda c: np.isclose(c[:, 0], length))
        self.f = jnp.asarray(L.traction_load(self.mesh, facets, (0.0, -0.5)))
        self.tip = np.flatnonzero(np.isclose(self.X[:, 0], length))
        self.right = self.tip
        self.mass = jnp.asarray(L.lumped_mass(self.mesh, 1.0))
        self._linear = {}

    def pot(self, params, f=None, mass=None):
        f = self.f if f is None else f
        return je.Potential(mesh=self.mesh, params=params, f_ext=f, mass=mass, psi=M.neo_hookean)

    def linear(self, kind):
        """``(settings, state)`` of one host solver per kind (the state's host back end
        counts this beam's factorisations)."""
        if kind not in self._linear:
            self._linear[kind] = je.solvers.init_linear(kind, self.mesh, self.bc)
        return self._linear[kind]


@pytest.fixture(scope="module")
def beam():
    return Beam()


@pytest.fixture(scope="module")
def host_beam():
    """A mesh of its own for the host back ends: bound solvers compare equal by (mesh,
    mask, kind, options), and jit caches then share compiled solves between equal ones."""
    return Beam(nx=10, length=5.0)


def _lame(E, nu=NU):
    return M.Lame.from_E_nu(E, nu, dim=2)


# ---------------------------------------------------------------------------- forward mode


def test_jvp_matches_fd_and_transposes(beam):
    """x*(E, ν, load scale) in forward mode: jvp columns vs central FD (≤ 1e-6), and
    reverse mode over the same custom_jvp (the transposed tangent solve) gives J too."""

    def xs(th):
        pot = beam.pot(_lame(th[0], th[1]), f=th[2] * beam.f)
        return _xs(pot, beam.bc, adjoint=FORWARD)

    jvp = jax.jit(lambda t, d: jax.jvp(xs, (t,), (d,)))
    th = jnp.array([E_MOD, NU, 1.0])
    eye = jnp.eye(3)
    J = jnp.stack([jvp(th, eye[i])[1] for i in range(3)], axis=-1)  # (n, 2, 3)
    for i, h in enumerate([1e-3 * E_MOD, 1e-3, 1e-3]):
        fd = _fd(lambda t, i=i: jvp(t, eye[i])[0], th, eye[i], h)
        assert _rel(J[..., i], fd) <= 1e-6, (i, _rel(J[..., i], fd))
    J_rev = jax.jit(jax.jacrev(xs))(th)
    assert _rel(J_rev, J) <= 1e-9


@pytest.mark.extended
def test_jvp_vjp_consistency_field_and_dirichlet(beam):
    """⟨ẋ, x̄⟩ from forward mode equals ⟨θ̇, θ̄⟩ from the default reverse mode, for a
    per-cell μ field together with a prescribed end displacement; the Dirichlet tangent
    matches finite differences."""
    mu0, lam0 = (float(v) for v in M.lame(E_MOD, NU, dim=2))
    n = beam.mesh.n_cells
    rng = np.random.default_rng(1)
    mu = jnp.asarray(mu0 * (1.0 + 0.3 * rng.uniform(-1, 1, n)))
    bc_r = L.fix(beam.mesh, beam.right)
    bc = L.combine(beam.bc, bc_r)
    mask_r = jnp.asarray(bc_r.mask)
    direction = jnp.asarray([[0.2, -0.5]])

    def xs(theta, adjoint):
        mu, s = theta
        values = jnp.where(mask_r, jnp.asarray(beam.X) + s * direction, bc.values)
        pot = beam.pot(M.Lame(mu, lam0), f=jnp.zeros_like(beam.f))
        return _xs(pot, L.Dirichlet(bc.mask, values), adjoint=adjoint)

    theta = (mu, jnp.asarray(0.4))
    tdot = (jnp.asarray(mu0 * rng.standard_normal(n)), jnp.asarray(0.7))
    xbar = jnp.asarray(rng.standard_normal(beam.X.shape))
    jvp = jax.jit(lambda t, d: jax.jvp(lambda u: xs(u, FORWARD), (t,), (d,)))
    vjp = jax.jit(lambda t, xb: jax.vjp(lambda u: xs(u, REVERSE), t)[1](xb))
    _, xdot = jvp(theta, tdot)
    ((mu_bar, s_bar),) = vjp(theta, xbar)
    lhs = float(jnp.sum(xdot * xbar))
    rhs = float(jnp.sum(mu_bar * tdot[0]) + s_bar * tdot[1])
    assert abs(lhs - rhs) <= 1e-9 * (abs(lhs) + abs(rhs)), (lhs, rhs)
    # the Dirichlet tangent alone against FD
    e_s = (jnp.zeros(n), jnp.asarray(1.0))
    _, xdot_s = jvp(theta, e_s)
    fd = _fd(lambda s: jvp((mu, s), e_s)[0], theta[1], 1.0, 1e-3)
    assert _rel(xdot_s, fd) <= 1e-6
    # prescribed dofs move exactly with the prescribed values
    np.testing.assert_allclose(np.asarray(xdot_s)[beam.right], np.broadcast_to(direction, (3, 2)))


@pytest.mark.extended
def test_failed_solve_gives_nan_derivatives_and_gradient_error(beam):
    """One Newton step cannot reach rtol = 1e-12: the forward tangent and the reverse
    gradient are NaN (never a gradient at a non-equilibrium point), je.solvers.value_and_grad
    raises GradientError; outside jit the solve raises SolveError unless throw=False."""
    bad = TIGHT.replace(max_steps=1)

    def solution(E, adjoint=FORWARD):
        return je.solve(beam.pot(_lame(E)), beam.bc, solver=bad, adjoint=adjoint)

    res, dres = jax.jit(lambda E: jax.jvp(solution, (E,), (jnp.asarray(1.0),)))(jnp.asarray(E_MOD))
    assert int(res.status) == Status.MAX_STEPS
    assert not bool(res.ok)
    assert np.all(np.isnan(np.asarray(dres.x)))

    def loss(E):
        return jnp.sum(solution(E, REVERSE).x ** 2)

    vg = je.solvers.value_and_grad(loss)
    with pytest.raises(GradientError, match="not finite"):
        vg(jnp.asarray(E_MOD))
    # the same gradient, not checked: NaN, the value is finite
    value, g = jax.jit(jax.value_and_grad(loss))(jnp.asarray(E_MOD))
    assert np.isfinite(float(value)) and np.isnan(float(g))
    # outside jit
    res = je.solve(beam.pot(_lame(E_MOD)), beam.bc, solver=bad, throw=False)
    assert res.reason and Status(int(res.status)) == Status.MAX_STEPS
    with pytest.raises(je.SolveError, match="MAX_STEPS"):
        je.solve(beam.pot(_lame(E_MOD)), beam.bc, solver=bad)
    with pytest.raises(ValueError, match="mode"):
        je.ImplicitAdjoint(mode="sideways")


# ------------------------------------------------------------------- host adjoints, jit, vmap


def _tip_loss(beam, th, solver):
    x = _xs(beam.pot(_lame(th[0], th[1])), beam.bc, solver=solver)
    return jnp.sum((x[beam.tip] - jnp.asarray(beam.X[beam.tip]) + 0.3) ** 2)


@pytest.mark.extended
def test_host_adjoint_matches_cg_and_reuses_factorisation(host_beam):
    """With a bound Direct or AMG solver the adjoint is device PCG preconditioned by the
    last Newton factorisation (or AMG hierarchy): it converges to the matrix-free CG
    gradient (≤ 1e-8), applies the host back end and factorises at most once more."""
    th = jnp.array([E_MOD, NU])
    g_cg = jax.jit(jax.grad(lambda t: _tip_loss(host_beam, t, TIGHT)))(th)
    pullback = jax.jit(lambda vjp, ct: vjp(ct))
    for kind in ("direct", "amg"):
        lin, state = host_beam.linear(kind)
        solver = TIGHT.replace(linear=lin)
        host = state.host
        f0 = host.factorizations
        _, vjp = jax.jit(lambda t, s=solver: jax.vjp(lambda u: _tip_loss(host_beam, u, s), t))(th)
        f1, a1 = host.factorizations, host.applications
        assert f1 > f0  # the forward Newton solve factorised on the host
        (g_host,) = pullback(vjp, jnp.ones(()))
        assert np.all(np.isfinite(np.asarray(g_host))), kind
        assert _rel(g_host, g_cg) <= 1e-8, (kind, _rel(g_host, g_cg))
        assert host.factorizations - f1 <= 1, (kind, host.factorizations - f1)
        assert host.applications > a1, kind  # the adjoint used the host back end


def test_linear_solver_resolution_under_jit(beam):
    """With the mesh traced (the potential is a jit argument) "auto" resolves to CG and
    gives the concrete solve's x*; host solvers without a state made outside jit raise a
    ValueError that names init_linear."""
    pot = beam.pot(_lame(E_MOD))
    seen = []

    def x_of(p, linear):
        seen.append(je.solvers.linear.resolve(linear, p.mesh, beam.bc))
        return _xs(p, beam.bc, solver=TIGHT.replace(linear=linear))

    x_auto = jax.jit(x_of, static_argnums=1)(pot, "auto")
    assert isinstance(seen[-1], je.CG)
    x_ref = je.solve(pot, beam.bc, solver=je.Newton(rtol=1e-12)).x  # concrete: Direct
    np.testing.assert_allclose(x_auto, x_ref, rtol=0, atol=1e-10)
    for linear in (je.Direct(), je.AMG(), "direct"):
        with pytest.raises(ValueError, match="init_linear"):
            jax.jit(x_of, static_argnums=1)(pot, linear)


@pytest.mark.extended
def test_vmap_over_materials_cg_and_host_refusal(beam):
    """jax.vmap of je.solve over two (μ, λ) sets with linear="cg" gives the two separate
    solves; host solvers under vmap raise a ValueError that says so."""
    E = jnp.array([E_MOD, 2.5 * E_MOD])
    params = M.Lame.from_E_nu(E, jnp.array([0.3, 0.4]), dim=2)

    def x_of(p, linear):
        return je.solve(beam.pot(p), beam.bc, solver=TIGHT.replace(linear=linear)).x

    xb = jax.jit(jax.vmap(lambda p: x_of(p, "cg")))(params)
    assert xb.shape == (2, *beam.X.shape)
    for i in range(2):
        p_i = jax.tree_util.tree_map(lambda a, i=i: a[i], params)
        x_i = je.solve(beam.pot(p_i), beam.bc, solver=TIGHT).x
        np.testing.assert_allclose(xb[i], x_i, rtol=0, atol=1e-10)
    assert float(jnp.abs(xb[0] - xb[1]).max()) > 1e-2  # two different solutions
    with pytest.raises(ValueError, match="vmap"):
        jax.jit(jax.vmap(lambda p: x_of(p, "direct")))(params)


# -------------------------------------------------------------------------------- dynamics


def _v0(beam, amplitude):
    return jnp.zeros_like(beam.mesh.points).at[:, 1].set(amplitude * jnp.asarray(beam.X[:, 0]))


def _released(beam, th, method="backward_euler", n_steps=10):
    """θ = (E, load scale, initial tip-velocity amplitude): loss over a dynamic rollout."""
    base = beam.pot(_lame(th[0]), f=th[1] * beam.f, mass=beam.mass)
    _, traj = D.rollout(
        base, D.init_state(beam.mesh.points, _v0(beam, th[2] / 4)), beam.bc,
        D.Integrator(0.1, method), n_steps, solver=DYN,
    )  # fmt: skip
    tip = traj.frames[:, beam.tip]  # (n_steps, 3, 2)
    return jnp.sum(tip[..., 1] ** 2) + 0.01 * jnp.sum(traj.frames[-1] ** 2), traj


@functools.cache
def _rollout_vg(beam, method):
    return jax.jit(jax.value_and_grad(lambda t: _released(beam, t, method), has_aux=True))


def _check_rollout_grad(beam, method):
    th = jnp.array([E_MOD, 1.0, 0.2])
    vg = _rollout_vg(beam, method)
    (_, traj), g = vg(th)
    assert np.all(np.asarray(traj.status) == Status.SUCCESS)
    for i, h in enumerate([1e-3 * E_MOD, 1e-3, 1e-3]):
        fd = float(_fd(lambda t: vg(t)[0][0], th, jnp.zeros(3).at[i].set(1.0), h))
        assert _rel(g[i], fd) <= 1e-6, (i, float(g[i]), fd)


def test_rollout_gradient_matches_fd(beam):
    """10 backward-Euler steps: d loss / d(E, load, v0) against central FD (≤ 1e-6)."""
    _check_rollout_grad(beam, "backward_euler")


@pytest.mark.slow
def test_rollout_gradient_matches_fd_bdf2(beam):
    _check_rollout_grad(beam, "bdf2")


@pytest.mark.extended
def test_rollout_matches_simulate(beam):
    """The differentiated rollout follows the same trajectory as the host loop simulate
    (same Newton solves, one compiled step per time step)."""
    th = jnp.array([E_MOD, 1.0, 0.2])
    (_, traj), _ = _rollout_vg(beam, "backward_euler")(th)
    base = beam.pot(_lame(E_MOD), mass=beam.mass)
    xs = []
    final, records = D.simulate(
        base, D.init_state(beam.mesh.points, _v0(beam, 0.05)), beam.bc, D.Integrator(0.1), 10,
        solver=DYN, progress=False, callback=lambda st, res, rec: xs.append(st.x),
    )  # fmt: skip
    assert [r["status"] for r in records] == ["SUCCESS"] * 10
    np.testing.assert_allclose(traj.frames, jnp.stack(xs), rtol=0, atol=1e-12)
    np.testing.assert_allclose(traj.frames[-1], final.x, rtol=0, atol=1e-12)
    # rtol 1e-12 sits at the residual's round-off floor: whether the last step is needed
    # depends on the rounding of two differently compiled programs (measured: 4 against 5
    # Newton steps at one time step on a fresh install, the frames equal to 1e-12)
    steps = np.asarray(traj.stats["steps"])
    host_steps = np.array([r["newton_steps"] for r in records])
    assert np.all(np.abs(steps - host_steps) <= 1), (steps, host_steps)


def _residual_bytes(f, x):
    """Bytes of the residuals a reverse sweep of f stores (the leaves of its VJP)."""
    vjp = jax.jit(lambda x: jax.vjp(f, x)[1])(x)
    return sum(leaf.nbytes for leaf in jax.tree_util.tree_leaves(vjp)), vjp


def _free_swing_loss(beam, E, n_steps, h, checkpoint, adjoint=REVERSE, solver=None):
    """Σ tip-y² over a release from a linear velocity profile (no load)."""
    solver = je.Newton(rtol=1e-10, atol=1e-12, linear="cg") if solver is None else solver
    base = beam.pot(_lame(E), f=jnp.zeros_like(beam.f), mass=beam.mass)
    _, traj = D.rollout(
        base, D.init_state(beam.mesh.points, _v0(beam, 0.05)), beam.bc, D.Integrator(h),
        n_steps, solver=solver, adjoint=adjoint, checkpoint=checkpoint,
        observe=lambda s: s.x[beam.tip],
    )  # fmt: skip
    return jnp.sum(traj.frames[..., 1] ** 2), traj


@pytest.mark.slow
def test_checkpointed_rollout_same_gradient_fewer_residuals(beam):
    """40 steps observing only the tip: segments of 7 steps (5 full + a tail of 5) give the
    same gradient with ≤ 1/2 of the stored residuals."""

    def loss(E, checkpoint):
        return _free_swing_loss(beam, E, 40, 0.1, checkpoint)[0]

    E = jnp.asarray(E_MOD)
    nb_plain, vjp_plain = _residual_bytes(lambda E: loss(E, None), E)
    nb_seg, vjp_seg = _residual_bytes(lambda E: loss(E, 7), E)
    g_plain, g_seg = vjp_plain(1.0)[0], vjp_seg(1.0)[0]
    np.testing.assert_allclose(g_seg, g_plain, rtol=1e-12)
    state_bytes = 4 * beam.mesh.points.size * 8  # x, v, x_prev, v_prev
    assert nb_plain >= 40 * state_bytes / 2  # grows with the number of steps
    assert nb_seg <= nb_plain / 2, (nb_seg, nb_plain)
    assert nb_seg <= 10 * state_bytes, (nb_seg, state_bytes)


@pytest.mark.slow
def test_checkpoint_step_bounds_forward_mode_residuals(beam):
    """200 steps with ImplicitAdjoint(mode="forward") (whose linearisation keeps the element
    Hessians of every step): per-step checkpointing keeps only x* and the state, segments
    O(√n) states; the gradient is the same in all variants."""

    def loss(E, checkpoint, adjoint):
        return _free_swing_loss(beam, E, 200, 0.05, checkpoint, adjoint)[0]

    E = jnp.asarray(E_MOD)
    out = {
        ck: _residual_bytes(lambda E, ck=ck: loss(E, ck, FORWARD), E) for ck in (None, "step", 14)
    }
    grads = {ck: float(v[1](1.0)[0]) for ck, v in out.items()}
    g_rev = float(jax.jit(jax.grad(lambda E: loss(E, None, REVERSE)))(E))
    for g in grads.values():
        assert _rel(g, g_rev) <= 1e-10
    Ke_bytes = 200 * beam.mesh.n_cells * 6 * 6 * 8
    assert out[None][0] >= Ke_bytes
    assert out["step"][0] <= out[None][0] / 10
    assert out[14][0] <= out[None][0] / 100


# ------------------------------------------------------------------------- fit from motion


@pytest.mark.slow  # a TrajectoryCase's gradient vs FD: tests/test_fitting.py
def test_trajectory_case_recovers_E_from_oscillation():
    """A 2D cantilever bent by a tip load is released (load off, v₀ = 0); 4 frames of its
    first 24 backward-Euler steps identify E from a start off by 3× (same mesh, no noise)."""
    from jaxelastic.fitting import Material, TrajectoryCase, fit

    mesh = je.rectangle(6, 2, size=(3.0, 0.5))
    X = np.asarray(mesh.points)
    bc = L.fix(mesh, L.nodes_on_plane(mesh, 0, 0.0))
    facets = L.facets_where(mesh, lambda c: np.isclose(c[:, 0], 3.0))
    f = jnp.asarray(L.traction_load(mesh, facets, (0.0, -0.4)))
    E_true = 100.0
    pot = je.Potential(mesh=mesh, params=_lame(E_true), f_ext=f, psi=M.neo_hookean)
    x_bent = je.solve(pot, bc, solver=TIGHT).x
    mass = jnp.asarray(L.lumped_mass(mesh, 1.0))
    base = pot.replace(f_ext=jnp.zeros_like(f), mass=mass)
    state0 = D.init_state(x_bent)
    integ = D.Integrator(0.5)
    frames = np.array([6, 12, 18, 24])
    _, traj = jax.jit(lambda b: D.rollout(b, state0, bc, integ, 24, solver=DYN))(base)
    assert np.all(np.asarray(traj.status) == Status.SUCCESS)
    tip = np.flatnonzero(np.isclose(X[:, 0], 3.0))
    # the tip really oscillates through the rest line within the window
    assert float(jnp.min(traj.frames[:, tip, 1])) < 0 < float(jnp.max(traj.frames[:, tip, 1]))
    case = TrajectoryCase(
        pot=base,
        state0=state0,
        bc=bc,
        observed=traj.frames[frames - 1],
        frames=frames,
        integ=integ,
        n_steps=24,
    )
    res = fit([case], Material(3.0 * E_true, NU), fields=("E",), max_iter=40, solver=DYN)
    assert res.converged
    assert abs(res.E / E_true - 1) <= 1e-3, res.E
    assert res.loss_history[-1] < 1e-6 * res.loss_history[0]


@pytest.mark.slow
def test_rollout_gradient_dirichlet_and_x0_match_fd(beam):
    """10 steps with the right end driven by ``X + a·sin(2t)·d`` and a perturbed initial
    shape ``x₀ = X + b·u``: d loss/d(a, b) against central FD (≤ 1e-6)."""
    bc_r = L.fix(beam.mesh, beam.right)
    bc = L.combine(beam.bc, bc_r)
    mask_r = jnp.asarray(bc_r.mask)
    X = jnp.asarray(beam.X)
    direction = jnp.asarray([[0.1, -0.3]])
    u = jnp.stack([0.0 * X[:, 0], 0.02 * X[:, 0] ** 2], axis=1)  # zero at the clamp
    mid = np.flatnonzero(np.isclose(beam.X[:, 0], 2.0))
    base = beam.pot(_lame(E_MOD), f=jnp.zeros_like(beam.f), mass=beam.mass)

    def loss(th):
        a, b = th

        def bc_fn(t):
            values = jnp.where(mask_r, X + a * jnp.sin(2.0 * t) * direction, bc.values)
            return L.Dirichlet(bc.mask, values)

        x0 = X + b * jnp.where(mask_r, 0.0, u)
        _, traj = D.rollout(base, D.init_state(x0), bc_fn, D.Integrator(0.1), 10, solver=DYN)
        return jnp.sum(traj.frames[:, mid] ** 2), traj

    vg = jax.jit(jax.value_and_grad(loss, has_aux=True))
    th = jnp.array([0.5, 1.0])
    (_, traj), g = vg(th)
    assert np.all(np.asarray(traj.status) == Status.SUCCESS)
    for i in range(2):
        fd = float(_fd(lambda t: vg(t)[0][0], th, jnp.zeros(2).at[i].set(1.0), 1e-3))
        assert _rel(g[i], fd) <= 1e-6, (i, float(g[i]), fd)


@pytest.mark.slow
def test_forward_mode_with_host_solver(host_beam):
    """jacfwd/jacrev of mode="forward" and jacrev of reverse mode with the bound host
    direct solver (one host-preconditioned adjoint per Jacobian column, applied
    sequentially) equal the matrix-free reverse-mode Jacobian; the Jacobians factorise at
    most once beyond the forward Newton solve."""
    lin, state = host_beam.linear("direct")
    host = state.host

    def xs(th, linear, adjoint):
        solver = TIGHT.replace(linear=linear)
        return _xs(host_beam.pot(_lame(th[0], th[1])), host_beam.bc, solver, adjoint)

    th = jnp.array([E_MOD, NU])
    rev = REVERSE
    J_ref = jax.jit(jax.jacrev(lambda t: xs(t, "cg", rev)))(th)
    f0 = host.factorizations
    jax.block_until_ready(jax.jit(lambda t: xs(t, lin, rev))(th))
    newton = host.factorizations - f0  # factorisations of the plain forward solve
    for name, jac, adjoint in (
        ("jacfwd", jax.jacfwd, FORWARD),
        ("jacrev-forward", jax.jacrev, FORWARD),
        ("jacrev", jax.jacrev, rev),
    ):
        f0 = host.factorizations
        J = jax.jit(jac(lambda t, a=adjoint: xs(t, lin, a)))(th)
        assert _rel(J, J_ref) <= 1e-9, (name, _rel(J, J_ref))
        assert host.factorizations - f0 <= newton + 1, (name, host.factorizations - f0, newton)


@pytest.mark.slow
def test_checkpoint_recomputation_counts(host_beam):
    """Host factorisations over forward + reverse of 10 steps with the bound direct solver:
    ``"step"`` checkpointing saves the Newton solutions (no re-solve: as many as without
    checkpointing), segments re-solve each step once in the reverse sweep; every adjoint
    uses the host back end, and the gradients agree."""
    lin, state = host_beam.linear("direct")
    host = state.host
    solver = je.Newton(rtol=1e-10, atol=1e-12, linear=lin)
    counts, grads = {}, {}
    for ck in (None, "step", 5):

        def loss(E, ck=ck):
            return _free_swing_loss(host_beam, E, 10, 0.05, ck, solver=solver)

        f0, a0 = host.factorizations, host.applications
        (_, traj), grads[ck] = jax.jit(jax.value_and_grad(loss, has_aux=True))(E_MOD)
        assert np.all(np.asarray(traj.status) == Status.SUCCESS)
        newton = int(jnp.sum(traj.stats["steps"]))
        counts[ck] = (host.factorizations - f0, newton, host.applications - a0)
    fac, newton, _ = counts[None]
    # forward: one factorisation per Newton step; reverse: at most one refactorisation per
    # step's adjoint (it is preconditioned by the last factorisation on the host)
    assert newton <= fac <= newton + 10, counts
    assert counts["step"][:2] == counts[None][:2], counts
    assert newton + counts[5][1] <= counts[5][0] <= 2 * newton + 10, counts
    assert counts[5][1] == newton
    for ck, (_, newton, applications) in counts.items():
        assert applications > newton, (ck, counts)  # Newton steps + adjoint PCG iterations
    for g in grads.values():
        assert _rel(g, grads[None]) <= 1e-9  # adjoint rtol 1e-10; preconditioners differ
