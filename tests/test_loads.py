"""Dirichlet data, node selectors, consistent loads, lumped masses, tractions, reactions."""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic as je
from jaxelastic import loads as L
from jaxelastic import materials as M
from jaxelastic import postprocess

MU, LAM = (float(v) for v in M.lame(1.0e4, 0.3))
PARAMS = M.Lame(MU, LAM)


@pytest.fixture(scope="module")
def rect():
    """2 × 1 rectangle, 4 × 4 cells (spacing ½ × ¼)."""
    return je.rectangle(4, 4, size=(2.0, 1.0))


@pytest.fixture(scope="module")
def blk():
    """3 × 1 × 1 bar, 3 × 2 × 2 cubes (spacing 1 × ½ × ½)."""
    return je.box(3, 2, 2, size=(3.0, 1.0, 1.0))


# --------------------------------------------------------------------------------------
# Dirichlet data
# --------------------------------------------------------------------------------------


def test_fix_clamped_default(rect):
    nodes = L.nodes_on_plane(rect, 0, 0.0)
    bc = L.fix(rect, nodes)
    mask = np.asarray(bc.mask)
    assert mask.shape == (rect.n_nodes, 2) and mask.dtype == bool
    assert mask[nodes].all() and mask.sum() == 2 * nodes.size
    np.testing.assert_array_equal(np.asarray(bc.values), np.asarray(rect.points))


def test_fix_constant_vector_and_components(blk):
    nodes = L.nodes_on_plane(blk, 0, 3.0)
    bc = L.fix(blk, nodes, components=(0, 2), displacement=[0.1, 0.2, 0.3])
    mask = np.asarray(bc.mask)
    X = np.asarray(blk.points)
    v = np.asarray(bc.values)
    assert mask[nodes][:, [0, 2]].all() and not mask[nodes][:, 1].any()
    assert mask.sum() == 2 * nodes.size
    np.testing.assert_allclose(v[nodes, 0], X[nodes, 0] + 0.1)
    np.testing.assert_allclose(v[nodes, 2], X[nodes, 2] + 0.3)
    # an unprescribed component keeps the rest position (the 0.2 is ignored)
    np.testing.assert_allclose(v[nodes, 1], X[nodes, 1])
    others = np.setdiff1d(np.arange(blk.n_nodes), nodes)
    np.testing.assert_array_equal(v[others], X[others])


def test_fix_array_and_callable_agree(rect):
    nodes = L.nodes_on_plane(rect, 1, 1.0)
    X = np.asarray(rect.points)[nodes]
    u = np.stack([0.1 * X[:, 0], -0.05 * X[:, 0] ** 2], axis=1)
    a = L.fix(rect, nodes, displacement=u)
    b = L.fix(
        rect, nodes, displacement=lambda Xn: np.stack([0.1 * Xn[:, 0], -0.05 * Xn[:, 0] ** 2], 1)
    )
    np.testing.assert_array_equal(np.asarray(a.mask), np.asarray(b.mask))
    np.testing.assert_allclose(np.asarray(a.values), np.asarray(b.values))
    np.testing.assert_allclose(np.asarray(a.values)[nodes], X + u)


def test_fix_boolean_mask_equals_indices(rect):
    sel = np.asarray(rect.points)[:, 0] < 0.6
    a = L.fix(rect, sel, displacement=[0.0, -0.1])
    b = L.fix(rect, np.flatnonzero(sel), displacement=[0.0, -0.1])
    np.testing.assert_array_equal(np.asarray(a.mask), np.asarray(b.mask))
    np.testing.assert_array_equal(np.asarray(a.values), np.asarray(b.values))


def test_fix_refuses_bad_input(rect):
    with pytest.raises(ValueError, match="empty"):
        L.fix(rect, L.nodes_on_plane(rect, 0, 5.0))  # no node there
    with pytest.raises(ValueError, match="empty"):
        L.fix(rect, np.zeros(rect.n_nodes, dtype=bool))
    with pytest.raises(ValueError, match="components"):
        L.fix(rect, [0, 1], components=(2,))
    with pytest.raises(ValueError, match="shape"):
        L.fix(rect, [0, 1], displacement=np.zeros((3, 2)))
    with pytest.raises(ValueError, match="NaN"):
        L.fix(rect, [0, 1], displacement=[np.nan, 0.0])
    with pytest.raises(ValueError):
        L.fix(rect, [rect.n_nodes])  # out of range
    with pytest.raises(ValueError, match="mask"):
        L.fix(rect, np.ones(rect.n_nodes - 1, dtype=bool))


def test_combine_union_and_override(rect):
    left = L.nodes_on_plane(rect, 0, 0.0)
    bottom = L.nodes_on_plane(rect, 1, 0.0)
    a = L.fix(rect, left, displacement=[0.1, 0.0])
    b = L.fix(rect, bottom, components=(1,), displacement=[0.0, -0.2])
    c = L.combine(a, b)
    mask = np.asarray(c.mask)
    X = np.asarray(rect.points)
    assert mask[left].all() and mask[bottom, 1].all()
    np.testing.assert_array_equal(mask, np.asarray(a.mask) | np.asarray(b.mask))
    corner = 0  # on both sets: the later set wins on y, the earlier keeps x
    np.testing.assert_allclose(np.asarray(c.values)[corner], X[corner] + [0.1, -0.2])
    # bottom nodes that are not on the left keep their rest x (not prescribed)
    only_b = np.setdiff1d(bottom, left)
    np.testing.assert_allclose(np.asarray(c.values)[only_b, 1], X[only_b, 1] - 0.2)
    assert not mask[only_b, 0].any()
    with pytest.raises(ValueError):
        L.combine()
    np.testing.assert_array_equal(np.asarray(L.combine(a).mask), np.asarray(a.mask))


def test_no_dirichlet(blk):
    bc = L.no_dirichlet(blk)
    assert not np.asarray(bc.mask).any()
    assert bc.mask.shape == blk.points.shape


# --------------------------------------------------------------------------------------
# Node selectors
# --------------------------------------------------------------------------------------


def test_node_selectors(blk):
    X = np.asarray(blk.points)
    plane = L.nodes_on_plane(blk, 0, 3.0)
    np.testing.assert_array_equal(plane, np.flatnonzero(np.isclose(X[:, 0], 3.0)))
    assert plane.size == 9
    inbox = L.nodes_in_box(blk, [0.5, 0.0, 0.0], [2.5, 1.0, 0.5])
    expect = np.flatnonzero((X[:, 0] >= 0.5) & (X[:, 0] <= 2.5) & (X[:, 2] <= 0.5))
    np.testing.assert_array_equal(inbox, expect)
    assert inbox.size == 2 * 3 * 2
    where = L.nodes_where(blk, lambda Y: Y[:, 1] + Y[:, 2] > 1.2)
    np.testing.assert_array_equal(where, np.flatnonzero(X[:, 1] + X[:, 2] > 1.2))
    assert L.nodes_where(blk, lambda Y: Y[:, 0] > 10).size == 0
    with pytest.raises(ValueError, match="predicate"):
        L.nodes_where(blk, lambda Y: Y[:, :2] > 0)
    # the plane tolerance is relative to the mesh size, not absolute
    big = je.rectangle(2, 2, size=(1e4, 1e4))
    assert L.nodes_on_plane(big, 0, 1e4 + 1e-6).size == 3


def test_facets_where_and_normals(blk):
    f = L.facets_where(blk, lambda X: np.isclose(X[:, 0], 3.0))
    assert f.shape == (2 * 2 * 2, 3)
    N, area = L.facet_normals(blk.points, f)
    np.testing.assert_allclose(N, np.tile([1.0, 0.0, 0.0], (f.shape[0], 1)), atol=1e-14)
    np.testing.assert_allclose(area.sum(), 1.0)
    # all boundary facets: outward normals integrate to zero, areas to the surface
    fb = je.mesh.boundary_facets(blk)
    N, area = L.facet_normals(blk.points, fb)
    np.testing.assert_allclose((N * area[:, None]).sum(0), 0.0, atol=1e-13)
    np.testing.assert_allclose(area.sum(), 2 * (3 + 3 + 1))


# --------------------------------------------------------------------------------------
# Loads and masses
# --------------------------------------------------------------------------------------


def test_traction_load_2d_exact(rect):
    right = L.facets_where(rect, lambda X: np.isclose(X[:, 0], 2.0))
    t = np.array([3.0, -1.5])
    f = L.traction_load(rect, right, t)
    nodes = L.nodes_on_plane(rect, 0, 2.0)
    np.testing.assert_allclose(f.sum(0), t * 1.0)  # edge length 1
    others = np.setdiff1d(np.arange(rect.n_nodes), nodes)
    np.testing.assert_array_equal(f[others], 0.0)
    # consistent distribution: ends get half of an interior node
    y = np.asarray(rect.points)[nodes, 1]
    fy = f[nodes, 0]
    np.testing.assert_allclose(fy[np.isclose(y, 0.0)], 3.0 * 0.25 / 2)
    np.testing.assert_allclose(fy[np.isclose(y, 0.5)], 3.0 * 0.25)
    # first moment is exact for a constant traction: Σ f_a y_a = t ∫ y ds
    np.testing.assert_allclose((f[nodes] * y[:, None]).sum(0), t * 0.5)
    # top edge (length 2), callable, linear in x: ∫_0^2 (x, 1) dx = (2, 2)
    top = L.facets_where(rect, lambda X: np.isclose(X[:, 1], 1.0))
    g = L.traction_load(rect, top, lambda Xc: np.stack([Xc[:, 0], np.ones(len(Xc))], 1))
    np.testing.assert_allclose(g.sum(0), [2.0, 2.0])


def test_traction_load_3d_exact(blk):
    end = L.facets_where(blk, lambda X: np.isclose(X[:, 0], 3.0))
    t = np.array([1.0, -2.0, 0.5])
    f = L.traction_load(blk, end, t)
    np.testing.assert_allclose(f.sum(0), t * 1.0)  # face area 1
    top = L.facets_where(blk, lambda X: np.isclose(X[:, 2], 1.0))
    f2 = L.traction_load(blk, top, np.tile([0.0, 0.0, -4.0], (top.shape[0], 1)))
    np.testing.assert_allclose(f2.sum(0), [0.0, 0.0, -4.0 * 3.0])  # face area 3
    # callable, linear in the position: the centroid rule is exact, ∫∫ (y, x, 1) dA
    f3 = L.traction_load(blk, top, lambda Xc: np.stack([Xc[:, 1], Xc[:, 0], 1 + 0 * Xc[:, 0]], 1))
    np.testing.assert_allclose(f3.sum(0), [0.5 * 3.0, 4.5 * 1.0, 3.0])
    # the nodal loads reproduce the moment of a constant traction about the origin
    X = np.asarray(blk.points)
    np.testing.assert_allclose(np.cross(X, f2).sum(0), np.cross([1.5, 0.5, 1.0], [0, 0, -12.0]))


def test_point_load(blk):
    f = L.point_load(blk, [0, 5, 5], [1.0, 2.0, 3.0])
    np.testing.assert_allclose(f[0], [1, 2, 3])
    np.testing.assert_allclose(f[5], [2, 4, 6])  # repeated nodes accumulate
    np.testing.assert_allclose(f.sum(0), [3, 6, 9])
    g = L.point_load(blk, [1, 2], np.array([[1.0, 0, 0], [0, 0, -1.0]]))
    np.testing.assert_allclose(g[[1, 2]], [[1, 0, 0], [0, 0, -1]])
    assert np.count_nonzero(np.abs(g).sum(1)) == 2


@pytest.mark.parametrize("which", ["rect", "blk"])
def test_lumped_mass_and_gravity(rect, blk, which):
    mesh = rect if which == "rect" else blk
    measure = 2.0 if which == "rect" else 3.0
    m = L.lumped_mass(mesh, 7.5)
    assert m.shape == (mesh.n_nodes,) and (m > 0).all()
    np.testing.assert_allclose(m.sum(), 7.5 * measure)
    # per-cell density: the mass of the heavy half
    X = np.asarray(mesh.points)[np.asarray(mesh.cells)].mean(1)
    rho = np.where(X[:, 0] < 1.0, 10.0, 1.0)
    vol = np.asarray(mesh.volumes)
    np.testing.assert_allclose(L.lumped_mass(mesh, rho).sum(), (rho * vol).sum())
    g = np.zeros(mesh.dim)
    g[-1] = -9.81
    fg = L.gravity_load(mesh, 7.5, g)
    np.testing.assert_allclose(fg, m[:, None] * g[None, :])
    np.testing.assert_allclose(fg.sum(0), 7.5 * measure * g)
    for bad in (0.0, -1.0, np.nan):
        with pytest.raises(ValueError, match="density"):
            L.lumped_mass(mesh, bad)


# --------------------------------------------------------------------------------------
# Stress on facets and reactions
# --------------------------------------------------------------------------------------


def test_facet_tractions_uniform_stretch_linear(blk):
    a = 1.1
    x = jnp.asarray(np.asarray(blk.points) * np.array([a, 1.0, 1.0]))
    P11 = (2 * MU + LAM) * (a - 1)
    P22 = LAM * (a - 1)
    for axis, value, N, expect in [
        (0, 3.0, [1, 0, 0], [P11, 0, 0]),
        (0, 0.0, [-1, 0, 0], [-P11, 0, 0]),
        (1, 1.0, [0, 1, 0], [0, P22, 0]),
        (2, 0.0, [0, 0, -1], [0, 0, -P22]),
    ]:
        fac = L.facets_where(blk, lambda X, k=axis, v=value: np.isclose(X[:, k], v))
        Nf, _ = L.facet_normals(blk.points, fac)
        np.testing.assert_allclose(Nf, np.tile(N, (fac.shape[0], 1)), atol=1e-14)
        tau = postprocess.facet_tractions(M.linear, x, blk, PARAMS, fac)
        assert tau.shape == (fac.shape[0], 3)
        np.testing.assert_allclose(tau, np.tile(expect, (fac.shape[0], 1)), atol=1e-9 * MU)


def test_facet_tractions_simple_shear_neo_hookean(rect):
    """F = I + γ e₁e₂ᵀ: neo-Hookean P₁₂ = μγ, P₂₂ = 0, so τ = (μγ, 0) on the top edge."""
    gamma = 0.3
    X = np.asarray(rect.points)
    x = jnp.asarray(X + np.stack([gamma * X[:, 1], 0 * X[:, 1]], 1))
    top = L.facets_where(rect, lambda Y: np.isclose(Y[:, 1], 1.0))
    tau = postprocess.facet_tractions(M.neo_hookean, x, rect, PARAMS, top)
    np.testing.assert_allclose(tau, np.tile([MU * gamma, 0.0], (top.shape[0], 1)), atol=1e-9 * MU)
    # per-cell parameters are picked from the owning cell
    mu_cells = np.full(rect.n_cells, MU)
    tau2 = postprocess.facet_tractions(
        M.neo_hookean, x, rect, M.Lame(jnp.asarray(mu_cells), LAM), top
    )
    np.testing.assert_allclose(tau2, tau)
    with pytest.raises(ValueError, match="not a facet"):
        postprocess.facet_tractions(
            M.neo_hookean, x, rect, PARAMS, np.array([[0, rect.n_nodes - 1]])
        )


def test_reaction_force_balances_applied_load(blk):
    """A clamped bar under an end traction and a point load: reaction = −Σ f_ext."""
    clamp = L.fix(blk, L.nodes_on_plane(blk, 0, 0.0))
    end = L.facets_where(blk, lambda X: np.isclose(X[:, 0], 3.0))
    f = L.traction_load(blk, end, [200.0, 0.0, -300.0])
    f = f + L.point_load(blk, L.nodes_in_box(blk, [1, 1, 1], [1, 1, 1]), [0.0, -150.0, 0.0])
    pot = je.Potential(mesh=blk, params=PARAMS, f_ext=jnp.asarray(f), psi=M.neo_hookean)
    res = je.solve(pot, clamp)
    R = np.asarray(
        postprocess.reaction_force(M.neo_hookean, res.x, blk, PARAMS, clamp, f_ext=pot.f_ext)
    )
    np.testing.assert_allclose(R, -f.sum(0), rtol=0, atol=1e-7 * np.abs(f).sum())
    # away from the supports the nodal force balance holds dof by dof
    g = -np.asarray(je.forces(M.neo_hookean, res.x, blk, PARAMS)) - f
    free = ~np.asarray(clamp.mask)
    assert np.abs(g[free]).max() < 1e-6 * np.abs(f).sum()
    # at the rest shape (not in equilibrium) the "reaction" is just −Σ_D f_ext
    R0 = np.asarray(
        postprocess.reaction_force(M.neo_hookean, blk.points, blk, PARAMS, clamp, f_ext=pot.f_ext)
    )
    np.testing.assert_allclose(R0, -f[np.asarray(clamp.mask)[:, 0]].sum(0), atol=1e-12)
