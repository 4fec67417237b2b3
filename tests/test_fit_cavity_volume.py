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


# -- from a scene file: [[fit.case.observation]] kind = "volume" --------------------------

RING_INNER = "sqrt(x**2 + y**2) < 1.0 + 1e-6"


def _ring_scene(tmp_path, E: float, fit: str = "") -> str:
    """A quarter ring 1 ≤ |X| ≤ 2 (plane strain, symmetry rollers) inflated by 100 Pa on
    its inner wall, the cavity closed at the centre; ``fit``: the [fit] tables."""
    import meshio

    from jaxelastic.mesh import annulus

    m = annulus(1.0, 2.0, 4, 2)
    pts = np.c_[np.asarray(m.points), np.zeros(m.n_nodes)]
    meshio.write(tmp_path / "ring.vtu", meshio.Mesh(pts, [("triangle", np.asarray(m.cells))]))
    text = f'''name = "ring"
[mesh]
file = "ring.vtu"
[material]
model = "neo_hookean"
E = {E}
nu = 0.3
[[dirichlet]]
nodes = {{ plane = {{ axis = "x", value = 0.0 }} }}
components = ["x"]
[[dirichlet]]
nodes = {{ plane = {{ axis = "y", value = 0.0 }} }}
components = ["y"]
[[cavity]]
name = "inside"
facets = {{ where = "{RING_INNER}" }}
origin = [0.0, 0.0]
[[pressure]]
facets = {{ where = "{RING_INNER}" }}
pressure = 100.0
cavity = "inside"
'''
    path = tmp_path / f"ring_{len(fit)}.toml"
    path.write_text(text + fit)
    return str(path)


VOLUME_FIT = """[fit]
fields = ["E"]
optimizer = "lm"
[[fit.case]]
load_factors = [0.5, 1.0]
[[fit.case.observation]]
kind = "volume"
cavity = "{cavity}"
file = "pv.csv"
sigma = 1e-4
"""


@pytest.mark.parametrize(
    "cavity, header, match",
    [
        ("lung", "factor,volume", r"observation\[0\].cavity 'lung' names no \[\[cavity\]\]"),
        ("inside", "factor,force", "the first line must be 'factor,volume'"),
    ],
)
def test_scene_volume_observations_refuse_bad_entries(tmp_path, cavity, header, match):
    from jaxelastic.scene import SceneError
    from jaxelastic.scene.fit import run_fit

    (tmp_path / "pv.csv").write_text(f"{header}\n0.5,0.9\n1.0,1.1\n")
    path = _ring_scene(tmp_path, 700.0, VOLUME_FIT.format(cavity=cavity))
    with pytest.raises(SceneError, match=match):
        run_fit(path, tmp_path / "out", progress=False)


def test_scene_volume_observation_needs_its_cavity_key():
    from jaxelastic.scene.schema import FitObservation

    with pytest.raises(ValueError, match="kind = 'volume' needs cavity"):
        FitObservation(kind="volume", file="pv.csv", sigma=1.0)
    with pytest.raises(ValueError, match="cavity belongs to kind = 'volume' only"):
        FitObservation(kind="surface", file="s.npz", sigma=1.0, cavity="inside")


@pytest.mark.extended
def test_scene_fit_of_young_modulus_from_a_pressure_volume_curve(tmp_path):
    """The ring's cavity area at two pressures (E = 1000) from a scene file: LM from
    E = 700 recovers E, and fit.png has the P–V panel."""
    from jaxelastic.scene import build, load_scene
    from jaxelastic.scene.fit import run_fit

    b = build(load_scene(_ring_scene(tmp_path, 1000.0)))
    vols = []
    for f in (0.5, 1.0):
        pot = b.potential.replace(pressure=b.potential.pressure.scaled(f))
        r = je.solve(pot, b.bc, solver=je.Newton(rtol=1e-12))
        vols.append(float(b.cavities.term.volumes(r.x)[0]))
    assert vols[0] > 1.1 * float(b.cavities.term.volumes(b.x0)[0])  # inflated
    rows = "".join(f"{f},{v!r}\n" for f, v in zip((0.5, 1.0), vols, strict=True))
    (tmp_path / "pv.csv").write_text("factor,volume\n" + rows)
    path = _ring_scene(tmp_path, 700.0, VOLUME_FIT.format(cavity="inside"))
    s = run_fit(path, tmp_path / "out", progress=False)
    assert s["status"] == "ok" and s["result"]["converged"]
    assert abs(s["fitted"]["E"] / 1000.0 - 1.0) < 1e-6
    assert s["cases"][0]["observations"][0]["kind"] == "cavity_volume"
    assert (tmp_path / "out" / "fit.png").stat().st_size > 10_000
