"""``jax.vmap`` of a static solve over scenes: material parameters, Dirichlet values, loads.

One small 2D neo-Hookean strip (clamped at x = 0, its right end moved by a prescribed
δ, a distributed load s·f₀ on its top): each batch member has its own (E, ν, δ, s).
Checked, for the device solvers (CG, and the device multigrid where it exists):
the batched solve equals a loop of single solves (float64, ≤ 1e-10), statuses are per
member (a NaN member fails alone), the gradient of a loss of the batched solve equals the
loop's gradients and central finite differences, and the host back ends refuse vmap
with an error that names the device alternatives.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic as je
from jaxelastic import loads
from jaxelastic import materials as M

DEVICE_SOLVERS = (["multilevel"] if hasattr(je, "Multilevel") else []) + ["cg"]
# the default run checks the device multigrid (CG when it is absent); CG too under -m slow
PARAMS = [pytest.param(s, marks=pytest.mark.slow) if i else s for i, s in enumerate(DEVICE_SOLVERS)]

# (E, ν, δ [length], s): one scene per row; the last row differs in every entry
THETA = np.array(
    [
        [100.0, 0.30, 0.05, 1.0],
        [150.0, 0.25, -0.03, 0.5],
        [80.0, 0.40, 0.08, 2.0],
    ]
)


class Strip:
    """The strip, its clamp + end-motion Dirichlet data and the unit top load."""

    def __init__(self):
        self.mesh = je.rectangle(8, 2, (4.0, 1.0))
        X = np.asarray(self.mesh.points)
        self.left = loads.nodes_on_plane(self.mesh, 0, 0.0)
        self.right = loads.nodes_on_plane(self.mesh, 0, 4.0)
        self.top = loads.nodes_on_plane(self.mesh, 1, 1.0)
        self.bc0 = loads.combine(
            loads.fix(self.mesh, self.left), loads.fix(self.mesh, self.right, components=(1,))
        )
        f0 = np.zeros_like(X)
        f0[self.top, 1] = -0.2
        self.f0 = jnp.asarray(f0)
        self.pot0 = je.Potential(mesh=self.mesh, params=M.Lame(1.0, 1.0), psi=M.neo_hookean)

    def scene(self, th):
        """``(pot, bc)`` of one θ = (E, ν, δ, s) (traceable)."""
        E, nu, delta, s = th[0], th[1], th[2], th[3]
        pot = self.pot0.replace(params=M.Lame.from_E_nu(E, nu, dim=2), f_ext=s * self.f0)
        shift = jnp.zeros_like(self.mesh.points).at[self.right, 1].set(delta)
        bc = self.bc0._replace(values=self.bc0.values + shift)
        return pot, bc


@pytest.fixture(scope="module")
def strip():
    return Strip()


def _solver(strip, linear):
    newton = je.Newton(rtol=1e-12, linear=linear)
    return je.solvers.prepare_solver(newton, strip.mesh, strip.bc0)  # multilevel: setup once


@pytest.fixture(scope="module", params=PARAMS)
def setup(request, strip):
    """Per device solver: the jitted single and batched solves of θ and their results."""
    solver = _solver(strip, request.param)

    def one(th):
        pot, bc = strip.scene(th)
        r = je.solve(pot, bc, solver=solver, throw=False)
        return r.x, r.status, r.stats["steps"]

    single = jax.jit(one)
    batched = jax.jit(jax.vmap(one))
    return request.param, solver, single, batched


def _tip_loss(strip, x):
    """Squared mean y-displacement of the top nodes (a scalar per scene)."""
    u = x[strip.top, 1] - strip.mesh.points[strip.top, 1]
    return jnp.mean(u) ** 2


def test_batched_equals_loop_and_statuses_are_per_member(strip, setup):
    """vmap over (E, ν, δ, s) gives each member's single solve (≤ 1e-10), the members
    differ, and a NaN member fails alone (its status is its single solve's; the others
    converge as without it)."""
    name, _, single, batched = setup
    th = np.vstack([THETA, [np.nan, 0.3, 0.0, 1.0]])  # the last member cannot be solved
    xb, stb, stepsb = batched(jnp.asarray(th))
    assert xb.shape == (4, *strip.mesh.points.shape) and stb.shape == (4,)
    for i in range(4):
        x, st, steps = single(jnp.asarray(th[i]))
        assert int(stb[i]) == int(st), (name, i)
        if i < 3:
            assert int(st) == je.Status.SUCCESS, (name, i)
            np.testing.assert_allclose(xb[i], x, rtol=0, atol=1e-10, err_msg=f"{name} {i}")
            assert int(stepsb[i]) == int(steps)
    assert int(stb[3]) != je.Status.SUCCESS
    for i in range(3):  # three genuinely different scenes
        for j in range(i):
            assert float(jnp.max(jnp.abs(xb[i] - xb[j]))) > 1e-3


def test_gradient_of_batched_loss(strip, setup):
    """∂/∂θ of Σ_b loss(x_b(θ_b)) through the batched solve equals the loop of single
    gradients (≤ 1e-8 relative) and central finite differences of the batched solve in E,
    ν, δ and s (≤ 1e-5 relative)."""
    name, solver, _, batched = setup

    def x_of(th):
        pot, bc = strip.scene(th)
        return je.solve(pot, bc, solver=solver).x

    def loss_batched(ths):
        return jnp.sum(jax.vmap(lambda t: _tip_loss(strip, x_of(t)))(ths))

    ths = jnp.asarray(THETA)
    g = jax.jit(jax.grad(loss_batched))(ths)
    g1 = jax.jit(jax.grad(lambda t: _tip_loss(strip, x_of(t))))
    for i in range(len(THETA)):
        gi = g1(ths[i])
        assert float(jnp.max(jnp.abs(g[i] - gi))) <= 1e-8 * float(jnp.max(jnp.abs(gi))), name

    def loss_fd(t):  # the forward solves of the batched function compiled above
        return float(jnp.sum(jax.vmap(lambda x: _tip_loss(strip, x))(batched(t)[0])))

    h = np.array([1e-3, 1e-5, 1e-6, 1e-5])  # per component of θ (E, ν, δ, s)
    for k in range(4):
        e = np.zeros_like(THETA)
        e[:, k] = h[k]
        fd = (loss_fd(ths + e) - loss_fd(ths - e)) / (2 * h[k])
        an = float(jnp.sum(g[:, k]))
        assert abs(fd - an) <= 1e-5 * abs(an) + 1e-14, (name, k, fd, an)


def test_host_back_ends_refuse_vmap_and_name_the_alternative(strip):
    """Direct and AMG under vmap raise (at trace time) a ValueError naming vmap and the
    device solvers to use instead."""
    ths = jnp.asarray(THETA)
    for linear in ("direct", "amg"):
        solver = _solver(strip, linear)

        def one(th, solver=solver):
            pot, bc = strip.scene(th)
            return je.solve(pot, bc, solver=solver, throw=False).x

        with pytest.raises(ValueError, match="vmap") as err:
            jax.jit(jax.vmap(one))(ths)
        assert "linear='cg'" in str(err.value), str(err.value)
        if "multilevel" in DEVICE_SOLVERS:
            assert "multilevel" in str(err.value), str(err.value)
