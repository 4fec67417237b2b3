"""The user-facing surface: the top-level names, their sign conventions, the deprecations."""

import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic as je


def test_top_level_is_small_and_every_name_resolves():
    names = [n for n in je.__all__ if not isinstance(getattr(je, n), type(je))]
    assert 25 <= len(names) <= 40, names
    for n in je.__all__:
        assert getattr(je, n) is not None, n
    for n in ("fix", "neo_hookean", "simulate", "fit", "solve", "Potential", "Lame", "shard"):
        assert n in je.__all__, n
    for n in ("project_psd", "svd_rv", "assemble", "hvp", "element_hessians"):
        assert n not in je.__all__, n  # kernels live in their packages


@pytest.mark.parametrize(
    "name, new",
    [
        ("project_psd", lambda: je.mechanics.project_psd),
        ("svd_rv", lambda: je.kinematics.svd_rv),
        ("assemble", lambda: je.mechanics.assemble),
        ("element_hessians", lambda: je.mechanics.element_hessians),
        ("Partition", lambda: je.parallel.Partition),
        ("benchmarks", lambda: je.verification),
        ("lame", lambda: je.materials.lame),
        ("rubber", lambda: je.materials.rubber),
        ("fibres", lambda: je.materials.fibres),
        ("spectral", lambda: je.materials.spectral),
        ("fusion", lambda: je.mechanics.fusion),
    ],
)
def test_moved_names_warn_and_still_work(name, new):
    with pytest.warns(DeprecationWarning, match=f"je.{name} is deprecated"):
        obj = getattr(je, name)
    assert obj is new()
    with pytest.raises(AttributeError, match="no attribute"):
        je.no_such_name  # noqa: B018


@pytest.mark.parametrize(
    "module, name",
    [
        ("loads", "reaction_force"),
        ("loads", "facet_tractions"),
        ("io", "cell_fields"),
        ("io", "nodal_stress"),
        ("io", "stress_fields"),
    ],
)
def test_postprocessing_names_moved_from_loads_and_io_warn(module, name):
    with pytest.warns(DeprecationWarning, match=f"use jaxelastic.postprocess.{name}"):
        obj = getattr(getattr(je, module), name)
    assert obj is getattr(je.postprocess, name)
    with pytest.raises(AttributeError, match="no attribute"):
        getattr(je, module).no_such_name  # noqa: B018


def test_element_forces_have_the_sign_of_forces():
    mesh = je.box(2, 1, 1)
    p = je.Lame.from_E_nu(1e3, 0.3)
    rng = np.random.default_rng(0)
    x = mesh.points + 0.05 * jnp.asarray(rng.standard_normal(mesh.points.shape))
    fe = je.mechanics.element_forces(je.neo_hookean, x, mesh, p)
    ge = je.mechanics.element_gradients(je.neo_hookean, x, mesh, p)
    np.testing.assert_array_equal(np.asarray(fe), -np.asarray(ge))
    f = je.forces(je.neo_hookean, x, mesh, p)
    np.testing.assert_allclose(je.mechanics.assemble(mesh, fe), f, rtol=1e-12, atol=1e-12)
    with pytest.warns(DeprecationWarning, match="element_gradients"):
        old = je.element_forces  # the former top-level name: the gradients, as before
    np.testing.assert_array_equal(np.asarray(old(je.neo_hookean, x, mesh, p)), np.asarray(ge))


def test_lame_from_E_nu():
    mu, lam = je.materials.lame(2e5, 0.25)
    assert je.Lame.from_E_nu(2e5, 0.25) == je.Lame(mu, lam)
    mu2, lam2 = je.materials.lame(2e5, 0.25, dim=2, plane="stress")
    assert je.Lame.from_E_nu(2e5, 0.25, dim=2, plane="stress") == je.Lame(mu2, lam2)
    with pytest.raises(ValueError, match="Poisson"):
        je.Lame.from_E_nu(1.0, 0.5)


def test_old_solver_binding_names_warn():
    mesh = je.box(2, 1, 1)
    bc = je.fix(mesh, je.loads.nodes_on_plane(mesh, 0, 0.0))
    with pytest.warns(DeprecationWarning, match="init_linear"):
        lin = je.solvers.bind_linear("cg", mesh, bc)
    assert isinstance(lin, je.CG)
    with pytest.warns(DeprecationWarning, match="prepare_solver"):
        prepared = je.solvers.bind_solver(je.Newton(linear="cg"), mesh, bc)
    assert isinstance(prepared, je.solvers.PreparedSolver)
    with pytest.warns(DeprecationWarning, match="solved_potential"):
        assert je.solvers.contact_potential is je.solvers.solved_potential
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        je.solvers.prepare_solver(je.Newton(linear="cg"), mesh, bc)  # the new name is quiet
