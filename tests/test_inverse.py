"""Inverse elastostatics, :func:`jaxelastic.unloaded_shape`: the direct (inverse-motion,
Newton on X) and the backward-displacement fixed-point methods recover the rest shape of
a neo-Hookean cantilever sagging under its own weight, and of an inflated thick sphere; the
forward solve from the result reproduces the loaded shape (≤ 1e-8 relative); bad targets
are refused; the node colouring behind the Jacobian is a distance-2 colouring."""

import json

import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic as je
from jaxelastic import loads as L
from jaxelastic import materials as M
from jaxelastic.solvers.inverse import node_colouring

PARAMS = je.Lame.from_E_nu(1000.0, 0.3)
TIGHT = je.Newton(rtol=1e-12)


def _sagged(mesh, g):
    """A loaded shape to invert: the cantilever clamped at x = 0 under gravity ``g``.

    Returns ``(pot, bc, loads)`` built on the *loaded* mesh (as from an image) and the
    true rest points."""

    def weight(m):
        return L.gravity_load(m, 1.0, g)

    bc0 = L.fix(mesh, L.nodes_on_plane(mesh, 0, 0.0))
    pot0 = je.Potential(mesh=mesh, params=PARAMS, f_ext=weight(mesh), psi=M.neo_hookean)
    x_hat = je.solve(pot0, bc0, solver=TIGHT).x
    seen = je.from_arrays(np.asarray(x_hat), np.asarray(mesh.cells), mesh.element)
    bc = L.fix(seen, L.nodes_on_plane(seen, 0, 0.0))
    pot = je.Potential(mesh=seen, params=PARAMS, f_ext=weight(seen), psi=M.neo_hookean)
    return pot, bc, weight, mesh.points


def test_direct_unloaded_shape_round_trip_2d():
    pot, bc, weight, X_true = _sagged(je.rectangle(8, 2, size=(4.0, 0.5)), (0.0, -1.0))
    sag = float(jnp.max(jnp.abs(pot.mesh.points - X_true)))
    assert sag > 0.5  # a large deflection (an eighth of the length)
    res = je.unloaded_shape(pot, bc, pot.mesh.points, loads=weight)
    assert res.ok and res.stats["method"] == "direct"
    assert res.stats["round_trip"] <= 1e-8
    assert res.stats["steps"] <= 10  # Newton: quadratic once close
    np.testing.assert_allclose(np.asarray(res.x), np.asarray(X_true), atol=1e-9 * sag)


def test_unloaded_shape_refuses_bad_targets():
    mesh = je.rectangle(2, 1)
    bc = L.fix(mesh, L.nodes_on_plane(mesh, 0, 0.0))
    pot = je.Potential(mesh=mesh, params=PARAMS, psi=M.neo_hookean)
    with pytest.raises(ValueError, match=r"x_target must have shape \(n_nodes, dim\) = \(6, 2\)"):
        je.unloaded_shape(pot, bc, np.zeros((5, 2)))
    bad = np.asarray(mesh.points).copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match=r"x_target has NaN/inf at 1 node\(s\), e.g. \[3\]"):
        je.unloaded_shape(pot, bc, bad)
    with pytest.raises(ValueError, match="method must be one of"):
        je.unloaded_shape(pot, bc, mesh.points, method="newton")


@pytest.mark.parametrize("make", [lambda: je.rectangle(5, 3), lambda: je.box(4, 2, 2)])
def test_node_colouring_is_a_distance_two_colouring(make):
    mesh = make()
    cells = np.asarray(mesh.cells)
    colour = node_colouring(cells, mesh.n_nodes)
    # every pair of nodes that share a neighbour (or a cell) has two colours
    neighbours = [set() for _ in range(mesh.n_nodes)]
    for c in cells:
        for a in c:
            neighbours[a].update(c.tolist())
    for i in range(mesh.n_nodes):
        near = set().union(*(neighbours[j] for j in neighbours[i])) - {i}
        assert colour[i] not in {int(colour[j]) for j in near}
    assert colour.max() + 1 < mesh.n_nodes  # fewer products than columns


@pytest.mark.extended
@pytest.mark.parametrize("dim", [2, 3])
def test_direct_and_fixed_point_agree_and_direct_converges_faster(dim):
    if dim == 2:
        mesh, g = je.rectangle(16, 4, size=(4.0, 0.5)), (0.0, -1.0)
    else:
        mesh, g = je.box(8, 2, 2, size=(4.0, 0.5, 0.5)), (0.0, -1.0, 0.0)
    pot, bc, weight, X_true = _sagged(mesh, g)
    direct = je.unloaded_shape(pot, bc, pot.mesh.points, loads=weight)
    fixed = je.unloaded_shape(
        pot, bc, pot.mesh.points, loads=weight, method="fixed_point", max_steps=200
    )
    for res in (direct, fixed):
        assert res.ok
        assert res.stats["round_trip"] <= 1e-8
        np.testing.assert_allclose(np.asarray(res.x), np.asarray(X_true), atol=1e-8)
    # linear against quadratic convergence
    assert direct.stats["steps"] < fixed.stats["steps"]
    h = fixed.stats["residual_history"]
    rates = h[1:10] / h[:9]
    assert np.all(rates < 1.0)  # a contraction


@pytest.mark.extended
def test_unloaded_shape_of_a_p2_beam_with_dead_loads():
    """Loads given as fixed nodal forces (no ``loads`` callable) on a tri6 mesh."""
    mesh = je.to_quadratic(je.rectangle(6, 1, size=(3.0, 0.5)))
    bc0 = L.fix(mesh, L.nodes_on_plane(mesh, 0, 0.0))
    tip = L.facets_where(mesh, lambda X: np.isclose(X[:, 0], 3.0))
    f = jnp.asarray(L.traction_load(mesh, tip, (0.0, -20.0)))
    pot0 = je.Potential(mesh=mesh, params=PARAMS, f_ext=f, psi=M.neo_hookean)
    x_hat = je.solve(pot0, bc0, solver=TIGHT).x
    pot = pot0.replace(mesh=mesh.with_points(x_hat))
    bc = L.with_rest_points(bc0, mesh.points, x_hat)
    res = je.unloaded_shape(pot, bc, x_hat)
    assert res.stats["round_trip"] <= 1e-8
    np.testing.assert_allclose(np.asarray(res.x), np.asarray(mesh.points), atol=1e-8)


@pytest.mark.extended
def test_unload_command_writes_the_rest_shape(tmp_path):
    from jaxelastic.cli import main

    out = tmp_path / "unload"
    rc = main(["unload", "cook", "--set", "mesh.n=4", "--out", str(out), "--no-cache"])
    assert rc == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "SUCCESS" and summary["round_trip"] <= 1e-8
    assert (out / "rest.vtu").stat().st_size > 0
    # a dynamic scene is refused with the reason
    assert main(["unload", "swing2d", "--out", str(tmp_path / "d"), "--no-cache"]) == 2


@pytest.mark.extended
def test_unloaded_shape_of_an_inflated_thick_sphere():
    """An octant of a thick neo-Hookean sphere (P2 + F-bar) inflated by an internal pressure
    on its cavity (the −p·V potential, symmetry planes): the direct method recovers the rest
    shape from the inflated one, and the forward solve from it reproduces the inflated shape
    (≤ 1e-8 relative)."""
    from jaxelastic.mesh import spherical_shell

    def cavity(m):
        return L.facets_where(m, lambda X: np.linalg.norm(X, axis=1) < 1.0 + 1e-9)

    def symmetry(m):
        return L.combine(
            *[L.fix(m, L.nodes_on_plane(m, i, 0.0), components=(i,)) for i in range(3)]
        )

    rest = spherical_shell(1.0, 2.0, 2, 1, order=2, formulation="fbar")
    params, p = je.Lame(1.0, 50.0), 0.3
    faces = cavity(rest)
    pot0 = je.Potential(
        rest, params, psi=M.neo_hookean, pressure=L.pressure_load(rest, faces, p, origin=[0, 0, 0])
    )
    x_hat = je.solve_incremental(pot0, symmetry(rest), steps=2, solver=TIGHT).x
    seen = rest.with_points(x_hat)  # the "imaged" inflated shape
    assert float(jnp.max(jnp.linalg.norm(x_hat - rest.points, axis=1))) > 0.1
    pot = je.Potential(
        seen, params, psi=M.neo_hookean, pressure=L.pressure_load(seen, faces, p, origin=[0, 0, 0])
    )
    res = je.unloaded_shape(pot, symmetry(seen), seen.points)
    assert res.ok and res.stats["round_trip"] <= 1e-8
    np.testing.assert_allclose(np.asarray(res.x), np.asarray(rest.points), atol=1e-9)
