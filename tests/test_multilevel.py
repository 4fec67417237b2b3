"""The device multigrid preconditioner (je.Multilevel): accuracy against the host direct
solver, vmap, implicit gradients, float32, indefinite starts, symmetry and iteration growth."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic as je
from jaxelastic import loads as L
from jaxelastic import materials as M
from jaxelastic import verification as benchmarks
from jaxelastic.mechanics import potential as P
from jaxelastic.solvers import cg
from jaxelastic.solvers.multilevel import build_hierarchy, preconditioner

TIGHT = dict(rtol=1e-11, max_steps=40)
ML = je.Multilevel(max_coarse=40)  # a few levels even on these small meshes


def _beam(dtype=np.float64):
    mesh = je.rectangle(24, 6, size=(4.0, 1.0), dtype=dtype)
    bc = L.fix(mesh, L.nodes_on_plane(mesh, 0, 0.0))
    tip = L.facets_where(mesh, lambda X: np.isclose(X[:, 0], 4.0))
    f = jnp.asarray(L.traction_load(mesh, tip, (0.0, -40.0)), dtype)
    return mesh, bc, f


def _pot(mesh, f, E, nu=0.3):
    p = M.Lame.from_E_nu(E, nu, dim=2)
    return je.Potential(mesh=mesh, params=p, f_ext=f, psi=M.neo_hookean)


@pytest.fixture(scope="module")
def beam():
    return _beam()


def test_hierarchy_has_levels_and_binds_once(beam):
    mesh, bc, _ = beam
    a = je.solvers.init_linear(ML, mesh, bc)[1]
    b = je.solvers.init_linear("multilevel", mesh, bc)[1]
    assert len(a.hierarchy.sizes) >= 3 and a.hierarchy.sizes[0] == mesh.n_dofs
    assert je.solvers.init_linear(ML, mesh, bc)[1].hierarchy is a.hierarchy  # cached setup
    assert b.hierarchy is not a.hierarchy  # other max_coarse, other hierarchy
    with pytest.raises(ValueError, match="coarse_scale"):
        je.Multilevel(coarse_scale=2.5)


@pytest.mark.extended
def test_matches_direct_2d(beam):
    mesh, bc, f = beam
    pot = _pot(mesh, f, 1e3)
    ref = je.solve(pot, bc, solver=je.Newton(linear="direct", **TIGHT))
    res = je.solve(pot, bc, solver=je.Newton(linear=ML, **TIGHT))
    assert int(res.stats["linear_iterations"]) > int(res.stats["steps"])  # really iterative
    np.testing.assert_allclose(res.x, ref.x, rtol=0, atol=1e-10)


@pytest.mark.slow  # (15 s; the 2D comparison runs by default)
def test_matches_direct_3d_twist():
    b = benchmarks.twist(4)
    newton = je.Newton(**TIGHT)
    ref = je.solve(b.pot, b.bc, solver=newton.replace(linear="direct"))
    res = je.solve(b.pot, b.bc, solver=newton.replace(linear=je.Multilevel(max_coarse=60)))
    np.testing.assert_allclose(res.x, ref.x, rtol=0, atol=1e-10)


@pytest.mark.slow  # vmap and gradients of Multilevel: also tests/test_vmap.py
def test_vmap_over_material_and_gradient(beam):
    """vmap over E gives the separate solves; the implicit gradient (adjoint solve by
    Multilevel.exact) matches a central difference."""
    mesh, bc, f = beam
    newton = je.Newton(linear=ML, **TIGHT)

    def tip(E, solver=newton):
        return je.solve(_pot(mesh, f, E), bc, solver=solver).x[-1, 1]

    Es = jnp.array([1e3, 2e3])
    batched = jax.jit(jax.vmap(tip))(Es)
    for i in range(2):
        np.testing.assert_allclose(batched[i], tip(Es[i]), rtol=1e-10)
    g = jax.jit(jax.grad(tip))(1.5e3)
    h = 1.0
    fd = (tip(1.5e3 + h) - tip(1.5e3 - h)) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=1e-5)
    assert float(g) > 0  # a stiffer beam sags less (tip y rises towards 0)


@pytest.mark.slow
def test_float32_solve_matches_float64(beam):
    mesh32, bc32, f32 = _beam(np.float32)
    res = je.solve(_pot(mesh32, f32, 1e3), bc32, solver=je.Newton(linear=ML, rtol=1e-5))
    assert res.x.dtype == jnp.float32
    mesh, bc, f = beam
    ref = je.solve(_pot(mesh, f, 1e3), bc, solver=je.Newton(linear="direct", **TIGHT))
    u, u_ref = np.asarray(res.x - mesh32.points), np.asarray(ref.x - mesh.points)
    assert np.abs(u - u_ref).max() <= 1e-4 * np.abs(u_ref).max()


def _compressed_start(mesh, bc):
    """A start compressed to 45 % along x and perturbed: an indefinite Hessian."""
    X = np.asarray(mesh.points)
    rng = np.random.default_rng(0)
    x0 = X * np.array([0.45, 1.0]) + 0.004 * rng.standard_normal(X.shape)
    return jnp.asarray(np.where(np.asarray(bc.mask), X, x0))


@pytest.mark.extended  # the projected retry is in the default tier (test_newton)
def test_indefinite_start_projects_and_recovers(beam):
    """From a strongly compressed start the Hessian is indefinite: CG meets negative
    curvature, the element Hessians are PSD-projected, and the solve still converges to
    the direct solver's answer."""
    mesh, bc, f = beam
    pot = _pot(mesh, f, 1e3)
    x0 = _compressed_start(mesh, bc)
    newton = je.Newton(linear=ML, **TIGHT)
    res = je.solve(pot, bc, x0=x0, solver=newton)
    assert int(res.stats["projected"]) + int(res.stats["negative_curvature"]) >= 1
    ref = je.solve(pot, bc, solver=newton.replace(linear="direct"))
    np.testing.assert_allclose(res.x, ref.x, rtol=0, atol=1e-9)


@pytest.mark.parametrize("kind", [pytest.param("direct", marks=pytest.mark.extended), "amg"])
def test_host_newton_indefinite_start_projects(beam, kind):
    """The host Newton loop's first solve runs outside jit on the assembled matrix
    (newton._host_assembled_step); from an indefinite start the projected retry (blocks
    projected by compiled calls) takes over, and the solve converges to the device
    solver's answer."""
    mesh, bc, f = beam
    pot = _pot(mesh, f, 1e3)
    x0 = _compressed_start(mesh, bc)
    res = je.solve(pot, bc, x0=x0, solver=je.Newton(linear=kind, **TIGHT))
    assert int(res.status) == 0
    assert int(res.stats["projected"]) >= 1
    ref = je.solve(pot, bc, x0=x0, solver=je.Newton(linear=ML, **TIGHT))
    np.testing.assert_allclose(res.x, ref.x, rtol=0, atol=1e-9)


def _system(n):
    b = benchmarks.twist(n)
    mesh, bc = b.mesh, b.bc
    x = jnp.asarray(mesh.points) + 0.05 * jnp.sin(3.0 * jnp.asarray(mesh.points))
    Ke = P.elastic_element_hessians(b.pot, x, True)
    return b, Ke, ~bc.mask


@pytest.mark.slow
def test_preconditioner_is_symmetric_positive_definite():
    b, Ke, free = _system(4)
    h = build_hierarchy(b.mesh.cells, b.mesh.points, b.bc.mask, max_coarse=30)
    assert len(h.levels) >= 3, h
    fm = free.astype(jnp.float64)
    M_ = jax.jit(lambda r: fm * preconditioner(h, Ke, None, free)(r))
    rng = np.random.default_rng(1)
    U = jnp.asarray(rng.standard_normal((3, *free.shape))) * fm[None]
    MU = jnp.stack([M_(u) for u in U])
    G = jnp.einsum("aij,bij->ab", U, MU)  # uᵢᵀ M⁻¹ uⱼ
    np.testing.assert_allclose(G, G.T, rtol=1e-12, atol=1e-12 * float(jnp.abs(G).max()))
    assert float(jnp.linalg.eigvalsh(0.5 * (G + G.T)).min()) > 0


@pytest.mark.slow
def test_iterations_grow_slowly_with_size():
    """PCG iterations to 1e-8 on the linearised twist at n = 4, 8, 12 (216–6591 dofs):
    the count grows by at most a few iterations per doubling of n (block-Jacobi CG
    roughly doubles)."""
    its = []
    for n in (4, 8, 12):
        b, Ke, free = _system(n)
        fm = free.astype(jnp.float64)
        h = build_hierarchy(b.mesh.cells, b.mesh.points, b.bc.mask, max_coarse=200)

        @jax.jit
        def run(Ke, rhs, h=h, fm=fm, free=free, pot=b.pot):
            M_ = preconditioner(h, Ke, None, free, degree=4, coarse_scale=1.3)

            def A(v):
                return fm * P.element_hessian_vp(pot, Ke, fm * v) + (1 - fm) * v

            tol = 1e-8 * jnp.linalg.norm(rhs)
            return cg(A, rhs, lambda r: fm * M_(r), tol=tol, max_iter=300)

        rhs = jnp.asarray(np.random.default_rng(n).standard_normal(free.shape)) * fm
        res = run(Ke, rhs)
        assert int(res.status) == 0
        its.append(int(res.stats["iterations"]))
    assert its[2] <= its[0] + 8 and its[2] <= 1.6 * its[0], its


@pytest.mark.extended
def test_projected_upper_by_blocks(beam, monkeypatch):
    """The host Newton retry's projection (a PSD test per block of cells, then eigh of the
    failing cells only, padded; Python loops of compiled calls with tail blocks) assembles
    the upper data of projecting every cell, to round-off; cells that pass the test are
    the positive semidefinite ones."""
    from jaxelastic.mechanics import project_psd
    from jaxelastic.solvers.linear import assemble_upper
    from jaxelastic.solvers.newton import retry as N

    mesh, bc, f = beam
    pot = _pot(mesh, f, 1e3)
    host = je.solvers.init_linear("direct", mesh, bc)[1].host
    K_in = je.mechanics.element_hessians(pot.psi, _compressed_start(mesh, bc), mesh, pot.params)
    K_rest = je.mechanics.element_hessians(pot.psi, mesh.points, mesh, pot.params)
    half = np.arange(mesh.n_cells) < mesh.n_cells // 2  # PSD cells and indefinite ones
    Ke = jnp.where(half[:, None, None], K_rest, K_in)
    emap = jnp.asarray(host.element_map)
    ref = assemble_upper(project_psd(Ke), emap, host.nnz_upper)
    monkeypatch.setattr(N, "PROJECT_BLOCK_CELLS", 7)
    assert mesh.n_cells % 7 != 0  # tail blocks
    bad = np.concatenate(
        [np.asarray(N.not_psd(Ke, s, min(7, mesh.n_cells - s))) for s in range(0, mesh.n_cells, 7)]
    )
    lam_min = np.linalg.eigvalsh(np.asarray(Ke))[:, 0]
    scale = np.abs(np.diagonal(np.asarray(Ke), axis1=1, axis2=2)).max(axis=1)
    assert 0 < bad.sum() < mesh.n_cells  # both kinds of cells in this start
    assert np.all(lam_min[~bad] >= -1e-10 * scale[~bad]) and np.all(lam_min[bad] < 0)
    data = assemble_upper(Ke, emap, host.nnz_upper)
    got = N.projected_upper(data, Ke, host.element_map, host.nnz_upper, 0)
    # elasticity alone: through the matrices without translations, the same to round-off
    data = assemble_upper(Ke, emap, host.nnz_upper)  # (the first call donated it)
    got_dim = N.projected_upper(data, Ke, host.element_map, host.nnz_upper, mesh.dim)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9 * float(jnp.abs(ref).max()))
    np.testing.assert_allclose(got_dim, ref, rtol=0, atol=1e-9 * float(jnp.abs(ref).max()))
    # most of the first block failing: every cell projected, untested; the same result
    monkeypatch.setattr(N, "PROJECT_ALL_FRACTION", -1.0)
    data = assemble_upper(Ke, emap, host.nnz_upper)
    got_all = N.projected_upper(data, Ke, host.element_map, host.nnz_upper, mesh.dim)
    np.testing.assert_allclose(got_all, ref, rtol=0, atol=1e-9 * float(jnp.abs(ref).max()))
