"""Never a wrong answer reported as success.

Every solve reports its most deformed cells (min J, largest strain) and the tolerance it
reached; an inverted solution of a material undefined at J <= 0 is a failure, one of a
material defined there a warning; a tolerance below the round-off floor is reported; a
scene summary warns about inverted cells and displacements beyond the body's size.
"""

from __future__ import annotations

import re
import subprocess
import sys
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _common import TINY_SCENE, scene_toml

import jaxelastic as je
from jaxelastic import cli, loads
from jaxelastic import contact as C
from jaxelastic import materials as M
from jaxelastic.contact.log_barrier import default_dhat
from jaxelastic.mechanics.kinematics import deformation_extremes, principal_stretch_range
from jaxelastic.mesh import MeshError
from jaxelastic.scene import SceneError, apply_overrides, build, load_scene, run_scene
from jaxelastic.scene.outputs import LARGE_DISPLACEMENT, run_table, run_warnings
from jaxelastic.solvers import SolveError, SolveWarning, Status

P3 = M.Lame.from_E_nu(1e3, 0.3)


@pytest.fixture(scope="module")
def cube():
    return je.box(2, 2, 2)


# ---------------------------------------------------------------- min J, largest strain


@pytest.mark.parametrize("d", [2, 3])
def test_principal_stretch_range_matches_the_singular_values(d):
    rng = np.random.default_rng(0)
    mats = [rng.normal(size=(d, d)) for _ in range(20)]
    mats += [np.eye(d), 2.0 * np.eye(d), np.diag([1.0] * (d - 1) + [-1.0])]
    mats.append(np.diag([3.0, 3.0] + [0.5] * (d - 2)))  # a repeated stretch
    lo, hi = jax.jit(jax.vmap(principal_stretch_range))(jnp.asarray(np.stack(mats)))
    sv = np.linalg.svd(np.stack(mats), compute_uv=False)
    np.testing.assert_allclose(lo, sv.min(1), rtol=1e-7, atol=1e-7)
    np.testing.assert_allclose(hi, sv.max(1), rtol=1e-7, atol=1e-7)


def test_every_solution_reports_min_J_strain_and_the_tolerance_reached(cube):
    """One solve with rtol below the round-off floor: min J and the largest strain with
    their cells, the relative residual reached, and a one-time SolveWarning."""
    bc = loads.fix(cube, cube.points[:, 0] < 1e-9)
    f = jnp.zeros_like(cube.points).at[:, 2].set(-20.0)
    pot = je.Potential(cube, P3, f_ext=f, psi=M.neo_hookean)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("default")  # Python's own filter: once per calling line
        for _ in range(2):
            sol = je.solve(pot, bc, solver=je.Newton(rtol=1e-16, linear="cg"))
    floor = [w for w in rec if issubclass(w.category, SolveWarning)]
    assert len(floor) == 1
    assert "below the residual's round-off floor" in str(floor[0].message)
    st = sol.stats
    F = np.asarray(je.mechanics.kinematics.deformation_gradients(sol.x, cube))[:, 0]
    J = np.linalg.det(F)
    sv = np.linalg.svd(F, compute_uv=False)
    strain = np.maximum(sv.max(1) - 1.0, 1.0 - sv.min(1))
    assert float(st["min_J"]) == pytest.approx(J.min(), rel=1e-10)
    assert int(st["min_J_cell"]) == int(np.argmin(J))
    assert float(st["max_strain"]) == pytest.approx(strain.max(), rel=1e-8)
    assert int(st["max_strain_cell"]) == int(np.argmax(strain))
    assert float(st["achieved_rtol"]) == pytest.approx(
        float(st["residual"]) / float(st["residual_reference"])
    )
    assert bool(st["floor_limited"])
    assert float(st["residual"]) > float(st["tolerance"])
    assert float(st["residual"]) <= float(st["residual_floor"])


def _reflected(mesh):
    """All dofs prescribed at the mirror image of the rest shape: every cell has J = -1."""
    xr = mesh.points * jnp.array([[-1.0, 1.0, 1.0]])
    return je.Dirichlet(mask=jnp.ones(mesh.points.shape, bool), values=xr), xr


def _user_stvk(F, p):  # a user law that is finite (garbage) at J <= 0, not marked
    return M.stvk(F, p)


def test_an_inverted_solution_of_a_material_undefined_there_fails(cube):
    bc, xr = _reflected(cube)
    pot = je.Potential(cube, P3, psi=_user_stvk)
    sol = je.solve(pot, bc, x0=xr, throw=False)
    assert int(sol.status) == Status.INVERTED
    assert float(sol.stats["min_J"]) == pytest.approx(-1.0)
    with pytest.raises(SolveError, match=r"INVERTED: .* min J -1 in cell \d+"):
        je.solve(pot, bc, x0=xr)


def test_an_inverted_solution_of_a_material_defined_there_warns(cube):
    bc, xr = _reflected(cube)
    with pytest.warns(SolveWarning, match=r"inverted cells \(J <= 0\).*stats\['min_J'\]"):
        sol = je.solve(je.Potential(cube, P3, psi=M.stvk), bc, x0=xr)
    assert int(sol.status) == Status.SUCCESS
    assert float(sol.stats["min_J"]) == pytest.approx(-1.0)


def test_deformation_extremes_use_the_compatible_F():
    mesh = je.box(1, 1, 1, formulation="fbar")
    x = mesh.points.at[0].set(mesh.points[0] + jnp.array([0.0, 0.0, 2.0]))
    F = je.mechanics.kinematics.deformation_gradients(x, mesh, fbar=False)
    J = np.linalg.det(np.asarray(F))
    assert float(jax.jit(deformation_extremes)(x, mesh).min_J) == pytest.approx(J.min())


# ------------------------------------------------------------------------- scene summary


@pytest.mark.extended
def test_a_scene_with_absurd_displacements_warns_in_summary_and_table(tmp_path):
    sc = apply_overrides(TINY_SCENE, {"material.model": "stable_neo_hookean", "material.E": 3.0})
    with pytest.warns(SolveWarning, match="of the body's diagonal"):
        s = run_scene(load_scene(sc), tmp_path, progress=False)
    assert s["status"] == "ok"
    (w,) = s["warnings"]
    assert re.match(r"the largest displacement is \d+ % of the body's diagonal", w)
    assert "units of E" in w and "supports" in w
    d = s["static"]["deformation"]
    assert d["min_J"] > 0 and d["max_strain"] > 1.0
    table = run_table(s)
    assert table.splitlines()[0] == "tiny: ok (static) with 1 WARNING (below)"
    assert "  WARNING " in table and "min J " in table and "largest strain" in table


def test_run_warnings_name_inverted_cells_and_the_floor():
    s = dict(
        dynamic=dict(
            max_displacement_relative=0.5 * LARGE_DISPLACEMENT,
            deformation=dict(min_J=0.5, min_J_run=-3.0, min_J_run_t=0.25, min_J_run_cell=7),
            floor_limited_solves=2,
            achieved_rtol_max=3.7e-8,
        ),
        solver=dict(rtol=1e-12),
    )
    inv, floor = run_warnings(s)
    assert inv.startswith("inverted cells: J = -3 in cell 7 at t = 0.25 s")
    assert "units of E" in inv
    assert floor.startswith("2 solve(s) stopped at the residual's round-off floor")
    assert "3.7e-08" in floor
    s["solver"]["rtol"] = 1e-8  # within FLOOR_WARNING of the request: the table says it
    assert len(run_warnings(s)) == 1


@pytest.mark.extended
def test_drop_with_a_wrong_unit_is_not_silently_ok(tmp_path):
    """``jaxelastic run drop --set material.E=0.1`` (stable neo-Hookean: defined at J <= 0)."""
    sc = load_scene("drop", overrides={"material.E": 0.1, "output.vtu": False, "output.png": False})
    with pytest.warns(SolveWarning):
        s = run_scene(sc, tmp_path, progress=False)
    text = " ".join(s["warnings"])
    assert "inverted cells" in text and "of the body's diagonal" in text
    assert s["dynamic"]["deformation"]["min_J_run"] <= 0


def test_the_run_table_puts_warnings_first_and_reports_min_J():
    s = dict(
        scene=dict(name="x"),
        status="ok",
        warnings=["inverted cells: J = -3 ...", "the largest displacement is 538 % ..."],
        mesh=dict(n_cells=4, element="tet4", n_nodes=8, dim=3),
        static=dict(
            newton_steps=3,
            linear_iterations=3,
            final_residual=1e-9,
            achieved_rtol_max=3.7e-8,
            floor_limited_solves=1,
            max_displacement=2.0,
            elastic_energy=1.0,
            deformation=dict(
                min_J=-3.0,
                min_J_cell=2,
                min_J_at=[0.0, 0.0, 0.0],
                max_strain=5.0,
                max_strain_cell=1,
                max_strain_at=[1.0, 0.0, 0.0],
            ),
        ),
    )
    lines = run_table(s).splitlines()
    assert lines[0] == "x: ok (static) with 2 WARNINGS (below)"
    assert re.match(r"  WARNING 1 +inverted cells", lines[1])
    assert re.match(r"  WARNING 2 +the largest displacement", lines[2])
    text = "\n".join(lines)
    assert "final residual 1e-09 (relative 3.7e-08, 1 at the round-off floor)" in text
    assert re.search(r"min J +-3 in cell 2 at \(0, 0, 0\); largest strain 500 % in cell 1", text)


# ------------------------------------------------------------------ obstacles and contact


def _contact_pot(mesh):
    return je.Potential(mesh, M.Lame.from_E_nu(1e3, 0.3), psi=M.neo_hookean)


GROUND = dict(point=jnp.array([0.0, 0.0, -0.1]), normal=jnp.array([0.0, 0.0, 1.0]))


@pytest.mark.parametrize(
    "make, match",
    [
        # a sphere inside the body with no node inside it
        (
            lambda: C.Sphere(jnp.array([0.25, 0.25, 0.25]), jnp.asarray(0.1)),
            r"obstacle 1 \(Sphere\) intersects the body at the rest shape: its interior "
            r"point \(0\.25, 0\.25, 0\.25\) lies in cell",
        ),
        # a box poking through the top face between nodes
        (
            lambda: C.Box(jnp.array([0.3, 0.3, 0.9]), jnp.array([0.45, 0.45, 1.5])),
            r"obstacle 1 \(Box\) intersects the body at the rest shape: \d+ boundary facet "
            r"point\(s\) inside it",
        ),
    ],
)
def test_an_obstacle_intersecting_the_rest_body_is_refused(cube, make, match):
    with pytest.raises(ValueError, match=match):
        C.make_contact(_contact_pot(cube), [C.HalfSpace(**GROUND), make()])


@pytest.mark.parametrize(
    "ob, match",
    [
        (C.HalfSpace(**GROUND, friction=jnp.asarray(-0.5)), r"obstacle 0 \(HalfSpace\): friction"),
        (
            C.HalfSpace(GROUND["point"], jnp.array([0.0, 0.0, jnp.nan])),
            r"obstacle 0 \(HalfSpace\): normal must be finite",
        ),
        (
            C.HalfSpace(GROUND["point"], jnp.zeros(3)),
            r"obstacle 0 \(HalfSpace\): normal must be a non-zero vector",
        ),
        (
            C.HalfSpace(GROUND["point"], jnp.array([0.0, 0.0, 1e-200])),
            r"normal must be a non-zero vector .* of length between 1e-100",
        ),
        (C.Sphere(jnp.array([0.0, 0.0, 5.0]), jnp.asarray(-1.0)), r"\(Sphere\): radius must be"),
        (
            C.Box(jnp.array([0.0, 0.0, 2.0]), jnp.array([1.0, 1.0, 1.5])),
            r"\(Box\): hi must exceed lo",
        ),
    ],
)
def test_obstacle_parameters_are_checked_by_the_python_api(cube, ob, match):
    with pytest.raises(ValueError, match=match):
        C.make_contact(_contact_pot(cube), [ob])


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(dhat=0.0), r"dhat must be a finite number > 0 \[m\], got 0.0"),
        (dict(dhat=float("nan")), r"dhat must be a finite number > 0"),
        (dict(dhat=10.0), r"dhat = 10 m is more than 0.1 x the body's size"),
        (dict(kappa=-1.0), r"kappa must be a finite number > 0 \[N/m\]"),
    ],
)
def test_barrier_settings_are_named(cube, kw, match):
    with pytest.raises(ValueError, match=match):
        C.make_contact(_contact_pot(cube), [C.HalfSpace(**GROUND)], **kw)


def test_the_automatic_barrier_reach_is_rotation_invariant(cube):
    c, s = np.cos(0.7), np.sin(0.7)
    R = jnp.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    X = cube.points
    assert float(default_dhat(X @ R.T)) == pytest.approx(float(default_dhat(X)), rel=1e-12)
    # the unrotated block keeps the bounding-box diagonal it had
    assert float(default_dhat(X, 1.0)) == pytest.approx(np.sqrt(3.0), rel=1e-12)


def test_a_scene_obstacle_inside_the_body_is_named_by_its_key():
    sc = dict(TINY_SCENE, obstacle=[{"sphere": {"center": [1.0, 0.5], "radius": 0.1}}])
    with pytest.raises(SceneError, match=r"\[\[obstacle\]\]\[0\] \(Sphere\) intersects the body"):
        build(load_scene(sc))


# ------------------------------------------------------------------------------- meshes


def _box_arrays():
    m = je.box(2, 2, 2)
    return np.asarray(m.points).copy(), np.asarray(m.cells)


def test_a_tangled_mesh_is_refused_not_reoriented():
    X, C = _box_arrays()
    X[13] = [1.5, 0.5, 0.5]  # the centre node pulled out through a face: cells fold over
    with (
        pytest.warns(UserWarning, match="reoriented"),
        pytest.raises(
            MeshError, match=r"the mesh is tangled: \d+ interior facet\(s\) have both their cells"
        ),
    ):
        je.from_arrays(X, C)
    m = je.rectangle(3, 3)
    X2 = np.asarray(m.points).copy()
    X2[5] += [0.9, 0.0]
    with pytest.warns(UserWarning), pytest.raises(MeshError, match="the mesh is tangled"):
        je.from_arrays(X2, np.asarray(m.cells))


def test_a_mesh_that_merely_has_clockwise_cells_is_still_reoriented():
    X, C = _box_arrays()
    flipped = C.copy()
    flipped[::2] = flipped[::2][:, [0, 2, 1, 3]]
    with pytest.warns(UserWarning, match="reoriented 24 of 48"):
        m = je.from_arrays(X, flipped)
    assert np.all(np.asarray(m.volumes) > 0)


def _split_mesh():
    """Two unit cubes side by side whose shared face has duplicated nodes."""
    X, C = _box_arrays()
    P = np.concatenate([X, X + np.array([[1.0, 0.0, 0.0]])])
    with pytest.warns(UserWarning, match=r"18 nodes share their rest position .* split"):
        return je.from_arrays(P, np.concatenate([C, C + len(X)]))


def test_duplicated_nodes_warn_and_a_free_part_is_refused():
    mesh = _split_mesh()
    assert je.mesh.connected_parts(mesh)[0] == 2
    bc = loads.fix(mesh, np.asarray(mesh.points)[:, 0] < 1e-9)  # holds the left cube only
    pot = je.Potential(mesh, P3, psi=M.neo_hookean)
    with pytest.raises(ValueError, match=r"2 parts that no cell connects.* part 1 \(27 nodes"):
        je.solve(pot, bc)


def test_unreferenced_nodes_are_refused():
    X, C = _box_arrays()
    with pytest.raises(MeshError, match=r"1 node\(s\) belong to no cell"):
        je.from_arrays(np.concatenate([X, [[5.0, 5.0, 5.0]]]), C)


def _interior_facets(mesh, k=2):
    cells = np.asarray(mesh.cells)
    local = np.asarray(mesh.element_type.facet_nodes)[:, : mesh.dim]
    allf = np.sort(cells[:, local].reshape(-1, mesh.dim), axis=1)
    keys, counts = np.unique(allf, axis=0, return_counts=True)
    return keys[counts == 2][:k]


def test_loads_on_interior_facets_are_refused(cube):
    inner = _interior_facets(cube)
    facets = np.concatenate([je.mesh.boundary_facets(cube)[:3], inner])
    with pytest.raises(ValueError, match=r"traction_load: 2 of 5 facet\(s\) are interior"):
        loads.traction_load(cube, facets, [0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match=r"facet_tractions: 2 of 5 facet\(s\) are interior"):
        je.postprocess.facet_tractions(M.neo_hookean, cube.points, cube, P3, facets)


def test_facet_tractions_do_not_depend_on_the_facets_node_order(cube):
    """A uniaxial stretch: τ = P·N on the pulled face, whatever the order of its nodes."""
    x = cube.points * jnp.array([[1.1, 1.0, 1.0]])
    top = loads.facets_where(cube, lambda X: X[:, 0] > 1.0 - 1e-9)
    t1 = je.postprocess.facet_tractions(M.neo_hookean, x, cube, P3, top)
    t2 = je.postprocess.facet_tractions(M.neo_hookean, x, cube, P3, top[:, ::-1])
    np.testing.assert_allclose(t2, t1, rtol=1e-12)
    assert np.all(t1[:, 0] > 0)  # tension: the traction points out of the body


# ---------------------------------------------------------------- Dirichlet data, names


def test_fix_refuses_a_displacement_in_the_components_slot(cube):
    with pytest.raises(
        TypeError,
        match=r"components must be integer axis indices .* "
        r"displacement=\[0.4, 0, 0\]",
    ):
        loads.fix(cube, [0, 1], [0.4, 0, 0])
    bc = loads.fix(cube, [0], (0, 2))
    assert np.asarray(bc.mask)[0].tolist() == [True, False, True]


@pytest.mark.parametrize("name", ["../../x", "/tmp/x", ".hidden", "a\\b", "", "c:x"])
def test_a_scene_name_is_a_name_not_a_path(name):
    with pytest.raises(SceneError, match=r"name must be a name, not a path"):
        load_scene(dict(TINY_SCENE, name=name))


# ------------------------------------------------- one validation per material, API and scene

BAD_FAMILIES = [
    (M.arruda_boyce, dict(lambda_m=0.8), "arruda_boyce", r"lambda_m .*must be > 1"),
    (M.gent, dict(Jm=-1.0), "gent", r"Jm .*must be >= 0.01"),
    (M.gent, dict(Jm=1e-6), "gent", r"Jm .*must be >= 0.01"),
    (M.ogden, dict(alpha1=0.0), "ogden", r"alpha1 must be nonzero"),
    (M.ogden, dict(mu1=-0.618), "ogden", r"mu1 must have the sign of alpha1"),
    (M.mooney_rivlin, dict(c01=-0.2), "mooney_rivlin", r"c01 must exceed -c10"),
    (M.yeoh, dict(kappa=-1.0), "yeoh", r"kappa \(the bulk modulus\) must be > 0"),
    (M.holzapfel_gasser_ogden, dict(k2=0.0), "holzapfel_gasser_ogden", r"k2 must be > 0"),
    (
        M.holzapfel_gasser_ogden,
        dict(a01=jnp.array([1e-12, 0.0, 0.0])),
        "holzapfel_gasser_ogden",
        r"a01 \(a fibre direction\) must have length",
    ),
    (M.guccione, dict(bt=0.0), "guccione", r"bt must be > 0"),
    (M.guccione, dict(s0=jnp.array([-2.0, 0.0, 0.0])), "guccione", r"s0 must not be parallel"),
]


@pytest.mark.parametrize("psi, change, model, match", BAD_FAMILIES, ids=lambda v: str(v)[:20])
def test_unstable_family_constants_are_refused_by_the_python_api(cube, psi, change, model, match):
    params = M.FAMILY_PARAMS[model](**change)
    with pytest.raises(M.MaterialParameterError, match=f"{model}: {match}"):
        M.check_material(params, 3)
    bc = loads.fix(cube, cube.points[:, 0] < 1e-9)
    if model == "guccione":  # a shared basis is broadcast to the cells first
        params = M.per_cell_basis(params, cube.n_cells)
    with pytest.raises(M.MaterialParameterError, match=match):
        je.solve(je.Potential(cube, params, psi=psi), bc)


@pytest.mark.parametrize(
    "material, match",
    [
        (
            {"model": "arruda_boyce", "mu": 0.26, "lambda_m": 0.8, "kappa": 260.0},
            r"\[material\]\.lambda_m \(the locking stretch sqrt\(N\)\) must be > 1",
        ),
        (
            {"model": "gent", "mu": 0.26, "Jm": 1e-6, "kappa": 260.0},
            r"\[material\]\.Jm .*must be >= 0.01",
        ),
        (
            {
                "model": "ogden",
                **dict(mu1=0.6, mu2=0.001, mu3=-0.01, alpha1=0.0, alpha2=5.0, alpha3=-2.0),
                "kappa": 400.0,
            },
            r"\[material\]\.alpha1 must be nonzero",
        ),
        (
            {
                "model": "guccione",
                **dict(C=2.0, bf=8.0, bt=2.0, bfs=4.0, kappa=1000.0),
                **dict(f0=[1.0, 0.0, 0.0], s0=[-3.0, 0.0, 0.0]),
            },
            r"\[material\]\.s0 must not be parallel to f0; its part across f0",
        ),
    ],
)
def test_the_scene_schema_uses_the_same_validation(material, match):
    with pytest.raises(SceneError, match=match):
        load_scene(dict(TINY_SCENE, material=material))


def test_the_documented_hgo_parameters_make_a_potential(cube):
    params = M.holzapfel_gasser_ogden_params()  # shared (3,) fibre directions
    pot = je.Potential(cube, params, psi=M.holzapfel_gasser_ogden)  # refused before
    assert pot.params.a01.shape == (cube.n_cells, 3)
    np.testing.assert_allclose(pot.params.a02[5], params.a02)


@pytest.mark.extended
def test_the_documented_hgo_parameters_work_in_a_solve(cube):
    bc = loads.fix(cube, cube.points[:, 0] < 1e-9)
    f = jnp.zeros_like(cube.points).at[:, 0].set(0.1)
    params = M.holzapfel_gasser_ogden_params()
    sol = je.solve(je.Potential(cube, params, f_ext=f, psi=M.holzapfel_gasser_ogden), bc)
    assert bool(sol.ok) and float(sol.stats["min_J"]) > 0


# ------------------------------------------------------------------- command line, signals


def _python(code: str):
    """``python -c code`` with captured output."""
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)


def test_a_broken_toml_value_in_set_names_the_toml_error(capsys):
    assert cli.main(["run", "default", "--set", 'material={model="x"']) == 2
    err = capsys.readouterr().err
    assert "--set material: invalid TOML value '{model=\"x\"'" in err
    assert "Unclosed inline table" in err or "inline table" in err


def test_deeply_nested_toml_is_a_scene_error(tmp_path, capsys):
    p = tmp_path / "deep.toml"
    p.write_text('name = "x"\nmesh = ' + "[" * 5000 + "]" * 5000 + "\n")
    assert cli.main(["run", str(p), "--out", str(tmp_path / "out")]) == 2
    assert "nested too deeply" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_a_refused_scene_leaves_no_empty_output_directory(tmp_path, capsys):
    sc = dict(TINY_SCENE, obstacle=[{"sphere": {"center": [1.0, 0.5], "radius": 0.1}}])
    p = tmp_path / "s.toml"
    p.write_text(scene_toml(sc))
    out = tmp_path / "new" / "out"
    assert cli.main(["run", str(p), "--out", str(out), "--no-progress"]) == 2
    assert "intersects the body" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize(
    "sets, match",
    [
        (["integrator.h=1e-320", "integrator.duration=1e-320"], r"\[integrator\]\.h = 1e-320 s"),
        (
            ["integrator.initial_velocity=[1e200, 0.0]", "integrator.duration=0.05"],
            r"\[integrator\]\.initial_velocity: a speed of 1e\+200 m/s",
        ),
    ],
)
def test_absurd_time_steps_and_velocities_name_the_key(tmp_path, capsys, sets, match):
    args = ["run", "swing2d", "--out", str(tmp_path / "o"), "--no-progress"]
    for s in sets:
        args += ["--set", s]
    assert cli.main(args) == 2
    assert re.search(match, capsys.readouterr().err)


@pytest.mark.extended
def test_a_closed_stdout_ends_quietly():
    p = subprocess.Popen(
        [sys.executable, "-c", "from jaxelastic.cli import command; import sys; "
         "sys.argv[1:] = ['schema']; command()"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert p.stdout is not None and p.stderr is not None
    p.stdout.readline()
    p.stdout.close()  # like `| head -1`
    err = p.stderr.read()
    assert p.wait(timeout=120) == 0
    assert "Traceback" not in err and "BrokenPipe" not in err


SIGNAL_AT_START = """
import os, signal, sys, time
from jaxelastic import cli
def early(argv=None):
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(5)
    raise SystemExit("the signal was not handled")
cli._main = early
sys.exit(cli.main(["run", "default"]))
"""

SIGNAL_AT_EXIT = """
import atexit, os, signal, sys, time
from jaxelastic import cli
def bye():
    os.kill(os.getpid(), signal.SIGINT)
    time.sleep(0.2)
atexit.register(bye)
cli.main = lambda argv=None: 0
cli.command()
"""


# Ctrl-C while the command imports JAX: a finder on sys.meta_path sends SIGINT to the
# process the moment ``jax`` is first imported (wherever that happens), as a user pressing
# Ctrl-C in the first second would; the command is started as the console script does.
SIGNAL_DURING_IMPORT = """
import importlib.abc, os, signal, sys
class _CtrlC(importlib.abc.MetaPathFinder):
    sent = False
    def find_spec(self, name, path=None, target=None):
        if name == "jax" and not _CtrlC.sent:
            _CtrlC.sent = True
            os.kill(os.getpid(), signal.SIGINT)
        return None
sys.meta_path.insert(0, _CtrlC())
sys.argv[1:] = ["run", "default", "--out", {out!r}, "--no-cache"]
from jaxelastic.cli import command
command()
"""


def test_ctrl_c_while_the_command_imports_jax_is_one_line_and_130(tmp_path):
    r = _python(SIGNAL_DURING_IMPORT.format(out=str(tmp_path / "out")))
    assert "Traceback" not in r.stderr, r.stderr
    assert r.returncode == 130, r.stderr
    assert r.stderr.strip() == "jaxelastic: interrupted by SIGINT; nothing was written"
    assert not (tmp_path / "out").exists()


@pytest.mark.extended
def test_sigterm_from_the_start_of_the_command_is_one_line_and_130():
    r = _python(SIGNAL_AT_START)
    assert r.returncode == 130
    assert "interrupted by SIGTERM" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.extended
def test_a_signal_during_the_exit_handlers_prints_no_traceback():
    r = _python(SIGNAL_AT_EXIT)
    assert r.returncode == 0
    assert "Traceback" not in r.stderr


# ------------------------------------------------------------------ outputs that do not mislead

PULL = dict(
    TINY_SCENE,
    name="pull",
    traction=[],
    dirichlet=[
        {"nodes": {"plane": {"axis": "x", "value": 0.0}}},
        {"nodes": {"plane": {"axis": "x", "value": 2.0}}, "displacement": [0.1, 0.0]},
    ],
)


@pytest.mark.extended
def test_a_tensile_test_reports_the_force_on_each_support(tmp_path):
    s = run_scene(load_scene(PULL), tmp_path, progress=False)
    per = s["static"]["reactions"]
    assert [e["key"] for e in per] == ["[dirichlet][0]", "[dirichlet][1]"]
    f0, f1 = per[0]["reaction_force"][0], per[1]["reaction_force"][0]
    assert f1 > 1.0 and f0 == pytest.approx(-f1, rel=1e-9)  # the machine reads f1
    table = run_table(s)
    assert re.search(r"\[dirichlet\]\[1\] \(6 dofs\): \(56\.\d+, ", table)
    vtu = next(tmp_path.glob("static_*.vtu")).read_text(errors="ignore")
    assert 'compressor="vtkZLibDataCompressor"' in vtu


def test_the_reaction_row_lists_each_support_and_hides_round_off():
    r = dict(
        reaction_force=[-6e-14, 2e-14],
        total_applied_load=[0.0, 0.0],
        reactions=[
            dict(key="[dirichlet][0]", dofs=6, reaction_force=[-56.0, 1.0]),
            dict(key="[dirichlet][1]", dofs=6, reaction_force=[56.0, -1.0]),
        ],
    )
    s = dict(
        scene=dict(name="pull"),
        status="ok",
        mesh=dict(n_cells=16, element="tri3", n_nodes=15, dim=2),
        static=dict(newton_steps=3, linear_iterations=3, final_residual=1e-11,
                    max_displacement=0.1, elastic_energy=1.0, **r),
    )  # fmt: skip
    text = run_table(s)
    assert "0 N in total" in text and "e-14" not in text
    assert "[dirichlet][1] (6 dofs): (56, -1) N" in text


@pytest.mark.parametrize("value", [2.178e7, 0.0])
def test_a_uniform_field_is_drawn_uniform_with_its_value(value):
    import matplotlib

    matplotlib.use("Agg")
    from jaxelastic import plot

    mesh = je.rectangle(2, 2)
    noise = 1e-9 * value * np.random.default_rng(0).standard_normal(mesh.n_nodes)
    fig = plot.final_shape_figure(
        mesh, {"rest": mesh.points, "x": mesh.points * 1.01}, values=value + noise,
        values_label="von Mises [Pa]",
    )  # fmt: skip
    cbar = [a for a in fig.axes if a.get_label() == "<colorbar>"][0]
    fig.canvas.draw()
    labels = [t.get_text() for t in cbar.get_yticklabels()]
    assert labels == [f"{value:.4g}"]
    assert cbar.get_ylabel() == "von Mises [Pa] (uniform)"
    assert cbar.yaxis.get_offset_text().get_text() == ""


def test_contact_pictures_draw_the_obstacles():
    import matplotlib

    matplotlib.use("Agg")
    from jaxelastic import plot

    a = jnp.asarray
    mesh = je.rectangle(2, 2)
    obs = (
        C.HalfSpace(a([0.0, -0.1]), a([0.0, 1.0])),
        C.Sphere(a([2.0, 0.5]), a(0.3)),
        C.Box(a([-1.0, 0.0]), a([-0.5, 1.0])),
    )
    conf = {"rest": mesh.points, "x": mesh.points * 1.01}
    bare = plot.final_shape_figure(mesh, conf)
    fig = plot.final_shape_figure(mesh, conf, obstacles=obs)
    assert len(fig.axes[0].patches) == len(bare.axes[0].patches) + 3
    cube = je.box(1, 1, 1)
    fig3 = plot.final_shape_figure(
        cube, {"rest": cube.points, "x": cube.points * 1.01}, obstacles=(GROUND_3D,)
    )
    bare3 = plot.final_shape_figure(cube, {"rest": cube.points, "x": cube.points * 1.01})
    assert len(fig3.axes[0].collections) == len(bare3.axes[0].collections) + 1


GROUND_3D = C.HalfSpace(jnp.array([0.0, 0.0, -0.1]), jnp.array([0.0, 0.0, 1.0]))


# ------------------------------------------------------------------ docs that cannot go stale


def test_the_docs_list_every_shipped_scene():
    import jaxelastic.scene as scene_pkg
    from jaxelastic.scene import shipped_scenes

    names = sorted(shipped_scenes())
    doc = scene_pkg.__doc__ or ""
    listed = re.search(r"Shipped scenes \(.*?\): (.*?)\.\n", doc, re.S)
    assert listed is not None
    assert sorted(re.findall(r"``(\w+)``", listed.group(1))) == names
    guide = (ROOT / "docs" / "guide" / "scenes.md").read_text()
    line = re.search(r"jaxelastic scenes +# shipped: (.*)", guide)
    assert line is not None and sorted(line.group(1).split(", ")) == names


ROOT = Path(__file__).resolve().parents[1]
