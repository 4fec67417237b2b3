"""Quadratic (P2) and composite elements: shape functions, quadrature, meshes, loads, IO,
patch tests, autodiff consistency, convergence rates and the 3D cantilever."""

import dataclasses
import functools
import itertools
from math import factorial

import jax
import jax.numpy as jnp
import meshio
import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from _common import MODEL_DIMS

import jaxelastic as je
from jaxelastic import loads as L
from jaxelastic import materials, postprocess
from jaxelastic.io import MeshData, read_mesh, write_vtu
from jaxelastic.mesh import (
    MeshError,
    boundary_facets,
    boundary_nodes,
    from_arrays,
    linear_cells,
    to_quadratic,
    vertex_nodes,
)
from jaxelastic.mesh.elements import ELEMENTS, TET10, TRI6, edge_table, get_element, ref_nodes

P2 = [TRI6, TET10]


# ------------------------------------------------------------------------------ helpers


def _monomial_integral(powers):
    """∫ ξ^a η^b (ζ^c) over the unit simplex = a! b! c! / (a+b+c+d)!."""
    return np.prod([factorial(p) for p in powers]) / factorial(sum(powers) + len(powers))


def _rule_degree(points, weights):
    """Largest total degree a simplex rule integrates exactly (1e-13 relative)."""
    points, weights = np.asarray(points), np.asarray(weights)
    d = points.shape[1]
    for k in range(12):
        for pw in itertools.product(range(k + 1), repeat=d):
            if sum(pw) != k:
                continue
            exact = _monomial_integral(pw)
            if abs(np.sum(weights * np.prod(points ** np.asarray(pw), axis=1)) - exact) > (
                1e-13 * exact
            ):
                return k - 1
    return 11


def linear_solve(psi, mesh, params, bc, f_ext=None):
    """Equilibrium of a quadratic energy (linear material, standard or B-bar) by one sparse
    solve with the assembled element Hessians at rest: returns positions ``(n, d)``."""
    X = np.asarray(mesh.points)
    n, d = X.shape
    Ke = np.asarray(
        jax.jit(je.mechanics.element_hessians, static_argnums=0)(psi, mesh.points, mesh, params)
    )
    dofs = (np.asarray(mesh.cells)[:, :, None] * d + np.arange(d)).reshape(mesh.n_cells, -1)
    k = dofs.shape[1]
    K = sp.csr_matrix(
        (Ke.ravel(), (np.repeat(dofs, k, axis=1).ravel(), np.tile(dofs, (1, k)).ravel())),
        shape=(n * d, n * d),
    )
    mask = np.asarray(bc.mask).ravel()
    u = np.where(mask, (np.asarray(bc.values) - X).ravel(), 0.0)
    rhs = (np.zeros(n * d) if f_ext is None else np.asarray(f_ext).ravel()) - K @ u
    free = ~mask
    u[free] = spla.spsolve(K[free][:, free].tocsc(), rhs[free])
    return X + u.reshape(n, d)


def _affine_patch(mesh, seed=0, curve=0.0):
    """Interior P1 nodes jittered; mid-edge nodes at the new midpoints plus ``curve``
    random offsets (curved isoparametric cells)."""
    rng = np.random.default_rng(seed)
    X = np.asarray(mesh.points).copy()
    inner = np.setdiff1d(np.arange(mesh.n_nodes), boundary_nodes(mesh))
    corners = vertex_nodes(mesh)
    h = np.ptp(X, axis=0).max() / 8
    jit_nodes = np.intersect1d(inner, corners)
    X[jit_nodes] += 0.15 * h * rng.uniform(-1, 1, (jit_nodes.size, mesh.dim))
    el = mesh.element_type
    if el.n_nodes > el.dim + 1:
        cells = np.asarray(mesh.cells)
        ends = cells[:, edge_table(el)]  # (c, e, 2)
        mids = cells[:, el.dim + 1 :]
        X[mids] = X[ends].mean(axis=2)
        mid_inner = np.intersect1d(np.unique(mids), inner)
        X[mid_inner] += curve * h * rng.uniform(-1, 1, (mid_inner.size, mesh.dim))
    return from_arrays(
        X, mesh.cells, mesh.element, orient="refuse", formulation=mesh.formulation
    ), inner


# ----------------------------------------------------------------------------- elements


@pytest.mark.parametrize("el", P2, ids=lambda e: e.name)
def test_p2_shape_functions_interpolate_reproduce_quadratics_and_gradients(el):
    nodes = ref_nodes(el.dim)
    np.testing.assert_allclose(el.shape_functions(nodes), np.eye(el.n_nodes), atol=1e-15)
    xi = np.random.default_rng(0).dirichlet(np.ones(el.dim + 1), size=20)[:, 1:]
    N = el.shape_functions(xi)
    np.testing.assert_allclose(N.sum(axis=1), 1.0, atol=1e-14)

    def f(p):  # a full quadratic
        return 1 + p[:, 0] - 2 * p[:, 1] + p[:, 0] * p[:, 1] + p[:, 1] ** 2 + p[:, -1] ** 2

    np.testing.assert_allclose(N @ f(nodes), f(xi), atol=1e-13)
    G = el.shape_gradients(xi)
    np.testing.assert_allclose(G.sum(axis=1), 0.0, atol=1e-13)
    h = 1e-6
    for j in range(el.dim):
        e = np.zeros(el.dim)
        e[j] = h
        fd = (el.shape_functions(xi + e) - el.shape_functions(xi - e)) / (2 * h)
        np.testing.assert_allclose(G[:, :, j], fd, atol=1e-8)


def test_quadrature_degrees_and_weights():
    assert _rule_degree(TRI6.quad_points, TRI6.quad_weights) == 4
    assert _rule_degree(TET10.quad_points, TET10.quad_weights) == 5
    assert _rule_degree(*TRI6.mass_rule()) == 4
    assert _rule_degree(*TET10.mass_rule()) == 5
    for el in ELEMENTS.values():
        assert np.all(np.asarray(el.quad_weights) > 0)
        assert sum(el.quad_weights) == pytest.approx(0.5 if el.dim == 2 else 1 / 6, rel=1e-14)


@pytest.mark.parametrize("name", ["tri3x4", "tet4x8"])
def test_composite_sub_simplices_tile_the_reference_cell(name):
    el = get_element(name)
    G = el.shape_gradients()  # (s, k, d), constant per sub-simplex
    assert G.shape == (len(el.sub_cells), el.n_nodes, el.dim)
    # X(ξ) = ξ is reproduced on every sub-simplex, nodes outside it have zero gradient
    eye = np.broadcast_to(np.eye(el.dim), (len(G), el.dim, el.dim))
    np.testing.assert_allclose(np.einsum("ka,skb->sab", ref_nodes(el.dim), G), eye, atol=1e-14)
    for s, sub in enumerate(el.sub_cells):
        outside = np.setdiff1d(np.arange(el.n_nodes), sub)
        assert np.all(G[s, outside] == 0)
        Y = ref_nodes(el.dim)[list(sub)]
        assert np.linalg.det((Y[1:] - Y[0]).T) > 0  # positively oriented
    assert len({frozenset(s) for s in el.sub_cells}) == len(el.sub_cells)


# --------------------------------------------------------------------------------- mesh


@pytest.mark.parametrize("dim", [2, 3])
def test_to_quadratic_adds_one_midpoint_per_edge(dim):
    p1 = je.rectangle(3, 2, size=(3.0, 2.0)) if dim == 2 else je.box(2, 1, 2)
    p2 = to_quadratic(p1)
    again = to_quadratic(p1)
    np.testing.assert_array_equal(np.asarray(p2.cells), np.asarray(again.cells))
    n = (3, 2) if dim == 2 else (2, 1, 2)
    assert p2.n_nodes == np.prod([2 * k + 1 for k in n])  # the doubled structured grid
    X, X2 = np.asarray(p1.points), np.asarray(p2.points)
    np.testing.assert_array_equal(X2[: p1.n_nodes], X)  # P1 numbering kept
    cells = np.asarray(p2.cells)
    ends = cells[:, edge_table(p2.element_type)]
    np.testing.assert_allclose(X2[cells[:, dim + 1 :]], X2[ends].mean(axis=2), atol=1e-15)
    assert len(np.unique(X2.round(12), axis=0)) == p2.n_nodes  # shared edges deduplicated
    np.testing.assert_allclose(np.asarray(p2.volumes), np.asarray(p1.volumes), rtol=1e-12)
    assert p2.element == ("tri6" if dim == 2 else "tet10")
    assert to_quadratic(p1, composite=True).formulation == "fbar"
    with pytest.raises(ValueError, match="P1 mesh"):
        to_quadratic(p2)


def test_generators_order_and_formulation():
    assert je.rectangle(2, 1, order=2).element == "tri6"
    assert je.box(1, 1, 1, order=2).element == "tet10"
    c = je.cook_membrane(2, order=1, formulation="fbar")
    assert (c.element, c.formulation) == ("tri3x4", "fbar")
    assert je.mesh.with_formulation(je.box(1, 1, 1, order=2), "fbar").formulation == "fbar"
    with pytest.raises(ValueError, match="order"):
        je.rectangle(2, 2, order=3)
    with pytest.raises(ValueError, match="formulation"):
        je.rectangle(2, 2, order=2, formulation="mixed")
    with pytest.raises(ValueError, match="composite=True"):
        je.mesh.with_formulation(je.rectangle(2, 2), "fbar")


def test_curved_tri6_area_and_edge_length_isoparametric():
    delta = 0.1
    pts = np.array([[0, 0], [1, 0], [0, 1], [0.5, -delta], [0.5, 0.5], [0, 0.5]])
    m = from_arrays(pts, [[0, 1, 2, 3, 4, 5]])
    assert m.element == "tri6"
    # a parabolic bulge adds 2/3 · base · sagitta
    assert float(m.volumes[0]) == pytest.approx(0.5 + 2 / 3 * delta, rel=1e-13)
    f = boundary_facets(m)
    bottom = f[np.all(np.isin(f[:, :2], [0, 1]), axis=1)]
    _, length, normal = L.facet_integrals(m.points, bottom, m.element_type)
    s = np.linspace(0, 1, 200001)  # arc length of x = s, y = -4δ s(1-s)
    arc = np.sum(np.hypot(np.diff(s), np.diff(-4 * delta * s * (1 - s))))
    assert length[0] == pytest.approx(arc, rel=1e-4)
    np.testing.assert_allclose(normal[0], [0, -1], atol=1e-12)


def test_p2_cell_checks_orientation_and_distortion():
    pts = np.array([[0, 0], [1, 0], [0, 1], [0.5, 0], [0.5, 0.5], [0, 0.5]], float)
    flipped = [[0, 2, 1, 5, 4, 3]]  # the same cell, clockwise
    with pytest.warns(UserWarning, match="reoriented 1"):
        m = from_arrays(pts, flipped)
    assert float(m.volumes[0]) == pytest.approx(0.5)
    np.testing.assert_array_equal(np.asarray(m.cells)[0], [0, 1, 2, 3, 4, 5])
    with pytest.raises(MeshError, match="inverted"):
        from_arrays(pts, flipped, orient="refuse")
    bad = pts.copy()
    bad[3] = [0.5, 0.9]  # mid-node pulled across the cell: Jacobian changes sign
    with pytest.raises(MeshError, match="changes sign"):
        from_arrays(bad, [[0, 1, 2, 3, 4, 5]])
    with pytest.raises(MeshError, match="'fbar' on P1"):
        from_arrays(pts[:3], [[0, 1, 2]], formulation="fbar")


@pytest.mark.parametrize("element", ["tri6", "tet10", "tri3x4", "tet4x8"])
def test_boundary_facets_p2_outward_with_midpoints(element):
    dim = 2 if element.startswith("tri") else 3
    m = je.rectangle(2, 3, order=2) if dim == 2 else je.box(1, 2, 1, order=2)
    if element in ("tri3x4", "tet4x8"):
        m = (
            je.rectangle(2, 3, formulation="fbar")
            if dim == 2
            else je.box(1, 2, 1, formulation="fbar")
        )
    f = boundary_facets(m)
    p1 = boundary_facets(je.rectangle(2, 3) if dim == 2 else je.box(1, 2, 1))
    assert f.shape == (len(p1), 3 if dim == 2 else 6)
    X = np.asarray(m.points)
    ring = [(0, 1)] if dim == 2 else [(0, 1), (1, 2), (2, 0)]
    for j, (a, b) in enumerate(ring):
        np.testing.assert_allclose(X[f[:, dim + j]], (X[f[:, a]] + X[f[:, b]]) / 2, atol=1e-15)
    n, area = L.facet_normals(X, f, m.element_type)
    out = X[f[:, :dim]].mean(axis=1) - X.mean(axis=0)
    assert np.all(np.sum(n * out, axis=1) > 0)
    assert area.sum() == pytest.approx(4.0 if dim == 2 else 6.0, rel=1e-12)
    assert set(np.unique(f)) == set(boundary_nodes(m))
    assert len(linear_cells(m)) == m.n_cells * (4 if dim == 2 else 8)


# -------------------------------------------------------------------------------- loads


@pytest.mark.parametrize("element", ["tri3", "tri6", "tri3x4", "tet4", "tet10", "tet4x8"])
def test_traction_gravity_mass_totals(element):
    dim = 2 if element.startswith("tri") else 3
    kw = {"tri3": {}, "tet4": {}, "tri6": {"order": 2}, "tet10": {"order": 2}}.get(
        element, {"formulation": "fbar"}
    )
    size = (2.0, 1.5) if dim == 2 else (2.0, 1.5, 0.5)
    m = je.rectangle(2, 2, size=size, **kw) if dim == 2 else je.box(2, 1, 1, size=size, **kw)
    assert m.element == element
    vol = float(np.prod(size))
    t = np.arange(1.0, dim + 1)
    fac = L.facets_where(m, lambda X: np.abs(X[:, 0] - 2.0) < 1e-9)
    area = vol / 2.0
    np.testing.assert_allclose(L.traction_load(m, fac, t).sum(axis=0), t * area, rtol=1e-13)
    mass = L.lumped_mass(m, 3.0)
    assert np.all(mass > 0) and mass.sum() == pytest.approx(3.0 * vol, rel=1e-13)
    for consistent in (False, True):
        g = L.gravity_load(m, 3.0, t, consistent=consistent)
        np.testing.assert_allclose(g.sum(axis=0), 3.0 * vol * t, rtol=1e-13)


def test_p2_facet_shares_and_hrz_masses_of_single_cells():
    # 3-node edge: ∫N = A/6, A/6, 2A/3; 6-node triangle: 0 at corners, A/3 at mid-nodes
    tri = from_arrays(ref_nodes(2) * 2.0, [np.arange(6)])
    f = boundary_facets(tri)
    shares, area, _ = L.facet_integrals(tri.points, f, tri.element_type)
    np.testing.assert_allclose(shares / area[:, None], [[1 / 6, 1 / 6, 2 / 3]] * 3, atol=1e-14)
    tet = from_arrays(ref_nodes(3) * 2.0, [np.arange(10)])
    shares, area, _ = L.facet_integrals(tet.points, boundary_facets(tet), tet.element_type)
    np.testing.assert_allclose(
        shares / area[:, None], [[0, 0, 0, 1 / 3, 1 / 3, 1 / 3]] * 4, atol=1e-14
    )
    # HRZ (Hinton, Rock & Zienkiewicz 1976): corner:mid = ∫N_c² : ∫N_m² = 3 : 16 for both
    # (tri6: 1/30 : 8/45; tet10: 1/70 : 8/105), so masses 3/57, 16/57 and 1/36, 4/27 of ρV
    V = 2.0
    np.testing.assert_allclose(
        L.lumped_mass(tri, 1.0) / V, [3 / 57] * 3 + [16 / 57] * 3, rtol=1e-13
    )
    V = 8 / 6
    np.testing.assert_allclose(L.lumped_mass(tet, 1.0) / V, [1 / 36] * 4 + [4 / 27] * 6, rtol=1e-13)
    # consistent body load of tet10: -V/20 at corners, V/5 at mid-nodes
    g = L.gravity_load(tet, 1.0, [0, 0, 1.0], consistent=True)[:, 2] / V
    np.testing.assert_allclose(g, [-1 / 20] * 4 + [1 / 5] * 6, atol=1e-14)


def test_facet_tractions_p2_uniform_stress():
    m = je.box(1, 1, 1, order=2)
    F0 = np.array([[1.1, 0.05, 0.0], [0.02, 0.95, 0.03], [0.0, -0.04, 1.02]])
    x = jnp.asarray(np.asarray(m.points) @ F0.T)
    p = je.Lame(1.0, 2.0)
    f = boundary_facets(m)
    tau = postprocess.facet_tractions(materials.neo_hookean, x, m, p, f)
    P = np.asarray(je.first_piola(materials.neo_hookean)(jnp.asarray(F0), p))
    n, _ = L.facet_normals(m.points, f)
    np.testing.assert_allclose(tau, n @ P.T, atol=1e-12)


# ------------------------------------------------------------------------------- energy


@functools.partial(jax.jit, static_argnums=0)
def _forces_and_energy(psi, x, m, p):
    return je.forces(psi, x, m, p), je.energy(psi, x, m, p)


@pytest.mark.parametrize(
    "name, d",
    [
        pytest.param(
            n, d, id=f"{n}-{d}D", marks=() if d == 2 or n == "corotated" else pytest.mark.slow
        )
        for n, d in MODEL_DIMS
    ],
)
def test_patch_test_affine_map_on_curved_p2_meshes(name, d):
    """Every material reproduces an affine map exactly on distorted, curved P2 cells."""
    base = je.rectangle(3, 3, order=2) if d == 2 else je.box(2, 2, 2, order=2)
    m, inner = _affine_patch(base, seed=d, curve=0.1)
    psi = materials.BUILTIN[name]
    p = je.Lame(1.0, 3.0)
    F0 = np.eye(d) + 0.1 * np.random.default_rng(1).uniform(-1, 1, (d, d))
    x = jnp.asarray(np.asarray(m.points) @ F0.T + 0.3)
    f, E = _forces_and_energy(psi, x, m, p)
    P0 = np.asarray(je.first_piola(psi)(jnp.asarray(F0), p))
    assert np.abs(np.asarray(f)[inner]).max() <= 1e-12 * max(np.abs(P0).max(), 1.0)
    E = float(E)
    assert E == pytest.approx(
        float(psi(jnp.asarray(F0), p)) * float(m.volumes.sum()), rel=1e-12, abs=1e-14
    )


@pytest.mark.parametrize("dim", [2, 3])
def test_p2_forces_hvp_hessians_match_finite_differences(dim):
    base = je.rectangle(2, 2, order=2) if dim == 2 else je.box(1, 1, 1, order=2)
    m, _ = _affine_patch(base, seed=3, curve=0.05)
    psi, p = materials.neo_hookean, je.Lame(1.0, 4.0)
    rng = np.random.default_rng(4)
    x = m.points + 0.03 * jnp.asarray(rng.standard_normal(m.points.shape))
    v = jnp.asarray(rng.standard_normal(x.shape))
    check_derivatives(psi, x, v, m, p)


def check_derivatives(psi, x, v, m, p):
    """Forces = −∇E and HVP = ∇²E·v by central differences; element Hessians symmetric
    and assembling to the HVP (shared with test_fbar)."""
    h = 1e-6
    E, f_of, hvp_of, K_of = (
        jax.jit(fn, static_argnums=0)
        for fn in (
            je.energy,
            je.forces,
            lambda s, y, *a: je.mechanics.hvp(s, y, *a),
            je.mechanics.element_hessians,
        )
    )
    f = f_of(psi, x, m, p)
    fd = (E(psi, x + h * v, m, p) - E(psi, x - h * v, m, p)) / (2 * h)
    assert float(-jnp.sum(f * v)) == pytest.approx(float(fd), rel=1e-7)
    Hv = hvp_of(psi, x, v, m, p)
    fd_f = -(f_of(psi, x + h * v, m, p) - f_of(psi, x - h * v, m, p)) / (2 * h)
    np.testing.assert_allclose(Hv, fd_f, atol=1e-6 * float(jnp.abs(Hv).max()))
    K = K_of(psi, x, m, p)
    np.testing.assert_allclose(K, jnp.swapaxes(K, 1, 2), atol=1e-12 * float(jnp.abs(K).max()))
    ve = v[m.cells].reshape(m.n_cells, -1)
    Kv = je.mechanics.assemble(m, jnp.einsum("cij,cj->ci", K, ve).reshape(m.cells.shape + (m.dim,)))
    np.testing.assert_allclose(Kv, Hv, atol=1e-12 * float(jnp.abs(Hv).max()))


def test_composite_standard_energy_equals_p1_on_refined_mesh():
    comp = je.mesh.with_formulation(je.box(1, 2, 1, formulation="fbar"), "standard")
    refined = from_arrays(comp.points, linear_cells(comp), "tet4", orient="refuse")
    x = comp.points + 0.02 * jnp.asarray(
        np.random.default_rng(5).standard_normal(comp.points.shape)
    )
    p = je.Lame(1.0, 2.0)
    psi = materials.neo_hookean
    fc, Ec = _forces_and_energy(psi, x, comp, p)
    fr, Er = _forces_and_energy(psi, x, refined, p)
    assert float(Ec) == pytest.approx(float(Er), rel=1e-13)
    np.testing.assert_allclose(fc, fr, atol=1e-12)


# ------------------------------------------------------------------- accuracy: linear P2


def _timoshenko(X, P=1000.0, Lb=48.0, D=12.0, E=3e7, nu=0.3):
    """Plane-stress cantilever exact field (REFERENCES: Timoshenko & Goodier), y ∈ [-D/2, D/2]."""
    I = D**3 / 12
    x, y = X[..., 0], X[..., 1]
    ux = -P * y / (6 * E * I) * ((6 * Lb - 3 * x) * x + (2 + nu) * (y**2 - D**2 / 4))
    uy = (
        P
        / (6 * E * I)
        * (3 * nu * y**2 * (Lb - x) + (4 + 5 * nu) * D**2 * x / 4 + (3 * Lb - x) * x**2)
    )
    return jnp.stack([ux, uy], axis=-1)


def _collapsed_gauss(n):
    """Duffy-collapsed Gauss rule on the unit triangle, exact to degree 2n − 2."""
    g, w = np.polynomial.legendre.leggauss(n)
    g, w = (g + 1) / 2, w / 2
    a, b = np.meshgrid(g, g, indexing="ij")
    wa, wb = np.meshgrid(w, w, indexing="ij")
    pts = np.stack([a.ravel(), (b * (1 - a)).ravel()], axis=1)
    return pts, (wa * wb * (1 - a)).ravel()


def _errors_p2(mesh, x, exact, C):
    """L2 and energy-norm errors of a tri6 displacement against an exact field."""
    xi, w = _collapsed_gauss(6)
    el = mesh.element_type
    N, G = el.shape_functions(xi), el.shape_gradients(xi)
    Xe = np.asarray(mesh.points)[np.asarray(mesh.cells)]
    ue = (np.asarray(x) - np.asarray(mesh.points))[np.asarray(mesh.cells)]
    Jac = np.einsum("cka,rkb->crab", Xe, G)
    detJ, Jinv = np.linalg.det(Jac), np.linalg.inv(Jac)
    Xq = np.einsum("rk,cka->cra", N, Xe)
    uh = np.einsum("rk,cka->cra", N, ue)
    gh = np.einsum("cka,rkb,crbj->craj", ue, G, Jinv)
    u_ex = np.asarray(exact(jnp.asarray(Xq)))
    g_ex = np.asarray(jax.jit(jax.vmap(jax.vmap(jax.jacfwd(exact))))(jnp.asarray(Xq)))
    wq = detJ * w[None, :]
    e = uh - u_ex
    de = gh - g_ex
    eps = 0.5 * (de + np.swapaxes(de, -1, -2))
    en = np.einsum("cr,crij,ijkl,crkl->", wq, eps, C, eps)
    return np.sqrt(np.einsum("cr,cra->", wq, e * e)), np.sqrt(en)


def test_p2_convergence_rates_timoshenko():
    """P2 on the Timoshenko cantilever with the exact field on the whole boundary:
    L2 error ∝ h³, energy-norm error ∝ h² (± 0.2)."""
    mu, lam = je.materials.lame(3e7, 0.3, dim=2, plane="stress")
    p = je.Lame(mu, lam)
    C = np.einsum("ij,kl->ijkl", np.eye(2), np.eye(2)) * lam + mu * (
        np.einsum("ik,jl->ijkl", np.eye(2), np.eye(2))
        + np.einsum("il,jk->ijkl", np.eye(2), np.eye(2))
    )
    errs = []
    for k in (1, 2, 4):
        m = je.rectangle(4 * k, k, size=(48.0, 12.0), origin=(0.0, -6.0), order=2)
        bn = boundary_nodes(m)
        bc = L.fix(m, bn, displacement=lambda X: np.asarray(_timoshenko(jnp.asarray(X))))
        x = linear_solve(materials.linear, m, p, bc)
        errs.append(_errors_p2(m, x, _timoshenko, C))
    errs = np.asarray(errs)
    rates = np.log2(errs[:-1] / errs[1:])
    assert rates[-1, 0] == pytest.approx(3.0, abs=0.2), rates
    assert rates[-1, 1] == pytest.approx(2.0, abs=0.2), rates
    assert errs[-1, 0] < 1e-3 * float(jnp.abs(_timoshenko(jnp.array([48.0, 0.0]))).max())


def _cantilever3d(m_depth, **kw):
    """10 × 1 × 1 cantilever (REFERENCES "3D beam"), E = 1000, ν = 0.3, end shear P = 1:
    mean end-face deflection / Timoshenko δ = PL³/(3EI) + PL/(κGA)."""
    Lb, D, E, nu, P = 10.0, 1.0, 1000.0, 0.3, 1.0
    I, A, G = D**4 / 12, D * D, E / (2 * (1 + nu))
    kappa = 10 * (1 + nu) / (12 + 11 * nu)
    delta = P * Lb**3 / (3 * E * I) + P * Lb / (kappa * G * A)
    m = je.box(10 * m_depth, m_depth, m_depth, size=(Lb, D, D), **kw)
    fac = L.facets_where(m, lambda X: np.abs(X[:, 0] - Lb) < 1e-9)
    f = L.traction_load(m, fac, [0.0, 0.0, -P / A])
    bc = L.fix(m, L.nodes_on_plane(m, 0, 0.0))
    x = linear_solve(materials.linear, m, je.Lame.from_E_nu(E, nu), bc, f)
    end = L.nodes_on_plane(m, 0, Lb)
    return -float(np.mean(x[end, 2] - np.asarray(m.points)[end, 2])) / delta


def test_cantilever3d_p2_one_element_through_depth():
    # measured: P2 97.6 % with one element through the depth (P1: ≈ 22 %, REFERENCES)
    assert _cantilever3d(1, order=2) >= 0.97


@pytest.mark.slow
def test_cantilever3d_p2_two_elements_through_depth():
    # measured: P2 98.9 %, composite F-bar 84 %, P1 60 % (this mesh) at 2 elements
    assert _cantilever3d(2, order=2) >= 0.98
    assert _cantilever3d(2) < 0.65


# ------------------------------------------------------------------------ io and scenes


def test_p2_mesh_file_round_trip_with_facet_sets(tmp_path):
    m = je.rectangle(2, 1, size=(2.0, 1.0), order=2)
    X3 = np.column_stack([np.asarray(m.points), np.zeros(m.n_nodes)])
    f = boundary_facets(m)
    right = f[np.all(np.abs(np.asarray(m.points)[f[:, :2], 0] - 2.0) < 1e-12, axis=1)]
    cells = [("line3", right), ("triangle6", np.asarray(m.cells))]
    raw = meshio.Mesh(
        X3,
        cells,
        cell_data={
            "gmsh:physical": [np.full(len(right), 3), np.full(m.n_cells, 7)],
            "gmsh:geometrical": [np.full(len(right), 1), np.full(m.n_cells, 1)],
        },
        field_data={"right": np.array([3, 1]), "body": np.array([7, 2])},
    )
    path = tmp_path / "p2.msh"
    meshio.write(path, raw, file_format="gmsh22", binary=False)
    md = read_mesh(path)
    assert md.mesh.element == "tri6"
    np.testing.assert_allclose(np.asarray(md.mesh.points), np.asarray(m.points))
    np.testing.assert_array_equal(np.asarray(md.mesh.cells), np.asarray(m.cells))
    np.testing.assert_array_equal(np.sort(md.facet_sets["right"], axis=0), np.sort(right, axis=0))
    assert md.facet_sets["right"].shape == (1, 3)


@pytest.mark.parametrize("dim", [2, 3])
def test_write_vtu_p2_cell_fields_are_quadrature_averages(tmp_path, dim):
    m = je.rectangle(2, 2, order=2) if dim == 2 else je.box(1, 1, 1, order=2)
    X = np.asarray(m.points)
    x = X + 0.05 * np.sin(3 * X[:, :1]) * (1 + X)  # non-affine: J varies in a cell
    psi, p = materials.neo_hookean, je.Lame(1.0, 2.0)
    path = tmp_path / "s.vtu"
    write_vtu(path, m, x, psi=psi, params=p)
    back = meshio.read(path)
    assert back.cells[0].type == ("triangle6" if dim == 2 else "tetra10")
    F = np.asarray(je.kinematics.deformation_gradients(jnp.asarray(x), m))
    w = np.asarray(m.weights)
    J_avg = np.sum(w * np.linalg.det(F), axis=1) / w.sum(axis=1)
    np.testing.assert_allclose(back.cell_data["J"][0], J_avg, rtol=1e-12)
    assert np.ptp(np.linalg.det(F), axis=1).max() > 1e-3  # the average is not trivial
    W = np.asarray(back.cell_data["energy_density"][0])
    assert float(np.sum(W * np.asarray(m.volumes))) == pytest.approx(
        float(je.energy(psi, jnp.asarray(x), m, p)), rel=1e-12
    )


def test_scene_lifts_p1_file_sets_to_p2():
    from jaxelastic.scene.problem import lift_file_mesh

    p1 = je.rectangle(2, 1, size=(2.0, 1.0))
    X = np.asarray(p1.points)
    f1 = boundary_facets(p1)
    right = f1[np.all(np.abs(X[f1, 0] - 2.0) < 1e-12, axis=1)]
    left = np.flatnonzero(X[:, 0] == 0.0)
    md = MeshData(p1, {"left": left}, {}, {"right": right}, np.arange(p1.n_nodes), "x.msh")
    for order, form, element in ((2, "standard", "tri6"), (None, "fbar", "tri3x4")):
        mesh, md2 = lift_file_mesh(md, order, form)
        assert (mesh.element, mesh.formulation) == (element, form)
        Xq = np.asarray(mesh.points)
        np.testing.assert_array_equal(md2.point_sets["left"], np.flatnonzero(Xq[:, 0] == 0.0))
        assert md2.facet_sets["right"].shape == (1, 3)
        assert Xq[md2.facet_sets["right"][0, 2], 1] == pytest.approx(0.5)
        assert md2.node_map[-1] == -1
    with pytest.raises(MeshError, match="order = 1"):
        lift_file_mesh(dataclasses.replace(md, mesh=to_quadratic(p1)), 1, "standard")


def test_plot_p2_outline_passes_through_mid_nodes():
    from jaxelastic import plot

    m = je.rectangle(2, 2, order=2)
    edges = plot.feature_edges(m)
    assert set(np.unique(edges)) == set(boundary_nodes(m))
    assert len(edges) == 2 * len(boundary_facets(m))
    fig = plot.final_shape_figure(m, {"rest": m.points, "moved": m.points * 1.1})
    assert fig.axes
