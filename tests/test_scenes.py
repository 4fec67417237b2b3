"""Scene files: validation with messages naming the key, the JSON Schema and the generated
reference, building, running end to end."""

import json
import os
import sys
import textwrap
import xml.etree.ElementTree as ET

import meshio
import numpy as np
import pytest
from _common import TINY_SCENE

try:
    import tomllib
except ModuleNotFoundError:  # Python < 3.11
    import tomli as tomllib

import jaxelastic as je
import jaxelastic.scene as jscene
from jaxelastic.scene import SceneError, apply_overrides, build, load_scene, run_scene
from jaxelastic.solvers import SolveError

TINY = TINY_SCENE


def _bad(overrides, base=TINY):
    return apply_overrides(base, overrides)


# ----------------------------------------------------------------------------------------
# loading and validation
# ----------------------------------------------------------------------------------------


def test_shipped_scenes_parse_and_build():
    shipped = jscene.shipped_scenes()
    assert {"default", "twist", "cook", "swing2d"} <= set(shipped)
    for name, path in shipped.items():
        s = load_scene(path)
        assert s.source == path and s.label == f"{name}.toml" and s.name == name
        b = build(s)
        pot = b.potential
        assert (pot.mass is None) == s.static  # no mass term in statics
        has_loads = bool(s["traction"] or s["point_load"] or "gravity" in s.data)
        assert (pot.f_ext is None) == (not has_loads)  # no load term without loads
        gen = s["mesh"].get("generator")  # a mesh file has its own dimension
        assert b.mesh.dim == (3 if gen in ("box",) else 2 if gen else b.mesh_data.mesh.dim)
        assert np.asarray(b.bc.mask).any() or pot.contact is not None  # drop: held by contact
    # a shipped scene is also found by name
    assert load_scene("twist").source == shipped["twist"]


def test_default_scene_is_the_documented_beam():
    s = load_scene("default")
    assert s["material"]["model"] == "neo_hookean"
    assert s["integrator"]["type"] == "dynamic"
    assert s["integrator"]["method"] == "backward_euler"
    assert s["integrator"]["settle"] and s["integrator"]["compare_static"]
    assert s["integrator"]["alpha"] > 0 and "gravity" in s.data


def test_twist_boundary_data_match_the_jax_fem_formula():
    b = build("twist")
    X = np.asarray(b.mesh.points)
    vals, mask = np.asarray(b.bc.values), np.asarray(b.bc.mask)
    left = np.abs(X[:, 0]) < 1e-12
    right = np.abs(X[:, 0] - 1.0) < 1e-12
    y, z = X[left, 1], X[left, 2]
    c, s = np.cos(np.pi / 3), np.sin(np.pi / 3)
    uy = (0.5 + (y - 0.5) * c - (z - 0.5) * s - y) / 2
    uz = (0.5 + (y - 0.5) * s + (z - 0.5) * c - z) / 2
    np.testing.assert_allclose(vals[left] - X[left], np.stack([0 * y, uy, uz], 1), atol=1e-14)
    np.testing.assert_allclose(vals[right], X[right])
    assert mask[left | right].all() and not mask[~(left | right)].any()
    # the user psi: mu/2 (J^(-2/3) I_C - 3) + kappa/2 (J - 1)^2, zero at rest
    F = np.diag([1.1, 0.9, 1.0])
    J = np.linalg.det(F)
    mu, kappa = float(b.params.mu), float(b.params.lam)
    expected = mu / 2 * (J ** (-2 / 3) * np.sum(F * F) - 3) + kappa / 2 * (J - 1) ** 2
    assert float(b.psi(F, b.params)) == pytest.approx(expected, rel=1e-13)
    assert kappa == pytest.approx(10 / (3 * (1 - 0.6)))


def test_defaults_round_trip_and_freeze():
    s = load_scene(TINY)
    assert s.static and s.dim == 2 and s.label == "<dict>"
    assert s["solver"]["rtol"] == 1e-8 and s["solver"]["linear"] == "auto"
    assert s["output"]["every"] == 1 and s["output"]["vtu"] is True
    with pytest.raises(TypeError):
        s["material"]["E"] = 5.0  # read-only
    again = load_scene(s.to_dict())
    assert again.data == s.data
    json.dumps(s.to_dict())  # JSON-serialisable


def test_overrides():
    s = load_scene("default", overrides={"mesh.n": [6, 2, 2], "integrator.duration": 0.5})
    assert list(s["mesh"]["n"]) == [6, 2, 2] and s["integrator"]["duration"] == 0.5
    d = apply_overrides(TINY, {"dirichlet.0.components": ["y"], "solver.rtol": 1e-6})
    assert d["dirichlet"][0]["components"] == ["y"] and d["solver"]["rtol"] == 1e-6
    assert "solver" not in TINY  # the input is not modified
    with pytest.raises(SceneError, match="not an index"):
        apply_overrides(TINY, {"dirichlet.5.components": [0]})


BAD = [
    ({"foo": 1}, "unknown top-level key 'foo' (valid: name, description, mesh"),
    ({"solver.max_iters": 5}, "unknown key [solver].max_iters (valid: max_steps"),
    ({"material.E": "big"}, "[material].E must be a number, got string 'big'"),
    ({"material.E": -1}, "[material].E must be > 0, got -1"),
    ({"material.E": 0.0}, "[material].E must be > 0, got 0.0"),
    ({"material.nu": 0.5}, "[material].nu must be < 0.5, got 0.5"),
    ({"material.nu": 0.7}, "[material].nu must be < 0.5"),
    ({"material.model": "rubber"}, "[material].model: unknown material 'rubber' (built-in:"),
    ({"material.model": "no_such_module_xyz:psi"}, "[material].model: cannot import module"),
    ({"material.model": "jaxelastic.materials:nope"}, "module 'jaxelastic.materials' has no"),
    ({"material.model": "jaxelastic.materials:BUILTIN"}, "is not callable"),
    ({"material.mu": 1.0}, "[material] needs either E and nu, or mu and lam"),
    ({"material.density": -3.0}, "[material].density must be > 0"),
    ({"integrator": {"type": "dynamic", "h": 0.01, "duration": 1.0}}, "[material].density is "),
    ({"gravity": {"g": [0.0, -9.81]}}, "[material].density is required with [gravity]"),
    ({"integrator": {"type": "explicit"}}, "[integrator].type must be one of 'static', 'dyn"),
    ({"integrator.h": 0.1}, "unknown key [integrator].h for type = 'static'"),
    ({"integrator.load_steps": 0}, "[integrator].load_steps must be >= 1, got 0"),
    ({"solver.max_steps": 1.5}, "[solver].max_steps must be an integer, got float 1.5"),
    ({"solver.hessian": "exact"}, "[solver].hessian must be one of 'hvp', 'element'"),
    ({"solver.require_positive_J": 1}, "[solver].require_positive_J must be true or false"),
    ({"mesh.n": [4]}, "[mesh].n must be an array of 2 integers"),
    ({"mesh.n": [4, 0]}, "[mesh].n[1] must be >= 1, got 0"),
    ({"mesh.size": [1.0, -1.0]}, "[mesh].size[1] must be > 0"),
    ({"mesh.file": "x.msh"}, "[mesh] needs exactly one of generator"),
    ({"mesh": {"file": "does_not_exist.msh"}}, "[mesh].file: no such mesh file"),
    ({"mesh.generator": "sphere"}, "[mesh].generator must be one of 'box', 'rectangle', 'cook'"),
    ({"traction.0.total_force": [0.0, 1.0, 0.0]}, "[traction][0].total_force must have 2 comp"),
    ({"traction.0.traction": [0.0, 1.0]}, "[traction][0] needs exactly one of traction"),
    ({"dirichlet": []}, "[dirichlet]: a static scene needs at least one Dirichlet condition"),
    ({"dirichlet": {"nodes": {"box": {"lo": [0, 0], "hi": [1, 1]}}}}, "write [[dirichlet]]"),
    ({"dirichlet.0.nodes": {"plane": {"axis": "w", "value": 0}}}, "nodes.plane.axis must be"),
    ({"dirichlet.0.nodes": {"plane": {"axis": 2, "value": 0}}}, "axis of a 2D mesh (0..1)"),
    ({"dirichlet.0.nodes": {"plane": {"axis": 0}}}, "[dirichlet][0].nodes.plane.value is requ"),
    ({"dirichlet.0.nodes": {"box": {"lo": [1, 1], "hi": [0, 0]}}}, "lo must not exceed hi"),
    ({"dirichlet.0.nodes": {"sphere": {}}}, "unknown key [dirichlet][0].nodes.sphere"),
    ({"dirichlet.0.nodes": {"where": "__import__('os')"}}, "'__import__' is not allowed"),
    ({"dirichlet.0.nodes": {"where": "x.__class__"}}, "Attribute is not allowed"),
    ({"dirichlet.0.nodes": {"where": "X.sum()"}}, "[dirichlet][0].nodes.where"),
    ({"dirichlet.0.nodes": {"where": "open(1)"}}, "function 'open' is not allowed"),
    ({"dirichlet.0.nodes": {"where": "x <"}}, "invalid expression"),
    ({"dirichlet.0.nodes": {"where": "q < 1"}}, "unknown name 'q'"),
    ({"dirichlet.0.components": [0, 0]}, "[dirichlet][0].components repeats a component"),
    ({"dirichlet.0.ramp_time": 1.0}, "[dirichlet][0].ramp_time is only valid in a dynamic"),
    ({"dirichlet.0.displacement": [0.0]}, "[dirichlet][0].displacement must have 2 comp"),
    ({"dirichlet.0.displacement": "jaxelastic.scene.examples:nope"}, "has no attribute"),
    ({"material.plane": "plate"}, "[material].plane must be one of 'strain', 'stress'"),
    ({"output.every": 0}, "[output].every must be >= 1, got 0"),
    ({"output.probes": [[1.0, 2.0, 3.0]]}, "[output].probes[0] must have 2 components"),
    ({"output.gif": True}, "unknown key [output].gif"),
    ({"name": 3}, "name must be a string, got integer 3"),
]


@pytest.mark.parametrize("overrides, message", BAD, ids=[m[:40] for _, m in BAD])
def test_bad_scenes_are_refused_naming_the_key(overrides, message):
    with pytest.raises(SceneError) as e:
        load_scene(_bad(overrides))
    assert str(e.value).startswith("scene '<dict>': ")
    assert message in str(e.value)


def test_several_problems_are_listed():
    bad = _bad({"material.E": "big", "output.every": 0, "fit": {"case": {"weight": 1.0}}})
    with pytest.raises(SceneError) as e:
        load_scene(bad)
    lines = str(e.value).splitlines()
    assert lines[0] == "scene '<dict>': [material].E must be a number, got string 'big'"
    assert lines[1] == "  and: [output].every must be >= 1, got 0"
    assert lines[2] == "  and: [fit.case] must be an array of tables: write [[fit.case]]"


def test_bad_scene_3d_specific():
    with pytest.raises(SceneError, match=r"\[material\].plane applies to 2D meshes only"):
        load_scene("default", overrides={"material.plane": "stress"})
    with pytest.raises(SceneError, match=r"\[gravity\].g must have 3 components"):
        load_scene("default", overrides={"gravity.g": [0.0, -9.81]})
    with pytest.raises(SceneError, match=r"\[integrator\].duration must be >= h"):
        load_scene("default", overrides={"integrator.duration": 0.001})
    rot = {"rotate": {"axis": 3, "angle_deg": 10.0}}
    with pytest.raises(SceneError, match=r"displacement.rotate.axis must be 0, 1, 2"):
        load_scene("default", overrides={"dirichlet.0.displacement": rot})
    with pytest.raises(SceneError, match=r"displacement.rotate.axis must be 'z' \(2\) in 2D"):
        load_scene(
            apply_overrides(
                TINY, {"dirichlet.0.displacement": {"rotate": {"axis": "x", "angle_deg": 1.0}}}
            )
        )
    with pytest.raises(SceneError, match=r"\[integrator\].h must be > 0"):
        load_scene("default", overrides={"integrator.h": 0})


@pytest.mark.parametrize(
    "overrides, message",
    [
        (
            {"dirichlet.0.nodes": {"plane": {"axis": "x", "value": 5.0}}},
            "[dirichlet][0].nodes selects no nodes",
        ),
        (
            {"dirichlet.0.nodes": {"box": {"lo": [3.0, 3.0], "hi": [4.0, 4.0]}}},
            "[dirichlet][0].nodes selects no nodes",
        ),
        ({"dirichlet.0.nodes": {"where": "x > 100"}}, "[dirichlet][0].nodes selects no nodes"),
        ({"dirichlet.0.nodes": {"where": "x + 1"}}, "not a boolean mask"),
        ({"dirichlet.0.nodes": {"group": "left"}}, "a generated mesh has no named groups"),
        (
            {"traction.0.facets": {"box": {"lo": [1.9, 0.4], "hi": [2.1, 0.6]}}},
            "[traction][0].facets selects no boundary facets",
        ),
        ({"material.model": "jaxelastic.scene.where:where_mask"}, "[material].model"),
        (
            {"material.model": "stable_neo_hookean_log"},
            "[material].model 'stable_neo_hookean_log' fails at F = I in 2D",
        ),
        (
            {
                "dirichlet.0.displacement": "jaxelastic.scene.examples:pendulum_velocity",
                "mesh.n": [2, 1],
            },
            None,
        ),
    ],
)
def test_bad_scenes_refused_at_build(overrides, message):
    s = load_scene(_bad(overrides))
    if message is None:  # a valid user displacement function
        build(s)
        return
    with pytest.raises(SceneError) as e:
        build(s)
    assert message in str(e.value) and str(e.value).startswith("scene '<dict>': ")


def test_scene_file_errors(tmp_path):
    p = tmp_path / "broken.toml"
    p.write_text("[mesh\n")
    with pytest.raises(SceneError, match="scene 'broken.toml': invalid TOML"):
        load_scene(p)
    with pytest.raises(SceneError, match="no such file"):
        load_scene(tmp_path / "missing.toml")
    p.write_text('[mesh]\ngenerator = "box"\nn = [2, 2, 2]\n[material]\nmodel = "linear"\n')
    with pytest.raises(SceneError, match=r"scene 'broken.toml': \[material\] needs either E"):
        load_scene(p)


def test_where_expressions():
    X = np.array([[0.0, 0.0], [1.0, 0.5], [2.0, 1.0]])
    m = jscene.where_mask
    assert m("x < 1e-9", X).tolist() == [True, False, False]
    assert m("(X[:, 0] > 0.5) & (abs(y - 0.5) < 0.6)", X).tolist() == [False, True, True]
    assert m("np.isclose(x, 1.0) or y >= 1", X).tolist() == [False, True, True]
    assert m("not (x > 0)", X).tolist() == [True, False, False]
    assert m("0 < x <= 1", X).tolist() == [False, True, False]
    assert m("hypot(x, y) < 10", X).all()


def test_user_module_next_to_the_scene_file(tmp_path):
    (tmp_path / "my_psi_mod_for_test.py").write_text(
        textwrap.dedent(
            """
            import jax.numpy as jnp

            def psi(F, p):
                E = 0.5 * (F.T @ F - jnp.eye(F.shape[0]))
                return p.mu * jnp.sum(E * E) + 0.5 * p.lam * jnp.trace(E) ** 2
            """
        )
    )
    d = apply_overrides(TINY, {"material.model": "my_psi_mod_for_test:psi"})
    s = load_scene(d, base_dir=str(tmp_path))
    b = build(s)
    assert float(b.psi(np.eye(2), b.params)) == 0.0
    assert str(tmp_path) not in sys.path  # the search path is restored


# ----------------------------------------------------------------------------------------
# running
# ----------------------------------------------------------------------------------------


def _write_group_mesh(path):
    """rectangle(4, 2) of size 2 x 1 as a Gmsh file with 'left'/'right' edge groups."""
    r = je.rectangle(4, 2, size=(2.0, 1.0))
    X = np.asarray(r.points)
    f = je.mesh.boundary_facets(r)
    left = f[np.all(X[f, 0] < 1e-12, axis=1)]
    right = f[np.all(np.abs(X[f, 0] - 2.0) < 1e-12, axis=1)]
    cells = [("line", left), ("line", right), ("triangle", np.asarray(r.cells))]
    m = meshio.Mesh(
        np.column_stack([X, np.zeros(len(X))]),
        cells,
        cell_data={
            "gmsh:physical": [
                np.full(len(c), t) for (_, c), t in zip(cells, [1, 2, 3], strict=True)
            ],
            "gmsh:geometrical": [
                np.full(len(c), t) for (_, c), t in zip(cells, [1, 2, 3], strict=True)
            ],
        },
        field_data={"left": np.array([1, 1]), "right": np.array([2, 1]), "body": np.array([3, 2])},
    )
    meshio.write(path, m, file_format="gmsh22", binary=False)


def test_static_scene_end_to_end(tmp_path):
    out = tmp_path / "out"
    summary = run_scene(TINY, out, progress=False)
    assert summary["status"] == "ok"
    with open(out / "summary.json") as f:
        on_disk = json.load(f)  # valid JSON (no NaN)
    assert on_disk["status"] == "ok" and on_disk["scene"]["name"] == "tiny"
    st = on_disk["static"]
    assert st["final_residual"] < 1e-6 and st["newton_steps"] >= 1
    np.testing.assert_allclose(st["reaction_force"], [0.0, 10.0], atol=1e-6)  # balances load
    np.testing.assert_allclose(st["total_applied_load"], [0.0, -10.0])
    probe = on_disk["probes"][0]
    assert probe["node_position"] == [2.0, 0.5] and probe["displacement"][1] < 0
    vtu = meshio.read(out / "static_0000.vtu")
    assert {"displacement"} <= set(vtu.point_data)
    assert {"J", "stress_P", "energy_density", "von_mises"} <= set(vtu.cell_data)
    assert {"cauchy_stress_nodal", "von_mises_nodal"} <= set(vtu.point_data)  # recovered
    u = vtu.point_data["displacement"][:, :2]
    np.testing.assert_allclose(u[probe["node"]], probe["displacement"], atol=1e-12)
    # the largest displacement: where, and its size against the body
    norms = np.linalg.norm(u, axis=1)
    assert st["max_displacement_node"] == int(np.argmax(norms))
    assert st["max_displacement"] == pytest.approx(norms.max(), rel=1e-12)
    assert st["max_displacement_at"] == vtu.points[st["max_displacement_node"], :2].tolist()
    assert st["max_displacement_relative"] == pytest.approx(norms.max() / np.hypot(2.0, 1.0))
    assert (out / "static.pvd").exists() and (out / "final_shape.png").exists()
    assert set(on_disk["timings"]) >= {"build", "solve_incl_compile", "outputs", "total"}


def test_static_scene_from_a_mesh_file_with_groups_and_load_steps(tmp_path):
    _write_group_mesh(tmp_path / "strip.msh")
    scene_file = tmp_path / "strip.toml"
    scene_file.write_text(
        textwrap.dedent(
            """
            name = "strip"
            [mesh]
            file = "strip.msh"
            [material]
            model = "neo_hookean"
            E = 1000.0
            nu = 0.3
            [[dirichlet]]
            nodes = { group = "left" }
            [[traction]]
            facets = { group = "right" }
            total_force = [0.0, -10.0]
            [integrator]
            load_steps = 2
            [output]
            vtu = false
            png = false
            """
        )
    )
    out = tmp_path / "res"
    s = run_scene(scene_file, out, progress=False)
    ref = run_scene(TINY, tmp_path / "ref", progress=False)
    assert len(s["static"]["load_steps"]) == 2
    assert s["static"]["load_steps"][0]["load_factor"] == 0.5
    assert s["static"]["max_displacement"] == pytest.approx(
        ref["static"]["max_displacement"], rel=1e-6
    )
    assert sorted(os.listdir(out)) == ["summary.json"]
    # an input whose name an output would take is never overwritten
    clash = tmp_path / "summary.json"
    clash.write_text(scene_file.read_text().replace("strip.msh", "strip.msh"))
    with pytest.raises(SceneError, match="would be overwritten"):
        run_scene(str(clash), tmp_path, progress=False)


def test_out_dir_that_is_a_file_is_refused(tmp_path):
    f = tmp_path / "afile"
    f.write_text("x")
    with pytest.raises(SceneError, match="is not a directory"):
        run_scene(TINY, f, progress=False)
    assert f.read_text() == "x"


def test_failed_solve_still_writes_the_summary(tmp_path):
    bad = apply_overrides(TINY, {"solver.max_steps": 1, "output.png": False, "output.vtu": False})
    with pytest.raises(SolveError, match="MAX_STEPS"):
        run_scene(bad, tmp_path, progress=False)
    with open(tmp_path / "summary.json") as f:
        s = json.load(f)
    assert s["status"] == "failed" and "MAX_STEPS" in s["error"]


def test_default_scene_small_variant_end_to_end(tmp_path):
    """The default beam on a coarse mesh, heavily damped: settles close to the static one."""
    scene = load_scene(
        "default",
        overrides={
            "mesh.n": [8, 2, 2],
            "integrator.h": 0.05,
            "integrator.duration": 6.0,
            "integrator.alpha": 8.0,
            "integrator.settle_tol": 1e-7,
            "output.every": 10,
        },
    )
    out = tmp_path / "beam"
    s = run_scene(scene, out, progress=False)
    d, c = s["dynamic"], s["comparison"]
    assert s["status"] == "ok" and d["settled"] and d["t_end"] < 6.0
    assert d["kinetic_over_elastic"] < 1e-7
    assert c["relative_to_tip_deflection"] < 1e-2
    assert c["tip_deflection_static"] > 0.05  # it visibly sags
    per = d["per_step"]
    n = d["steps"]
    assert len(per["t"]) == n + 1 and len(per["newton_steps"]) == n
    assert all(k >= 1 for k in per["newton_steps"]) and per["linear_iterations"][0] > 0
    assert per["kinetic"][0] == 0.0 and per["external"][-1] < 0  # it fell
    # energies: the damped system dissipates, total energy never grows (up to round-off)
    tot = np.asarray(per["total"])
    assert np.all(np.diff(tot) <= 1e-9 * np.abs(tot).max())
    t = s["timings"]
    assert t["first_step_incl_compile"] > t["step_median"] > 0
    # outputs
    for name in (
        "summary.json",
        "dynamic.pvd",
        "static.pvd",
        "final_shape.png",
        "tip_displacement.png",
        "energy.png",
    ):
        assert (out / name).is_file(), name
    files = [ds.get("file") for ds in ET.parse(out / "dynamic.pvd").getroot().iter("DataSet")]
    assert files[0] == "dynamic_0000.vtu" and len(files) >= 2
    last = meshio.read(out / files[-1])
    assert {"displacement", "velocity"} <= set(last.point_data)
    assert {"J", "stress_P", "energy_density"} <= set(last.cell_data)
    assert {"cauchy_stress_nodal", "von_mises_nodal"} <= set(last.point_data)
    with open(out / "summary.json") as f:
        on_disk = json.load(f)
    assert on_disk["comparison"]["max_nodal_distance"] == c["max_nodal_distance"]
    d = on_disk["dynamic"]  # the largest displacement of the final state
    u_last = np.linalg.norm(last.point_data["displacement"], axis=1)
    assert d["max_displacement_node"] == int(np.argmax(u_last))


def test_stale_series_files_are_removed(tmp_path):
    from jaxelastic.scene.outputs import remove_stale

    for name in (
        "dynamic_0000.vtu",
        "dynamic_0001.vtu",
        "dynamic_0002.vtu",
        "dynamic_x.vtu",
        "mydynamic_0005.vtu",
        "dynamic_0003.vtu.bak",
    ):
        (tmp_path / name).write_text("")
    remove_stale(str(tmp_path), "dynamic", 2)
    assert sorted(os.listdir(tmp_path)) == [
        "dynamic_0000.vtu",
        "dynamic_0001.vtu",
        "dynamic_0003.vtu.bak",
        "dynamic_x.vtu",
        "mydynamic_0005.vtu",
    ]


DYN2D = apply_overrides(
    TINY,
    {
        "material.density": 100.0,
        "integrator": {"type": "dynamic", "h": 0.01, "duration": 0.1},
        "dirichlet.0.displacement": "jaxelastic.scene.examples:shear_wave",
        "dirichlet.0.ramp_time": 0.5,
    },
)


def test_time_dependent_dirichlet_and_initial_velocity():
    d = apply_overrides(
        DYN2D,
        {
            "dirichlet": [
                {
                    "nodes": {"plane": {"axis": "x", "value": 0.0}},
                    "displacement": "jaxelastic.scene.examples:shear_wave",
                    "ramp_time": 0.5,
                },
                {
                    "nodes": {"where": "x > 1.99"},
                    "components": ["y"],
                    "displacement": {"rotate": {"angle_deg": 90.0, "center": [2.0, 0.0]}},
                },
            ],
            "integrator.initial_velocity": [1.0, 2.0],
        },
    )
    b = build(d)
    assert b.time_dependent and b.integrator.h == 0.01 and b.potential.mass is not None
    X = np.asarray(b.mesh.points)
    left, right = X[:, 0] < 1e-12, X[:, 0] > 1.99
    for t in (0.0, 0.125, 0.25, 1.0):
        bc = b.bc_fn(t)
        u = np.asarray(bc.values) - X
        expected = min(t / 0.5, 1.0) * 0.05 * np.sin(2 * np.pi * t)
        np.testing.assert_allclose(u[left, 0], expected, atol=1e-15)
        np.testing.assert_allclose(u[left, 1], 0.0, atol=1e-15)
        # rotation by 90 deg about (2, 0): (2, y) -> (2 - y, 0); only u_y is prescribed
        mask = np.asarray(bc.mask)
        assert mask[right, 1].all() and not mask[right, 0].any()
        np.testing.assert_allclose(u[right, 1], -X[right, 1], atol=1e-14)
    v0 = np.asarray(b.v0)
    np.testing.assert_allclose(v0[left], 0.0)  # Dirichlet dofs start at rest
    np.testing.assert_allclose(v0[~left & ~right], np.tile([1.0, 2.0], ((~left & ~right).sum(), 1)))
    np.testing.assert_allclose(v0[right, 0], 1.0)  # x is free on the right edge


def test_loads_are_assembled():
    d = apply_overrides(
        TINY,
        {
            "material.density": 10.0,
            "gravity": {"g": [0.0, -2.0]},
            "point_load": [
                {"nodes": {"box": {"lo": [2.0, 0.0], "hi": [2.0, 1.0]}}, "total_force": [3.0, 0.0]},
                {"nodes": {"where": "(x > 1.99) & (y > 0.99)"}, "force": [0.0, 1.0]},
            ],
        },
    )
    b = build(d)
    f = np.asarray(b.potential.f_ext)
    area = 2.0 * 1.0
    np.testing.assert_allclose(f.sum(0), [3.0, -10.0 - 10.0 * area * 2.0 + 1.0], rtol=1e-13)
    assert b.potential.mass is None  # static: no mass even with gravity
    s = load_scene(apply_overrides(TINY, {"traction": []}))
    assert s["traction"] == () and build(s).potential.f_ext is None


def test_documented_example_is_a_valid_scene():
    from jaxelastic.scene.docs import EXAMPLE

    s = load_scene(tomllib.loads(EXAMPLE))
    b = build(s)
    assert b.mesh.dim == 3 and b.potential.mass is not None and b.potential.f_ext is not None
    assert "```toml\n" + EXAMPLE + "```" in jscene.reference_markdown()


# ----------------------------------------------------------------------------------------
# the JSON Schema, the generated reference, the solver defaults
# ----------------------------------------------------------------------------------------


def test_json_schema_validates_the_shipped_scenes(capsys):
    from jaxelastic import cli
    from jaxelastic.scene.schema import SceneSpec

    assert cli.main(["schema"]) == 0
    schema = json.loads(capsys.readouterr().out)
    assert schema == json.loads(json.dumps(jscene.json_schema()))
    tables = {"mesh", "material", "dirichlet", "traction", "point_load", "gravity", "solver"}
    tables |= {"integrator", "output", "fit"}
    assert tables <= set(schema["properties"]) and schema["required"] == ["mesh", "material"]
    defs = schema["$defs"]
    for name in ("MeshSpec", "MaterialSpec", "SolverSpec", "DynamicIntegrator", "FitSpec"):
        assert defs[name]["properties"] and defs[name]["additionalProperties"] is False
    jsonschema = pytest.importorskip("jsonschema")
    jsonschema.Draft202012Validator.check_schema(schema)
    validator = jsonschema.Draft202012Validator(schema)
    for name, path in jscene.shipped_scenes().items():
        with open(path, "rb") as f:
            raw = tomllib.load(f)
        assert not list(validator.iter_errors(raw)), name  # the editor's check
        SceneSpec.model_validate(raw, context={"base_dir": os.path.dirname(path)})
    bad = apply_overrides(TINY, {"material.E": -1.0, "solver.linear": "lu"})
    assert len(list(validator.iter_errors(bad))) == 2


def test_committed_reference_is_the_generated_one():
    path = os.path.join(os.path.dirname(__file__), os.pardir, "docs", "scenes.md")
    with open(path, encoding="utf-8") as f:
        committed = f.read()
    assert committed == jscene.reference_markdown(), "run: python scripts/gen_scene_docs.py"


def test_solver_defaults_are_newtons():
    from jaxelastic.scene.problem import newton_of
    from jaxelastic.scene.schema import SolverSpec

    n, spec = je.Newton(), SolverSpec()
    assert newton_of(spec) == n.replace(linear="auto")
    cg = newton_of(SolverSpec(linear="cg"))
    assert cg.linear == je.CG(preconditioner=spec.preconditioner, max_iter=spec.cg_max_iter)
    assert je.CG() == cg.linear  # the CG defaults, too


# ---- pictures: automatic magnification ---------------------------------------------------


@pytest.mark.parametrize(
    "umax, factor",
    [
        (0.3, 1.0),  # 13 % of the diagonal: true scale
        (0.12, 1.0),  # 5.4 %: still true scale
        (0.1, 2.0),  # 4.5 % -> 2 (9 %)
        (8.7e-5, 2000.0),  # 0.0039 %: 0.1 * 2.236 / 8.7e-5 = 2570 -> 2000 (nearest on a log scale)
        (3e-5, 10000.0),  # 7450 -> 10000 (13 %)
        (0.0, 1.0),  # at rest
    ],
)
def test_magnification_reaches_about_ten_percent_in_1_2_5_steps(umax, factor):
    from jaxelastic.plot import magnification

    X = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 1.0], [0.0, 1.0]])  # diagonal sqrt(5)
    x = X.copy()
    x[2, 1] -= umax
    assert magnification(X, [x]) == factor
    if factor > 1:  # the magnified largest displacement: 6-16 % of the diagonal
        assert 0.06 <= factor * umax / np.sqrt(5.0) <= 0.16


def test_nice_125_and_the_factor_in_the_title():
    from jaxelastic.plot import final_shape_figure, nice_125

    assert [nice_125(v) for v in (1.0, 1.4, 1.5, 3.1, 3.3, 7.0, 7.2, 37.0, 0.03)] == [
        1.0,
        1.0,
        2.0,
        2.0,
        5.0,
        5.0,
        10.0,
        50.0,
        0.02,
    ]
    with pytest.raises(ValueError):
        nice_125(0.0)
    mesh = je.rectangle(4, 2, size=(2.0, 1.0))
    X = np.asarray(mesh.points)
    x = X.copy()
    x[:, 1] -= 1e-6 * X[:, 0] ** 2  # 4e-6 m at the tip: 1.8e-4 % of the diagonal
    fig = final_shape_figure(mesh, {"rest": X, "static": x}, title="t")
    ax = fig.axes[0]
    assert ax.get_title() == "t (displacements ×50000)"
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert labels == ["rest", "static (u ×50000)"]  # in the legend below the axes, too
    assert fig.axes[1].get_ylabel() == "|u| [m]"  # the colour bar
    # the drawn (magnified) outline reaches ~10 % of the diagonal; scale=1 draws true scale
    ylo = ax.get_ylim()[0]
    assert -0.32 < ylo < -0.24  # -0.2 at the tip, minus the 4 % margin
    fig1 = final_shape_figure(mesh, {"rest": X, "static": x}, title="t", scale=1)
    assert fig1.axes[0].get_title() == "t" and fig1.axes[0].get_ylim()[0] > -0.1


def test_static_outputs_evaluate_the_stresses_once(tmp_path, monkeypatch):
    """The VTU file and the picture of a static run share one stress evaluation, and the
    picture is coloured by the nodal von Mises stress the VTU holds."""
    import jaxelastic.io.vtk as jvtk
    import jaxelastic.scene.outputs as jout

    calls, seen = [], {}
    orig_fields = jvtk.stress_fields

    def counting(*args, **kwargs):
        calls.append(1)
        return orig_fields(*args, **kwargs)

    orig_figure = jout._plot.final_shape_figure

    def figure(*args, **kwargs):
        seen["values"] = kwargs.get("values")
        return orig_figure(*args, **kwargs)

    monkeypatch.setattr(jvtk, "stress_fields", counting)
    monkeypatch.setattr(jout, "stress_fields", counting)
    monkeypatch.setattr(jout._plot, "final_shape_figure", figure)
    out = tmp_path / "out"
    assert run_scene(TINY, out, progress=False)["status"] == "ok"
    assert len(calls) == 1
    vtu = meshio.read(out / "static_0000.vtu")
    np.testing.assert_array_equal(seen["values"], vtu.point_data["von_mises_nodal"])
    assert (out / "final_shape.png").exists()


def test_plot_edges_from_given_facets():
    """feature_edges / wire_edges with the boundary pieces passed in (computed once per
    picture) equal those computed from the mesh."""
    from jaxelastic.plot import feature_edges, wire_edges

    mesh = je.box(3, 2, 2)
    facets = je.mesh.boundary_facets(mesh)  # P1: the linear pieces are the facets
    np.testing.assert_array_equal(feature_edges(mesh, facets=facets), feature_edges(mesh))
    np.testing.assert_array_equal(wire_edges(mesh, facets=facets), wire_edges(mesh))
