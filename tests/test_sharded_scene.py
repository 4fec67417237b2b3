"""``[solver] devices = N`` in scenes: validation, the clear errors, and a sharded CLI run.

The CLI run (``jaxelastic run twist --set solver.devices=2``) goes in-process when this
process sees at least two devices, else in a subprocess started with
``XLA_FLAGS=--xla_force_host_platform_device_count=2``; its ``summary.json`` must record
the devices and the partition, and its probes, energy and reaction must equal the
one-device run of the same scene to 1e-12 relative (slow: two compiles, 75 s on a loaded
machine), and so must a dynamic sharded scene (time steps and the static comparison). The
fast test builds a sharded scene and checks its padded Dirichlet path and summary header.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest

from jaxelastic import cli
from jaxelastic.scene import SceneError, build, load_scene, run_scene

TWIST = {"mesh.n": [3, 3, 3], "solver.linear": "cg", "output.png": False, "output.vtu": False}
SETS = [f"{k}={json.dumps(v).lower()}" for k, v in TWIST.items()]


def test_devices_default_and_range():
    assert load_scene("twist").spec.solver.devices == 1
    with pytest.raises(SceneError, match=r"\[solver\]\.devices"):
        load_scene("twist", overrides={"solver.devices": 0})


@pytest.mark.parametrize("linear", ["direct", "amg"])
def test_host_linear_solvers_refused_when_sharded(linear):
    with pytest.raises(SceneError) as e:
        load_scene("twist", overrides={"solver.devices": 2, "solver.linear": linear})
    msg = str(e.value)
    assert "[solver].devices = 2" in msg and f'"{linear}"' in msg and '"cg"' in msg


def test_fit_scene_refuses_devices():
    with pytest.raises(SceneError, match="devices = 1"):
        load_scene("fit_cantilever", overrides={"solver.devices": 2})


def test_too_many_devices_names_the_xla_flag():
    n = len(jax.devices()) + 1
    with pytest.raises(SceneError) as e:
        build(load_scene("twist", overrides={**TWIST, "solver.devices": n}))
    msg = str(e.value)
    assert "[solver].devices" in msg and "--xla_force_host_platform_device_count" in msg
    assert "initialize_from_env" in msg


@pytest.mark.skipif(len(jax.devices()) < 2, reason="needs 2 devices (tests/conftest.py)")
def test_build_shards_the_scene_and_the_header_records_it(tmp_path):
    from jaxelastic.scene.outputs import run_header, run_table
    from jaxelastic.scene.problem import padded_dirichlet

    built = build(load_scene("twist", overrides={**TWIST, "solver.devices": 2}))
    sh = built.shard
    assert sh is not None and len(sh.devices) == 2
    part = sh.partition
    assert built.potential.mesh.n_nodes == part.n_nodes  # outputs stay natural
    assert sh.x0.shape == (part.n_padded_nodes, 3)
    # the load path's Dirichlet data in the padded layout: natural part unchanged,
    # padding fixed at its rest point, placed like the sharded bc
    bc = padded_dirichlet(sh, built.bc_fn(0.5))
    mask, values = np.asarray(bc.mask), np.asarray(bc.values)
    nat = built.bc_fn(0.5)
    np.testing.assert_array_equal(part.to_natural(mask, kind="nodes"), np.asarray(nat.mask))
    np.testing.assert_array_equal(part.to_natural(values, kind="nodes"), np.asarray(nat.values))
    assert mask[~part.node_real].all()
    np.testing.assert_array_equal(values[~part.node_real], sh.rest[~part.node_real])
    assert bc.mask.sharding == sh.bc.mask.sharding
    h = run_header(built, str(tmp_path))
    assert h["devices"] == 2 and h["partition"]["shards"] == 2
    assert sum(h["partition"]["cells"]) == built.mesh.n_cells
    assert h["linear_solver"].startswith("cg")
    h["status"], h["scene"]["name"] = "ok", "twist"
    assert "2 shards" in run_table(h)


def _sharded_summary(tmp_path, scene: str, sets: list[str]) -> dict:
    """``jaxelastic run SCENE --set solver.devices=2 ...``'s summary (in-process when two
    devices are at hand, else in a subprocess with two host devices)."""
    out = tmp_path / "sharded"
    argv = ["run", scene, "--out", str(out), "--no-progress", "--json", "--no-cache"]
    argv += [a for s in [*sets, "solver.devices=2"] for a in ("--set", s)]
    if len(jax.devices()) >= 2:
        assert cli.main(argv) == 0
    else:
        env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
        r = subprocess.run(
            [sys.executable, "-m", "jaxelastic", *argv],
            env=env,
            capture_output=True,
            text=True,
            timeout=600,
            check=False,
        )
        assert r.returncode == 0, r.stderr[-3000:]
    with open(out / "summary.json") as f:
        return json.load(f)


def _rel(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-300))


@pytest.mark.slow
def test_cli_sharded_twist_matches_one_device(tmp_path):
    s = _sharded_summary(tmp_path, "twist", SETS)
    assert s["status"] == "ok" and s["devices"] == 2
    p = s["partition"]
    assert p["shards"] == 2 and len(p["devices"]) == 2
    assert sum(p["cells"]) == s["mesh"]["n_cells"] == 6 * 27
    assert sum(p["owned_nodes"]) == s["mesh"]["n_nodes"]
    assert min(p["interface_nodes"]) > 0 and p["halo_bytes_total"] < p["replicated_bytes"]
    one = run_scene(load_scene("twist", overrides=TWIST), tmp_path / "one", progress=False)
    assert one["devices"] == 1 and one["partition"] is None
    for k in ("elastic_energy", "max_displacement"):
        assert _rel(s["static"][k], one["static"][k]) <= 1e-12, k
    for p_s, p_1 in zip(s["probes"], one["probes"], strict=True):
        assert _rel(p_s["displacement"], p_1["displacement"]) <= 1e-12
    # the net reaction of the twist is zero up to round-off (no load): compare absolutely
    diff = np.subtract(s["static"]["reaction_force"], one["static"]["reaction_force"])
    assert np.abs(diff).max() <= 1e-9


@pytest.mark.slow
def test_sharded_dynamic_scene_matches_one_device(tmp_path):
    sets = {
        "mesh.n": [2, 10],
        "solver.linear": "cg",
        "integrator.duration": 0.05,
        "integrator.compare_static": True,
        "output.png": False,
    }
    s = _sharded_summary(
        tmp_path, "swing2d", [f"{k}={json.dumps(v).lower()}" for k, v in sets.items()]
    )
    one = run_scene(load_scene("swing2d", overrides=sets), tmp_path / "one", progress=False)
    assert s["dynamic"]["steps"] == one["dynamic"]["steps"] == 5
    for k in ("kinetic", "elastic"):
        assert _rel(s["dynamic"]["per_step"][k], one["dynamic"]["per_step"][k]) <= 1e-12, k
    assert _rel(s["dynamic"]["tip"]["displacement"], one["dynamic"]["tip"]["displacement"]) <= 1e-12
    assert _rel(s["static"]["tip_displacement"], one["static"]["tip_displacement"]) <= 1e-12
