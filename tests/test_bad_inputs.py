"""Bad input at the Python API gets a clear error before anything is compiled.

One test per case, each asserting the message: positions and load arrays of the wrong
shape, a ψ that does not return a scalar float, NaN/inf input outside jit (and NaN, not an
error, inside jit), float32 meshes with x64 enabled, NaN positions in ``write_vtu``,
plane-strain von Mises, interrupted atomic writes, ``.pvd`` time stamps, empty meshes.
"""

from __future__ import annotations

import os
import re
import warnings
import xml.etree.ElementTree as ET

import jax
import jax.numpy as jnp
import meshio
import numpy as np
import pytest

import jaxelastic as je
from jaxelastic import io as jio
from jaxelastic import loads, postprocess
from jaxelastic import materials as M
from jaxelastic.io import MeshIOError, TimeSeriesWriter, read_mesh, write_vtu
from jaxelastic.postprocess import cell_fields


@pytest.fixture(scope="module")
def cube():
    return je.box(2, 2, 2)  # 27 nodes, 48 tets


@pytest.fixture(scope="module")
def square():
    return je.rectangle(2, 2)  # 9 nodes, 8 triangles


P3 = M.Lame.from_E_nu(1e3, 0.3)
P2 = M.Lame.from_E_nu(1e3, 0.3, dim=2)


def vector_psi(F, p):
    return jnp.ones(3)


def int_psi(F, p):
    return 0


# ------------------------------------------------------------------------- shapes


def test_energy_positions_of_a_2d_shape_on_a_3d_mesh(cube):
    x = cube.points[:, :2]
    with pytest.raises(ValueError) as e:
        je.energy(M.neo_hookean, x, cube, P3)
    assert str(e.value) == (
        "je.energy: x must have shape (n_nodes, dim) = (27, 3) like mesh.points (a 3D mesh of "
        "27 nodes), got (27, 2)"
    )


def test_forces_positions_with_extra_rows(cube):
    x = jnp.concatenate([cube.points, jnp.zeros((3, 3))])
    with pytest.raises(
        ValueError, match=re.escape("je.forces: x must have shape (n_nodes, dim) = (27, 3)")
    ):
        je.forces(M.neo_hookean, x, cube, P3)


def test_hvp_direction_of_the_wrong_shape(cube):
    with pytest.raises(
        ValueError, match=re.escape("je.mechanics.hvp: v must have shape (n_nodes, dim) = (27, 3)")
    ):
        je.mechanics.hvp(M.neo_hookean, cube.points, jnp.zeros((27, 2)), cube, P3)


def test_element_hessians_and_densities_check_positions(square):
    for fn in (
        je.mechanics.element_hessians,
        je.mechanics.energy_densities,
        je.mechanics.element_gradients,
    ):
        with pytest.raises(ValueError, match=r"x must have shape \(n_nodes, dim\) = \(9, 2\)"):
            fn(M.linear, jnp.zeros((9, 3)), square, P2)


def test_swapped_mesh_and_positions(square):
    with pytest.raises(TypeError, match=r"je.energy: mesh must be a je.Mesh .* got ArrayImpl"):
        je.energy(M.linear, square, square.points, P2)


def test_potential_f_ext_of_a_2d_shape_on_a_3d_mesh(cube):
    with pytest.raises(ValueError) as e:
        je.Potential(cube, P3, f_ext=np.zeros((27, 2)), psi=M.neo_hookean)
    assert str(e.value) == (
        "Potential: f_ext must have shape (n_nodes, dim) = (27, 3) for this mesh of 27 nodes "
        "in 3D, got (27, 2)"
    )


def test_potential_f_ext_with_extra_rows(cube):
    with pytest.raises(
        ValueError, match=re.escape("f_ext must have shape (n_nodes, dim) = (27, 3)")
    ):
        je.Potential(cube, P3, f_ext=jnp.zeros((30, 3)), psi=M.neo_hookean)


def test_potential_mass_of_the_wrong_shape(cube):
    with pytest.raises(ValueError, match=re.escape("mass must have shape (n_nodes,) = (27,)")):
        je.Potential(cube, P3, mass=jnp.ones((27, 3)), psi=M.neo_hookean)


def test_potential_predictor_and_previous_positions(cube):
    for name in ("x_tilde", "x_prev"):
        with pytest.raises(ValueError, match=rf"{name} must have shape \(n_nodes, dim\)"):
            je.Potential(cube, P3, psi=M.neo_hookean, **{name: jnp.zeros((27, 2))})
    with pytest.raises(ValueError, match=r"inertia_weight must have shape \(\) \(a scalar\)"):
        je.Potential(cube, P3, psi=M.neo_hookean, inertia_weight=jnp.ones(2))


def test_shape_checks_are_static_under_jit_vmap_grad(square):
    """The checks see static (per-example) shapes: jit/vmap/grad run, and a wrong shape
    still fails at trace time with the same message."""
    X = square.points
    f = jax.jit(lambda x: je.energy(M.linear, x, square, P2))
    assert float(f(X)) == pytest.approx(0.0, abs=1e-12)
    xs = jnp.stack([X, 1.01 * X])
    e = jax.vmap(lambda x: je.energy(M.linear, x, square, P2))(xs)
    assert e.shape == (2,)
    g = jax.grad(lambda mu: je.energy(M.linear, 1.01 * X, square, M.Lame(mu, P2.lam)))(1.0)
    assert np.isfinite(float(g))
    with pytest.raises(ValueError, match=re.escape("x must have shape (n_nodes, dim) = (9, 2)")):
        f(jnp.zeros((9, 3)))
    pot = je.Potential(square, P2, f_ext=jnp.zeros((9, 2)), psi=M.linear)
    fs = jnp.zeros((3, 9, 2))
    gs = jax.vmap(lambda f: je.mechanics.potential.gradient(pot.replace(f_ext=f), X))(fs)
    assert gs.shape == (3, 9, 2)


def test_load_builders_name_the_argument(square):
    with pytest.raises(
        ValueError, match=re.escape("force must have shape (2,) or (2, 2) (one per node), got (3,)")
    ):
        loads.point_load(square, [0, 1], [1.0, 2.0, 3.0])
    facets = loads.facets_where(square, lambda X: X[:, 0] > 0.99)
    with pytest.raises(
        ValueError, match=re.escape("traction must have shape (2,) or (2, 2) (one per facet)")
    ):
        loads.traction_load(square, facets, np.zeros(3))
    with pytest.raises(
        ValueError, match=re.escape("g must have shape (2,) for a 2D mesh, got (3,)")
    ):
        loads.gravity_load(square, 1.0, (0.0, 0.0, -9.81))
    with pytest.raises(ValueError, match=re.escape("density must be a scalar or have shape (8,)")):
        loads.lumped_mass(square, np.ones(5))
    bc = loads.fix(square, [0])
    with pytest.raises(ValueError, match=re.escape("reaction_force: f_ext must have shape")):
        postprocess.reaction_force(M.linear, square.points, square, P2, bc, f_ext=np.zeros((9, 3)))


# ---------------------------------------------------------------------------- ψ


def test_psi_returning_a_vector(cube):
    with pytest.raises(TypeError) as e:
        je.forces(vector_psi, cube.points, cube, P3)
    assert str(e.value) == (
        "je.forces: ψ 'vector_psi' returned an array of shape (3,) and dtype float64 at F = I "
        "(3×3); a strain-energy density must return a scalar float for one unbatched F of "
        "shape (3, 3) (reduce with jnp.sum, return floats: 0.0 not 0)"
    )


def test_psi_returning_the_python_int_zero(cube):
    with pytest.raises(
        TypeError, match=r"je.energy: ψ 'int_psi' returned the Python int 0 at F = I"
    ):
        je.energy(int_psi, cube.points, cube, P3)


def test_psi_checked_at_potential_construction(cube):
    with pytest.raises(
        TypeError, match=r"Potential: ψ 'vector_psi' returned an array of shape \(3,\)"
    ):
        je.Potential(cube, P3, psi=vector_psi)


def test_psi_check_under_jit_names_psi(square):
    f = jax.jit(lambda x: je.forces(int_psi, x, square, P2))
    with pytest.raises(TypeError, match=r"ψ 'int_psi' returned the Python int 0 at F = I \(2×2\)"):
        f(square.points)


def test_psi_check_is_cached(square):
    calls = []

    def psi(F, p):
        calls.append(F.shape)
        return M.linear(F, p)

    je.energy(psi, square.points, square, P2)
    first = len(calls)
    je.energy(psi, square.points, square, P2)
    # the second call skips the check at F = I (and reuses the compiled energy: no trace)
    assert len(calls) - first <= first - 1
    second = len(calls)
    je.Potential(square, P2, psi=psi)  # same ψ, dim, dtype and parameters: cached
    assert len(calls) == second


# ---------------------------------------------------------------------- non-finite


def test_forces_with_nan_parameters_outside_jit(square):
    with pytest.raises(ValueError) as e:
        je.forces(M.linear, square.points, square, M.Lame(mu=jnp.nan, lam=1.0))
    assert str(e.value) == (
        "je.forces: params.mu is nan; refusing non-finite input (inside jax.jit nothing is "
        "checked and the result is NaN)"
    )


def test_energy_with_nan_positions_outside_jit(square):
    x = np.asarray(square.points).copy()
    x[4, 1] = np.nan
    with pytest.raises(
        ValueError,
        match=re.escape("je.energy: x has 1 NaN/inf value(s) of 18, the first at node 4"),
    ):
        je.energy(M.linear, x, square, P2)


def test_nan_inside_jit_is_returned_not_raised(square):
    f = jax.jit(lambda mu: je.forces(M.linear, 1.01 * square.points, square, M.Lame(mu, 1.0)))
    assert np.isnan(np.asarray(f(jnp.nan))).all()


def test_write_vtu_refuses_nan_positions(tmp_path, square):
    x = np.asarray(square.points).copy()
    x[[2, 5]] = np.inf
    path = tmp_path / "state.vtu"
    with pytest.raises(ValueError) as e:
        write_vtu(path, square, x)
    assert str(e.value) == (
        f"write_vtu: x (positions) has NaN/inf coordinates at 2 of 9 node(s), e.g. nodes "
        f"[2, 5]; refusing to write {str(path)!r} (was the solve successful? check "
        "solution.status)"
    )
    assert os.listdir(tmp_path) == []


# ------------------------------------------------------------------------- dtypes


def test_float32_mesh_keeps_its_dtype_and_loads_follow():
    m = je.box(1, 1, 1, dtype=np.float32)
    assert m.points.dtype == m.dN.dtype == m.weights.dtype == jnp.float32
    assert loads.gravity_load(m, 1.0, (0, 0, -1.0)).dtype == np.float32
    assert loads.lumped_mass(m, 1.0).dtype == np.float32
    assert loads.point_load(m, [0], (1.0, 0, 0)).dtype == np.float32
    assert loads.fix(m, [0]).values.dtype == jnp.float32
    with pytest.raises(je.MeshError, match="dtype must be float32 or float64, got int32"):
        je.from_arrays(np.asarray(m.points), np.asarray(m.cells), dtype=np.int32)


def test_potential_refuses_float64_loads_on_a_float32_mesh():
    m = je.box(1, 1, 1, dtype=np.float32)
    with pytest.raises(ValueError) as e:
        je.Potential(m, P3, f_ext=np.zeros((8, 3)), psi=M.neo_hookean)
    assert str(e.value) == (
        "Potential: f_ext has dtype float64 but the mesh is float32 (mesh.points); mixing them "
        "would promote the solve to float64. Build the mesh in float64 (e.g. "
        "je.from_arrays(points, cells, dtype=jnp.float64) or je.rectangle(..., "
        "dtype=jnp.float64)) or cast f_ext to float32"
    )


def test_potential_refuses_float64_parameters_on_a_float32_mesh():
    m = je.box(1, 1, 1, dtype=np.float32)
    p = M.Lame(mu=jnp.asarray(1.0, jnp.float64), lam=1.0)
    with pytest.raises(ValueError, match="params.mu has dtype float64 but the mesh is float32"):
        je.Potential(m, p, psi=M.neo_hookean)


def test_float32_mesh_solves_in_float32_with_x64_enabled():
    """Python-float parameters (weakly typed) and the loads builders keep a float32 mesh in
    float32: the solve runs (no while_loop carry TypeError) and returns float32."""
    m = je.box(2, 1, 1, size=(2.0, 1.0, 1.0), dtype=np.float32)
    f = loads.gravity_load(m, 1.0, (0.0, 0.0, -10.0))
    bc = loads.fix(m, loads.nodes_on_plane(m, 0, 0.0))
    pot = je.Potential(m, P3, f_ext=f, psi=M.neo_hookean)
    sol = je.solve(pot, bc, solver=je.Newton(rtol=1e-4), throw=False)
    assert sol.x.dtype == jnp.float32 and np.isfinite(np.asarray(sol.x)).all()


# -------------------------------------------------------------- VTU von Mises in 2D


def test_von_mises_plane_strain_uses_the_out_of_plane_stress(square):
    """Linear material, homogeneous small strain: σ_zz = ν(σ_xx + σ_yy) (plane strain)."""
    E, nu = 1000.0, 0.3
    p = M.Lame.from_E_nu(E, nu, dim=2)
    A = np.array([[1 + 2e-6, 3e-7], [-1e-7, 1 - 5e-7]])
    x = np.asarray(square.points) @ A.T
    out = cell_fields(M.linear, x, square, p)
    P = out["stress_P"][0].reshape(2, 2)
    sig = P @ A.T / np.linalg.det(A)
    np.testing.assert_allclose(out["stress_zz"], nu * (sig[0, 0] + sig[1, 1]), rtol=1e-5)
    s = np.zeros((3, 3))
    s[:2, :2] = sig
    s[2, 2] = nu * (sig[0, 0] + sig[1, 1])
    dev = s - np.trace(s) / 3 * np.eye(3)
    np.testing.assert_allclose(out["von_mises"], np.sqrt(1.5 * np.sum(dev**2)), rtol=1e-5)
    stress = cell_fields(M.linear, x, square, p, plane="stress")
    np.testing.assert_allclose(stress["stress_zz"], 0.0)
    assert not np.allclose(stress["von_mises"], out["von_mises"], rtol=1e-3)


def test_von_mises_of_a_psi_without_a_3d_embedding_warns(square):
    def psi_2d_only(F, p):
        if F.shape != (2, 2):
            raise ValueError("2D only")
        return M.linear(F, p)

    x = 1.01 * np.asarray(square.points)
    with pytest.warns(UserWarning) as w:
        out = cell_fields(psi_2d_only, x, square, P2)
    assert str(w[0].message) == (
        "plane strain: von_mises is written with σ_zz = 0 (the in-plane stress state) and "
        "without stress_zz, since σ_zz cannot be taken from the 3D embedding of ψ "
        "'test_von_mises_of_a_psi_without_a_3d_embedding_warns.<locals>.psi_2d_only': "
        "ValueError: 2D only"
    )
    assert "stress_zz" not in out


def test_von_mises_of_a_genuinely_2d_model_warns(square):
    def iso_2d(F, p):  # J^(-2/d): not the plane-strain restriction of its 3D form
        d = F.shape[0]
        J = jnp.linalg.det(F)
        return p.mu / 2 * (J ** (-2 / d) * jnp.sum(F * F) - d) + p.lam / 2 * (J - 1) ** 2

    with pytest.warns(
        UserWarning,
        match=r"in-plane stress on diag\(F, 1\) differs .* not the plane-strain restriction",
    ):
        cell_fields(iso_2d, 1.01 * np.asarray(square.points), square, P2)


# --------------------------------------------------------------------------- files


def test_interrupt_while_creating_the_temp_file_leaves_nothing(tmp_path, monkeypatch):
    """A KeyboardInterrupt landing right after the temporary file was created (where
    ``tempfile.mkstemp`` would not yet have told us its name) leaves no ``.tmp``."""
    real_open = os.open

    def interrupted(path, *args, **kw):
        fd = real_open(path, *args, **kw)
        if str(path).endswith(".tmp"):
            os.close(fd)
            raise KeyboardInterrupt
        return fd

    monkeypatch.setattr(jio.files.os, "open", interrupted)
    with pytest.raises(KeyboardInterrupt):
        jio.write_json(tmp_path / "summary.json", {"a": 1})
    monkeypatch.undo()
    assert os.listdir(tmp_path) == []


def test_pvd_time_stamps_are_short(tmp_path, square):
    times = [0.0, 0.1 * 7, 0.1 + 0.2, 1e-20, 1.0, 1.0 + 1e-15]
    with TimeSeriesWriter(tmp_path, "run", square) as w:
        for t in times:
            w.write(t, square.points)
    text = (tmp_path / "run.pvd").read_text()
    assert "0.7000000000000001" not in text and "0.30000000000000004" not in text
    stamps = [d.get("timestep") for d in ET.parse(tmp_path / "run.pvd").getroot().iter("DataSet")]
    assert stamps == ["0", "0.7", "0.3", "1e-20", "1.0", repr(1.0 + 1e-15)]  # 12 digits tie: repr


def test_read_mesh_of_an_empty_vtu_says_empty(tmp_path):
    path = tmp_path / "empty.vtu"
    meshio.write(path, meshio.Mesh(np.zeros((0, 3)), []))
    with pytest.raises(MeshIOError) as e:
        read_mesh(path)
    assert str(e.value) == f"{path}: the mesh is empty (0 points, 0 cells)"
    tets = tmp_path / "empty_tets.vtu"
    meshio.write(tets, meshio.Mesh(np.zeros((0, 3)), [("tetra", np.zeros((0, 4), int))]))
    with pytest.raises(MeshIOError, match="the mesh is empty"):
        read_mesh(tets)


def test_read_mesh_of_other_empty_files_says_empty(tmp_path):
    blank = tmp_path / "blank.msh"
    blank.write_bytes(b"")
    with pytest.raises(MeshIOError, match=r"the file is empty \(0 bytes\)"):
        read_mesh(blank)
    gmsh = tmp_path / "empty.msh"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        meshio.write(gmsh, meshio.Mesh(np.zeros((0, 3)), []))
    with pytest.raises(MeshIOError) as e:
        read_mesh(gmsh)
    assert str(e.value) == (
        f"{gmsh}: the mesh is empty (0 points, 0 cells); a mesh needs triangle (2D) or "
        "tetrahedron (3D) cells"
    )


# ----------------------------------------------------------------------------------------
# refusals that would otherwise end in a misleading status or a false SUCCESS
# ----------------------------------------------------------------------------------------


def _clamped_cube(cube):
    f = jnp.asarray(loads.point_load(cube, loads.nodes_on_plane(cube, 0, 1.0), [0, 0, -10.0]))
    pot = je.Potential(mesh=cube, params=P3, f_ext=f, psi=M.neo_hookean)
    return pot, loads.fix(cube, loads.nodes_on_plane(cube, 0, 0.0))


def test_dirichlet_mask_must_be_boolean(cube):
    pot, bc = _clamped_cube(cube)
    for mask in (bc.mask.astype(int), bc.mask.astype(float)):
        with pytest.raises(TypeError, match=r"bc\.mask must be a boolean array.*astype\(bool\)"):
            je.solve(pot, je.Dirichlet(mask, bc.values))


def test_nonfinite_prescribed_values_are_refused(cube):
    pot, bc = _clamped_cube(cube)
    values = jnp.where(bc.mask, jnp.nan, bc.values)
    with pytest.raises(ValueError, match=r"bc\.values is not finite at \d+ prescribed dof"):
        je.solve(pot, je.Dirichlet(bc.mask, values))
    free_nan = jnp.where(bc.mask, bc.values, jnp.nan)  # ignored off the mask: fine
    assert je.solve(pot, je.Dirichlet(bc.mask, free_nan)).ok


def test_potential_fields_and_mesh_must_be_arrays(cube):
    pot, bc = _clamped_cube(cube)
    with pytest.raises(TypeError, match=r"pot\.f_ext must be an array.*got list"):
        je.solve(pot.replace(f_ext=np.asarray(pot.f_ext).tolist()), bc)
    with pytest.raises(TypeError, match=r"pot\.mesh must be a je\.Mesh"):
        je.solve(je.Potential(mesh=np.zeros((3, 3)), params=P3, psi=M.neo_hookean), bc)


@pytest.mark.parametrize(
    "params, match",
    [
        (M.Lame(1e5, 1e30), r"lam / mu exceeds 1e\+12"),
        (M.Lame(-1.0, 1.0), r"shear modulus mu must be > 0"),
        (M.Lame(1.0, -1.0), r"bulk modulus lam \+ 2 mu / 3 must be > 0"),
        (M.Lame(1.0, np.inf), r"must be finite"),
    ],
)
def test_impossible_lame_parameters_are_refused(cube, params, match):
    pot, bc = _clamped_cube(cube)
    with pytest.raises(ValueError, match=match):
        je.solve(pot.replace(params=params), bc)


def test_one_bad_cell_of_a_lame_field_is_named(cube):
    pot, bc = _clamped_cube(cube)
    mu = np.full(cube.n_cells, float(P3.mu))
    mu[7] = -1.0
    with pytest.raises(ValueError, match=r"at 1 cell\(s\), first cell 7"):
        je.solve(pot.replace(params=M.Lame(jnp.asarray(mu), P3.lam)), bc)


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(xtol=1.0), r"xtol must be in \[0, 0\.001\]"),
        (dict(xtol=float("nan")), r"xtol must be finite"),
        (dict(max_steps=2.5), r"max_steps must be an integer >= 1"),
        (dict(max_steps="10"), r"max_steps must be an integer >= 1"),
        (dict(ls_max=-1), r"ls_max must be an integer >= 1"),
        (dict(armijo=2.0), r"armijo .* must be in \[0, 1\)"),
        (dict(armijo=-1.0), r"armijo .* must be in \[0, 1\)"),
        (dict(rtol=float("nan")), r"rtol must be finite"),
    ],
)
def test_newton_settings_are_checked(kw, match):
    with pytest.raises(ValueError, match=match):
        je.Newton(**kw)
    with pytest.raises(TypeError, match="require_positive_J must be True or False"):
        je.Newton(require_positive_J="yes")


def test_assemble_checks_its_shapes(cube):
    with pytest.raises(ValueError, match=r"per_element must have shape \(48, 4, 3\)"):
        je.mechanics.assemble(cube, jnp.ones((3, 4, 3)))
    with pytest.raises(TypeError, match="mesh must be a je.Mesh"):
        je.mechanics.assemble(jnp.ones((48, 4, 3)), cube)  # arguments swapped
    np.testing.assert_allclose(
        float(je.mechanics.assemble(cube, jnp.ones((48, 4, 3))).sum()), 48 * 4 * 3
    )


def test_node_indices_must_be_integers_and_loads_finite(cube):
    with pytest.raises(ValueError, match="node indices must be integers"):
        loads.fix(cube, np.array([0.5, 1.7]))
    with pytest.raises(ValueError, match="force must be finite"):
        loads.point_load(cube, [0, 1], [0.0, np.nan, 0.0])


@pytest.mark.parametrize("scale", [1e200, 1e-120])
def test_coordinates_beyond_float64_are_refused(scale):
    P = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], float) * scale
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the refusal, not a RuntimeWarning
        with pytest.raises(je.MeshError, match="over- or underflow float64.*rescale"):
            je.from_arrays(P, np.array([[0, 1, 2, 3], [1, 2, 3, 4]]))


def test_negative_rayleigh_damping_is_refused(cube):
    pot, bc = _clamped_cube(cube)
    pot = pot.replace(mass=jnp.asarray(loads.lumped_mass(cube, 1000.0)))
    st = je.dynamics.init_state(cube.points)
    for kw in (dict(alpha=-1.0), dict(beta=float("nan"))):
        with pytest.raises(ValueError, match="Rayleigh damping .* must be finite and >= 0"):
            je.dynamics.step(pot, st, bc, je.Integrator(h=0.01, **kw))


def test_generator_extents_and_plane_axes_are_checked(cube):
    with pytest.raises(ValueError, match=r"size must have 3 entries"):
        je.box(2, 2, 2, size=(1.0, 1.0))
    with pytest.raises(ValueError, match=r"size entries must be finite and > 0"):
        je.rectangle(2, 2, size=(1.0, -1.0))
    with pytest.raises(ValueError, match=r"origin must have 2 entries"):
        je.rectangle(2, 2, origin=(0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match=r'axis must be 0 … 2 or "x", "y", "z" for a 3D mesh'):
        loads.nodes_on_plane(cube, 5, 0.0)
    np.testing.assert_array_equal(
        loads.nodes_on_plane(cube, "z", 1.0), loads.nodes_on_plane(cube, 2, 1.0)
    )


def test_parameters_a_builtin_psi_cannot_read_are_named(cube):
    pot, bc = _clamped_cube(cube)
    for params in ({"mu": 1.0, "lam": 1.0}, 1.0):
        with pytest.raises(TypeError, match=r"could not read its parameters.*je\.Lame\(mu, lam\)"):
            je.solve(pot.replace(params=params), bc)


def test_write_vtu_names_a_missing_directory_not_its_temporary(cube, tmp_path):
    with pytest.raises(FileNotFoundError, match=r"the directory .*nope.* does not exist"):
        write_vtu(tmp_path / "nope" / "a.vtu", cube, np.asarray(cube.points))
    with pytest.raises(IsADirectoryError, match="it is a directory"):
        write_vtu(tmp_path, cube, np.asarray(cube.points))


def test_read_mesh_names_a_nan_node_by_its_file_index(tmp_path):
    pts = np.array([[9, 9, 9], [0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])  # node 0 unused
    pts[4, 2] = np.nan
    meshio.write(tmp_path / "m.vtu", meshio.Mesh(pts, [("tetra", np.array([[1, 2, 3, 4]]))]))
    with pytest.raises(MeshIOError, match=r"NaN/inf coordinates, e\.g\. file nodes \[4\]"):
        read_mesh(tmp_path / "m.vtu")


def test_lame_names_a_non_numeric_argument():
    for E, nu, name in (("1e5", 0.3, "Young's modulus E"), (1e5, None, "Poisson's ratio nu")):
        with pytest.raises(TypeError, match=f"{name} must be a real number"):
            je.materials.lame(E, nu)
