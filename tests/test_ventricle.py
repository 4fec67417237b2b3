"""The truncated-ellipsoid ventricle (Land et al. 2015, problems 2 and 3): the mesh
generator against the analytic wall and cavity volumes, its surfaces, the scene fibre rule,
the shipped ``ventricle`` scene, and (extended) the benchmark apex displacements."""

import math

import numpy as np
import pytest
from _common import load_script

from jaxelastic import materials as M
from jaxelastic.materials.fibre_rules import transmural_coordinate
from jaxelastic.mesh import boundary_facets, ellipsoid_surfaces, truncated_ellipsoid
from jaxelastic.mesh.elements import facet_rule
from jaxelastic.scene import build, load_scene
from jaxelastic.scene.errors import SceneError


def _cap(a: float, c: float, zb: float) -> float:
    """Volume of the spheroid ρ²/a² + z²/c² ≤ 1 below the plane z = zb."""
    return math.pi * a * a * (zb + 2.0 * c / 3.0 - zb**3 / (3.0 * c * c))


CAVITY = _cap(7.0, 17.0, 5.0)
WALL = _cap(10.0, 20.0, 5.0) - CAVITY


def _volumes(m):
    """(wall, cavity) volumes of a mesh: the sum of its quadrature weights (the integral
    of det J, exact for the isoparametric cells) and the cavity closed by the base,
    ``−(1/3) ∫ (x − c)·n da`` over the endocardium by the facet rule (as the pressure
    term computes it, here in NumPy)."""
    wall = float(np.sum(np.asarray(m.weights)))
    N, dN, w = facet_rule(m.element_type)  # (r, k), (r, k, 2), (r,)
    xf = np.asarray(m.points)[ellipsoid_surfaces(m)["endocardium"]]  # (f, k, 3)
    xq = np.einsum("rk,fkd->frd", N, xf) - [0.0, 0.0, 5.0]
    T = np.einsum("fkd,rke->frde", xf, dN)
    nvec = np.cross(T[..., 0], T[..., 1])
    return wall, float(-np.einsum("r,frd,frd->", w, xq, nvec) / 3.0)


@pytest.mark.parametrize("order, rate", [(1, 2.0), (2, 4.0)])
def test_volumes_converge_at_the_expected_rate(order, rate):
    """Halving h: the wall and cavity volume errors fall by 2² (P1, straight facets) and
    2⁴ (P2, curved isoparametric facets) within 10 % of the exponent."""
    errs = []
    for n in (1, 2):
        wall, cav = _volumes(truncated_ellipsoid(4 * n, 8 * n, n, order=order))
        errs.append((abs(wall / WALL - 1.0), abs(cav / CAVITY - 1.0)))
    for (w1, c1), (w2, c2) in zip(errs[:-1], errs[1:], strict=True):
        assert math.log2(w1 / w2) == pytest.approx(rate, rel=0.1)
        assert math.log2(c1 / c2) == pytest.approx(rate, rel=0.1)
    assert max(errs[-1]) < (0.05 if order == 1 else 2e-4)


def test_layout_base_plane_apex_line_and_positive_cells():
    n_u, n_v, n_t = 3, 6, 2
    m = truncated_ellipsoid(n_u, n_v, n_t)
    X, cells = np.asarray(m.points), np.asarray(m.cells)
    n2 = 1 + n_u * n_v
    assert m.n_nodes == (n_t + 1) * n2 and m.n_cells == 3 * n_t * n_v * (2 * n_u - 1)
    D = X[cells[:, 1:]] - X[cells[:, :1]]
    vol = np.linalg.det(D) / 6.0
    assert vol.min() > 1e-3 * vol.max()  # no inverted or degenerate tet
    apex = np.arange(n_t + 1) * n2
    np.testing.assert_allclose(X[apex], [[0, 0, -17.0], [0, 0, -18.5], [0, 0, -20.0]])
    ring = X[np.arange(n_t + 1)[:, None] * n2 + 1 + (n_u - 1) * n_v + np.arange(n_v)]
    assert np.all(ring[..., 2] == 5.0)  # the base ring of every layer, exactly
    # every node on its layer's ellipsoid, t = k / n_t (the transmural coordinate)
    t = np.asarray(transmural_coordinate(X))
    np.testing.assert_allclose(t, np.repeat(np.arange(n_t + 1) / n_t, n2), atol=1e-12)


def test_p2_nodes_on_the_surfaces_and_the_base():
    m = truncated_ellipsoid(3, 6, 1, order=2, formulation="fbar")
    assert m.element_type.name == "tet10" and m.formulation == "fbar"
    X = np.asarray(m.points)
    s = ellipsoid_surfaces(m)
    for name, (a, c) in (("endocardium", (7.0, 17.0)), ("epicardium", (10.0, 20.0))):
        Y = X[np.unique(s[name])]  # mid-edge nodes included
        np.testing.assert_allclose((Y[:, 0] ** 2 + Y[:, 1] ** 2) / a**2 + Y[:, 2] ** 2 / c**2, 1)
    assert np.all(X[np.unique(s["base"]), 2] == 5.0)
    assert X[:, 2].max() == 5.0


def test_surfaces_partition_the_boundary_with_outward_normals():
    n_u, n_v, n_t = 3, 6, 2
    m = truncated_ellipsoid(n_u, n_v, n_t)
    s = ellipsoid_surfaces(m)
    assert len(s["endocardium"]) == len(s["epicardium"]) == n_v * (2 * n_u - 1)
    assert len(s["base"]) == 2 * n_v * n_t
    assert sum(len(f) for f in s.values()) == len(boundary_facets(m))
    X = np.asarray(m.points)
    for name, sign in (("endocardium", -1.0), ("epicardium", 1.0), ("base", 1.0)):
        f = X[s[name]]
        nrm = np.cross(f[:, 1] - f[:, 0], f[:, 2] - f[:, 0])
        centre = f.mean(axis=1) - ([0, 0, 5.0] if name == "base" else 0.0)
        out = np.sum(nrm * (centre if name != "base" else [0, 0, 1.0]), axis=1)
        assert np.all(sign * out > 0), name  # endocardium: outward = into the cavity


def test_composite_element_and_other_radii():
    m = truncated_ellipsoid(2, 4, 1, endo=(0.7, 1.7), epi=(1.0, 2.0), base=0.5, formulation="fbar")
    assert m.element_type.name == "tet4x8"
    s = ellipsoid_surfaces(m, endo=(0.7, 1.7), epi=(1.0, 2.0), base=0.5)
    assert set(s) == {"endocardium", "epicardium", "base"}
    with pytest.raises(ValueError, match="no boundary facet on the epicardium"):
        ellipsoid_surfaces(m, endo=(0.7, 1.7), epi=(1.1, 2.0), base=0.5, tol=1e-12)


@pytest.mark.parametrize(
    "kw, message",
    [
        (dict(n_v=2), "n_v must be at least 3"),
        (dict(n_u=0), "n_u must be a positive integer"),
        (dict(endo=(10.0, 17.0)), "need endo < epi"),
        (dict(endo=(7.0,)), "endo must be two finite radii"),
        (dict(base=17.5), "must cut the endocardium"),
        (dict(order=3), "order must be 1 or 2"),
        (dict(formulation="xbar"), "formulation"),
    ],
)
def test_bad_arguments_refused(kw, message):
    args = dict(n_u=2, n_v=4, n_t=1) | kw
    with pytest.raises(ValueError, match=message):
        truncated_ellipsoid(**args)


# --- the shipped scene and the fibre rule ---------------------------------------------

RADII = {"endo_radii": [0.007, 0.017], "epi_radii": [0.010, 0.020]}


def test_ventricle_scene_builds_with_its_cavity_and_helix_fibres():
    b = build(load_scene("ventricle"))
    term = b.potential.pressure
    assert term is not None and term.n_surfaces == 1 and not term.follower
    V0 = float(b.cavities.term.volumes(b.x0)[0])
    assert V0 == pytest.approx(_cap(0.007, 0.017, 0.005), rel=3e-3)  # 4 x 8 x 1, P2
    mesh, p = b.potential.mesh, b.potential.params
    X = np.asarray(mesh.points)[np.asarray(mesh.cells)[:, :4]].mean(axis=1)
    f0, s0 = M.helix_fibres(X, (0.007, 0.017), (0.010, 0.020))
    np.testing.assert_allclose(np.asarray(p.f0), np.asarray(f0), atol=1e-12)
    np.testing.assert_allclose(np.asarray(p.s0), np.asarray(s0), atol=1e-12)
    Y = np.asarray(mesh.points)  # the base nodes are fixed, no others
    fixed = np.asarray(b.bc.mask).all(axis=1)
    assert np.array_equal(fixed, np.isclose(Y[:, 2], 0.005, rtol=0, atol=1e-12))


def test_helix_rule_angles_reach_the_fibres():
    """endo = epi = 0: circumferential fibres everywhere (f0 ⟂ z)."""
    b = build(
        load_scene(
            "ventricle",
            overrides={"material.f0": {"rule": "helix", "endo": 0.0, "epi": 0.0} | RADII},
        )
    )
    f0 = np.asarray(b.potential.params.f0)
    assert np.abs(f0[:, 2]).max() < 1e-12


@pytest.mark.parametrize(
    "f0, message",
    [
        ({"rule": "transmural", "endo": 90.0}, "endo is a helix angle"),
        ({"rule": "spiral"}, "rule"),
        ({"rule": "helix", "endo_radii": [10.0, 17.0]}, "need endo_radii < epi_radii"),
        ({"rule": "helix", "sheet": 1.0}, "unknown key"),
    ],
)
def test_bad_fibre_rules_refused(f0, message):
    with pytest.raises(SceneError, match=message):
        load_scene("ventricle", overrides={"material.f0": f0})


def test_fibre_rule_needs_a_3d_mesh():
    over = {
        "material": {
            "model": "guccione",
            "C": 1.0,
            "bf": 1.0,
            "bt": 1.0,
            "bfs": 1.0,
            "kappa": 100.0,
            "f0": {"rule": "helix"},
            "s0": [0.0, 1.0],
        }
    }
    with pytest.raises(SceneError, match="needs a 3D mesh"):
        build(load_scene("cook", overrides=over))


# --- the benchmarks (extended) ---------------------------------------------------------


def _bench():
    return load_script("bench_cardiac")


@pytest.mark.extended  # two solves of 5 load increments (~40 s loaded)
def test_land_problem_2_coarse_brackets_the_consensus():
    """Problem 2 on the 4 × 8 × 1 mesh, κ = 1000 kPa: plain P2 short of the consensus
    apex z (−26.5 endo, −28.2 epi), P2 + F-bar past it, each within 2 %."""
    bench = _bench()
    p2 = bench.ventricle(2, 1, 2, "standard", 1000.0)
    fb = bench.ventricle(2, 1, 2, "fbar", 1000.0)
    assert p2["ok"] and fb["ok"], (p2, fb)
    for key, ref in (("z_endo", -26.5), ("z_epi", -28.2)):
        assert fb[key] < ref < p2[key], (key, p2[key], fb[key])
        assert abs(p2[key] / ref - 1) < 0.02 and abs(fb[key] / ref - 1) < 0.02


@pytest.mark.extended  # one scene run (~30 s loaded)
def test_ventricle_scene_runs(tmp_path):
    from jaxelastic.scene import run_scene

    summary = run_scene("ventricle", tmp_path, progress=False)
    cav = summary["cavities"]["cavity"]
    assert cav["load_factor"][-1] == 1.0 and np.all(np.diff(cav["volume"]) > 0)
    z = [p["node_position"][2] + p["displacement"][2] for p in summary["probes"]]
    assert z == pytest.approx([-0.02686, -0.02834], abs=2e-5)  # the P2 + F-bar row


@pytest.mark.extended  # two solves of 5 increments (~2 min loaded)
def test_land_problem_3_approaches_the_consensus_with_the_fibre_resolution():
    """Problem 3 (helix fibres, T_a = 60 kPa, p = 15 kPa), P2, κ = 1000 kPa: one layer
    of cells through the wall barely contracts (per-cell fibres miss the longitudinal
    ones of the surfaces); two layers bring the apex within 0.7 mm (endo) and 1.3 mm (epi)
    of the consensus (−12.0 to −12.5 endo, −15.2 to −15.5 epi)."""
    bench = _bench()
    coarse = bench.ventricle(3, 1, 2, "standard", 1000.0)
    fine = bench.ventricle(3, 2, 2, "standard", 1000.0)
    assert coarse["ok"] and fine["ok"], (coarse, fine)
    assert -17.0 < coarse["z_endo"] < fine["z_endo"]  # the apex rises, more when resolved
    assert abs(fine["z_endo"] - (-12.25)) < 0.7 and abs(fine["z_epi"] - (-15.35)) < 1.3
