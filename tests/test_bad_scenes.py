"""Bad input that must end with a clear error, noise-free valid input, and interruptions.

* a mesh too large for the memory is refused before anything is allocated, with the
  estimate, the memory available and the override (``[solver] max_memory_gb``);
* a scene argument or ``[mesh] file`` that is a directory, an empty VTU;
* ``--out`` where no directory can be created;
* a free body in dynamics (no overflow warning, no 1e29 energy ratio), absurd ``where``
  arithmetic;
* SIGINT / SIGTERM stop a run at a step boundary with consistent files and exit status
  130, and SIGKILL leaves only readable files.
"""

import importlib
import json
import os
import signal
import subprocess
import sys
import time
import warnings
import xml.etree.ElementTree as ET

import meshio
import numpy as np
import pytest
from _common import TINY_SCENE, scene_toml

from jaxelastic import cli
from jaxelastic.scene import (
    SceneError,
    apply_overrides,
    build,
    load_scene,
    memory,
    run_scene,
    shipped_scenes,
)
from jaxelastic.scene.interrupt import Interrupted, handle_signals
from jaxelastic.scene.outputs import remove_temporaries
from jaxelastic.scene.run import settle_ratio

# the modules (the package re-exports functions of the same names)
build_mod = importlib.import_module("jaxelastic.scene.problem")
run_mod = importlib.import_module("jaxelastic.scene.run")

TINY = TINY_SCENE

BIG_BOX = {
    "mesh": {"generator": "box", "n": [2000, 2000, 2000]},
    "material": {"model": "neo_hookean", "E": 1e6, "nu": 0.3},
    "dirichlet": [{"nodes": {"plane": {"axis": "x", "value": 0.0}}}],
}


def _write(path, data: dict):
    path.write_text(scene_toml(data))
    return path


# ----------------------------------------------------------------------------------------
# memory
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("n", [[2000, 2000, 2000], [400, 400, 400]])
def test_a_mesh_too_large_is_refused_before_any_allocation(n, monkeypatch):
    def no_mesh(*a, **k):
        raise AssertionError("the mesh generator must not run")

    monkeypatch.setattr(build_mod, "box", no_mesh)
    scene = load_scene(apply_overrides(BIG_BOX, {"mesh.n": n}))
    t0 = time.perf_counter()
    with pytest.raises(SceneError) as e:
        build(scene)
    assert time.perf_counter() - t0 < 0.5
    msg = str(e.value)
    assert msg.startswith(f"scene '<dict>': [mesh].n = {n} needs about ")
    assert "GB of memory to build and solve" in msg and "tet4 cells" in msg
    assert "GB of memory available" in msg
    assert "[solver] max_memory_gb = " in msg and "--set solver.max_memory_gb=" in msg


def test_a_mesh_too_large_exits_2_from_the_command_line(tmp_path, capsys):
    scene = _write(tmp_path / "big.toml", apply_overrides(BIG_BOX, {"mesh.n": [400, 400, 400]}))
    out = tmp_path / "out"
    t0 = time.perf_counter()
    assert cli.main(["run", str(scene), "--out", str(out), "--no-cache"]) == 2
    assert time.perf_counter() - t0 < 1.0
    err = capsys.readouterr().err
    assert err.startswith("jaxelastic: error: scene 'big.toml': [mesh].n = [400, 400, 400] needs")
    assert "more than the" in err and "max_memory_gb" in err
    assert not out.exists()  # refused before the output directory is created


def test_max_memory_gb_is_the_budget_and_the_override():
    small = load_scene(apply_overrides(TINY, {"solver.max_memory_gb": 0.01}))
    with pytest.raises(SceneError, match=r"more than \[solver\]\.max_memory_gb = 0\.01; use a"):
        memory.check(small)
    huge = load_scene(apply_overrides(BIG_BOX, {"mesh.n": [400, 400, 400]}))
    allowed = load_scene(huge, overrides={"solver.max_memory_gb": 1e5})
    parts = memory.check(allowed)  # the override: checked against 1e5 GB, not the machine
    assert parts is not None and sum(parts.values()) > 1e12
    with pytest.raises(SceneError, match=r"\[solver\]\.max_memory_gb must be > 0"):
        load_scene(huge, overrides={"solver.max_memory_gb": 0})


def test_shipped_scenes_pass_the_memory_check():
    for name, path in shipped_scenes().items():
        scene = load_scene(path)
        parts = memory.check(scene)
        if scene.spec.mesh.generator is not None:
            assert parts is not None and sum(parts.values()) < 2e9, name


def test_memory_estimate_sizes():
    p2 = load_scene(apply_overrides(TINY, {"mesh.order": 2}))
    size = memory.mesh_size(p2)
    mesh = build(p2).mesh
    assert (size.n_nodes, size.n_cells, size.element) == (mesh.n_nodes, mesh.n_cells, "tri6")
    box = load_scene("default")
    size, mesh = memory.mesh_size(box), build(box).mesh
    assert (size.n_nodes, size.n_cells, size.element) == (mesh.n_nodes, mesh.n_cells, "tet4")
    lifted = memory.file_mesh_size(100, 300, 3, 4, 2, "standard")
    assert lifted.element == "tet10" and lifted.n_nodes == 500 and "lifted" in lifted.what
    parts = memory.estimate(box, size)
    assert list(parts) == sorted(parts, key=lambda k: -parts[k])  # largest first
    assert {"element Hessians", "Hessian scatter map", "Cholesky factor"} <= set(parts)


def test_a_mesh_file_too_large_is_refused_after_reading(tmp_path):
    r = build(load_scene(TINY)).mesh
    pts = np.column_stack([np.asarray(r.points), np.zeros(r.n_nodes)])
    meshio.write(tmp_path / "m.vtu", meshio.Mesh(pts, [("triangle", np.asarray(r.cells))]))
    data = apply_overrides(TINY, {"solver.max_memory_gb": 1e-3, "mesh.order": 2})
    data["mesh"] = {"file": "m.vtu", "order": 2}
    with pytest.raises(SceneError, match=r"\[mesh\]\.file \(lifted to P2 nodes\) needs about"):
        build(load_scene(data, base_dir=str(tmp_path)))


# ----------------------------------------------------------------------------------------
# files and directories
# ----------------------------------------------------------------------------------------


def test_a_scene_that_is_a_directory(tmp_path, capsys):
    (tmp_path / "a.toml").write_text("")
    with pytest.raises(SceneError, match=r"is a directory, not a scene file; give a scene TOML"):
        load_scene(tmp_path)
    assert cli.main(["run", str(tmp_path), "--no-cache"]) == 2
    err = capsys.readouterr().err
    assert "is a directory" in err and "a.toml" in err and "no such file" not in err


def test_a_mesh_file_that_is_a_directory(tmp_path):
    data = dict(TINY, mesh={"file": "."})
    with pytest.raises(SceneError, match=r"\[mesh\]\.file: '.*' is a directory, not a mesh file"):
        load_scene(data, base_dir=str(tmp_path))


def test_an_empty_vtu_is_named_empty(tmp_path):
    meshio.write(
        tmp_path / "e.vtu", meshio.Mesh(np.zeros((0, 3)), [("triangle", np.zeros((0, 3), int))])
    )
    data = dict(TINY, mesh={"file": "e.vtu"})
    with pytest.raises(SceneError) as e:
        build(load_scene(data, base_dir=str(tmp_path)))
    assert "[mesh].file: the mesh" in str(e.value)
    assert "is empty (0 points, 0 cells)" in str(e.value)
    assert "concatenate" not in str(e.value)


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs /proc")
def test_out_that_cannot_be_created(tmp_path, capsys):
    scene = _write(tmp_path / "tiny.toml", TINY)
    assert cli.main(["run", str(scene), "--out", "/proc/x/y", "--no-cache"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        "jaxelastic: error: --out '/proc/x/y': cannot create the output directory ('/proc' "
        "does not accept new directories: No such file or directory); choose a writable location"
    )
    (tmp_path / "file").write_text("")
    assert cli.main(["run", str(scene), "--out", str(tmp_path / "file" / "sub"), "--no-cache"]) == 2
    assert "is a file, not a directory" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------
# noise on valid input
# ----------------------------------------------------------------------------------------

FREE = {
    "name": "free",
    "mesh": {"generator": "rectangle", "n": [4, 2], "size": [2.0, 1.0]},
    "material": {"model": "neo_hookean", "E": 1000.0, "nu": 0.3, "density": 100.0},
    "integrator": {"type": "dynamic", "h": 0.01, "duration": 0.06, "settle": True},
    "output": {"png": False, "vtu": False},
}


def test_a_free_body_has_no_energy_ratio_and_no_warning(tmp_path):
    moving = apply_overrides(FREE, {"integrator.initial_velocity": [1.0, 0.5]})
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        s = run_scene(moving, tmp_path / "moving", progress=False)
        rest = run_scene(FREE, tmp_path / "rest", progress=False)
    d = s["dynamic"]
    assert d["kinetic_over_elastic"] is None and not d["settled"]  # it keeps moving
    with open(tmp_path / "moving" / "summary.json") as f:
        assert json.load(f)["dynamic"]["kinetic_over_elastic"] is None
    # at rest without load: kinetic and elastic energy both zero, settled after 5 steps
    assert rest["dynamic"]["settled"] and rest["dynamic"]["steps"] == 5


def test_settle_ratio():
    assert settle_ratio(1.0, 4.0, 5.0) == 0.25
    assert settle_ratio(125.0, 1e-28, 125.0) is None
    assert settle_ratio(125.0, 0.0, 125.0) is None
    assert settle_ratio(0.0, 0.0, 0.0) is None


@pytest.mark.parametrize(
    "expr, message",
    [
        ("x < 9 ** 9 ** 9", "9 ** 9 ** 9: overflow encountered in power"),
        ("x < 1e999", "a constant is beyond the range of float64"),
        ("x < " + "9" * 400, "(400 digits) is beyond the range of float64"),
        ("x < 1 / 0", "1 / 0: divide by zero"),
    ],
)
def test_absurd_where_arithmetic_is_refused_without_warnings(expr, message):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(SceneError) as e:
            load_scene(apply_overrides(TINY, {"dirichlet.0.nodes": {"where": expr}}))
    assert "[dirichlet][0].nodes.where: " in str(e.value) and message in str(e.value)


def test_where_floating_point_errors_at_build():
    scene = load_scene(apply_overrides(TINY, {"dirichlet.0.nodes": {"where": "sqrt(x - 1) > 0"}}))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(SceneError, match=r"invalid value encountered in sqrt"):
            build(scene)


# ----------------------------------------------------------------------------------------
# interruptions
# ----------------------------------------------------------------------------------------

LONG_DYNAMIC = apply_overrides(
    TINY,
    {
        "name": "long",
        "material.density": 100.0,
        "integrator": {"type": "dynamic", "h": 0.01, "duration": 1000.0},
        "output.png": False,
    },
)


def _start(tmp_path, data):
    scene = _write(tmp_path / "long.toml", data)
    out = tmp_path / "out"
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    cmd = [sys.executable, "-m", "jaxelastic", "run", str(scene), "--out", str(out)]
    proc = subprocess.Popen(
        [*cmd, "--no-progress", "--no-cache"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    deadline = time.monotonic() + 240
    while not (out / "dynamic_0002.vtu").exists():  # the time loop runs
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "no time step within 240 s"
        time.sleep(0.05)
    return proc, out


def _pvd_files(out):
    root = ET.parse(out / "dynamic.pvd").getroot()
    return [ds.get("file") for ds in root.iter("DataSet")]


def test_sigint_stops_a_dynamic_run_at_a_step_boundary(tmp_path):
    proc, out = _start(tmp_path, LONG_DYNAMIC)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith("jaxelastic")]
    assert len(lines) == 1 and lines[0].startswith("jaxelastic: interrupted by SIGINT after ")
    with open(out / "summary.json") as f:
        s = json.load(f)
    assert s["interrupted"] is True and s["status"] == "interrupted" and s["signal"] == "SIGINT"
    n = s["dynamic"]["steps"]
    assert n >= 2 and s["completed"].startswith(f"after {n} of 100000 time steps")
    assert len(s["dynamic"]["per_step"]["t"]) == n + 1
    files = _pvd_files(out)
    assert files == [f"dynamic_{i:04d}.vtu" for i in range(len(files))]
    assert files[-1] == f"dynamic_{n:04d}.vtu"  # the last completed step is written
    on_disk = sorted(f for f in os.listdir(out) if f.endswith(".vtu"))
    assert on_disk == files
    for name in files[-2:]:
        assert "displacement" in meshio.read(out / name).point_data
    assert not [f for f in os.listdir(out) if f.endswith(".tmp")]


def test_sigkill_leaves_only_readable_files(tmp_path):
    proc, out = _start(tmp_path, LONG_DYNAMIC)
    time.sleep(0.5)
    proc.kill()
    proc.communicate(timeout=60)
    assert proc.returncode == -signal.SIGKILL
    files = _pvd_files(out)  # the .pvd parses ...
    assert files and all((out / f).is_file() for f in files)  # ... and lists existing files
    for name in os.listdir(out):
        if name.endswith(".vtu"):
            meshio.read(out / name)
        elif name.endswith(".json"):
            json.loads((out / name).read_text())
    remove_temporaries(str(out))  # what the next run into out does first
    assert not [f for f in os.listdir(out) if f.endswith(".tmp")]


def test_sigterm_stops_a_static_run_at_a_load_increment(tmp_path, monkeypatch, capsys):
    real = run_mod.solve_incremental

    def signalled(*args, callback=None, **kw):
        def cb(s, sol):
            if signal.getsignal(signal.SIGTERM) not in (signal.SIG_DFL, None):
                os.kill(os.getpid(), signal.SIGTERM)  # handled: recorded, not fatal
            assert callback is not None
            callback(s, sol)

        return real(*args, callback=cb, **kw)

    monkeypatch.setattr(run_mod, "solve_incremental", signalled)
    data = apply_overrides(TINY, {"integrator.load_steps": 3, "output.png": False})
    scene = _write(tmp_path / "tiny.toml", data)
    out = tmp_path / "out"
    assert cli.main(["run", str(scene), "--out", str(out), "--no-cache", "--no-progress"]) == 130
    err = capsys.readouterr().err.strip()
    assert err.startswith("jaxelastic: interrupted by SIGTERM at load factor 0.3333")
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # the handlers are restored
    with open(out / "summary.json") as f:
        s = json.load(f)
    assert s["interrupted"] and s["signal"] == "SIGTERM"
    assert abs(s["static"]["load_factor"] - 1 / 3) < 1e-12
    files = [ds.get("file") for ds in ET.parse(out / "static.pvd").getroot().iter("DataSet")]
    assert files == ["static_0000.vtu"] and (out / "static_0000.vtu").is_file()
    assert not [f for f in os.listdir(out) if f.endswith(".tmp")]


def test_a_second_signal_stops_at_once():
    with handle_signals():
        os.kill(os.getpid(), signal.SIGINT)  # recorded
        with pytest.raises(Interrupted) as e:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)
    assert e.value.signame == "SIGINT"


def test_a_dynamic_scene_of_a_billion_steps_is_refused():
    data = dict(TINY, integrator={"type": "dynamic", "h": 1e-9, "duration": 1.0})
    data["material"] = dict(TINY["material"], density=1.0)
    with pytest.raises(SceneError, match=r"duration / h = 1e\+09 time steps, more than 1e\+06"):
        load_scene(data)


def test_a_probe_far_outside_the_body_is_refused():
    data = apply_overrides(TINY, {"output.probes": [[1e6, 1e6]]})
    with pytest.raises(
        SceneError, match=r"\[output\]\.probes\[0\] = \[1000000\.0, 1000000\.0\] lies"
    ):
        build(load_scene(data))
