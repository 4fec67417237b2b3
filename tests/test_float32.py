"""float32 end to end: three problems (the README example, the twist, the default scene)
converge and match float64, scenes honour ``[solver] precision``, nothing is promoted to
float64, and the float64 round-off floor exit still reports SUCCESS.

x64 is enabled (conftest), so every float32 case builds its mesh in float32 explicitly:
float32 arrays with x64 on, as a ``precision = "float32"`` scene does.
"""

import json
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _common import TINY_SCENE

import jaxelastic as je
from jaxelastic import dynamics
from jaxelastic import loads as L
from jaxelastic import materials as M
from jaxelastic.scene import SceneError, load_scene
from jaxelastic.scene.problem import build, linear_solver_name
from jaxelastic.scene.run import run_scene
from jaxelastic.verification import torsion as twist

F32, F64 = jnp.float32, jnp.float64


def rel_diff(x, ref, X) -> float:
    """Relative displacement difference ``‖x − ref‖ / ‖ref − X‖`` (in float64)."""
    x, ref, X = (np.asarray(a, dtype=np.float64) for a in (x, ref, X))
    return float(np.linalg.norm(x - ref) / np.linalg.norm(ref - X))


def float_dtypes(tree) -> set[str]:
    return {
        str(a.dtype)
        for a in jax.tree_util.tree_leaves(tree)
        if hasattr(a, "dtype") and jnp.issubdtype(a.dtype, jnp.floating)
    }


# --------------------------------------------------------------------------------------
# three problems: the README example, the twist, the default scene
# --------------------------------------------------------------------------------------


def readme_problem(dtype):
    """The first example of the README (its own ψ, 1,920 tets, gravity) in ``dtype``."""

    def psi(F, p):
        J = je.mechanics.kinematics.det(F)
        return p.mu / 2 * (J ** (-2 / 3) * jnp.sum(F * F) - 3) + p.lam / 2 * (J - 1) ** 2

    mesh = je.box(20, 4, 4, size=(5.0, 1.0, 1.0), dtype=dtype)
    mu, lam = je.materials.lame(1e6, 0.3)
    params = je.Lame(jnp.asarray(mu, dtype), jnp.asarray(lam, dtype))
    clamp = L.fix(mesh, L.nodes_on_plane(mesh, 0, 0.0))
    g = L.gravity_load(mesh, density=1000.0, g=[0, 0, -9.81])
    return je.Potential(mesh=mesh, params=params, f_ext=jnp.asarray(g), psi=psi), clamp


@pytest.mark.extended  # float32 solves stay in the default tier (test_newton)
def test_readme_example_in_float32_matches_float64():
    pot32, bc32 = readme_problem(F32)
    assert float_dtypes((pot32, bc32)) == {"float32"}
    r32 = je.solve(pot32, bc32)  # raises unless SUCCESS
    assert r32.x.dtype == F32
    floor = float(r32.stats["residual_floor"])
    assert 0 < float(r32.stats["residual"]) <= floor  # stopped at the round-off floor
    pot64, bc64 = readme_problem(F64)
    r64 = je.solve(pot64, bc64)
    assert float(r64.stats["residual_floor"]) < 1e-8 * floor  # ~eps ratio (5e8) apart
    assert rel_diff(r32.x, r64.x, pot64.mesh.points) <= 1e-5  # 4e-8 measured


@pytest.mark.slow  # float32 vs float64: README example and default scene below
def test_twist_n10_float32_at_rtol_1e_5_matches_float64():
    b32, b64 = twist(10, dtype=F32), twist(10, dtype=F64)
    r32 = je.solve(b32.pot, b32.bc, solver=je.Newton(rtol=1e-5))
    assert r32.x.dtype == F32 and int(r32.stats["steps"]) < 15
    r64 = je.solve(b64.pot, b64.bc, solver=je.Newton(rtol=1e-10))
    assert rel_diff(r32.x, r64.x, b64.pot.mesh.points) <= 1e-5  # 2e-7 measured


def scene_built(precision: str, **integrator):
    d = load_scene("default").to_dict()
    d["solver"] = dict(d.get("solver", {}), precision=precision)
    d["integrator"] = dict(d["integrator"], **integrator)
    return build(d)


@pytest.mark.slow  # 16-19 s; float32 scenes stay in the default run through the README example
@pytest.mark.parametrize("n_steps, static", [(5, False), (25, True)])
def test_default_scene_in_float32_matches_float64(n_steps, static):
    """The default scene (dynamics: backward Euler, damping, gravity) for some time steps
    (and its static solution), float32 vs float64. Stopping at the floor only once a full
    step stalls keeps the float32 trajectory on the float64 one (8e-7 over the whole run
    measured; stopping at the first step under the floor drifted to 8e-4)."""
    out = {}
    for prec in ("float32", "float64"):
        b = scene_built(prec)
        dt = F32 if prec == "float32" else F64
        assert b.mesh.points.dtype == dt
        assert float_dtypes((b.potential, b.bc, b.v0, b.params)) == {prec}
        state = dynamics.init_state(b.x0, b.v0)
        for _ in range(n_steps):
            state, res = dynamics.step(b.potential, state, b.bc, b.integrator, solver=b.solver)
            assert int(res.status) == je.Status.SUCCESS
        assert state.x.dtype == dt
        xs = je.solve(b.potential.replace(mass=None), b.bc, solver=b.solver).x if static else None
        out[prec] = (state.x, xs, b.mesh.points)
    x32, s32, _ = out["float32"]
    x64, s64, X = out["float64"]
    assert rel_diff(x32, x64, X) <= 1e-5
    if static:
        assert rel_diff(s32, s64, X) <= 1e-5


# --------------------------------------------------------------------------------------
# scenes: [solver] precision
# --------------------------------------------------------------------------------------


def test_precision_defaults_to_float64_and_refuses_other_values():
    assert load_scene("default").spec.solver.precision == "float64"
    d = load_scene("default").to_dict()
    d["solver"] = dict(d.get("solver", {}), precision="float16")
    with pytest.raises(SceneError, match="precision"):
        load_scene(d)


def test_float32_scene_builds_everything_in_float32_on_the_float64_selection():
    """Every float array of a float32 build is float32 (mesh, loads, parameters,
    Dirichlet data at any time, initial velocity), and the probes and tip are the nodes
    of the float64 build (selected on the float64 rest shape, so ties break alike)."""
    with jax.numpy_dtype_promotion("strict"):
        b32 = scene_built("float32")
    b64 = scene_built("float64")
    assert float_dtypes((b32.mesh, b32.potential, b32.params, b32.v0)) == {"float32"}
    assert float_dtypes(b32.bc_fn(0.3)) == {"float32"}
    assert b32.probes == b64.probes and b32.tip == b64.tip
    np.testing.assert_array_equal(np.asarray(b32.bc.mask), np.asarray(b64.bc.mask))
    np.testing.assert_array_equal(
        np.asarray(b32.mesh.points), np.asarray(b64.mesh.points).astype(np.float32)
    )


def test_float32_programs_hold_no_float64():
    """No silent promotion to float64 (``jnp.zeros`` defaults, NumPy float64 constants,
    ``jnp.asarray`` of float64 data) anywhere in a float32 scene's compiled solve or time
    step: their lowered programs hold no f64 array. (f64 *scalars* remain: Python floats
    such as ``1/h²`` enter as weakly typed scalars, which never widen an array.)"""
    b = scene_built("float32")
    solver = je.Newton(linear="cg")
    pot = b.potential
    state = dynamics.init_state(b.x0, b.v0)

    def static(pot, bc):
        return je.solve(pot.replace(mass=None), bc, solver=solver, throw=False).x

    def step(pot, state, bc):
        return dynamics.step(pot, state, bc, b.integrator, solver=solver)[0].x

    for name, fn, args in (("static", static, (pot, b.bc)), ("step", step, (pot, state, b.bc))):
        text = jax.jit(fn).lower(*args).as_text()
        arrays = re.findall(r"tensor<[0-9][0-9x]*xf64>", text)
        assert "xf32>" in text and not arrays, (name, sorted(set(arrays)))


@pytest.mark.extended
def test_float32_scene_summary_records_precision_and_linear_solver(tmp_path):
    scene = json.loads(json.dumps(TINY_SCENE))
    scene["solver"] = {"precision": "float32"}
    summary = run_scene(scene, str(tmp_path / "out"), progress=False)
    assert summary["status"] == "ok"
    assert summary["precision"] == "float32"
    assert summary["solver"]["precision"] == "float32"
    assert summary["linear_solver"].startswith("direct (")  # "auto" resolved, back end named
    saved = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert saved["precision"] == "float32" and saved["linear_solver"] == summary["linear_solver"]


def test_float32_fit_scene_is_refused_before_anything_runs(tmp_path):
    from jaxelastic.scene.fit import run_fit

    d = load_scene("fit_cantilever").to_dict()
    d["solver"] = dict(d.get("solver", {}), precision="float32")
    with pytest.raises(SceneError, match='precision = "float32" is not supported by a fit'):
        run_fit(d, str(tmp_path / "out"), progress=False)
    assert not (tmp_path / "out").exists()


def test_linear_solver_name_reads_the_bound_object():
    mesh = je.rectangle(4, 2)
    bc = L.fix(mesh, L.nodes_on_plane(mesh, 0, 0.0))
    assert linear_solver_name(je.solvers.linear.resolve("cg", mesh, bc)) == "cg (block_jacobi)"
    name = linear_solver_name(*je.solvers.init_linear("direct", mesh, bc))
    assert name.startswith("direct (") and name.endswith(")")


# --------------------------------------------------------------------------------------
# the round-off floor in float64
# --------------------------------------------------------------------------------------


@pytest.mark.extended
@pytest.mark.parametrize(
    "psi",
    [pytest.param(M.linear, marks=pytest.mark.slow), M.neo_hookean],
    ids=["linear", "neo_hookean"],
)
def test_float64_stiff_block_stops_with_success_at_the_floor(psi):
    """A steel block (E = 210 GPa) under a small end load in float64: rtol·‖f‖ lies below
    the residual's round-off floor (~eps·|K||x|), where the residual stagnates. Newton
    must stop there with SUCCESS (a non-quadratic ψ: once a full step stalls), report the
    floor, and give the answer a tight solve gives."""
    mesh = je.box(6, 2, 2, size=(3.0, 0.5, 0.5))
    params = je.Lame.from_E_nu(210e9, 0.3)
    clamp = L.fix(mesh, L.nodes_on_plane(mesh, 0, 0.0))
    end = L.facets_where(mesh, lambda X: np.isclose(X[:, 0], 3.0))
    f = jnp.asarray(L.traction_load(mesh, end, [0.0, 0.0, -1e4]))
    pot = je.Potential(mesh=mesh, params=params, f_ext=f, psi=psi)
    res = je.solve(pot, clamp, solver=je.Newton(rtol=1e-14, linear="direct"))
    floor = float(res.stats["residual_floor"])
    assert 0 < float(res.stats["residual"]) <= floor < 1e-6 * float(jnp.linalg.norm(f))
    assert int(res.stats["steps"]) <= 4
    loose = je.solve(pot, clamp, solver=je.Newton(rtol=1e-6, linear="direct"))
    u = np.asarray(res.x - mesh.points)
    np.testing.assert_allclose(
        np.asarray(loose.x - mesh.points), u, rtol=0, atol=1e-6 * abs(u).max()
    )
