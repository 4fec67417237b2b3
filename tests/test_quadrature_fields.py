"""Material data per quadrature point (``AtQuadrature``): a constant field gives exactly the
per-cell results (energy, forces, HVP, element Hessians, stresses, a solve) on P1, P2 and
F-bar meshes; the quadrature points are where the element puts them; the helix rule sampled
there has the prescribed angle at each point; the active tension is ramped by the load
factor; bad shapes and values are refused by name."""

import math

import jax.numpy as jnp
import numpy as np
import pytest
from _common import load_script

import jaxelastic as je
from jaxelastic import loads as L
from jaxelastic import materials as M
from jaxelastic.materials.fibre_rules import LAND_ENDO, LAND_EPI
from jaxelastic.mechanics import AtQuadrature, element_hessians, hvp
from jaxelastic.mesh import truncated_ellipsoid
from jaxelastic.mesh.geometry import quadrature_points
from jaxelastic.postprocess import cell_fields
from jaxelastic.scene import build, load_scene
from jaxelastic.scene.errors import SceneError


def _n_q(m) -> int:
    return int(m.weights.shape[1])


def _fields(m):
    """A non-uniform per-cell (f0, s0): a rotation of x, y about z by the centroid's x."""
    X = np.asarray(m.points)[np.asarray(m.cells)[:, : m.dim + 1]].mean(axis=1)
    a = 0.7 * X[:, 0] + 0.3
    f0 = np.stack([np.cos(a), np.sin(a), 0.2 + 0 * a], axis=1)
    s0 = np.stack([-np.sin(a), np.cos(a), 0 * a], axis=1)
    return jnp.asarray(f0), jnp.asarray(s0)


def _fibre_psi(F, p):
    """A cheap anisotropic ψ with a direction parameter ``p["a"]`` (compiles fast)."""
    a = p["a"] / jnp.sqrt(jnp.sum(p["a"] * p["a"]))
    Fa = F @ a
    J = jnp.linalg.det(F)
    return 0.5 * p["mu"] * (jnp.sum(F * F) - 3.0) + 2.0 * (J - 1.0) ** 2 + (Fa @ Fa - 1.0) ** 2


def _compare_kernels(psi, m, cell, point, full: bool = True):
    X = np.asarray(m.points)
    x = jnp.asarray(X + 0.05 * np.sin(2.0 * X[:, [1, 2, 0]]))
    v = jnp.asarray(np.cos(X))
    for fn in (je.energy, je.forces):
        np.testing.assert_allclose(
            fn(psi, x, m, point), fn(psi, x, m, cell), rtol=1e-12, atol=1e-12
        )
    np.testing.assert_allclose(hvp(psi, x, v, m, point), hvp(psi, x, v, m, cell), atol=1e-11)
    if not full:
        return
    K1, K2 = element_hessians(psi, x, m, point), element_hessians(psi, x, m, cell)
    np.testing.assert_allclose(K1, K2, atol=1e-11 * float(jnp.max(jnp.abs(K2))))
    s1, s2 = cell_fields(psi, x, m, point), cell_fields(psi, x, m, cell)
    np.testing.assert_allclose(s1["von_mises"], s2["von_mises"], rtol=1e-12)


def _cheap_pair(m):
    a, _ = _fields(m)
    cell = {"mu": 1.0, "a": a}
    point = {"mu": 1.0, "a": AtQuadrature(jnp.broadcast_to(a[:, None], (m.n_cells, _n_q(m), 3)))}
    return cell, point


def test_constant_per_point_field_equals_the_per_cell_one():
    """P2 (14 points per cell): energy, forces and HVP."""
    m = je.box(1, 1, 1, order=2)
    _compare_kernels(_fibre_psi, m, *_cheap_pair(m), full=False)


@pytest.mark.extended  # element Hessians and stresses compile for ~10-30 s per case (loaded)
@pytest.mark.parametrize("order, formulation", [(2, "standard"), (1, "fbar"), (2, "fbar")])
def test_constant_per_point_field_equals_the_per_cell_one_everywhere(order, formulation):
    """Energy, forces, HVP, element Hessians (F-bar terms too) and stresses."""
    m = je.box(1, 1, 1, order=order, formulation=formulation)
    _compare_kernels(_fibre_psi, m, *_cheap_pair(m))


@pytest.mark.extended  # Guccione with active tension compiles for ~1 min per case (loaded)
@pytest.mark.parametrize(
    "order, formulation", [(1, "standard"), (2, "standard"), (2, "fbar"), (1, "fbar")]
)
def test_constant_per_point_guccione_equals_the_per_cell_one(order, formulation):
    m = je.box(2, 1, 1, size=(2.0, 1.0, 1.0), order=order, formulation=formulation)
    f0, s0 = _fields(m)
    cell = M.ActiveTension(M.guccione_params(f0=f0, s0=s0), 3.0, f0)
    qp = M.per_quadrature_basis(cell.passive, m.n_cells, _n_q(m))
    point = M.ActiveTension(qp, 3.0, qp.f0)
    assert isinstance(point.passive.f0, AtQuadrature)
    _compare_kernels(M.with_active_tension(M.guccione), m, cell, point)


@pytest.mark.extended  # two Guccione solves (~45 s loaded)
def test_constant_per_point_field_gives_the_same_solution():
    m = je.box(3, 1, 1, size=(3.0, 1.0, 1.0), order=2)
    f0, s0 = _fields(m)
    cell = M.ActiveTension(M.guccione_params(f0=f0, s0=s0), 1.0, f0)
    qp = M.per_quadrature_basis(cell.passive, m.n_cells, _n_q(m))
    point = M.ActiveTension(qp, 1.0, qp.f0)
    psi = M.with_active_tension(M.guccione)
    bc = L.fix(m, L.nodes_on_plane(m, 0, 0.0))
    a = je.solve(je.Potential(m, cell, psi=psi), bc)
    b = je.solve(je.Potential(m, point, psi=psi), bc)
    assert a.ok and b.ok
    assert float(jnp.max(jnp.abs(a.x - m.points))) > 0.05  # the fibres contract it
    np.testing.assert_allclose(b.x, a.x, atol=1e-10)


@pytest.mark.parametrize("order, formulation", [(1, "standard"), (2, "standard"), (1, "fbar")])
def test_quadrature_points_are_the_elements(order, formulation):
    """On straight cells the points are the affine images X₀ + J ξ_q of the reference
    points (composite cells: the sub-tets' centroids, averaging to the cell centroid)."""
    m = je.box(2, 1, 1, size=(2.0, 1.0, 1.5), order=order, formulation=formulation)
    el = m.element_type
    Xq = np.asarray(quadrature_points(m.points, m.cells, el))
    assert Xq.shape == (m.n_cells, el.n_quad, 3)
    corners = np.asarray(m.points)[np.asarray(m.cells)[:, :4]]  # (c, 4, 3)
    J = np.swapaxes(corners[:, 1:] - corners[:, :1], 1, 2)  # columns X_i − X_0
    ref = np.einsum("cij,qj->cqi", J, np.asarray(el.quad_points)) + corners[:, None, 0]
    np.testing.assert_allclose(Xq, ref, atol=1e-13)
    # the quadrature rule integrates X exactly: Σ w X_q = cell measure × centroid
    np.testing.assert_allclose(
        np.einsum("cq,cqi->ci", np.asarray(m.weights), Xq),
        np.asarray(m.weights).sum(1)[:, None] * corners.mean(axis=1),
        atol=1e-13,
    )
    # the NumPy and JAX paths agree
    np.testing.assert_allclose(
        quadrature_points(np.asarray(m.points), np.asarray(m.cells), el), Xq, atol=1e-14
    )


def _t_closed_form(rho: float, z: float) -> float:
    """The transmural coordinate by bisection on the ellipse family written out here."""
    (a0, b0), (a1, b1) = LAND_ENDO, LAND_EPI
    lo, hi = -1.0, 2.0
    for _ in range(80):
        t = 0.5 * (lo + hi)
        a, b = a0 + t * (a1 - a0), b0 + t * (b1 - b0)
        lo, hi = (t, hi) if rho**2 / a**2 + z**2 / b**2 > 1.0 else (lo, t)
    return 0.5 * (lo + hi)


def test_helix_at_the_quadrature_points_has_the_prescribed_angle():
    m = truncated_ellipsoid(4, 8, 1, order=2)
    f0, s0 = M.helix_basis(m, at="quadrature")
    assert isinstance(f0, AtQuadrature) and f0.values.shape == (m.n_cells, 14, 3)
    Xq = np.asarray(quadrature_points(m.points, m.cells, m.element_type)).reshape(-1, 3)
    f, s = np.asarray(f0.values).reshape(-1, 3), np.asarray(s0.values).reshape(-1, 3)
    rng = np.random.default_rng(0)
    for i in rng.choice(len(Xq), 60, replace=False):
        x, y, z = Xq[i]
        rho = math.hypot(x, y)
        t = _t_closed_form(rho, z)
        (a0, b0), (a1, b1) = LAND_ENDO, LAND_EPI
        a, b = a0 + t * (a1 - a0), b0 + t * (b1 - b0)
        normal = np.array([x / a**2, y / a**2, z / b**2])
        np.testing.assert_allclose(s[i], normal / np.linalg.norm(normal), atol=1e-10)
        e_v = np.array([-y, x, 0.0]) / rho  # ∂X/∂v normalised (sin u < 0)
        e_u = np.cross(e_v, normal)  # the meridian tangent
        e_u /= np.linalg.norm(e_u)
        if e_u[2] < 0:  # ∂X/∂u has z component −r_l sin u > 0 (u ∈ (−π, 0))
            e_u = -e_u
        alpha = math.degrees(math.atan2(f[i] @ e_u, f[i] @ e_v))
        assert alpha == pytest.approx(90.0 - 180.0 * t, abs=1e-8)
    # through the one-cell-thick wall the points of a cell sample different angles
    spread = np.ptp(np.asarray(f0.values) @ np.array([0.0, 0.0, 1.0]), axis=1)
    assert np.median(spread) > 0.3
    # at="cells" is the centroid rule of before
    fc, _ = M.helix_basis(m, at="cells")
    cent = np.asarray(m.points)[np.asarray(m.cells)[:, :4]].mean(axis=1)
    np.testing.assert_allclose(fc, M.helix_fibres(jnp.asarray(cent))[0], atol=1e-14)


@pytest.mark.extended  # three Guccione solves (~7 s)
def test_params_path_ramps_the_active_tension():
    """Load stepping with ``params_path = ActiveTension.scaled``: the increment at s = 1/2
    is the solve at T_a/2, and the end the solve at T_a."""
    m = je.box(3, 1, 1, size=(3.0, 1.0, 1.0))
    ex = jnp.broadcast_to(jnp.array([1.0, 0.0, 0.0]), (m.n_cells, 3))
    p = M.ActiveTension({"mu": 1.0, "a": ex}, 0.5, ex)
    psi = M.with_active_tension(_fibre_psi)
    pot = je.Potential(m, p, psi=psi)
    bc = L.fix(m, L.nodes_on_plane(m, 0, 0.0))
    seen = {}
    res = je.solve_incremental(
        pot, bc, steps=2, params_path=p.scaled, callback=lambda s, r: seen.update({s: r.x})
    )
    half = je.solve(je.Potential(m, p.scaled(0.5), psi=psi), bc)
    full = je.solve(pot, bc)
    np.testing.assert_allclose(seen[0.5], half.x, atol=1e-9)
    np.testing.assert_allclose(res.x, full.x, atol=1e-9)
    tip = int(np.argmax(np.asarray(m.points)[:, 0]))
    assert float(half.x[tip, 0]) > float(full.x[tip, 0])  # contracted along the fibres


# ------------------------------------------------------------------ refused input


def test_bad_per_point_fields_are_refused_by_name():
    m = je.box(1, 1, 1, order=2)
    x, nq = m.points, _n_q(m)
    base = M.guccione_params()
    wrong_q = base._replace(f0=AtQuadrature(jnp.ones((m.n_cells, nq + 1, 3))))
    with pytest.raises(
        ValueError, match=r"params.f0 is an AtQuadrature of shape \(6, 15, 3\).*\(6, 14"
    ):
        je.energy(M.guccione, x, m, wrong_q)
    wrong_c = base._replace(f0=AtQuadrature(jnp.ones((m.n_cells + 1, nq, 3))))
    with pytest.raises(ValueError, match="n_cells"):
        je.forces(M.guccione, x, m, wrong_c)
    with pytest.raises(TypeError, match="one array of shape"):
        je.energy(M.guccione, x, m, base._replace(f0=AtQuadrature((1.0, 0.0, 0.0))))
    with pytest.raises(ValueError, match="per_quadrature_basis"):
        M.per_quadrature_basis(base._replace(f0=jnp.ones((m.n_cells + 1, 3))), m.n_cells, nq)
    with pytest.raises(ValueError, match="at must be 'cells' or 'quadrature'"):
        M.helix_basis(m, at="nodes")  # type: ignore[arg-type]
    base = M.per_quadrature_basis(base, m.n_cells, nq)
    nan = base._replace(f0=AtQuadrature(jnp.full((m.n_cells, nq, 3), jnp.nan)))
    with pytest.raises(ValueError, match="NaN"):
        je.energy(M.guccione, x, m, nan)
    zero = M.per_quadrature_basis(base, m.n_cells, nq)
    zero = zero._replace(f0=AtQuadrature(zero.f0.values.at[0, 1].set(0.0)))
    bc = L.fix(m, L.nodes_on_plane(m, 0, 0.0))
    with pytest.raises(ValueError, match="f0"):
        je.solve(je.Potential(m, zero, psi=M.guccione), bc)


@pytest.mark.parametrize("Ta", [float("nan"), -1.0])
def test_active_tension_must_be_finite_and_nonnegative(Ta):
    m = je.box(1, 1, 1)
    g = M.per_cell_basis(M.guccione_params(), m.n_cells)
    p = M.ActiveTension(g, Ta, g.f0)
    bc = L.fix(m, L.nodes_on_plane(m, 0, 0.0))
    with pytest.raises(ValueError, match="Ta"):
        je.solve(je.Potential(m, p, psi=M.with_active_tension(M.guccione)), bc)


# ------------------------------------------------------------------ the scene


def test_ventricle_active_scene_builds_per_point_fibres_and_tension():
    b = build(load_scene("ventricle_active"))
    p = b.potential.params
    assert isinstance(p, M.ActiveTension) and float(p.Ta) == 6.0e4
    assert isinstance(p.passive.f0, AtQuadrature) and isinstance(p.passive.s0, AtQuadrature)
    R = {"endo": (0.007, 0.017), "epi": (0.010, 0.020)}
    f0, s0 = M.helix_basis(b.mesh, at="quadrature", **R)
    np.testing.assert_allclose(p.passive.f0.values, f0.values, atol=1e-12)
    np.testing.assert_allclose(p.passive.s0.values, s0.values, atol=1e-12)
    np.testing.assert_array_equal(p.f0.values, p.passive.f0.values)  # along the law's fibres


@pytest.mark.parametrize(
    "overrides, match",
    [
        ({"material.active_tension": -1.0}, "active_tension"),
        ({"material.f0.at": "nodes"}, "at"),
    ],
)
def test_ventricle_active_scene_refuses_bad_values(overrides, match):
    with pytest.raises(SceneError, match=match):
        load_scene("ventricle_active", overrides=overrides)


def test_active_tension_is_refused_in_a_fit_and_with_a_prescribed_volume():
    base = {"plane": {"axis": "z", "value": 0.005}}
    obs = {"kind": "reaction", "file": "fit_plate_hole_force.csv", "sigma": 1.0}
    obs |= {"nodes": base, "direction": [0.0, 0.0, 1.0]}
    fit = {"fit": {"fields": ["C"], "case": [{"load_factors": [1.0], "observation": [obs]}]}}
    with pytest.raises(SceneError, match="leave active_tension out of a .fit. scene"):
        load_scene("ventricle_active", overrides=fit)
    volume = {"pressure": [], "cavity.0.volume": 1.2e-6}
    with pytest.raises(SceneError, match="prescribed volume"):
        build(load_scene("ventricle_active", overrides=volume))


def test_active_tension_is_a_guccione_key():
    with pytest.raises(SceneError, match="active_tension is a key of 'guccione'"):
        load_scene("default", overrides={"material.active_tension": 1.0})


def _bench():
    return load_script("bench_cardiac")


@pytest.mark.extended  # the scene (~50 s loaded) and the same problem from Python
def test_ventricle_active_scene_agrees_with_the_python_path(tmp_path):
    from jaxelastic.scene import run_scene

    summary = run_scene("ventricle_active", str(tmp_path), progress=False)
    z = [1e3 * (p["node_position"][2] + p["displacement"][2]) for p in summary["probes"]]
    assert -17.0 < z[0] and -20.0 < z[1]  # both apexes rise (the wall shortens)
    ref = _bench().ventricle(3, 1, 2, "standard", 1000.0, fibres="quadrature")
    assert ref["ok"]
    assert z == pytest.approx([ref["z_endo"], ref["z_epi"]], abs=2e-3)  # mm
    assert z == pytest.approx([-12.0, -15.2], abs=0.7)  # the consensus, one cell thick


@pytest.mark.extended  # one solve of 5 increments on 8 x 16 x 2 P2 (~1 min loaded)
def test_land_problem_3_with_per_point_fibres_reaches_the_consensus():
    """Problem 3 with helix fibres at the quadrature points, two cells through the wall:
    the apex within 0.2 mm of the code output (−12.0 endo, −15.2 epi)."""
    r = _bench().ventricle(3, 2, 2, "standard", 1000.0, fibres="quadrature")
    assert r["ok"], r
    assert abs(r["z_endo"] - (-12.0)) < 0.2 and abs(r["z_epi"] - (-15.2)) < 0.25
