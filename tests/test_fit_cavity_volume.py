"""Fitting Guccione's stiffness C to a pressure–volume curve: an octant of a thick
spherical shell (symmetry rollers on its three cut planes) inflated by a pressure on its
inner surface in four levels, its cavity volume observed at each (CavityVolume).

Extended tier: the gradient of the χ² misfit through the four solves (implicit adjoint)
matches central differences, and Levenberg–Marquardt recovers C from noise-free synthetic
volumes. Default tier: data of the wrong shape is refused.
"""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic as je
import jaxelastic.materials as M
from jaxelastic import fitting as F
from jaxelastic import loads as L
from jaxelastic.mesh import spherical_shell

SOLVER = je.Newton(rtol=1e-12)
MESH = spherical_shell(1.0, 1.5, 1, 1)  # 18 tets
# C = 2 kPa, b_f = 8, b_t = 2, b_fs = 4, κ = 1000 kPa; fibres along x, sheets along y
TRUE = M.per_cell_basis(M.guccione_params(), MESH.n_cells)
ONLY_C = M.Guccione(F.Positive(), *[F.Fixed()] * 6)
FACTORS = np.array([0.25, 0.5, 0.75, 1.0])


def inflation(params, volumes=None, sigma=1e-3):
    """The four-level inflation (to 0.5 kPa) of the shell octant ``1 ≤ |X| ≤ 1.5``
    observed by its cavity volume (closed by the cone to the centre), and its mesh."""
    mesh = MESH
    inner = L.facets_where(mesh, lambda X: np.linalg.norm(X, axis=1) < 1.0 + 1e-9)
    sym = [L.fix(mesh, L.nodes_on_plane(mesh, a, 0.0), components=(a,)) for a in range(3)]
    pressure = L.pressure_load(mesh, inner, 0.5, origin=[0.0, 0.0, 0.0])
    pot = je.Potential(mesh, params, psi=M.guccione, pressure=pressure)
    data = np.zeros(FACTORS.size) if volumes is None else volumes
    obs = F.CavityVolume(pressure, jnp.asarray(data), sigma)
    return F.LoadPathCase(pot, L.combine(*sym), FACTORS, (obs,))


def synthetic_volumes():
    case = inflation(TRUE)
    (v,), aux = case.predictions(TRUE, case.initial_warm(), case.bind(SOLVER), je.ImplicitAdjoint())
    assert bool(aux.ok)
    return np.asarray(v)


@pytest.mark.extended
def test_cavity_volume_observation_and_its_gradient():
    v = synthetic_volumes()
    rest = float(inflation(TRUE).observations[0].cavity.volumes(MESH.points)[0])
    assert 0.3 < rest < np.pi / 6  # the meshed octant of the unit ball: a polyhedron
    assert np.all(np.diff(v) > 0) and 1.01 * rest < v[0] and v[-1] < 1.5 * rest
    # the fitted constant's misfit gradient through the four solves vs central differences
    case = inflation(TRUE, v)
    obj = F.make_objective([case], TRUE._replace(C=2.6), transforms=ONLY_C, solver=SOLVER)
    (f, _), g = obj.value_and_grad(obj.z0)
    h = 1e-5
    fp = float(obj.value_and_grad(obj.z0 + h)[0][0])
    fm = float(obj.value_and_grad(obj.z0 - h)[0][0])
    fd = (fp - fm) / (2 * h)
    assert float(f) > 1.0
    assert abs(float(g[0]) - fd) <= 1e-6 * abs(fd)


@pytest.mark.extended
def test_pressure_volume_fit_recovers_guccione_c():
    v = synthetic_volumes()
    case = inflation(TRUE, v)
    lm = F.LMSettings(atol=1e-20)  # an exact fit: the cost ends at round-off
    res = F.fit([case], TRUE._replace(C=2.6), transforms=ONLY_C, optimizer=lm, solver=SOLVER)
    assert res.converged, res.stop_reason
    assert res.names == ("C",)
    assert abs(float(res.material.C) / 2.0 - 1.0) <= 1e-8
    assert res.uncertainty is not None and res.uncertainty.rank == 1


def test_cavity_volume_refuses_data_of_the_wrong_shape():
    case = inflation(TRUE)
    obs = case.observations[0]
    with pytest.raises(ValueError, match=r"cavity_volume observation: data must be"):
        F.LoadPathCase(case.pot, case.bc, FACTORS, (obs.__class__(obs.cavity, np.zeros((4, 2))),))
