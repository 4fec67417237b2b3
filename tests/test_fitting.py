"""Differentiable equilibrium (implicit function theorem) and fitting of any ψ parameter.

Gradients of scalar losses through :func:`jaxelastic.solve` are compared with central
finite differences (fourth-order stencil, solves at rtol 1e-12) for (E, ν) in 2D and 3D, a
per-cell μ field, a Mooney–Rivlin constant, a Dirichlet value, and a load magnitude; a
failed forward solve gives NaN cotangents and a raising host helper; the parametrisation
(transforms, regions, cells, any pytree) round-trips; and :func:`fit` recovers (E, ν) from
synthetic two-load-case targets and the Mooney–Rivlin (c10, c01) of a user-written ψ from a
uniaxial and a shear case.
"""

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic as je
from jaxelastic import fitting as F
from jaxelastic import loads as L
from jaxelastic import materials as M
from jaxelastic.fitting import (
    Bounded,
    Fixed,
    Free,
    LoadCase,
    Material,
    Positive,
    TrajectoryCase,
    add_noise,
    fit,
    loss_hessian,
    loss_landscape,
    make_objective,
)
from jaxelastic.solvers import GradientError, Status, value_and_grad

E_MOD, NU = 100.0, 0.3
TIGHT = je.Newton(rtol=1e-12)


def _x(pot, bc, solver=TIGHT, x0=None):
    """Equilibrium positions (differentiable)."""
    return je.solve(pot, bc, x0=x0, solver=solver).x


def _fd(f, x, direction, h):
    """Fourth-order central difference of f at x along direction."""
    fp1, fm1 = f(x + h * direction), f(x - h * direction)
    fp2, fm2 = f(x + 2 * h * direction), f(x - 2 * h * direction)
    return float((8.0 * (fp1 - fm1) - (fp2 - fm2)) / (12.0 * h))


def _value_of(vg):
    """The loss from an already-compiled value_and_grad (saves compiling the forward)."""
    return lambda x: vg(x)[0]


def _rel(a, b):
    return abs(a - b) / max(abs(b), 1e-300)


class Beam:
    """A neo-Hookean cantilever clamped at x = 0 with an end traction at x = L."""

    def __init__(self, dim):
        if dim == 2:
            self.mesh = je.rectangle(8, 2, size=(4.0, 0.5))
            t = (0.0, -0.5)
        else:
            self.mesh = je.box(4, 1, 1, size=(4.0, 1.0, 1.0))
            t = (0.0, 0.0, -0.5)
        self.dim = dim
        self.X = np.asarray(self.mesh.points)
        length = self.X[:, 0].max()
        self.clamp = L.nodes_on_plane(self.mesh, 0, 0.0)
        self.bc = L.fix(self.mesh, self.clamp)
        facets = L.facets_where(self.mesh, lambda c: np.isclose(c[:, 0], length))
        self.f = jnp.asarray(L.traction_load(self.mesh, facets, t))
        self.f_stretch = jnp.asarray(
            L.traction_load(self.mesh, facets, (5.0,) + (0.0,) * (dim - 1))
        )
        self.tip = np.flatnonzero(np.isclose(self.X[:, 0], length))
        self.tip_target = jnp.asarray(self.X[self.tip]) + 0.3 * jnp.asarray(
            [[0.1] + [0.0] * (dim - 2) + [-1.0]]
        )

    def pot(self, params, f=None):
        return je.Potential(
            mesh=self.mesh, params=params, f_ext=self.f if f is None else f, psi=M.neo_hookean
        )

    def tip_loss(self, x):
        return jnp.sum((x[self.tip] - self.tip_target) ** 2)


@pytest.fixture(scope="module")
def beam2():
    return Beam(2)


@pytest.fixture(scope="module")
def beam3():
    return Beam(3)


@pytest.mark.parametrize("dim", [2, 3])
def test_grad_E_nu(beam2, beam3, dim):
    b = beam2 if dim == 2 else beam3

    def loss(th):
        params = M.Lame.from_E_nu(th[0], th[1], dim=dim)
        return b.tip_loss(_x(b.pot(params), b.bc))

    th = jnp.array([E_MOD, NU])
    vg = value_and_grad(loss)
    val, g = vg(th)
    assert np.isfinite(float(val)) and float(val) > 0
    lj = _value_of(vg)
    for i, h in enumerate([1e-3 * E_MOD, 1e-3]):
        fd = _fd(lj, th, jnp.zeros(2).at[i].set(1.0), h)
        assert _rel(float(g[i]), fd) <= 1e-6, (i, float(g[i]), fd)


def test_grad_per_cell_mu_field(beam2):
    b = beam2
    mu0, lam0 = (float(v) for v in M.lame(E_MOD, NU, dim=2))
    n = b.mesh.n_cells
    rng = np.random.default_rng(0)
    mu_field = jnp.asarray(mu0 * (1.0 + 0.3 * rng.uniform(-1, 1, n)))

    def loss(mu):
        return b.tip_loss(_x(b.pot(M.Lame(mu, lam0)), b.bc))

    vg = value_and_grad(loss)
    val, g = vg(mu_field)
    assert g.shape == (n,)
    lj = _value_of(vg)
    # a random direction and two single cells (one near the clamp, one near the tip)
    d = jnp.asarray(rng.standard_normal(n))
    dirs = [d / jnp.linalg.norm(d), jnp.zeros(n).at[0].set(1.0), jnp.zeros(n).at[n - 1].set(1.0)]
    for v in dirs:
        fd = _fd(lj, mu_field, v, 1e-3 * mu0)
        assert _rel(float(jnp.sum(g * v)), fd) <= 1e-6, (float(jnp.sum(g * v)), fd)


def test_grad_dirichlet_value(beam2):
    """Prescribed end displacement s (stretch + shear of the right end), no traction."""
    b = beam2
    right = np.flatnonzero(np.isclose(b.X[:, 0], 4.0))
    bc_right = L.fix(b.mesh, right)
    bc = L.combine(b.bc, bc_right)
    mask_r = jnp.asarray(bc_right.mask)
    direction = jnp.asarray([[0.2, -0.5]])
    params = M.Lame(*(float(v) for v in M.lame(E_MOD, NU, dim=2)))
    mid = np.flatnonzero(np.isclose(b.X[:, 0], 2.0))
    target = jnp.asarray(b.X[mid]) + jnp.asarray([[0.05, -0.3]])
    pot = b.pot(params, f=jnp.zeros_like(b.f))

    def loss(s):
        values = jnp.where(mask_r, jnp.asarray(b.X) + s * direction, bc.values)
        x = _x(pot, L.Dirichlet(bc.mask, values))
        return jnp.sum((x[mid] - target) ** 2)

    s0 = jnp.asarray(0.4)
    vg = value_and_grad(loss)
    val, g = vg(s0)
    fd = _fd(_value_of(vg), s0, 1.0, 1e-3)
    assert _rel(float(g), fd) <= 1e-6, (float(g), fd)


@pytest.mark.extended
def test_grad_load_magnitude(beam2):
    b = beam2
    params = M.Lame(*(float(v) for v in M.lame(E_MOD, NU, dim=2)))

    def loss(s):
        return b.tip_loss(_x(b.pot(params, f=s * b.f), b.bc))

    s0 = jnp.asarray(1.0)
    vg = value_and_grad(loss)
    _, g = vg(s0)
    fd = _fd(_value_of(vg), s0, 1.0, 1e-3)
    assert _rel(float(g), fd) <= 1e-6, (float(g), fd)


@pytest.mark.extended
def test_grad_wrt_whole_potential_and_bc(beam2):
    """jax.grad w.r.t. the Potential and Dirichlet pytrees: f_ext cotangent is a field,
    the mask cotangent is float0, and the f_ext cotangent matches the load-scale gradient."""
    b = beam2
    params = M.Lame(*(float(v) for v in M.lame(E_MOD, NU, dim=2)))

    def loss(pot, bc):
        return b.tip_loss(_x(pot, bc))

    gp, gb = jax.jit(jax.grad(loss, argnums=(0, 1), allow_int=True))(b.pot(params), b.bc)
    assert gp.f_ext.shape == b.f.shape
    assert gb.mask.dtype == jax.dtypes.float0
    _, g_s = value_and_grad(lambda s: loss(b.pot(params, f=s * b.f), b.bc))(jnp.asarray(1.0))
    assert _rel(float(jnp.sum(gp.f_ext * b.f)), float(g_s)) <= 1e-10
    # only clamped dofs carry a Dirichlet-value cotangent (the reaction sensitivity)
    assert np.all(np.asarray(gb.values)[~np.asarray(b.bc.mask)] == 0)


@pytest.mark.slow  # the host adjoint vs CG: also tests/test_implicit.py
def test_warm_start_and_direct_solver_agree(beam2):
    """The gradient does not depend on the initial guess nor on the linear solver (matrix-free
    CG inside jit vs the host sparse Cholesky bound outside jit)."""
    b = beam2

    def loss(th, x0, solver):
        params = M.Lame.from_E_nu(th[0], th[1], dim=2)
        return b.tip_loss(_x(b.pot(params), b.bc, solver=solver, x0=x0))

    th = jnp.array([E_MOD, NU])
    grad = jax.jit(jax.grad(loss), static_argnums=2)
    cg = je.Newton(rtol=1e-12, linear=je.CG())
    g_cold = grad(th, b.mesh.points, cg)
    x_warm = _x(b.pot(M.Lame.from_E_nu(1.1 * E_MOD, NU, dim=2)), b.bc)
    g_warm = grad(th, x_warm, cg)
    direct = je.solvers.prepare_solver(je.Newton(rtol=1e-12, linear="direct"), b.mesh, b.bc)
    g_direct = grad(th, b.mesh.points, direct)
    np.testing.assert_allclose(g_warm, g_cold, rtol=1e-8)
    np.testing.assert_allclose(g_direct, g_cold, rtol=1e-8)


def test_failed_solve_gives_nan_and_raises(beam2):
    b = beam2
    bad = je.Newton(rtol=1e-12, max_steps=1)

    def loss(th):
        params = M.Lame.from_E_nu(th[0], th[1], dim=2)
        return b.tip_loss(je.solve(b.pot(params), b.bc, solver=bad, throw=False).x)

    th = jnp.array([E_MOD, NU])
    params = M.Lame.from_E_nu(E_MOD, NU, dim=2)
    res = je.solve(b.pot(params), b.bc, solver=bad, throw=False)
    assert int(res.status) == Status.MAX_STEPS
    _, g = jax.jit(jax.value_and_grad(loss))(th)
    assert np.all(np.isnan(np.asarray(g)))
    with pytest.raises(GradientError):
        je.solvers.check_finite_gradients(g)  # what value_and_grad / fit run on the host


def _targets(pots, bc, material, solver=TIGHT, **kw):
    """Equilibrium positions of each potential at ``material``, computed with the fitting
    objective's own compiled function (so the fit that follows does not recompile)."""
    cases = [LoadCase(pot=p, bc=bc, observed=p.mesh.points) for p in pots]
    obj = make_objective(cases, material, solver=solver, **kw)
    (_, auxs), _ = obj.value_and_grad(obj.z0)
    return [a.warm for a in auxs]


def _cases(b, material, nodes=None, **kw):
    """Bending + stretch load cases of beam b with synthetic targets at ``material``."""
    pots = [b.pot(None), b.pot(None, f=b.f_stretch)]
    xs = _targets(pots, b.bc, material, **kw)
    if nodes is None:
        return [LoadCase(pot=p, bc=b.bc, observed=x) for p, x in zip(pots, xs, strict=True)]
    return [
        LoadCase(pot=p, bc=b.bc, observed=x[nodes], nodes=nodes)
        for p, x in zip(pots, xs, strict=True)
    ]


def test_fit_E_nu_two_load_cases(beam2):
    """Synthetic targets on the same mesh (full observations), bending + stretch;
    start from E off by 3× and ν off by 0.15."""
    b = beam2
    E_true, nu_true = 100.0, 0.3
    cases = _cases(b, Material(E_true, nu_true))
    res = fit(cases, Material(3.0 * E_true, nu_true - 0.15), max_iter=60, solver=TIGHT)
    assert res.converged
    assert abs(res.E / E_true - 1) <= 1e-3, res.E
    assert abs(res.nu / nu_true - 1) <= 1e-3, res.nu
    assert res.loss_history[-1] < 1e-3 * res.loss_history[0]
    assert res.param_history.shape == (res.iterations + 1, 2)
    assert res.newton_steps.shape == (res.iterations + 1, 2)


@pytest.mark.slow  # marker observations: also tests/test_fit_cli.py, notebook 03
def test_fit_E_nu_markers(beam2):
    """Same, observing only 2 of 27 nodes (7 %): the top node at mid-span and at the tip."""
    b = beam2
    E_true, nu_true = 100.0, 0.3
    top = np.isclose(b.X[:, 1], 0.5)
    markers = jnp.asarray([np.flatnonzero(top & np.isclose(b.X[:, 0], xm))[0] for xm in (2.0, 4.0)])
    cases = _cases(b, Material(E_true, nu_true), markers)
    res = fit(cases, Material(3.0 * E_true, nu_true - 0.15), max_iter=60, solver=TIGHT)
    assert res.converged
    assert abs(res.E / E_true - 1) <= 1e-3, res.E
    assert abs(res.nu / nu_true - 1) <= 1e-3, res.nu


@pytest.mark.slow  # the 3D gradient is checked by test_grad_E_nu[3]
@pytest.mark.parametrize("markers", [False, True])
def test_fit_E_nu_3d(beam3, markers):
    """3D box(4,1,1) (24 tets, 20 nodes): full observations, or 2 marker nodes (10 %): the
    top corner at mid-span and at the tip. E off by 3x, nu off by 0.15."""
    b = beam3
    E_true, nu_true = 100.0, 0.3
    nodes = None
    if markers:
        top = np.isclose(b.X[:, 2], 1.0) & np.isclose(b.X[:, 1], 1.0)
        nodes = jnp.asarray([np.flatnonzero(top & np.isclose(b.X[:, 0], xm))[0] for xm in (2, 4)])
        assert nodes.size <= 0.1 * b.mesh.n_nodes
    cases = _cases(b, Material(E_true, nu_true), nodes)
    res = fit(cases, Material(3.0 * E_true, nu_true - 0.15), max_iter=60, solver=TIGHT)
    assert res.converged, res.stop_reason
    assert abs(res.E / E_true - 1) <= 1e-3, res.E
    assert abs(res.nu / nu_true - 1) <= 1e-3, res.nu


class Bar:
    """A two-material plane-stress bar (left half soft, right half stiff), 4 x 0.5, 64 cells."""

    def __init__(self):
        self.mesh = je.rectangle(16, 2, size=(4.0, 0.5))
        self.X = np.asarray(self.mesh.points)
        self.bc = L.fix(self.mesh, L.nodes_on_plane(self.mesh, 0, 0.0))
        facets = L.facets_where(self.mesh, lambda c: np.isclose(c[:, 0], 4.0))
        self.f = jnp.asarray(L.traction_load(self.mesh, facets, (0.0, -0.5)))
        self.f_stretch = jnp.asarray(L.traction_load(self.mesh, facets, (5.0, 0.0)))
        centroids = self.X[np.asarray(self.mesh.cells)].mean(axis=1)
        self.regions = (centroids[:, 0] > 2.0).astype(np.int32)

    def pot(self, params, f=None):
        return je.Potential(
            mesh=self.mesh, params=params, f_ext=self.f if f is None else f, psi=M.neo_hookean
        )


@pytest.fixture(scope="module")
def bar():
    return Bar()


@pytest.mark.extended
def test_fit_two_material_bar(bar):
    """Piecewise-constant E and nu over two regions (4 unknowns), bending + stretch, plane
    stress, from a uniform initial guess: both moduli well within 2 % (measured ~1e-12)."""
    true = Material(E=np.array([100.0, 300.0]), nu=np.array([0.3, 0.3]))
    kw = dict(regions=bar.regions, plane="stress")
    cases = _cases(bar, true, **kw)
    res = fit(cases, Material(200.0, 0.25), max_iter=100, solver=TIGHT, **kw)
    assert res.E.shape == (2,) and res.param_history.shape == (res.iterations + 1, 2, 2)
    err = np.abs(res.E / true.E - 1)
    assert np.all(err <= 1e-6), (res.E, res.stop_reason)
    assert np.all(np.abs(res.nu - true.nu) <= 1e-6), res.nu


def test_fit_with_noise(beam2):
    """1 % observation noise (sigma = 1 % of the RMS displacement), full observations,
    bending + stretch: report the error, assert a sane bound."""
    b = beam2
    E_true, nu_true = 100.0, 0.3
    clean = _cases(b, Material(E_true, nu_true))
    keys = jax.random.split(jax.random.PRNGKey(0), len(clean))
    cases = [
        LoadCase(pot=c.pot, bc=c.bc, observed=add_noise(c.observed, b.X, 0.01, k))
        for c, k in zip(clean, keys, strict=True)
    ]
    res = fit(
        cases, Material(3.0 * E_true, nu_true - 0.15), max_iter=60, solver=TIGHT, progress=True
    )
    e_E, e_nu = res.E / E_true - 1, res.nu - nu_true
    print(f"1% noise: E rel error {e_E:.2e}, nu abs error {e_nu:.2e}, loss {res.loss:.2e}")
    assert res.converged, res.stop_reason
    assert abs(e_E) <= 0.02 and abs(e_nu) <= 0.03, (e_E, e_nu)
    # the fitted loss sits at the noise floor (~2 * 1e-4 for two cases), not above it
    assert res.loss <= 1e-3


@pytest.mark.slow  # loss_hessian: also the Mooney-Rivlin fit below
def test_identifiability_bending_vs_stretch(beam2):
    """Gauss-Newton Hessian of the loss in (ln E, nu) at the truth: from a single bending
    case nu is nearly confounded with E (plane-strain bending sees ~E/(1-nu^2)); adding a
    stretch case removes the valley. Variance-inflation factor H_nn (H^-1)_nn = 1/(1-rho^2)."""
    b = beam2
    truth = Material(E_MOD, NU)
    bend, stretch = _cases(b, truth)
    vif = []
    for cases in ([bend], [bend, stretch]):
        H = loss_hessian(cases, truth, solver=TIGHT)
        assert np.all(np.linalg.eigvalsh(H) > 0), H
        vif.append(H[1, 1] * np.linalg.inv(H)[1, 1])
    print(f"VIF of nu: bending only {vif[0]:.3g}, bending + stretch {vif[1]:.3g}")
    assert vif[0] >= 20 * vif[1], vif


@pytest.mark.extended  # about 35 s: central differences of every region's E and nu
def test_grad_region_parameters_fd(bar):
    """Gradient of the fitting objective w.r.t. the unconstrained region variables (two
    regions; and per-cell fields with a Tikhonov term) vs 4th-order central differences."""
    true = Material(E=np.array([100.0, 300.0]), nu=np.array([0.3, 0.25]))
    kw = dict(regions=bar.regions, plane="stress")
    cases = _cases(bar, true, **kw)
    rng = np.random.default_rng(1)
    for regions, reg in ((bar.regions, 0.0), ("cells", 1e-2)):
        obj = make_objective(
            cases,
            Material(150.0, 0.2),
            regions=regions,
            regularization=reg,
            plane="stress",
            solver=TIGHT,
        )
        z = obj.z0 + 0.1 * jnp.asarray(rng.standard_normal(obj.z0.shape))

        def f(zz, obj=obj):
            return obj.value_and_grad(zz)[0][0]

        (_, _), g = obj.value_and_grad(z)
        n = z.size
        dirs = [jnp.zeros(n).at[0].set(1.0), jnp.zeros(n).at[n - 1].set(1.0)]
        d = jnp.asarray(rng.standard_normal(n))
        dirs.append(d / jnp.linalg.norm(d))
        for v in dirs:
            fd = _fd(f, z, v, 1e-3)
            assert _rel(float(jnp.sum(g * v)), fd) <= 1e-6, (regions, float(jnp.sum(g * v)), fd)


def test_fit_adam_E_only(beam2):
    """Adam (an optax transformation with a decaying step, no line search), fitting E alone
    with nu held at its (true) initial value."""
    import optax

    b = beam2
    cases = _cases(b, Material(E_MOD, NU))
    with pytest.raises(ValueError, match="optimizer"):
        fit(cases, Material(E_MOD, NU), optimizer="bfgs")
    res = fit(
        cases,
        Material(3.0 * E_MOD, NU),
        fields=("E",),
        optimizer=optax.adam(optax.exponential_decay(0.1, 10, 0.7)),
        max_iter=80,
        solver=TIGHT,
    )
    assert res.param_history.shape == (res.iterations + 1, 2)
    assert np.all(res.param_history[:, 1] == NU)  # nu never moves
    assert abs(res.E / E_MOD - 1) <= 1e-2, res.E
    assert res.loss_history[-1] <= 1e-4 * res.loss_history[0]


def test_loss_landscape_minimum_at_truth(beam2):
    b = beam2
    cases = _cases(b, Material(E_MOD, NU))
    Es, nus = np.array([80.0, 100.0, 125.0]), np.array([0.2, 0.3, 0.4])
    land = loss_landscape(cases, Es, nus, solver=TIGHT)
    assert land.shape == (3, 3) and np.all(np.isfinite(land))
    assert land[1, 1] <= 1e-16 and np.all(np.delete(land.ravel(), 4) > 1e-4)


def test_add_noise_definition():
    rng = np.random.default_rng(0)
    X = rng.standard_normal((4000, 3))
    obs = X + 0.2 * rng.standard_normal((4000, 3))
    rms = np.sqrt(np.mean(np.sum((obs - X) ** 2, axis=1)))
    noisy = np.asarray(add_noise(jnp.asarray(obs), jnp.asarray(X), 0.05, jax.random.PRNGKey(1)))
    assert abs(np.std(noisy - obs) / (0.05 * rms) - 1) <= 0.03


def test_transforms_roundtrip_and_validation():
    v = jnp.asarray([1e-3, 2.0, 3e7])
    for t, x in (
        (Positive(), v),
        (Positive(scale=1e5), v),
        (Bounded(-1.0, 0.5), jnp.asarray([-0.9, 0.0, 0.49])),
        (Free(), jnp.asarray([-3.0, 0.0, 2.0])),
    ):
        ref = t.reference(x)
        np.testing.assert_allclose(t.forward(t.inverse(x, ref), ref), x, rtol=1e-12)
    assert float(jnp.max(jnp.abs(Positive().inverse(v, Positive().reference(v))))) == 0.0
    assert not Fixed().fitted and Positive().log_scale and not Bounded(0, 1).log_scale
    with pytest.raises(ValueError, match="> 0"):
        Positive().check(-1.0, "c10")
    with pytest.raises(ValueError, match="lie in"):
        Bounded(0.0, 0.5).check(0.5, "nu")
    with pytest.raises(ValueError, match="lo < hi"):
        Bounded(1.0, 0.0)


class Fibre(NamedTuple):
    """A made-up parameter pytree: a nested dict, a per-region leaf and a held field."""

    k: Any
    extra: Any


def test_parametrization_of_any_pytree():
    """Per-leaf transforms and layouts: ``k`` per region (Positive), ``extra["a"]`` shared
    (Bounded), ``extra["b"]`` a held per-cell field passed through untouched."""
    mesh = je.rectangle(2, 1)  # 4 triangles
    labels = np.array([0, 0, 1, 1])
    held = jnp.arange(4.0)
    init = Fibre(k=2.0, extra={"a": 0.25, "b": held})
    pz = F.make_parametrization(
        init,
        Fibre(k=Positive(), extra={"a": Bounded(0.0, 1.0), "b": Fixed()}),
        regions=Fibre(k=labels, extra={"a": None, "b": None}),
        mesh=mesh,
        regularization=0.5,
    )
    assert pz.names == ("k", "extra[a]", "extra[b]") and pz.fitted == ("k", "extra[a]")
    z0 = pz.initial_z()
    assert z0.shape == (3,) and pz.sizes() == (2, 1, 0)
    np.testing.assert_allclose(z0[:2], 0.0)  # Positive is relative to the initial value
    p = pz.from_unconstrained(z0 + jnp.asarray([np.log(2.0), 0.0, 0.0]))
    np.testing.assert_allclose(p.k, [4.0, 2.0])
    assert p.extra["b"] is pz.init.extra["b"]
    psi = pz.expand(p)
    np.testing.assert_allclose(psi.k, [4.0, 4.0, 2.0, 2.0])
    assert jnp.shape(psi.extra["a"]) == ()
    np.testing.assert_allclose(pz.to_unconstrained(p), z0 + jnp.asarray([np.log(2.0), 0, 0]))
    # the Tikhonov penalty acts on the region leaf's unconstrained values only
    assert float(pz.penalty(z0 + jnp.asarray([0.0, 0.0, 5.0]))) == 0.0
    np.testing.assert_allclose(pz.penalty(z0 + jnp.asarray([1.0, 0.0, 0.0])), 0.5)
    # fields= fixes the other leaves; jit over the parametrisation (a pytree) works
    pk = F.make_parametrization(init, Fibre(Positive(), {"a": Free(), "b": Fixed()}), fields="k")
    assert pk.size == 1 and pk.fitted == ("k",)
    np.testing.assert_allclose(jax.jit(lambda q, z: q.psi_params(z).k)(pk, jnp.ones(1)), 2 * np.e)
    with pytest.raises(ValueError, match="fields"):
        F.make_parametrization(init, Free(), fields=("G",))
    with pytest.raises(ValueError, match="nothing to fit"):
        F.make_parametrization(init, Fixed())
    with pytest.raises(ValueError, match="> 0"):
        F.make_parametrization(Fibre(-1.0, {"a": 0.2, "b": held}))


def test_material_parametrization_and_adjacency():
    E, nu = jnp.asarray([1e3, 2e7]), jnp.asarray([-0.9, 0.49])
    mesh = je.rectangle(2, 1)  # 4 triangles
    labels = np.array([0, 0, 1, 1])
    pz = F.material_parametrization(Material(E, nu), mesh, regions=labels)
    p = pz.from_unconstrained(pz.to_unconstrained(Material(E, nu)))
    np.testing.assert_allclose(p.E, E, rtol=1e-13)
    np.testing.assert_allclose(p.nu, nu, rtol=1e-12)
    pn = F.material_parametrization(Material(10.0, 0.3), mesh, regions=labels, fields=("nu",))
    assert pn.initial_z().shape == (2,)
    lame = pn.psi_params(pn.initial_z())
    assert isinstance(lame, M.Lame) and lame.mu.shape == (4,)
    np.testing.assert_allclose(pn.from_unconstrained(pn.initial_z()).E, [10.0, 10.0])
    # adjacency of a 2x1 rectangle split into triangles: the two squares share an edge
    assert F.region_adjacency(mesh.cells, labels).tolist() == [[0, 1]]
    assert len(F.region_adjacency(mesh.cells, np.arange(4))) == 3  # 3 interior edges
    with pytest.raises(ValueError, match="fields"):
        F.material_parametrization(Material(10.0, 0.3), mesh, fields=("G",))
    with pytest.raises(ValueError, match="labels"):
        F.material_parametrization(Material(10.0, 0.3), mesh, regions=np.array([0, 2, 2, 2]))
    with pytest.raises(ValueError, match="lie in"):
        F.material_parametrization(Material(10.0, 0.6), mesh)
    with pytest.raises(ValueError, match="regularization needs regions"):
        F.material_parametrization(Material(10.0, 0.3), mesh, regularization=1.0)
    # nu restricted to (0, 0.5)
    p0 = F.material_parametrization(Material(10.0, 0.3), mesh, nu_bounds=(0.0, 0.5))
    assert 0.0 < float(p0.from_unconstrained(jnp.asarray([0.0, -40.0])).nu) < 1e-12


# ------------------------------------------------------------ a user-written Mooney–Rivlin


class MR(NamedTuple):
    """Compressible Mooney–Rivlin constants: c10, c01 [Pa] and the bulk modulus kappa [Pa]."""

    c10: Any
    c01: Any
    kappa: Any


def mooney_rivlin(F_, p: MR):
    """``ψ = c10 (Ī₁ − 3) + c01 (Ī₂ − 3) + κ/2 (J − 1)²`` with the isochoric invariants
    ``Ī₁ = J^(−2/3) I₁``, ``Ī₂ = J^(−4/3) I₂`` of C = FᵀF (2D: plane strain, F₃₃ = 1);
    +inf for J ≤ 0 (Holzapfel 2000, *Nonlinear Solid Mechanics*, §6.5, eq. 6.149)."""
    d = F_.shape[0]
    J = je.mechanics.kinematics.det(F_)
    C = F_.T @ F_
    I1 = jnp.trace(C) + (3 - d)
    I2 = 0.5 * (I1**2 - jnp.sum(C * C) - (3 - d))
    ok = J > 0
    Jp = jnp.where(ok, J, 1.0)
    iso = p.c10 * (Jp ** (-2 / 3) * I1 - 3) + p.c01 * (Jp ** (-4 / 3) * I2 - 3)
    return jnp.where(ok, iso + 0.5 * p.kappa * (J - 1) ** 2, jnp.inf)


MR_TRUE = MR(c10=0.4, c01=0.1, kappa=5.0)
MR_TRANSFORMS = MR(Positive(), Positive(), Fixed())


class Block:
    """A unit square, rectangle(4, 4): *uniaxial* tension (rollers at y = 0, a pull on
    y = 1) and *shear* (clamped at y = 0, a tangential traction on y = 1)."""

    def __init__(self):
        self.mesh = je.rectangle(4, 4, size=(1.0, 1.0))
        X = np.asarray(self.mesh.points)
        bottom = L.nodes_on_plane(self.mesh, 1, 0.0)
        origin = np.flatnonzero(np.all(np.isclose(X, 0.0), axis=1))
        top = L.facets_where(self.mesh, lambda c: np.isclose(c[:, 1], 1.0))
        self.bcs = dict(
            uniaxial=L.combine(L.fix(self.mesh, bottom, components=(1,)), L.fix(self.mesh, origin)),
            shear=L.fix(self.mesh, bottom),
        )
        self.f = dict(
            uniaxial=jnp.asarray(L.traction_load(self.mesh, top, (0.0, 0.6))),
            shear=jnp.asarray(L.traction_load(self.mesh, top, (0.3, 0.0))),
        )

    def pot(self, name, params=None):
        return je.Potential(mesh=self.mesh, params=params, f_ext=self.f[name], psi=mooney_rivlin)

    def cases(self, params=MR_TRUE):
        out = []
        for name in ("uniaxial", "shear"):
            x = je.solve(self.pot(name, params), self.bcs[name], solver=TIGHT).x
            out.append(LoadCase(pot=self.pot(name), bc=self.bcs[name], observed=x))
        return out


@pytest.fixture(scope="module")
def block():
    return Block()


@pytest.mark.slow  # user psi: the fit below recovers it to 1e-6
def test_grad_mooney_rivlin_constants_fd(block):
    """d loss / d(c10, c01) through the solver (implicit adjoint) vs central differences,
    directly on the ψ parameters and through the fitting objective in z."""
    cases = block.cases()
    bc = block.bcs["shear"]
    obs = cases[1].observed

    def loss(th):
        x = _x(block.pot("shear", MR(th[0], th[1], MR_TRUE.kappa)), bc)
        return jnp.sum((x - obs - 0.01) ** 2)

    th = jnp.array([0.3, 0.15])
    vg = value_and_grad(loss)
    _, g = vg(th)
    for i in range(2):
        fd = _fd(_value_of(vg), th, jnp.zeros(2).at[i].set(1.0), 1e-4)
        assert _rel(float(g[i]), fd) <= 1e-6, (i, float(g[i]), fd)
    obj = make_objective(cases, MR(0.3, 0.15, 5.0), transforms=MR_TRANSFORMS, solver=TIGHT)
    z = obj.z0 + 0.05
    (_, auxs), gz = obj.value_and_grad(z)
    assert all(bool(a.ok) for a in auxs) and gz.shape == (2,)
    for v in (jnp.asarray([1.0, 0.0]), jnp.asarray([0.6, -0.8])):
        fd = _fd(lambda zz: obj.value_and_grad(zz)[0][0], z, v, 1e-4)
        assert _rel(float(jnp.vdot(gz, v)), fd) <= 1e-6, (float(jnp.vdot(gz, v)), fd)


@pytest.mark.extended
def test_fit_mooney_rivlin_uniaxial_and_shear(block):
    """(c10, c01) of the user-written ψ from a uniaxial and a shear case (synthetic targets
    on the same mesh, κ held), from (0.2, 0.3): recovered to 1e-6 (measured ~1e-10)."""
    cases = block.cases()
    res = fit(cases, MR(0.2, 0.3, MR_TRUE.kappa), transforms=MR_TRANSFORMS, max_iter=100)
    assert res.converged, res.stop_reason
    assert isinstance(res.material, MR) and res.E is None
    assert res.material.kappa == MR_TRUE.kappa
    for name in ("c10", "c01"):
        got, want = getattr(res.material, name), getattr(MR_TRUE, name)
        assert abs(got / want - 1) <= 1e-6, (name, got)
    assert res.param_history.shape == (res.iterations + 1, 3)
    # the Hessian in (ln c10, ln c01) at the truth is positive definite: both identifiable
    H = loss_hessian(cases, MR_TRUE, transforms=MR_TRANSFORMS)
    assert H.shape == (2, 2) and np.all(np.linalg.eigvalsh(H) > 0), H


@pytest.mark.extended  # the adjoint of a rollout stays in the default tier (test_implicit)
def test_trajectory_case_gradient(beam2):
    """A released cantilever observed at 3 of 8 backward-Euler steps: zero loss at the truth,
    and the objective's gradient in z matches central differences."""
    b = beam2
    params = M.Lame.from_E_nu(E_MOD, NU, dim=2)
    x_bent = _x(b.pot(params), b.bc)
    mass = jnp.asarray(L.lumped_mass(b.mesh, 1.0))
    pot = b.pot(None, f=jnp.zeros_like(b.f)).replace(mass=mass)
    state0 = je.dynamics.init_state(x_bent)
    integ = je.Integrator(0.5)
    frames = np.array([3, 6, 8])
    _, traj = je.dynamics.rollout(pot.replace(params=params), state0, b.bc, integ, 8, solver=TIGHT)
    assert np.all(np.asarray(traj.status) == Status.SUCCESS)
    case = TrajectoryCase(
        pot=pot,
        state0=state0,
        bc=b.bc,
        observed=traj.frames[frames - 1],
        frames=frames,
        integ=integ,
        n_steps=8,
    )
    assert case.mesh is b.mesh
    obj = make_objective([case], Material(E_MOD, NU), solver=TIGHT)
    (f0, auxs), _ = obj.value_and_grad(obj.z0)
    assert float(f0) <= 1e-18 and int(auxs[0].newton_steps) >= 8
    z = obj.z0 + jnp.asarray([0.2, -0.1])
    (_, _), g = obj.value_and_grad(z)
    for v in (jnp.asarray([1.0, 0.0]), jnp.asarray([0.0, 1.0])):
        fd = _fd(lambda zz: obj.value_and_grad(zz)[0][0], z, v, 1e-3)
        assert _rel(float(jnp.vdot(g, v)), fd) <= 1e-6, (float(jnp.vdot(g, v)), fd)


def _block(n):
    """A 2 x 1 plane-strain block, rectangle(2n, n), clamped at x = 0; shear and stretch
    tractions on x = 2 (as two potentials)."""
    mesh = je.rectangle(2 * n, n, size=(2.0, 1.0))
    bc = L.fix(mesh, L.nodes_on_plane(mesh, 0, 0.0))
    fac = L.facets_where(mesh, lambda c: np.isclose(c[:, 0], 2.0))
    fs = [jnp.asarray(L.traction_load(mesh, fac, t)) for t in ((0.0, -1.0), (2.0, 0.0))]
    return mesh, bc, [je.Potential(mesh=mesh, params=None, f_ext=f, psi=M.neo_hookean) for f in fs]


@pytest.mark.slow
def test_no_inverse_crime_refinement():
    """Targets on a fine mesh (n = 32, 4,096 cells), fits on nested coarser meshes observing
    every coarse node: the error is discretisation error, shrinking with refinement
    (measured: E -12.8 %, -6.4 %, -2.8 %; nu -0.053, -0.024, +0.002 for n = 2, 4, 8)."""
    mesh_f, bc_f, pots_f = _block(32)
    xs = _targets(pots_f, bc_f, Material(E_MOD, NU))
    Xf = np.asarray(mesh_f.points)
    errs = []
    for n in (2, 4, 8):
        mesh, bc, pots = _block(n)
        idx = np.array([np.argmin(np.sum((Xf - x) ** 2, axis=1)) for x in np.asarray(mesh.points)])
        assert np.allclose(Xf[idx], mesh.points)
        cases = [LoadCase(pot=p, bc=bc, observed=x[idx]) for p, x in zip(pots, xs, strict=True)]
        res = fit(cases, Material(3.0 * E_MOD, NU - 0.15), max_iter=80, solver=TIGHT)
        assert res.converged, (n, res.stop_reason)
        errs.append((res.E / E_MOD - 1, res.nu - NU, res.loss))
        print(
            f"n={n} ({mesh.n_cells} cells): E error {errs[-1][0]:+.2e}, nu error "
            f"{errs[-1][1]:+.2e}, loss {errs[-1][2]:.2e}"
        )
    e_E = [abs(e[0]) for e in errs]
    assert e_E[0] > e_E[1] > e_E[2] and e_E[2] <= 0.04, e_E
    assert errs[0][2] > errs[1][2] > errs[2][2]  # misfit = model error, shrinking
    assert abs(errs[2][1]) <= 0.01


@pytest.mark.slow
def test_fit_per_cell_field_tv(bar):
    """E per cell (64 unknowns, nu known) with a small total-variation term recovers the
    two-material bar's piecewise-constant modulus (measured after 300 L-BFGS iterations:
    cells within 0.5 %; a Tikhonov term instead smears the jump by ~ +-10 %)."""
    true = Material(E=np.array([100.0, 300.0]), nu=np.array([0.3, 0.3]))
    cases = _cases(bar, true, regions=bar.regions, plane="stress")
    res = fit(
        cases,
        Material(200.0, 0.3),
        regions="cells",
        fields=("E",),
        plane="stress",
        regularization=1e-6,
        reg_kind="tv",
        max_iter=300,
        solver=TIGHT,
    )
    assert res.E.shape == (bar.mesh.n_cells,)
    err = np.abs(res.E / true.E[bar.regions] - 1)
    print(f"per-cell TV fit: max error {err.max():.2e}, median {np.median(err):.2e}")
    assert np.median(err) <= 1e-3 and err.max() <= 0.02, err


def test_fit_failed_solve_raises(beam2):
    """A forward solve that cannot converge (one Newton step allowed) stops the fit loudly."""
    b = beam2
    pot = b.pot(None)
    cases = [LoadCase(pot=pot, bc=b.bc, observed=pot.mesh.points + 0.1)]
    with pytest.raises(GradientError, match="forward solve failed"):
        fit(cases, Material(E_MOD, NU), solver=je.Newton(rtol=1e-12, max_steps=1))


def test_fit_callback_stops_at_an_iteration_boundary(beam2):
    """``callback(k, params, loss) -> True`` stops the fit after that iteration and keeps
    every iterate so far (the hook a Ctrl-C handler uses)."""
    cases = _cases(beam2, Material(100.0, 0.3))
    seen = []

    def stop_after_two(k, params, loss):
        seen.append((k, float(params.E), float(loss)))
        return k >= 2

    res = fit(cases, Material(300.0, 0.15), solver=TIGHT, callback=stop_after_two)
    assert res.stop_reason == "callback" and res.iterations == 2 and not res.converged
    assert [k for k, _, _ in seen] == [1, 2]
    assert len(res.loss_history) == 3 and seen[-1][2] == pytest.approx(res.loss)
    assert seen[-1][1] == pytest.approx(res.E)
