"""Derivatives with respect to the rest shape: :meth:`jaxelastic.Mesh.with_points` and
:mod:`jaxelastic.mesh.geometry`.

* the rest quantities of the JAX path (``dN``, weights, facet integrals, lumped masses)
  equal the NumPy ones of :func:`jaxelastic.from_arrays` and :mod:`jaxelastic.loads` to
  round-off (P1, P2, composite; 2D and 3D), also under jit;
* shape gradients ``d loss / d X`` through static solves, load steps, dynamics rollouts and
  a fitting case, against fourth-order central differences (≤ 1e-6 relative) for
  compliance, a probe displacement and a fit misfit (P1 and P2, 2D and 3D, F-bar);
* bad input: moved points that invert or collapse a cell are refused naming the cells
  outside jit, and give status INVERTED inside jit; wrong shapes and NaN are refused.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic as je
from jaxelastic import dynamics as D
from jaxelastic import fitting as F
from jaxelastic import loads as L
from jaxelastic import materials as M
from jaxelastic.mesh import geometry as G

TIGHT = je.Newton(rtol=1e-12)
PARAMS = je.Lame.from_E_nu(100.0, 0.3)


def _fd(f, x, direction, h):
    """Fourth-order central difference of f at x along direction."""
    fp1, fm1 = f(x + h * direction), f(x - h * direction)
    fp2, fm2 = f(x + 2 * h * direction), f(x - 2 * h * direction)
    return (8.0 * (fp1 - fm1) - (fp2 - fm2)) / (12.0 * h)


def _perturbed(mesh, scale=0.02, seed=0):
    """The mesh's points with a small random perturbation (a generic, non-symmetric shape)."""
    rng = np.random.default_rng(seed)
    return np.asarray(mesh.points) + scale * rng.standard_normal(mesh.points.shape)


MESHES = {
    "tri3": lambda: je.rectangle(4, 3),
    "tet4": lambda: je.box(2, 2, 1),
    "tri6": lambda: je.to_quadratic(je.rectangle(3, 2)),
    "tet10": lambda: je.to_quadratic(je.box(2, 1, 1)),
    "tri3x4-fbar": lambda: je.to_quadratic(je.rectangle(3, 2), composite=True),
    "tet4x8-fbar": lambda: je.to_quadratic(je.box(1, 1, 1), composite=True),
}


@pytest.mark.parametrize(
    "name",
    [
        n if n in ("tri3", "tet10", "tet4x8-fbar") else pytest.param(n, marks=pytest.mark.extended)
        for n in MESHES
    ],
)
def test_rest_quantities_of_moved_points_equal_the_host_ones(name):
    mesh = MESHES[name]()
    X = _perturbed(mesh)
    ref = je.from_arrays(X, np.asarray(mesh.cells), mesh.element, formulation=mesh.formulation)
    moved = jax.jit(lambda m, X: m.with_points(X))(mesh, jnp.asarray(X))
    for a, b in ((moved.dN, ref.dN), (moved.weights, ref.weights), (moved.points, ref.points)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-13, atol=1e-13)
    assert moved.cells is not None and moved.formulation == mesh.formulation
    # loads of the moved shape, traced (JAX path) against concrete (NumPy path)
    facets = je.mesh.boundary_facets(mesh)
    el = mesh.element_type

    def traced_loads(X):
        m = mesh.with_points(X)
        return (
            L.lumped_mass(m, 2.0),
            L.gravity_load(m, 2.0, np.ones(mesh.dim), consistent=True),
            L.traction_load(m, facets, np.ones(mesh.dim)),
            *L.facet_integrals(X, facets, el),
        )

    got = jax.jit(traced_loads)(jnp.asarray(X))
    want = (
        L.lumped_mass(ref, 2.0),
        L.gravity_load(ref, 2.0, np.ones(mesh.dim), consistent=True),
        L.traction_load(ref, facets, np.ones(mesh.dim)),
        *L.facet_integrals(X, facets, el),
    )
    for a, b in zip(got, want, strict=True):
        assert isinstance(b, np.ndarray)
        np.testing.assert_allclose(np.asarray(a), b, rtol=1e-12, atol=1e-14)


def test_with_points_refuses_bad_points_naming_the_cells():
    mesh = je.rectangle(3, 2)
    X = np.asarray(mesh.points).copy()
    with pytest.raises(je.MeshError, match=r"shape \(n_nodes, dim\) = \(12, 2\)"):
        mesh.with_points(X[:-1])
    bad = X.copy()
    bad[4] = np.nan
    with pytest.raises(je.MeshError, match=r"NaN/inf coordinates, e.g. nodes \[4\]"):
        mesh.with_points(bad)
    # push an interior node across the opposite edges: its cells invert
    inverted = X.copy()
    node = 5  # an interior node of the 3x2 grid
    inverted[node] = inverted[node] + np.array([2.0, 0.0])
    with pytest.raises(je.MeshError, match=r"inverted \(det J < 0\)") as err:
        mesh.with_points(inverted)
    cells = np.asarray(mesh.cells)
    flags = jax.jit(lambda m, X: G.invalid_cells(m.with_points(X)))(mesh, jnp.asarray(inverted))
    first = int(np.flatnonzero(np.asarray(flags))[0])
    assert f"cell {first}: nodes {cells[first].tolist()}" in str(err.value)
    assert node in cells[first]
    # collapse: a node on the line through its neighbours
    collapsed = X.copy()
    collapsed[:, 1] = np.where(np.isclose(X[:, 1], 0.5), 0.0, X[:, 1])
    with pytest.raises(je.MeshError, match="collapsed"):
        mesh.with_points(collapsed)
    # inside jit: no error, the per-cell flag
    assert bool(flags.any()) and not bool(G.invalid_cells(mesh).any())


@pytest.mark.extended
def test_solve_on_inverted_rest_points_inside_jit_reports_inverted():
    mesh = je.rectangle(3, 2)
    bc = L.fix(mesh, L.nodes_on_plane(mesh, 0, 0.0))
    inverted = np.asarray(mesh.points).copy()
    inverted[5] += np.array([2.0, 0.0])
    solver = je.Newton(linear="cg", max_steps=3)

    @jax.jit
    def run(m, X):
        pot = je.Potential(mesh=m.with_points(X), params=PARAMS, psi=M.neo_hookean)
        return je.solve(pot, bc, solver=solver)

    res = run(mesh, jnp.asarray(inverted))
    assert int(res.status) == je.Status.INVERTED
    assert int(run(mesh, mesh.points).status) == je.Status.SUCCESS


class Cantilever:
    """A cantilever clamped at x = 0 under gravity: the rest points X are the variable."""

    def __init__(self, mesh, g):
        self.mesh = mesh
        self.X0 = jnp.asarray(mesh.points)
        self.bc = L.fix(mesh, L.nodes_on_plane(mesh, 0, 0.0))
        Xn = np.asarray(mesh.points)
        self.probe = int(np.argmax(Xn[:, 0] - 1e-3 * Xn[:, 1:].sum(axis=1)))
        self.g = np.asarray(g, float)

    def potential(self, X, params=PARAMS):
        m = self.mesh.with_points(X)
        f = L.gravity_load(m, 1.0, self.g)
        return je.Potential(mesh=m, params=params, f_ext=f, psi=M.neo_hookean)

    def bc_of(self, X):
        """Clamped nodes follow the rest shape (prescribed displacement zero)."""
        return L.with_rest_points(self.bc, self.mesh.points, X)

    def compliance(self, X):
        pot = self.potential(X)
        x = je.solve(pot, self.bc_of(X), solver=TIGHT).x
        return jnp.sum(pot.f_ext * (x - X))

    def probe_displacement(self, X):
        x = je.solve(self.potential(X), self.bc_of(X), solver=TIGHT).x
        return x[self.probe, 1] - X[self.probe, 1]


def _check_shape_gradient(loss, X0, seed=3, h=1e-4, tol=1e-6, jit=True):
    """Directional derivative of ``loss`` against central differences along a random
    direction; ``jit``: compiled (the rest points are traced, the solves use the
    matrix-free CG), else eager (the host loops of load stepping)."""
    vg = jax.value_and_grad(loss)
    if jit:  # one compilation for the gradient and the differences
        vg = jax.jit(vg)
        loss = lambda X: vg(X)[0]  # noqa: E731
    g = vg(X0)[1]
    rng = np.random.default_rng(seed)
    d = jnp.asarray(rng.standard_normal(X0.shape))
    d = d / jnp.max(jnp.abs(d))
    fd = float(_fd(loss, X0, d, h))
    ad = float(jnp.sum(g * d))
    assert abs(ad - fd) <= tol * abs(fd), (ad, fd)
    return g


def test_shape_gradient_of_compliance_through_a_static_solve_2d_p1():
    c = Cantilever(je.rectangle(6, 2, size=(3.0, 0.5)), (0.0, -1.0))
    _check_shape_gradient(c.compliance, c.X0)


@pytest.mark.extended
@pytest.mark.parametrize(
    "name, loss",
    [
        ("tri6", "probe_displacement"),
        ("tet4", "compliance"),
        ("tet10", "probe_displacement"),
        ("tri3x4-fbar", "compliance"),
    ],
)
def test_shape_gradients_through_static_solves(name, loss):
    mesh = {
        "tri6": lambda: je.to_quadratic(je.rectangle(4, 1, size=(3.0, 0.5))),
        "tet4": lambda: je.box(4, 1, 1, size=(3.0, 0.5, 0.5)),
        "tet10": lambda: je.to_quadratic(je.box(2, 1, 1, size=(3.0, 0.5, 0.5))),
        "tri3x4-fbar": lambda: je.to_quadratic(je.rectangle(4, 1, size=(3.0, 0.5)), composite=True),
    }[name]()
    g = (0.0, -1.0) if mesh.dim == 2 else (0.0, -1.0, 0.0)
    c = Cantilever(mesh, g)
    _check_shape_gradient(getattr(c, loss), c.X0)


@pytest.mark.extended
def test_shape_gradient_through_load_steps_and_forward_mode():
    c = Cantilever(je.rectangle(6, 2, size=(3.0, 0.5)), (0.0, -2.0))

    def loss(X):
        res = je.solve_incremental(c.potential(X), c.bc_of(X), steps=2, solver=TIGHT)
        return res.x[c.probe, 1]

    g = _check_shape_gradient(loss, c.X0, jit=False)
    # forward mode (jvp) through one solve agrees with reverse mode
    d = jnp.asarray(np.random.default_rng(5).standard_normal(c.X0.shape))

    def probe_fwd(X):
        pot = c.potential(X)
        adj = je.ImplicitAdjoint(mode="forward")
        return je.solve(pot, c.bc_of(X), solver=TIGHT, adjoint=adj).x[c.probe, 1]

    _, tangent = jax.jvp(probe_fwd, (c.X0,), (d,))
    gs = jax.grad(lambda X: je.solve(c.potential(X), c.bc_of(X), solver=TIGHT).x[c.probe, 1])(c.X0)
    np.testing.assert_allclose(float(tangent), float(jnp.sum(gs * d)), rtol=1e-9)
    assert np.isfinite(np.asarray(g)).all()


@pytest.mark.extended
@pytest.mark.parametrize("order", [1, 2])
def test_shape_gradient_through_a_dynamics_rollout(order):
    mesh = je.rectangle(4, 1, size=(2.0, 0.5))
    if order == 2:
        mesh = je.to_quadratic(mesh)
    c = Cantilever(mesh, (0.0, -1.0))
    integ = D.Integrator(h=0.05)
    solver = je.Newton(rtol=1e-12, atol=1e-13)

    def loss(X):
        m = mesh.with_points(X)
        mass = L.lumped_mass(m, 1.0)
        f = L.gravity_load(m, 1.0, (0.0, -1.0))
        pot = je.Potential(mesh=m, params=PARAMS, f_ext=f, mass=mass, psi=M.neo_hookean)
        _, traj = D.rollout(pot, D.init_state(X), c.bc_of(X), integ, 4, solver=solver)
        return jnp.sum((traj.frames[-1] - X)[c.probe] ** 2)

    _check_shape_gradient(loss, c.X0, h=1e-4)


def _tapered(X0, a):
    """A rest-shape mode of amplitude a: the beam's depth grows linearly along it."""
    x = X0[:, 0] / jnp.max(X0[:, 0])
    return X0.at[:, 1].set(X0[:, 1] * (1.0 + a * x))


@pytest.mark.extended
def test_misfit_gradient_with_respect_to_a_shape_parameter_through_a_fitting_case():
    mesh = je.rectangle(6, 2, size=(3.0, 0.5))
    c = Cantilever(mesh, (0.0, -1.0))

    def case_at(a):
        """A LoadCase on the rest shape of amplitude a (observations from a = 0.3)."""
        X = _tapered(c.X0, a)
        return F.LoadCase(pot=c.potential(X), bc=c.bc_of(X), observed=observed)

    truth = je.solve(c.potential(_tapered(c.X0, 0.3)), c.bc_of(_tapered(c.X0, 0.3)), solver=TIGHT)
    observed = truth.x

    def misfit(a):
        case = case_at(a)
        solver = case.bind(TIGHT)
        loss, _ = case.evaluate(PARAMS, case.initial_warm(), solver, je.ImplicitAdjoint())
        return loss

    a0 = jnp.asarray(0.1)
    g = jax.grad(misfit)(a0)
    fd = _fd(misfit, a0, jnp.asarray(1.0), 1e-4)
    np.testing.assert_allclose(float(g), float(fd), rtol=1e-6)
    assert float(g) < 0  # the misfit falls towards the true amplitude
    assert float(misfit(jnp.asarray(0.3))) < 1e-20


@pytest.mark.extended
def test_fit_recovers_a_shape_amplitude_with_the_fitting_loop():
    """je.fit over a pytree holding a shape amplitude (a case following the protocol)."""
    mesh = je.rectangle(6, 2, size=(3.0, 0.5))
    c = Cantilever(mesh, (0.0, -1.0))
    X_true = _tapered(c.X0, 0.3)
    observed = je.solve(c.potential(X_true), c.bc_of(X_true), solver=TIGHT).x

    @jax.tree_util.register_dataclass
    @dataclasses.dataclass(frozen=True)
    class ShapeCase(F.Case):
        observed: jax.Array
        weight: float = dataclasses.field(default=1.0, metadata=dict(static=True))

        @property
        def mesh(self):
            return mesh

        def initial_warm(self):
            return c.X0

        def bind(self, solver):
            return je.solvers.prepare_solver(solver, mesh, c.bc)

        def evaluate(self, params, warm, solver, adjoint):
            X = _tapered(c.X0, params["a"])
            sol = je.solve(c.potential(X), c.bc_of(X), x0=warm, solver=solver, throw=False)
            loss = F.observation_loss(sol.x, self.observed, X, None)
            aux = F.CaseAux(sol.x, sol.ok, sol.stats["steps"], sol.stats["linear_iterations"])
            return loss, aux

    res = je.fit(
        [ShapeCase(observed)],
        {"a": jnp.asarray(0.1)},
        transforms={"a": F.Free()},
        solver=je.Newton(rtol=1e-12, linear="cg"),
        max_iter=30,
    )
    np.testing.assert_allclose(float(res.params["a"]), 0.3, rtol=1e-6)
