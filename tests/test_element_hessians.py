"""Element Hessians by contraction and displacement-based F.

``je.mechanics.element_hessians`` forms Kₑ = Σ_q B_qᵀ Ĉ_q B_q (+ a rank-3 element term under
F-bar/B-bar) from C = ∂²ψ/∂F²; ``element_hessians_reference`` differentiates the element
energy twice over the element's node coordinates with ``jax.hessian``. They must agree to
round-off for every built-in material, element and formulation, at generic deformed states
(and at the rest state, where the SVD-based models need their custom JVPs).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic as je
from jaxelastic import materials as M
from jaxelastic.mechanics import assemble, element_hessians_reference

LAME = M.Lame(jnp.asarray(1.3), jnp.asarray(2.1))

# jitted (ψ static): eager dispatch of the vmapped autodiff is ~5× slower on tiny meshes
_hessians = jax.jit(je.mechanics.element_hessians, static_argnums=0, static_argnames="project")
_reference = jax.jit(element_hessians_reference, static_argnums=0)


def _params(name: str, n_cells: int):
    if name in M.BUILTIN:
        return LAME
    p = M.FAMILY_PARAMS[name]()
    if name == "holzapfel_gasser_ogden":
        p = M.per_cell_fibres(p, n_cells)
    if name == "guccione":
        p = M.per_cell_basis(p, n_cells)
    return p


def _psi(name: str):
    return M.BUILTIN[name] if name in M.BUILTIN else M.FAMILIES[name]


def _mesh(dim: int, kind: str) -> je.Mesh:
    m = je.rectangle(2, 1) if dim == 2 else je.box(1, 1, 1)
    if kind == "p1":
        return m
    if kind == "composite":
        return je.mesh.to_quadratic(m, composite=True)
    if kind == "composite-bbar":
        return je.mesh.to_quadratic(m, composite=True, formulation="bbar")
    form = {"p2": "standard", "p2-fbar": "fbar", "p2-bbar": "bbar"}[kind]
    return je.mesh.to_quadratic(m, formulation=form)


def _deformed(mesh: je.Mesh, seed: int = 0, scale: float = 0.12) -> jax.Array:
    """A generic non-degenerate state: a random affine map (stretch, shear, rotation) plus
    nodal noise, so every quadrature point has a different F ≠ I."""
    rng = np.random.default_rng(seed)
    X = np.asarray(mesh.points)
    d = X.shape[1]
    A = np.eye(d) + scale * rng.uniform(-1, 1, (d, d))
    x = X @ A.T + 0.3 * scale * rng.uniform(-1, 1, X.shape) * 0.5
    return jnp.asarray(x)


def _rel(a, b) -> float:
    a, b = np.asarray(a), np.asarray(b)
    return float(np.abs(a - b).max() / np.abs(b).max())


def _check(name, mesh, x, tol=1e-12):
    psi, p = _psi(name), _params(name, mesh.n_cells)
    K = _hessians(psi, x, mesh, p)
    R = _reference(psi, x, mesh, p)
    kd = mesh.cells.shape[1] * mesh.dim
    assert K.shape == R.shape == (mesh.n_cells, kd, kd)
    assert bool(jnp.all(jnp.isfinite(K))), f"{name}: non-finite contracted Kₑ"
    err = _rel(K, R)
    assert err <= tol, f"{name} {mesh.element}/{mesh.formulation}: rel err {err:.2e}"
    return K


MODELS = list(M.BUILTIN) + list(M.FAMILIES)
# the default run covers every model in 3D P1; the rest of the sweep is marked slow
_FAST_2D = ("neo_hookean",)
_FAST_FBAR = ("neo_hookean", "corotated")
_FAST_FORMS = {("p2", 3), ("p2-fbar", 2), ("p2-fbar", 3), ("p2-bbar", 3), ("composite", 3)}


def _maybe_slow(case, fast: bool):
    """``case`` (a tuple of arguments, or one argument) in the default run, else slow."""
    if fast:
        return case
    return pytest.param(*(case if isinstance(case, tuple) else (case,)), marks=pytest.mark.slow)


P1_CASES = [
    _maybe_slow((n, d), d == 3 or n in _FAST_2D)
    for n in MODELS
    for d in (2, 3)
    if not (n == "stable_neo_hookean_log" and d == 2)
]


@pytest.mark.parametrize("name,dim", P1_CASES)
def test_contracted_equals_autodiff_every_material_p1(name, dim):
    mesh = _mesh(dim, "p1")
    _check(name, mesh, _deformed(mesh, seed=dim))


@pytest.mark.parametrize("name", [_maybe_slow(n, n in _FAST_FBAR) for n in MODELS])
def test_contracted_equals_autodiff_every_material_p2_fbar_3d(name):
    """The F-bar path (rank-one/volumetric coupling and the P:∂²F̄ term) for every ψ."""
    mesh = _mesh(3, "p2-fbar")
    _check(name, mesh, _deformed(mesh, seed=7))


ELEMENTS = ["p2", "p2-fbar", "p2-bbar", "composite", "composite-bbar"]
FORM_CASES = [
    _maybe_slow((kind, dim, name), name != "corotated" and (kind, dim) in _FAST_FORMS)
    for kind in ELEMENTS
    for dim in (2, 3)
    for name in (("linear",) if "bbar" in kind else ("neo_hookean", "corotated"))
]


@pytest.mark.parametrize("kind,dim,name", FORM_CASES)
def test_contracted_equals_autodiff_formulations(kind, dim, name):
    mesh = _mesh(dim, kind)
    K = _check(name, mesh, _deformed(mesh, seed=3))
    scale = float(jnp.abs(K).max())
    asym = float(jnp.abs(K - jnp.swapaxes(K, 1, 2)).max())
    assert asym <= 1e-13 * scale, f"Kₑ not symmetric: {asym:.2e} of {scale:.2e}"


@pytest.mark.parametrize(
    "kind,name",
    [
        ("p1", "corotated"),
        _maybe_slow(("p1", "fixed_corotated"), False),
        ("p2-fbar", "neo_hookean"),
    ],
)
def test_rest_state_hessian(kind, name):
    """F = I exactly (the first Newton step): SVD-based models and the F-bar terms with
    P̄ = 0 must be finite and equal to the reference."""
    mesh = _mesh(3, kind)
    _check(name, mesh, mesh.points)


def test_fbar_inverted_point_branch():
    """A quadrature point with J_q ≤ 0 inside a cell with J̄ > 0: F̄_q = F_q there (θ frozen),
    the other points keep the F-bar coupling; a finite-under-inversion ψ (stable
    neo-Hookean) must give the reference Kₑ."""
    mesh = _mesh(3, "p2-fbar")
    x = np.array(_deformed(mesh, seed=5, scale=0.05))
    cells = np.asarray(mesh.cells)
    a, b = cells[0, 0], cells[0, 1]  # local node 4 sits on the edge (0, 1)
    x[cells[0, 4]] = x[a] + 0.1 * (x[b] - x[a])  # past the quarter point: J < 0 near corner 0
    x = jnp.asarray(x)
    Jq = np.linalg.det(np.asarray(je.kinematics.deformation_gradients(x, mesh, fbar=False)))
    w = np.asarray(mesh.weights)
    assert (Jq[0] <= 0).any() and (w[0] * Jq[0]).sum() > 0, "case must have J_q ≤ 0 < J̄"
    _check("stable_neo_hookean", mesh, x)


@pytest.mark.parametrize("kind", ["p1", "p2-fbar", _maybe_slow("p2-bbar", False)])
def test_assembled_element_hessians_match_hvp(kind):
    mesh = _mesh(3, kind)
    x = _deformed(mesh, seed=11)
    psi = M.neo_hookean if "bbar" not in kind else M.linear
    v = jnp.asarray(np.random.default_rng(2).standard_normal(mesh.points.shape))
    K = _hessians(psi, x, mesh, LAME)
    ve = v[mesh.cells].reshape(mesh.n_cells, -1)
    Kv = assemble(mesh, jnp.einsum("cij,cj->ci", K, ve).reshape(mesh.cells.shape + (-1,)))
    Hv = jax.jit(je.mechanics.hvp, static_argnums=0)(psi, x, v, mesh, LAME)
    assert _rel(Kv, Hv) <= 1e-12


def test_project_psd_of_contracted_hessians():
    mesh = _mesh(3, "p2-fbar")
    x = _deformed(mesh, seed=4, scale=0.3)
    K = _hessians(M.stvk, x, mesh, LAME, project=True)
    assert float(jnp.linalg.eigvalsh(K).min()) >= -1e-10 * float(jnp.abs(K).max())


# ------------------------------------------------------------- displacement-based F (float32)


def _old_forces(psi, x, mesh, p):
    """Forces with F from absolute positions, F = Σ_a x_a ⊗ ∇N_a (the previous formula)."""
    xe = x[mesh.cells]
    F = jnp.einsum("cka,cqkb->cqab", xe, mesh.dN)
    P = jax.vmap(jax.vmap(jax.grad(psi), in_axes=(0, None)), in_axes=(0, None))(F, p)
    fe = jnp.einsum("cq,cqab,cqkb->cka", mesh.weights, P, mesh.dN)
    return -assemble(mesh, fe)


_forces = jax.jit(je.forces, static_argnums=0)


def _f32_box(offset: float) -> je.Mesh:
    """A float32 mesh whose points are exactly its float64 twin's (:func:`_f64_twin`)."""
    m = je.box(3, 3, 3)  # h = 1/3: coordinates and ∇N are not exact binary fractions
    pts = (np.asarray(m.points, dtype=np.float64) + offset).astype(np.float32)
    return je.from_arrays(pts.astype(np.float64), np.asarray(m.cells), dtype=jnp.float32)


def _f64_twin(m32: je.Mesh) -> je.Mesh:
    return je.from_arrays(np.asarray(m32.points, np.float64), np.asarray(m32.cells))


def test_float32_translated_mesh_rest_residual_is_zero():
    mesh = _f32_box(1.0e3)
    p = M.Lame(jnp.float32(1.0), jnp.float32(1.5))
    for psi in (M.neo_hookean, M.stvk, M.corotated):
        f = _forces(psi, mesh.points, mesh, p)
        assert f.dtype == jnp.float32
        assert float(jnp.abs(f).max()) == 0.0, psi.__name__
    # (F from absolute positions gives a non-zero rest residual here when XLA contracts
    # products into FMAs, and exactly 0 when it does not: that comparison is the deformed
    # test below, whose ratio does not hang on the compiler's flags)


def test_float32_deformed_residual_floor_drops():
    """Round-off of float32 forces against float64 at the same (float32) state and the same
    geometry: from the displacements it is smaller than from absolute positions, by a
    factor that grows with the distance from the origin."""
    p32 = M.Lame(jnp.float32(1.0), jnp.float32(1.5))
    p64 = M.Lame(jnp.float64(1.0), jnp.float64(1.5))
    ratios = []
    for offset in (0.0, 10.0):
        m32 = _f32_box(offset)
        m64 = _f64_twin(m32)
        x = _deformed(m32, seed=1, scale=0.1).astype(jnp.float32)
        exact = _forces(M.neo_hookean, x.astype(jnp.float64), m64, p64)
        new = _forces(M.neo_hookean, x, m32, p32)
        old = jax.jit(_old_forces, static_argnums=0)(M.neo_hookean, x, m32, p32)
        e_new = float(jnp.abs(new.astype(exact.dtype) - exact).max())  # float32 vs float64
        e_old = float(jnp.abs(old.astype(exact.dtype) - exact).max())
        ratios.append(e_old / e_new)
    # measured 2.0× at the origin on this 3×3×3 box (9× on a 6×6×6 one: the gain grows with
    # |X|/h) and 39× at an offset of 10
    assert ratios[0] >= 1.5 and ratios[1] >= 10.0, ratios


def test_mesh_dtype_is_the_working_dtype():
    mesh = _f32_box(0.0)
    x64 = jnp.asarray(np.asarray(mesh.points, np.float64) * 1.01)
    p = M.Lame(jnp.float32(1.0), jnp.float32(1.5))
    assert _forces(M.neo_hookean, x64, mesh, p).dtype == jnp.float32
    assert jax.jit(je.kinematics.deformation_gradients)(x64, mesh).dtype == jnp.float32
    assert _hessians(M.neo_hookean, x64, mesh, p).dtype == jnp.float32
    hvp = jax.jit(je.mechanics.hvp, static_argnums=0)
    assert hvp(M.neo_hookean, x64, x64, mesh, p).dtype == jnp.float32


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize(
    "kind",
    ["p1", *(pytest.param(k, marks=pytest.mark.extended) for k in ("p2", "composite", "p2-fbar"))],
)
def test_projection_without_translations_equals_project_psd(dim, kind):
    """``project=True`` projects through the (k−1)·d matrices with the translations taken
    out (``project_element_psd``): equal to ``project_psd`` of the unprojected element
    Hessians to round-off, on a state where most are indefinite; PSD, and the rigid
    translations stay in the kernel."""
    from jaxelastic.mechanics import project_element_psd, project_psd

    mesh = _mesh(dim, kind)
    x = _deformed(mesh, seed=2, scale=0.6)  # large enough that ψ's Hessian is indefinite
    psi, p = M.neo_hookean, LAME
    K = _hessians(psi, x, mesh, p)
    ref = project_psd(K)
    lam = np.linalg.eigvalsh(np.asarray(K))
    assert (lam[:, 0] < -1e-8 * np.abs(lam).max()).mean() > 0.3  # mostly indefinite
    for P in (_hessians(psi, x, mesh, p, project=True), project_element_psd(K, dim)):
        assert _rel(P, ref) <= 1e-12
        assert np.linalg.eigvalsh(np.asarray(P)).min() >= -1e-12 * np.abs(lam).max()
        k = mesh.cells.shape[1]
        t = np.tile(np.eye(dim), (k, 1))  # (k·d, d): the d translations, node-major
        assert np.abs(np.asarray(P) @ t).max() <= 1e-12 * np.abs(lam).max()
