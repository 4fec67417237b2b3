"""Guccione's law, the helix fibre rule and the active fibre tension
(jaxelastic.materials.cardiac, jaxelastic.materials.fibre_rules).

Autodiff P against the hand-derived P, rest state, objectivity, material symmetry (F and
the basis rotated together), finite differences of P and of the tangent, the isotropic
linearisation, the fibre rule's unit orthogonal directions and prescribed helix angles,
the active stress T_a F f0⊗f0 (second Piola T_a f0⊗f0), validation naming the parameter,
a unit cube stiffer along its fibres than along its sheets, and a scene solve.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _common import load_script
from scipy.spatial.transform import Rotation

import jaxelastic as je
from jaxelastic import loads as L
from jaxelastic import materials as M
from jaxelastic.materials import reference
from jaxelastic.materials.fibre_rules import transmural_coordinate

RNG = np.random.default_rng(7)


def _params(**kw):
    # a non-orthogonal, non-unit pair: ψ normalises f0 and orthogonalises s0
    p = M.guccione_params(f0=jnp.array([1.0, 0.4, -0.2]), s0=jnp.array([0.1, 2.0, 0.3]))
    return jax.tree_util.tree_map(lambda v: jnp.asarray(v, jnp.float64), p._replace(**kw))


def _random_F(d=3, scale=0.25):
    while True:
        F = np.eye(d) + scale * RNG.uniform(-1, 1, (d, d))
        if np.linalg.det(F) > 0.3:
            return jnp.asarray(F)


P_auto = jax.jit(jax.grad(M.guccione))
H_auto = jax.jit(jax.hessian(M.guccione))
P_hand = jax.jit(reference.P_guccione)


@pytest.mark.parametrize("d", (2, 3))
def test_autodiff_P_equals_hand_P(d):
    p = _params()
    for _ in range(5):
        F = _random_F(d)
        a, b = np.asarray(P_auto(F, p)), np.asarray(P_hand(F, p))
        assert np.abs(a - b).max() <= 1e-12 * np.abs(b).max()


def test_rest_state():
    p = _params()
    assert float(M.guccione(jnp.eye(3), p)) == 0.0
    assert np.abs(np.asarray(P_auto(jnp.eye(3), p))).max() <= 1e-14


def test_isotropic_linearisation():
    """b_f = b_t = b_fs = b: ψ ≈ (Cb/2) E:E + κ/2 (tr ε)², so μ = Cb/2 and λ = κ."""
    p = _params(bf=3.0, bt=3.0, bfs=3.0)
    H = np.asarray(H_auto(jnp.eye(3), p))
    mu, lam = 0.5 * 2.0 * 3.0, 1000.0
    eye = np.eye(3)
    want = mu * (np.einsum("ik,jl->ijkl", eye, eye) + np.einsum("il,jk->ijkl", eye, eye))
    want += lam * np.einsum("ij,kl->ijkl", eye, eye)
    assert np.abs(H - want).max() <= 1e-10 * lam
    assert float(p.shear_modulus) == mu
    assert float(p.bulk_modulus) == pytest.approx(lam + 2.0 * mu / 3.0, rel=1e-14)


def test_objectivity_and_material_symmetry():
    p = _params()
    for seed in range(3):
        F = _random_F()
        Q = jnp.asarray(Rotation.random(random_state=seed).as_matrix())
        psi = float(M.guccione(F, p))
        assert float(M.guccione(Q @ F, p)) == pytest.approx(psi, rel=1e-13)
        # rotating the reference body and its basis together leaves ψ unchanged
        pr = p._replace(f0=Q @ p.f0, s0=Q @ p.s0)
        assert float(M.guccione(F @ Q.T, pr)) == pytest.approx(psi, rel=1e-13)
        # and the law is anisotropic: rotating only the body changes ψ
        assert abs(float(M.guccione(F @ Q.T, p)) - psi) > 1e-6 * psi


def test_finite_differences_of_P_and_tangent():
    p, F, h = _params(), _random_F(), 1e-6
    P, H = np.asarray(P_auto(F, p)), np.asarray(H_auto(F, p))
    dP = np.zeros_like(P)
    dH = np.zeros_like(H)
    for i in range(3):
        for j in range(3):
            E = jnp.zeros((3, 3)).at[i, j].set(h)
            dP[i, j] = (float(M.guccione(F + E, p)) - float(M.guccione(F - E, p))) / (2 * h)
            dH[:, :, i, j] = (np.asarray(P_auto(F + E, p)) - np.asarray(P_auto(F - E, p))) / (2 * h)
    assert np.abs(dP - P).max() <= 1e-6 * np.abs(P).max()
    assert np.abs(dH - H).max() <= 1e-6 * np.abs(H).max()


def test_inverted_is_inf():
    assert float(M.guccione(jnp.diag(jnp.array([1.0, 1.0, -0.5])), _params())) == np.inf


# ------------------------------------------------------------------------- fibre rule
def _ellipsoid_points(r_s, r_l, n=12):
    u = np.linspace(-np.pi + 0.05, -np.arccos(5.0 / r_l), n)
    v = np.linspace(-np.pi, np.pi, n, endpoint=False)
    U, V = (a.ravel() for a in np.meshgrid(u, v))
    return np.stack([r_s * np.sin(U) * np.cos(V), r_s * np.sin(U) * np.sin(V), r_l * np.cos(U)], 1)


def test_helix_rule_angles_and_orthonormality():
    endo, epi, mid = (_ellipsoid_points(*r) for r in ((7.0, 17.0), (10.0, 20.0), (8.5, 18.5)))
    for X, t_want, alpha in ((endo, 0.0, 90.0), (epi, 1.0, -90.0), (mid, 0.5, 0.0)):
        t = np.asarray(transmural_coordinate(jnp.asarray(X)))
        np.testing.assert_allclose(t, t_want, atol=1e-12)
        f0, s0 = (np.asarray(a) for a in M.helix_fibres(jnp.asarray(X)))
        np.testing.assert_allclose(np.linalg.norm(f0, axis=1), 1.0, atol=1e-13)
        np.testing.assert_allclose(np.linalg.norm(s0, axis=1), 1.0, atol=1e-13)
        assert np.abs(np.sum(f0 * s0, axis=1)).max() <= 1e-13
        # e_v: the horizontal circumferential tangent; the helix angle from it
        rho = np.hypot(X[:, 0], X[:, 1])
        e_v = np.stack([-X[:, 1] / rho, X[:, 0] / rho, 0 * rho], 1)
        sin_a = np.sqrt(np.clip(1.0 - np.sum(f0 * e_v, axis=1) ** 2, 0, 1))
        np.testing.assert_allclose(sin_a, abs(np.sin(np.deg2rad(alpha))), atol=1e-7)
        # the sign of α: f0 points towards the base (+z) for α = +90° (e_u, u increasing)
        if alpha != 0.0:
            assert np.all(np.sign(f0[:, 2]) == np.sign(alpha))
        else:
            np.testing.assert_allclose(f0[:, 2], 0.0, atol=1e-13)
    # s0 is the outward normal: on the endocardium it points away from the cavity
    f0, s0 = M.helix_fibres(jnp.asarray(endo))
    assert np.all(np.sum(np.asarray(s0) * endo, axis=1) > 0)


def test_helix_rule_feeds_hgo_and_guccione():
    mesh = je.box(2, 2, 2, size=(1.0, 1.0, 1.0))
    X = np.asarray(mesh.points)[np.asarray(mesh.cells)].mean(axis=1) + np.array([7.5, 0.0, -8.0])
    f0, s0 = M.helix_fibres(jnp.asarray(X))
    x = mesh.points * 1.05
    g = M.guccione_params()._replace(f0=f0, s0=s0)
    h = M.per_cell_fibres(M.holzapfel_gasser_ogden_params(), mesh.n_cells)._replace(a01=f0)
    for psi, p in ((M.guccione, g), (M.holzapfel_gasser_ogden, h)):
        assert np.isfinite(float(je.energy(psi, x, mesh, p)))


# ---------------------------------------------------------------------- active tension
def test_active_stress_is_Ta_F_f0f0():
    psi = M.with_active_tension(M.guccione)
    assert M.with_active_tension(M.guccione) is psi  # cached: one compilation
    p = _params()
    f = np.asarray(p.f0) / np.linalg.norm(p.f0)
    for d in (3, 2):
        F = _random_F(d)
        pd = p if d == 3 else p._replace(f0=p.f0[:2], s0=p.s0[:2])
        fd = f if d == 3 else np.append(f[:2], 0.0) / np.linalg.norm(f[:2])
        ap = M.ActiveTension(passive=pd, Ta=jnp.asarray(60.0), f0=pd.f0)
        Pa = np.asarray(jax.grad(psi)(F, ap)) - np.asarray(P_auto(F, pd))
        F3 = np.asarray(je.materials.rubber.embed_plane_strain(F))
        want = 60.0 * F3 @ np.outer(fd, fd)
        np.testing.assert_allclose(Pa, want[:d, :d], rtol=1e-12, atol=1e-12)
        # the second Piola stress of the active part: S_a = F⁻¹ P_a = T_a f0⊗f0
        if d == 3:
            np.testing.assert_allclose(np.linalg.solve(F3, Pa), 60.0 * np.outer(f, f), atol=1e-12)
    assert float(psi(jnp.eye(3), ap._replace(f0=p.f0, passive=p))) == pytest.approx(0.0, abs=1e-13)


# -------------------------------------------------------------------------- validation
@pytest.mark.parametrize(
    ("kw", "name"),
    [
        ({"C": 0.0}, "C"),
        ({"bf": -1.0}, "bf"),
        ({"bfs": float("nan")}, "bfs"),
        ({"kappa": 0.0}, "kappa"),
        ({"f0": jnp.zeros(3)}, "f0"),
        ({"s0": jnp.array([2.0, 0.8, -0.4])}, "s0"),  # parallel to f0
    ],
)
def test_validation_names_the_parameter(kw, name):
    with pytest.raises(ValueError, match=rf"\b{name}\b"):
        M.check_guccione(_params(**kw))


def test_solve_refuses_bad_parameters():
    mesh = je.box(1, 1, 1)
    pot = je.Potential(
        mesh=mesh, params=M.per_cell_basis(_params(C=-1.0), mesh.n_cells), psi=M.guccione
    )
    bc = L.fix(mesh, L.nodes_on_plane(mesh, 0, 0.0))
    with pytest.raises(ValueError, match="guccione: C"):
        je.solve(pot, bc)


# ------------------------------------------------------------------------------ solves
def _pull_x(p, a=1.1):
    """Solve a unit cube stretched by ``a`` along x (symmetry planes, free laterally)."""
    mesh = je.box(1, 1, 1)
    bcs = [L.fix(mesh, L.nodes_on_plane(mesh, ax, 0.0), components=(ax,)) for ax in range(3)]
    u = np.array([a - 1.0, 0.0, 0.0])
    bcs.append(L.fix(mesh, L.nodes_on_plane(mesh, 0, 1.0), components=(0,), displacement=u))
    pot = je.Potential(mesh=mesh, params=M.per_cell_basis(p, mesh.n_cells), psi=M.guccione)
    sol = je.solve(pot, L.combine(*bcs), solver=je.Newton(rtol=1e-10, max_steps=60))
    assert bool(sol.ok)
    F = np.asarray(je.mechanics.kinematics.deformation_gradients(sol.x, mesh))[:, 0]
    return F, np.asarray(jax.vmap(P_hand, in_axes=(0, None))(jnp.asarray(F), p))


def test_cube_is_stiffer_along_fibres_than_sheets():
    """Uniaxial 10 % stretch of a unit cube along x, with the fibres along x, then with the
    sheets along x (the same solver, new parameter values): homogeneous, traction-free
    laterally, and the nominal stress along f0 exceeds that along s0 (b_f = 8 > b_t = 2)."""
    p = M.guccione_params()
    F, P = _pull_x(p)
    assert np.abs(P[:, 1:, 1:]).max() <= 1e-8 * P[0, 0, 0]
    np.testing.assert_allclose(F, np.broadcast_to(F[0], F.shape), atol=1e-9)
    _, Ps = _pull_x(p._replace(f0=jnp.array([0.0, 1.0, 0.0]), s0=jnp.array([1.0, 0.0, 0.0])))
    assert P[0, 0, 0] > 2.0 * Ps[0, 0, 0] > 0


_SCENE = {
    "material": {
        "model": "guccione",
        "C": 2.0,
        "bf": 8.0,
        "bt": 2.0,
        "bfs": 4.0,
        "kappa": 100.0,
        "f0": [{"where": "x < 0.5", "direction": [0.0, 1.0, 0.0]}, {"direction": [1, 0, 0]}],
        "s0": [0.0, 0.0, 1.0],
    },
    "integrator.load_steps": 2,
    "mesh.n": [2, 1, 1],
}


def test_scene_guccione_block_builds():
    """``model = "guccione"`` with f0 from where regions (cell centroids) and a shared s0."""
    from jaxelastic.scene import build, load_scene

    bt = build(load_scene("fibre_block", overrides=_SCENE))
    assert bt.psi is M.guccione
    f0 = np.asarray(bt.params.f0)
    assert f0.shape == (bt.mesh.n_cells, 3)
    assert {tuple(r) for r in f0} == {(0.0, 1.0, 0.0), (1.0, 0.0, 0.0)}


@pytest.mark.extended  # a scene run compiles its own Newton solver (~12 s on 2 cores)
def test_scene_guccione_block_solves(tmp_path):
    from jaxelastic.scene import load_scene, run_scene

    summary = run_scene(
        load_scene("fibre_block", overrides=_SCENE), tmp_path / "out", progress=False
    )
    assert summary["status"] == "ok"


@pytest.mark.parametrize(
    ("material", "message"),
    [
        ({"C": 0.0}, "C must be > 0"),
        ({"s0": [2.0, 0.0, 0.0]}, "s0 must not be parallel to f0"),
        ({"a01": [1.0, 0.0, 0.0]}, "a01 is not a parameter of 'guccione'"),
        ({"f0": None}, "f0 is required"),
    ],
)
def test_scene_validation_names_the_key(material, message):
    from jaxelastic.scene import SceneError, load_scene

    base = {"model": "guccione", "C": 2.0, "bf": 8.0, "bt": 2.0, "bfs": 4.0, "kappa": 100.0}
    base |= {"f0": [1.0, 0.0, 0.0], "s0": [0.0, 1.0, 0.0]}
    mat = {k: v for k, v in (base | material).items() if v is not None}
    with pytest.raises(SceneError, match=message):
        load_scene("fibre_block", overrides={"material": mat})


def test_scene_per_cell_parallel_basis_is_refused():
    from jaxelastic.scene import SceneError, build, load_scene

    ov = dict(_SCENE)
    ov["material"] = ov["material"] | {
        "s0": [{"where": "x < 0.5", "direction": [0, 1, 0]}, {"direction": [0, 0, 1]}]
    }
    with pytest.raises(SceneError, match=r"s0 must not be parallel to f0.*first cell"):
        build(load_scene("fibre_block", overrides=ov))


@pytest.mark.extended  # one follower-pressure Newton solve, ~55 steps (~20 s loaded)
def test_land_problem_1_coarse():
    """Land et al. 2015 problem 1 (the Guccione beam, follower pressure 0.004 kPa on its
    bottom face) on a 10 × 1 × 1 P2 mesh, κ = 1000 kPa: the deflected z of (10, 0.5, 1)
    approaches the consensus ≈ 4.15–4.17 mm from below (coarse mesh and penalty: stiffer;
    20 × 2 × 2 gives 4.07, see scripts/bench_cardiac.py)."""
    bench = load_script("bench_cardiac")
    r = bench.beam(1, "standard", 1000.0)
    assert r["ok"], r
    assert 3.7 < r["z"] < 4.17, r


def test_energy_gradient_wrt_helix_angles():
    """The rule is differentiable in the helix angles: d(energy)/d(α_endo, α_epi) of a
    deformed block in the ventricle wall against central differences."""
    mesh = je.box(2, 1, 1, size=(2.0, 1.0, 1.0), origin=(7.5, -0.5, -8.0))
    X = jnp.asarray(np.asarray(mesh.points)[np.asarray(mesh.cells)].mean(axis=1))
    x = mesh.points @ jnp.asarray([[1.08, 0.05, 0.0], [0.0, 0.95, 0.04], [0.03, 0.0, 1.02]]).T
    base = M.guccione_params()

    @jax.jit
    def energy(angles):
        f0, s0 = M.helix_fibres(X, alpha_endo=angles[0], alpha_epi=angles[1])
        return je.energy(M.guccione, x, mesh, base._replace(f0=f0, s0=s0))

    a = jnp.asarray([60.0, -60.0])
    g = np.asarray(jax.grad(energy)(a))
    h = 1e-4
    fd = [
        (float(energy(a + h * jnp.eye(2)[i])) - float(energy(a - h * jnp.eye(2)[i]))) / (2 * h)
        for i in range(2)
    ]
    np.testing.assert_allclose(g, fd, rtol=1e-6)
    assert np.abs(g).min() > 0


@pytest.mark.extended  # two Newton solves of a compiled active potential (~12 s loaded)
def test_active_tension_contracts_a_free_cube():
    """A unit cube on symmetry planes only, T_a = 1 kPa along x, ramped in two increments
    (s·T_a): the homogeneous contraction F = diag(a, b, b) with the total nominal stress
    zero (2-D root find on the hand P plus T_a F f0⊗f0)."""
    from scipy.optimize import fsolve

    p = M.guccione_params(kappa=100.0)
    psi = M.with_active_tension(M.guccione)
    f = np.array([1.0, 0.0, 0.0])

    def total(ab):
        F = np.diag([ab[0], ab[1], ab[1]])
        P = np.asarray(P_hand(jnp.asarray(F), p)) + 1.0 * F @ np.outer(f, f)
        return [P[0, 0], P[1, 1]]

    a, b = fsolve(total, [0.9, 1.0], xtol=1e-12)
    mesh = je.box(1, 1, 1)
    bc = L.combine(
        *[L.fix(mesh, L.nodes_on_plane(mesh, ax, 0.0), components=(ax,)) for ax in range(3)]
    )
    pc = M.per_cell_basis(p, mesh.n_cells)
    x = mesh.points
    for s in (0.5, 1.0):
        ap = M.ActiveTension(passive=pc, Ta=jnp.asarray(s * 1.0), f0=pc.f0)
        sol = je.solve(
            je.Potential(mesh=mesh, params=ap, psi=psi), bc, x0=x, solver=je.Newton(rtol=1e-10)
        )
        x = sol.x
    F = np.asarray(je.mechanics.kinematics.deformation_gradients(x, mesh))[:, 0]
    assert a < 1.0
    np.testing.assert_allclose(F, np.broadcast_to(np.diag([a, b, b]), F.shape), atol=1e-8)
