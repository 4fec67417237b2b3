"""Observation kinds of a load path: gradients of each kind's χ² against central
differences, point location and interpolation (P1, P2), distances to facets, load paths
(levels in order, sub-step retry, failures reported, never skipped) and bad input.

The gradients go through two load levels of a neo-Hookean bar (each level one implicit
adjoint solve); the finite differences use the fourth-order central stencil with solves at
rtol 1e-12.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic as je
from jaxelastic import fitting as F
from jaxelastic import loads as L
from jaxelastic import materials as M
from jaxelastic.fitting.measurements import locate_points, point_to_facet_distance
from jaxelastic.mesh import boundary_facets

TIGHT = je.Newton(rtol=1e-12)
ADJ = je.ImplicitAdjoint(rtol=1e-12)


def _bar(n=(2, 1, 1), order=1):
    mesh = je.box(*n, size=(2.0, 1.0, 1.0), order=order)
    right = L.nodes_on_plane(mesh, 0, 2.0)
    left = L.nodes_on_plane(mesh, 0, 0.0)
    bc = L.combine(L.fix(mesh, left), L.fix(mesh, right, displacement=[0.2, 0.05, 0.0]))
    top = L.facets_where(mesh, lambda c: np.isclose(c[:, 2], 1.0))
    f = jnp.asarray(L.traction_load(mesh, top, (0.0, 0.0, -2.0)))
    pot = je.Potential(mesh, M.Lame.from_E_nu(100.0, 0.3, dim=3), f_ext=f, psi=M.neo_hookean)
    return mesh, pot, bc, left, right


def _kinds(mesh, left, right, n_levels, rng):
    """One observation of every kind with placeholder data."""
    dim = 3
    pts = np.array([[0.5, 0.5, 0.5], [1.3, 0.2, 0.7], [1.9, 0.9, 0.1]])
    surf = np.asarray(mesh.points)[boundary_facets(mesh)[:5, :3]].mean(axis=1)
    surf = surf + 0.01 * rng.standard_normal(surf.shape)
    return (
        F.Positions(jnp.asarray([1, 4, 7]), jnp.zeros((n_levels, 3, dim)), 0.01),
        F.Points.at(mesh, pts, np.zeros((n_levels, 3, dim)), 0.01, components=("x", "y")),
        F.Reaction(jnp.asarray(right), jnp.asarray([1.0, 0.0, 0.0]), jnp.zeros(n_levels), 0.1),
        F.Moment(
            jnp.asarray(left),
            jnp.asarray([1.0, 0.0, 0.0]),
            jnp.asarray([0.0, 0.5, 0.5]),
            jnp.zeros(n_levels),
            0.01,
        ),
        F.Surface.at(mesh, np.broadcast_to(surf, (n_levels, *surf.shape)), 0.01),
    )


@pytest.fixture(scope="module")
def path():
    rng = np.random.default_rng(0)
    mesh, pot, bc, left, right = _bar()
    factors = np.array([0.5, 1.0])
    obs = _kinds(mesh, left, right, 2, rng)
    case = F.LoadPathCase(pot, bc, factors, obs)
    true = M.Lame.from_E_nu(120.0, 0.25, dim=3)
    preds, aux = jax.jit(lambda p: case.predictions(p, case.initial_warm(), TIGHT, ADJ))(true)
    assert bool(aux.ok)
    data = []
    for o, p in zip(obs, preds, strict=True):
        p = np.asarray(p)
        if isinstance(o, F.Surface):
            data.append(o)  # measured points stay; their distances are the residuals
            continue
        noisy = p + float(o.sigma) * rng.standard_normal(p.shape)
        data.append(type(o)(**{**o.__dict__, "data": jnp.asarray(noisy)}))
    return F.LoadPathCase(pot, bc, factors, tuple(data)), mesh


def _per_kind(case):
    """θ = (μ, λ) ↦ each observation's χ² (one compiled function)."""

    def fn(theta):
        p = M.Lame(theta[0], theta[1])
        preds, _ = case.predictions(p, case.initial_warm(), TIGHT, ADJ)
        return jnp.stack(
            [
                jnp.sum(((pr - o.target(o.data)) / o.sigma) ** 2)
                for pr, o in zip(preds, case.observations, strict=True)
            ]
        )

    return jax.jit(fn), jax.jit(jax.jacrev(fn))


@pytest.mark.extended  # ~60 s on a loaded 2-core machine (reverse mode through the scan)
def test_gradient_of_every_kind_matches_central_differences(path):
    case, _ = path
    f, jac = _per_kind(case)
    theta = jnp.array([38.0, 60.0])  # away from the data's (46.2, 69.2)
    J = np.asarray(jac(theta))  # (n_kinds, 2)
    for j in range(2):
        e = np.zeros(2)
        e[j] = 1.0
        h = 1e-3 * float(theta[j])
        fp1, fm1 = f(theta + h * e), f(theta - h * e)
        fp2, fm2 = f(theta + 2 * h * e), f(theta - 2 * h * e)
        fd = np.asarray((8.0 * (fp1 - fm1) - (fp2 - fm2)) / (12.0 * h))
        rel = np.abs(J[:, j] - fd) / np.abs(fd)
        kinds = [o.kind for o in case.observations]
        assert np.all(rel <= 1e-6), dict(zip(kinds, rel.tolist(), strict=True))


@pytest.mark.extended
def test_reaction_is_the_support_force():
    """Reaction of a bar pulled by u: the support force balances the applied load: the
    pulled face's resultant = −(left face's) + 0 for no body load."""
    mesh = je.box(2, 1, 1, size=(2.0, 1.0, 1.0))
    left, right = L.nodes_on_plane(mesh, 0, 0.0), L.nodes_on_plane(mesh, 0, 2.0)
    bc = L.combine(L.fix(mesh, left), L.fix(mesh, right, displacement=[0.1, 0.0, 0.0]))
    pot = je.Potential(mesh, M.Lame.from_E_nu(100.0, 0.3, dim=3), psi=M.linear)
    e = jnp.asarray([1.0, 0.0, 0.0])
    obs = (
        F.Reaction(jnp.asarray(right), e, jnp.zeros(1), 1.0),
        F.Reaction(jnp.asarray(left), e, jnp.zeros(1), 1.0),
    )
    case = F.LoadPathCase(pot, bc, [1.0], obs)
    (r_right, r_left), _ = case.predictions(pot.params, case.initial_warm(), TIGHT, ADJ)
    assert float(r_right[0]) > 0  # the machine pulls the body in +x
    np.testing.assert_allclose(float(r_right[0]), -float(r_left[0]), rtol=1e-9)


@pytest.mark.parametrize("order", [1, 2])
def test_points_interpolate_with_the_elements_shape_functions(order):
    """A field of the element's own order is interpolated exactly at random points."""
    mesh = je.box(2, 2, 1, size=(2.0, 1.0, 1.0), order=order)
    X = np.asarray(mesh.points)
    field = lambda p: np.stack(  # noqa: E731
        [p[:, 0] ** order + p[:, 1], p[:, 1] * p[:, 2] ** (order - 1), 1 + p[:, 2]], 1
    )
    pts = np.random.default_rng(1).uniform([0, 0, 0], [2, 1, 1], size=(20, 3))
    cell, N = locate_points(mesh, pts)
    u = np.einsum("nk,nkd->nd", N, field(X)[np.asarray(mesh.cells)[cell]])
    np.testing.assert_allclose(u, field(pts), atol=1e-12)


def test_point_outside_the_body_is_named():
    mesh = je.box(1, 1, 1)
    with pytest.raises(ValueError, match=r"point 1 at \[2.0, 0.5, 0.5\] lies outside"):
        locate_points(mesh, [[0.5, 0.5, 0.5], [2.0, 0.5, 0.5]])


def test_facet_distance_closed_forms():
    tri = jnp.asarray([[[0.0, 0, 0], [1.0, 0, 0], [0.0, 1, 0]]])
    d = lambda p: float(point_to_facet_distance(jnp.asarray(p), tri)[0])  # noqa: E731
    assert d([0.2, 0.2, 0.3]) == pytest.approx(0.3)  # above the face: plane distance
    assert d([0.2, 0.2, -0.3]) == pytest.approx(-0.3)  # below: negative
    assert d([2.0, 0.0, 0.0]) == pytest.approx(1.0)  # beyond a corner
    assert d([0.5, -1.0, 1.0]) == pytest.approx(np.sqrt(2.0))  # beyond an edge
    seg = jnp.asarray([[[0.0, 0.0], [1.0, 0.0]]])  # 2D: normal (t_y, −t_x) = (0, −1)
    assert float(point_to_facet_distance(jnp.asarray([0.5, -0.2]), seg)[0]) == pytest.approx(0.2)


def test_bad_observations_are_refused_before_any_solve():
    mesh, pot, bc, left, right = _bar()
    e = jnp.asarray([1.0, 0.0, 0.0])
    good = F.Reaction(jnp.asarray(right), e, jnp.zeros(3), 1.0)
    with pytest.raises(ValueError, match="data for 3 load levels, factors lists 2"):
        F.LoadPathCase(pot, bc, [0.5, 1.0], (good,))
    with pytest.raises(ValueError, match="sigma must be > 0"):
        F.LoadPathCase(pot, bc, [0.5, 1.0], (F.Reaction(right, e, jnp.zeros(2), 0.0),))
    nan = jnp.asarray([1.0, jnp.nan])
    with pytest.raises(ValueError, match=r"not finite at index \(1,\)"):
        F.LoadPathCase(pot, bc, [0.5, 1.0], (F.Reaction(right, e, nan, 1.0),))
    with pytest.raises(ValueError, match="factors must be a non-empty"):
        F.LoadPathCase(pot, bc, [], (good,))
