"""Scenes with [[pressure]] and [[cavity]]: the shipped balloon (build, run, summary and
pressure–volume plot) and the bad inputs refused before any solve."""

import json
import math

import numpy as np
import pytest

from jaxelastic.scene import build, load_scene
from jaxelastic.scene.errors import SceneError

INNER = "sqrt(x**2 + y**2 + z**2) < 0.1 + 1e-6"
OUTER = "sqrt(x**2 + y**2 + z**2) > 0.2 - 1e-6"


def test_balloon_builds_with_one_pressure_surface_and_a_cavity():
    b = build(load_scene("balloon"))
    term = b.potential.pressure
    assert term is not None and term.n_surfaces == 1
    assert b.cavities is not None and b.cavities.names == ("inside",)
    V0 = float(b.cavities.term.volumes(b.x0)[0])
    assert abs(V0 - math.pi / 6 * 0.1**3) / V0 < 1e-3  # an eighth of the sphere
    assert b.potential.f_ext is None  # the pressure is no dead load


def test_follower_pressure_scene_accepts_a_free_rim():
    """With follower = true the rim check is off (the follower load needs no closed lid)."""
    over = {"dirichlet.2.components": ["x"], "pressure.0.follower": True}
    b = build(load_scene("balloon", overrides=over))
    assert b.potential.pressure is not None and b.potential.pressure.follower


def test_scene_without_pressure_compiles_none():
    b = build(load_scene("cook"))
    assert b.potential.pressure is None and b.cavities is None


@pytest.mark.parametrize(
    "overrides, message",
    [
        ({"pressure.0.facets": {"where": "x > 100"}}, "[pressure][0].facets selects no nodes"),
        (
            {"pressure.0.facets": {"where": "abs(x - 0.15) < 0.01"}},
            "[pressure][0].facets selects no boundary facets",
        ),
        ({"pressure.0.facets": {"where": OUTER}}, "does not bound the named cavity"),
        ({"cavity.0.facets": {"where": OUTER}}, "do not bound a cavity"),
        ({"dirichlet.2.components": ["x"]}, "rim edge"),
        ({"pressure.0.origin": [0.05, 0.05, 0.05]}, "symmetry plane"),
        ({"cavity.0.origin": [0.0, 0.0]}, "[cavity][0].origin must have 3 components"),
    ],
)
def test_bad_pressure_scenes_refused_at_build(overrides, message):
    s = load_scene("balloon", overrides=overrides)
    with pytest.raises(SceneError) as e:
        build(s)
    assert message in str(e.value)


@pytest.mark.parametrize(
    "overrides, message",
    [
        ({"pressure.0.pressure": float("nan")}, "[pressure][0].pressure"),
        ({"pressure.0.cavity": "lung"}, "names no [[cavity]]"),
        ({"cavity.0.volume": -1e-3}, "[cavity][0].volume"),
        ({"cavity.0.volume": 1e-3}, "a scene with volume control has no [[pressure]]"),
        ({"solver.devices": 2}, "[[pressure]] runs on one device"),
        (
            {
                "integrator": {"type": "dynamic", "h": 0.01, "duration": 0.1},
                "material.density": 1e3,
                "pressure.0.ramp_time": -0.1,
            },
            "[pressure][0].ramp_time",
        ),
    ],
)
def test_bad_pressure_scenes_refused_at_load(overrides, message):
    with pytest.raises(SceneError) as e:
        load_scene("balloon", overrides=overrides)
    assert message in str(e.value)


@pytest.mark.extended
def test_balloon_runs_and_reports_its_pressure_volume_curve(tmp_path):
    """The shipped balloon (5 load steps to 0.5 μ): the cavity volume per load step in
    summary.json, pressure_volume.png, and the inner stretch on the incompressible
    closed form p = (μ/2)[(4/λ_b + λ_b⁻⁴) − (4/λ_a + λ_a⁻⁴)] within 1 %."""
    from jaxelastic.scene import run_scene

    summary = run_scene("balloon", tmp_path, progress=False)
    cav = summary["cavities"]["inside"]
    assert cav["load_factor"][0] == 0.0 and cav["load_factor"][-1] == 1.0
    assert np.all(np.diff(cav["volume"]) > 0)
    assert (tmp_path / "pressure_volume.png").is_file()
    on_disk = json.loads((tmp_path / "summary.json").read_text())
    assert on_disk["cavities"]["inside"]["volume"] == cav["volume"]
    mu = 3.0e5 / (2 * 1.499)
    la = (cav["volume"][-1] / cav["rest_volume"]) ** (1 / 3)  # the cavity stays spherical
    lb = (1 + (la**3 - 1) / 8) ** (1 / 3)
    p = 0.5 * mu * ((4 / lb + lb**-4) - (4 / la + la**-4))
    assert abs(p - 5.0e4) / 5.0e4 < 0.01


@pytest.mark.slow
def test_balloon_under_volume_control(tmp_path):
    """[[cavity]] volume = 1.3³ V₀ (no [[pressure]]): the cavity reaches it in the load steps
    and the pressure found agrees with the closed form at λ_a = 1.3 within 1 % (163–212 s
    on a loaded 2-core machine, hence the slow tier)."""
    from jaxelastic.scene import run_scene

    V0 = math.pi / 6 * 0.1**3
    over = {"pressure": [], "cavity.0.volume": V0 * 1.3**3, "integrator.load_steps": 1}
    summary = run_scene(load_scene("balloon", overrides=over), tmp_path, progress=False)
    cav = summary["cavities"]["inside"]
    assert abs(cav["volume"][-1] - V0 * 1.3**3) < 1e-6 * V0
    mu = 3.0e5 / (2 * 1.499)
    la = 1.3 * (V0 / cav["rest_volume"]) ** (1 / 3)
    lb = (1 + (la**3 - 1) / 8) ** (1 / 3)
    p = 0.5 * mu * ((4 / lb + lb**-4) - (4 / la + la**-4))
    assert abs(cav["pressure"][-1] - p) / p < 0.01
    assert all(r["multiplier_updates"] >= 1 for r in summary["static"]["load_steps"])


def _dynamic_balloon(tmp_path, **pressure):
    """The shipped balloon as a damped dynamic scene (rubber density, ~30 % of critical
    damping of its breathing mode)."""
    from importlib import resources

    data = resources.files("jaxelastic.scene") / "data"
    d = load_scene("balloon").to_dict()
    d["mesh"]["file"] = str(data / "balloon.vtu")
    d["material"]["density"] = 1000.0
    d["integrator"] = dict(
        type="dynamic", method="backward_euler", h=0.004, duration=0.4, alpha=60.0,
        settle=True, settle_tol=1e-6, settle_steps=3, compare_static=True,
    )  # fmt: skip
    d["pressure"][0].update(pressure)
    d["output"]["every"] = 5
    return load_scene(d)


@pytest.mark.extended  # about 50 P2 F-bar time steps and the static comparison (~20 s)
def test_dynamic_balloon_ramps_its_pressure_and_settles_at_the_static_inflation(tmp_path):
    from jaxelastic.scene import run_scene

    s = run_scene(_dynamic_balloon(tmp_path, ramp_time=0.05), tmp_path / "out", progress=False)
    assert s["status"] == "ok" and s["dynamic"]["settled"]
    cav = s["cavities"]["inside"]
    t, p, V = (np.asarray(cav[k]) for k in ("time", "pressure", "volume"))
    assert t[0] == 0.0 and np.all(np.diff(t) > 0)
    assert p[0] == 0.0 and p[-1] == 5.0e4  # ramped from 0 to the full pressure
    i = int(np.searchsorted(t, 0.02))
    assert p[i] == pytest.approx(5.0e4 * t[i] / 0.05)
    assert V[-1] > 1.5 * cav["rest_volume"]  # inflated (the static solution: la ~ 1.2)
    # settled at the static inflation of the same pressure
    assert s["comparison"]["relative_to_max_displacement"] < 1e-3
    assert (tmp_path / "out" / "pressure_volume.png").stat().st_size > 5_000


def test_pressure_ramps_and_volume_control_in_the_wrong_integrator_are_refused(tmp_path):
    with pytest.raises(SceneError, match=r"\[pressure\]\[0\].ramp_time is only valid in a dynamic"):
        load_scene("balloon", overrides={"pressure.0.ramp_time": 0.1})
    d = _dynamic_balloon(tmp_path).to_dict()
    del d["pressure"]
    d["cavity"][0]["volume"] = 1e-3
    with pytest.raises(SceneError, match="volume control is supported in static scenes"):
        load_scene(d)
