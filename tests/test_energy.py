"""Energy, forces, HVP and element Hessians: finite differences, assembly, patch test,
inversion, composition with jit/vmap/grad, and a user-defined material end to end.

Forces vs finite differences of the energy and HVP vs finite differences of the forces are
checked for every built-in model by ``jaxelastic.verification.derivative_check``
(``tests/test_crosscheck.py`` asserts that every row passes); here the same FD checks run on
two user-written models.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _common import IDS, MODEL_DIMS

import jaxelastic as je
from jaxelastic import materials as M
from jaxelastic.mechanics import cell_params_axes
from jaxelastic.mechanics.kinematics import det

MU, LAM = 1.3, 2.9
PARAMS = M.Lame(jnp.asarray(MU), jnp.asarray(LAM))
RECT = je.rectangle(3, 3)
BOX = je.box(2, 2, 2)
MESHES = {2: RECT, 3: BOX}


def deformed(mesh, seed=0, amp=0.1):
    """A rotated stretch of the rest shape plus a random perturbation, every J ≥ 0.25."""
    d = mesh.dim
    rng = np.random.default_rng(seed)
    X = np.asarray(mesh.points)
    A = rotation(d, 0.3) @ np.diag([1.2, 0.9, 1.05][:d])
    x = X @ A.T + amp * rng.uniform(-1, 1, X.shape)
    J = np.linalg.det(np.asarray(je.kinematics.deformation_gradients(jnp.asarray(x), mesh)))
    assert J.min() >= 0.25
    return jnp.asarray(x)


def rotation(d, angle):
    c, s = np.cos(angle), np.sin(angle)
    R = np.eye(d)
    R[:2, :2] = [[c, -s], [s, c]]
    if d == 3:  # compose with a rotation about x so that the axis is generic
        Rx = np.array([[1, 0, 0], [0, np.cos(0.4), -np.sin(0.4)], [0, np.sin(0.4), np.cos(0.4)]])
        R = Rx @ R
    return R


def rel(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300)


# --------------------------------------------------------------------------- jitted kit
# Each kit is compiled once per (ψ, mesh shape) and evaluated a few times: compile time is
# the cost, and XLA's backend optimisation level 0 cuts it (same float64 arithmetic).
kit_jit = functools.partial(
    jax.jit, static_argnames="psi", compiler_options={"xla_backend_optimization_level": 0}
)


@kit_jit
def energy_forces(x, mesh, p, *, psi):
    return je.energy(psi, x, mesh, p), je.forces(psi, x, mesh, p)


@kit_jit
def fd_kit(x, mesh, p, *, psi, h=1e-5):
    """Central differences over every dof: ``(∂E/∂x_i)_FD``, forces, ``(H e_i)_FD``, ``H e_i``."""
    n, d = x.shape
    basis = jnp.eye(n * d, dtype=x.dtype).reshape(n * d, n, d)
    ef = jax.vmap(lambda y: (je.energy(psi, y, mesh, p), je.forces(psi, y, mesh, p)))
    e_pm, f_pm = ef(jnp.concatenate([x[None] + h * basis, x[None] - h * basis]))
    fd_grad = ((e_pm[: n * d] - e_pm[n * d :]) / (2 * h)).reshape(n, d)
    fd_hess = -(f_pm[: n * d] - f_pm[n * d :]) / (2 * h)  # (n·d, n, d)
    hv = jax.vmap(lambda v: je.mechanics.hvp(psi, x, v, mesh, p))(basis)
    return fd_grad, je.forces(psi, x, mesh, p), fd_hess, hv


def check_fd(psi, mesh, p, x):
    fd_grad, f, fd_hess, hv = fd_kit(x, mesh, p, psi=psi)
    assert rel(-f, fd_grad) < 1e-6
    assert rel(hv, fd_hess) < 1e-6
    # the dense Hessian from the HVP is symmetric
    H = np.asarray(hv).reshape(mesh.n_dofs, mesh.n_dofs)
    np.testing.assert_allclose(H, H.T, atol=1e-10 * np.abs(H).max())


# --------------------------------------------------------------------------- assembly
DENSE_MODEL = {2: M.fixed_corotated, 3: M.neo_hookean}


@kit_jit
def element_kit(x, mesh, p, *, psi):
    """Per-element quantities, the scatter-path gradient, and the HVP of every unit vector."""
    Ke = je.mechanics.element_hessians(psi, x, mesh, p)
    fe = je.mechanics.element_gradients(psi, x, mesh, p)
    dens = je.mechanics.energy_densities(psi, x, mesh, p)
    g = jax.grad(je.energy, argnums=1)(psi, x, mesh, p)  # JAX's scatter path
    n, d = x.shape
    basis = jnp.eye(n * d, dtype=x.dtype).reshape(n * d, n, d)
    hv = jax.vmap(lambda v: je.mechanics.hvp(psi, x, v, mesh, p))(basis)  # rows: H e_i
    return Ke, fe, je.mechanics.assemble(mesh, fe), dens, g, hv


@pytest.mark.parametrize("d", [2, 3])
def test_forces_equal_minus_grad_energy_and_element_forces(d):
    psi, mesh = DENSE_MODEL[d], MESHES[d]
    x = deformed(mesh, seed=1)
    _, fe, fe_assembled, dens, g, _ = element_kit(x, mesh, PARAMS, psi=psi)
    e, f = energy_forces(x, mesh, PARAMS, psi=psi)
    assert rel(-f, g) < 1e-13  # the gather-assembly path equals JAX's scatter path
    assert fe.shape == (mesh.n_cells, d + 1, d)
    assert rel(-fe_assembled, f) < 1e-14
    assert dens.shape == (mesh.n_cells, 1)
    np.testing.assert_allclose(jnp.sum(mesh.weights * dens), e, rtol=1e-14)
    # translation invariance: the net elastic force vanishes
    assert np.abs(np.asarray(f).sum(0)).max() < 1e-12 * np.abs(f).max()


@pytest.mark.parametrize("d", [2, 3])
def test_element_hessians_assemble_to_dense_hessian(d):
    """Σ element Hessians (dense assembly) = [hvp(e_i)] (the dense Hessian from the HVP)."""
    psi, mesh = DENSE_MODEL[d], MESHES[d]
    x = deformed(mesh, seed=2)
    n, k = mesh.n_dofs, d + 1
    Ke, _, _, _, _, hv = (np.asarray(a) for a in element_kit(x, mesh, PARAMS, psi=psi))
    assert Ke.shape == (mesh.n_cells, k * d, k * d)
    cells = np.asarray(mesh.cells)
    dofs = (cells[:, :, None] * d + np.arange(d)).reshape(mesh.n_cells, k * d)  # node-major
    K = np.zeros((n, n))
    for c in range(mesh.n_cells):
        K[np.ix_(dofs[c], dofs[c])] += Ke[c]
    H_hvp = hv.reshape(n, n)
    assert rel(K, H_hvp) < 1e-13
    np.testing.assert_allclose(H_hvp, H_hvp.T, atol=1e-13 * np.abs(H_hvp).max())


def test_project_psd():
    rng = np.random.default_rng(0)
    A = rng.standard_normal((5, 6, 6))
    K = A + np.swapaxes(A, 1, 2)  # symmetric, indefinite
    assert np.linalg.eigvalsh(K).min() < 0
    Kp = np.asarray(je.mechanics.project_psd(jnp.asarray(K)))
    np.testing.assert_allclose(Kp, np.swapaxes(Kp, 1, 2), atol=1e-14)
    assert np.linalg.eigvalsh(Kp).min() > -1e-12
    # positive eigenpairs are kept: Kp − K is PSD-negative part only
    w, Q = np.linalg.eigh(K)
    np.testing.assert_allclose(Kp, np.einsum("bij,bj,bkj->bik", Q, np.maximum(w, 0), Q), atol=1e-12)
    # PSD input is returned unchanged
    B = A @ np.swapaxes(A, 1, 2)
    np.testing.assert_allclose(je.mechanics.project_psd(jnp.asarray(B)), B, atol=1e-12)
    # a floor clamps from below
    Kf = np.asarray(je.mechanics.project_psd(jnp.asarray(K), floor=0.5))
    assert np.linalg.eigvalsh(Kf).min() > 0.5 - 1e-12


def test_projection_matters_for_an_indefinite_configuration():
    """StVK under strong compression has indefinite element Hessians; project=True fixes it."""
    mesh = je.rectangle(2, 2)
    x = 0.3 * mesh.points
    eh = jax.jit(je.mechanics.element_hessians, static_argnums=0, static_argnames="project")
    K = np.asarray(eh(M.stvk, x, mesh, PARAMS))
    Kp = np.asarray(eh(M.stvk, x, mesh, PARAMS, project=True))
    assert np.linalg.eigvalsh(K).min() < -1e-3 * MU
    # (every cell's Hessian here is negative semidefinite: Kp is 0 up to round-off)
    assert np.linalg.eigvalsh(Kp).min() >= -1e-12 * np.abs(K).max()
    # cells whose Hessian was already PSD are left unchanged
    psd = np.linalg.eigvalsh(K).min(axis=1) >= 0
    np.testing.assert_allclose(Kp[psd], K[psd], atol=1e-12 * np.abs(K).max())
    np.testing.assert_allclose(Kp, np.asarray(je.mechanics.project_psd(jnp.asarray(K))), atol=1e-12)


# --------------------------------------------------------------------------- patch test
@pytest.mark.parametrize("name,d", MODEL_DIMS, ids=IDS)
def test_patch_affine_deformation_has_no_interior_forces(name, d):
    """Any affine map x = A X + c gives a uniform F = A, hence zero force at interior nodes."""
    mesh = MESHES[d]
    rng = np.random.default_rng(d)
    A = np.eye(d) + 0.2 * rng.standard_normal((d, d))
    assert np.linalg.det(A) > 0.3
    X = np.asarray(mesh.points)
    x = jnp.asarray(X @ A.T + rng.standard_normal(d))
    _, f = energy_forces(x, mesh, PARAMS, psi=M.BUILTIN[name])
    f = np.asarray(f)
    interior = np.setdiff1d(np.arange(mesh.n_nodes), je.mesh.boundary_nodes(mesh))
    assert interior.size > 0
    scale = np.abs(f).max()
    assert scale > 1e-3 * MU * float(mesh.volumes.mean()) ** ((d - 1) / d)  # really loaded
    assert np.abs(f[interior]).max() <= 1e-12 * scale
    assert np.abs(f.sum(0)).max() <= 1e-12 * scale  # and zero net force


# --------------------------------------------------------------------------- inversion
def _invert_one_cell():
    """RECT with its corner node 3 = (1, 0), which belongs to one cell, folded over it."""
    x = np.asarray(RECT.points).copy()
    x[3] = [0.5, 0.5]
    J = np.linalg.det(np.asarray(je.kinematics.deformation_gradients(jnp.asarray(x), RECT)))[:, 0]
    assert (J <= 0).sum() == 1
    return jnp.asarray(x)


def test_neo_hookean_energy_is_inf_with_one_inverted_cell():
    x = _invert_one_cell()
    e, _ = energy_forces(x, RECT, PARAMS, psi=M.neo_hookean)
    assert np.isposinf(e)


@pytest.mark.parametrize("name", ["stable_neo_hookean", "fixed_corotated", "corotated", "arap"])
def test_stable_models_are_finite_with_one_inverted_cell(name):
    x = _invert_one_cell()
    psi = M.BUILTIN[name]
    e, f = energy_forces(x, RECT, PARAMS, psi=psi)
    assert np.isfinite(e) and e > 0
    assert np.all(np.isfinite(f))


# --------------------------------------------------------------------------- composition
@pytest.mark.parametrize("d", [3])
def test_jit_and_vmap_composition(d):
    """energy/forces/hvp under jit (mesh and params as arguments) and vmapped over a batch
    of positions and directions give the same numbers."""
    psi = M.neo_hookean
    mesh = MESHES[d]
    xs = jnp.stack([deformed(mesh, seed=s, amp=0.05) for s in range(3)])
    vs = jnp.asarray(np.random.default_rng(0).standard_normal(xs.shape))
    e_j = jax.jit(je.energy, static_argnums=0)
    f_j = jax.jit(je.forces, static_argnums=0)
    h_j = jax.jit(je.mechanics.hvp, static_argnums=0)
    e1 = np.stack([e_j(psi, x, mesh, PARAMS) for x in xs])
    f1 = np.stack([f_j(psi, x, mesh, PARAMS) for x in xs])
    h1 = np.stack([h_j(psi, x, v, mesh, PARAMS) for x, v in zip(xs, vs, strict=True)])

    @jax.jit
    def batched(xs, vs, mesh, p):
        e = jax.vmap(je.energy, in_axes=(None, 0, None, None))(psi, xs, mesh, p)
        f = jax.vmap(lambda x: je.forces(psi, x, mesh, p))(xs)
        h = jax.vmap(lambda x, v: je.mechanics.hvp(psi, x, v, mesh, p))(xs, vs)
        return e, f, h

    e_b, f_b, h_b = batched(xs, vs, mesh, PARAMS)
    np.testing.assert_allclose(e_b, e1, rtol=1e-13)
    np.testing.assert_allclose(f_b, f1, atol=1e-13 * np.abs(f1).max())
    np.testing.assert_allclose(h_b, h1, atol=1e-13 * np.abs(h1).max())
    # the same compiled function serves another mesh of the same shape (mesh is an argument)
    moved = je.rectangle(3, 3, size=(2.0, 1.0)) if d == 2 else je.box(2, 2, 2, size=(2, 1, 1))
    e_other = e_j(psi, moved.points, moved, PARAMS)
    assert abs(float(e_other)) < 1e-12


@pytest.mark.parametrize("d", [2])
def test_grad_wrt_lame_parameters(d):
    """jax.grad of the energy w.r.t. shared and per-cell Lamé parameters vs FD."""
    psi = M.stable_neo_hookean  # nonlinear in (μ, λ) through λ′ and α
    mesh = MESHES[d]
    x = deformed(mesh, seed=4)
    E = jax.jit(lambda mu, lam: je.energy(psi, x, mesh, M.Lame(mu, lam)))
    g_mu, g_lam = jax.grad(E, argnums=(0, 1))(MU, LAM)
    h = 1e-6
    np.testing.assert_allclose(g_mu, (E(MU + h, LAM) - E(MU - h, LAM)) / (2 * h), rtol=1e-7)
    np.testing.assert_allclose(g_lam, (E(MU, LAM + h) - E(MU, LAM - h)) / (2 * h), rtol=1e-7)
    # per-cell fields (n_cells,)
    nc = mesh.n_cells
    rng = np.random.default_rng(1)
    mu_c = jnp.asarray(MU * (1 + 0.3 * rng.uniform(size=nc)))
    lam_c = jnp.asarray(LAM * (1 + 0.3 * rng.uniform(size=nc)))
    gm_c, gl_c = jax.grad(E, argnums=(0, 1))(mu_c, lam_c)
    assert gm_c.shape == (nc,) and gl_c.shape == (nc,)
    dm, dl = rng.standard_normal(nc), rng.standard_normal(nc)
    fd = (E(mu_c + h * dm, lam_c + h * dl) - E(mu_c - h * dm, lam_c - h * dl)) / (2 * h)
    np.testing.assert_allclose(jnp.dot(gm_c, dm) + jnp.dot(gl_c, dl), fd, rtol=1e-7)
    # a uniform per-cell field is the shared parameter: same energy, gradients sum up
    ones = jnp.ones(nc)
    np.testing.assert_allclose(E(MU * ones, LAM * ones), E(MU, LAM), rtol=1e-14)
    gm_u, gl_u = jax.grad(E, argnums=(0, 1))(MU * ones, LAM * ones)
    np.testing.assert_allclose(gm_u.sum(), g_mu, rtol=1e-12)
    np.testing.assert_allclose(gl_u.sum(), g_lam, rtol=1e-12)
    # mixed: per-cell μ, shared λ
    np.testing.assert_allclose(E(MU * ones, LAM), E(MU, LAM), rtol=1e-14)


def test_cell_params_axes():
    nc = RECT.n_cells
    assert cell_params_axes(M.Lame(1.0, jnp.ones(nc)), nc) == M.Lame(None, 0)
    assert cell_params_axes({"a": jnp.ones((nc, 3)), "b": 2.0}, nc) == {"a": 0, "b": None}
    with pytest.raises(ValueError, match="n_cells"):
        cell_params_axes(M.Lame(jnp.ones(nc + 1), 1.0), nc)
    with pytest.raises(ValueError, match="n_cells"):
        je.energy(M.linear, RECT.points, RECT, M.Lame(jnp.ones(nc + 1), 1.0))
    with pytest.raises(ValueError, match="n_cells"):
        je.forces(M.linear, RECT.points, RECT, M.Lame(1.0, jnp.ones((3, nc))))


# --------------------------------------------------------------------------- user model
def mooney_rivlin(F, p):
    """Compressible Mooney–Rivlin (3D), isochoric invariants: ψ = c10(Ī₁ − 3) + c01(Ī₂ − 3)
    + κ/2 (J − 1)², Ī₁ = J^{-2/3} I₁, Ī₂ = J^{-4/3} I₂. Linearises to μ = 2(c10 + c01),
    λ = κ − 2μ/3. Parameters: a plain dict (any pytree works)."""
    C = F.T @ F
    I1 = jnp.trace(C)
    I2 = 0.5 * (I1**2 - jnp.sum(C * C))
    J = det(F)
    return (
        p["c10"] * (J ** (-2.0 / 3.0) * I1 - 3.0)
        + p["c01"] * (J ** (-4.0 / 3.0) * I2 - 3.0)
        + 0.5 * p["kappa"] * (J - 1.0) ** 2
    )


def isochoric_neo_hookean(F, p):
    """2D isochoric neo-Hookean ψ = μ/2 (J^{-2/d} I_C − d) + κ/2 (J − 1)²; λ = κ − 2μ/d."""
    d = F.shape[0]
    J = det(F)
    return (
        0.5 * p["mu"] * (J ** (-2.0 / d) * jnp.sum(F * F) - d) + 0.5 * p["kappa"] * (J - 1.0) ** 2
    )


USER = {
    3: (mooney_rivlin, {"c10": jnp.asarray(0.4), "c01": jnp.asarray(0.25), "kappa": 5.0}),
    2: (isochoric_neo_hookean, {"mu": jnp.asarray(1.3), "kappa": jnp.asarray(4.0)}),
}


def user_lame(d):
    _, p = USER[d]
    mu = 2 * (p["c10"] + p["c01"]) if d == 3 else p["mu"]
    return float(mu), float(p["kappa"] - 2 * mu / d)


@pytest.mark.parametrize("d", [2, 3])
def test_user_model_end_to_end(d):
    psi, p = USER[d]
    mesh = MESHES[d]
    # forces and HVP vs finite differences
    check_fd(psi, mesh, p, deformed(mesh, seed=7))
    # rest state and linearisation
    I = jnp.eye(d)
    point = jax.jit(lambda F, p: (psi(F, p), jax.grad(psi)(F, p), jax.hessian(psi)(F, p)))
    psi0, P0, C = point(I, p)
    assert abs(float(psi0)) < 1e-14 and np.abs(P0).max() < 1e-14
    mu, lam = user_lame(d)
    C_lin = jax.jit(jax.hessian(M.linear))(I, M.Lame(mu, lam))
    assert rel(C, C_lin) < 1e-9
    # rotation invariance
    F = jnp.asarray(np.eye(d) + 0.2 * np.random.default_rng(0).standard_normal((d, d)))
    Q = jnp.asarray(rotation(d, 0.6))
    np.testing.assert_allclose(point(Q @ F, p)[0], point(F, p)[0], rtol=1e-12)
    # per-cell parameter field through the same pytree
    p_cells = dict(p, kappa=jnp.full(mesh.n_cells, float(p["kappa"])))
    x = deformed(mesh, seed=8)
    e_j = jax.jit(je.energy, static_argnums=0)
    np.testing.assert_allclose(e_j(psi, x, mesh, p_cells), e_j(psi, x, mesh, p), rtol=1e-13)
    # the small-strain response matches linear elasticity on the mesh
    u = 1e-6 * jnp.asarray(np.random.default_rng(2).standard_normal(mesh.points.shape))
    _, f_user = energy_forces(mesh.points + u, mesh, p, psi=psi)
    _, f_lin = energy_forces(
        mesh.points + u, mesh, M.Lame(jnp.asarray(mu), jnp.asarray(lam)), psi=M.linear
    )
    assert rel(f_user, f_lin) < 1e-5
