"""Compilation: the persistent cache makes a second CLI run faster, and a dynamic scene
compiles its Newton solve once for the time steps and the static comparison.

Measured (``scripts/bench_compile.py``; the small scene below, 2 cores, loaded machine):
first run 10.5 s CPU, second run with the cache 5.1 s CPU (22 cache entries, 22 hits). The
test asks for a second run at most 80 % of the first (CPU time of the child process,
steadier than wall time on a shared machine).
"""

import functools
import os
import re
import subprocess
import sys
from collections import Counter

import jax
import pytest

# the default scene, small and short: compile time dominates the run
SMALL = [
    "--set",
    "mesh.n=[4,1,1]",
    "--set",
    "integrator.duration=0.1",
    "--set",
    "output.png=false",
    "--set",
    "output.vtu=false",
]

# the compiled pieces of the Newton solve (the Python loop of
# jaxelastic.solvers.newton.minimize) and of the time step (jaxelastic.dynamics.simulate)
# that the cache must hold
NEWTON = ("_loop_start", "_loop_prepare", "_loop_finish")
STEP = ("_prepare_step", "_finish_step")


def _run_timed(out, cache_dir) -> tuple[float, str]:
    """Run ``jaxelastic run`` on the small scene: ``(CPU seconds of the child, stderr)``."""
    env = dict(os.environ, JAXELASTIC_CACHE_DIR=str(cache_dir), JAX_LOG_COMPILES="1")
    cmd = [sys.executable, "-m", "jaxelastic", "run", "--out", str(out), "--no-progress", *SMALL]
    p = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    assert p.stderr is not None
    stderr = p.stderr.read()  # the child's stderr until it exits
    _, status, ru = os.wait4(p.pid, 0)
    p.returncode = os.waitstatus_to_exitcode(status)
    assert p.returncode == 0, stderr[-3000:]
    return ru.ru_utime + ru.ru_stime, stderr


def _hits(stderr: str) -> set[str]:
    return set(re.findall(r"Persistent compilation cache hit for 'jit_(\w+)'", stderr))


def test_second_cli_run_hits_the_cache_and_is_faster(tmp_path):
    cache = tmp_path / "cache"
    cpu1, err1 = _run_timed(tmp_path / "a", cache)
    entries = sorted(os.listdir(cache))
    assert entries, "the first run wrote no persistent cache entry"
    for name in NEWTON + STEP:
        assert any(e.startswith(f"jit_{name}-") for e in entries), (name, entries)
    assert not _hits(err1)  # a fresh cache directory
    cpu2, err2 = _run_timed(tmp_path / "b", cache)
    hits = _hits(err2)
    assert set(NEWTON + STEP) <= hits, hits
    # what is left on the second run is import, tracing, the cache loads and the run
    # itself: no piece of the default scene's Newton loop holds a host callback
    assert cpu2 < 0.8 * cpu1, (cpu1, cpu2)


@pytest.mark.extended
def test_dynamic_scene_compiles_one_newton_solve(tmp_path):
    """The time steps and the static comparison of the default scene (small) share one
    compilation of each Newton piece: the static potential has the step potential's pytree
    structure and dtypes (jaxelastic.dynamics.static_potential)."""
    from jax import monitoring

    from jaxelastic.scene import load_scene, run_scene

    compiles: Counter = Counter()

    def listen(event, duration, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles[str(kw.get("fun_name", ""))] += 1

    overrides = {
        "mesh.n": [4, 1, 1],
        "integrator.duration": 0.1,
        "output.png": False,
        "output.vtu": False,
    }
    scene = load_scene("default", overrides=overrides)
    jax.clear_caches()  # count this run's compilations only
    monitoring.register_event_duration_secs_listener(listen)
    # (without the test session's persistent cache: a hit there is no compilation)
    jax.config.update("jax_enable_compilation_cache", False)
    try:
        summary = run_scene(scene, tmp_path / "out", progress=False)
    finally:
        jax.config.update("jax_enable_compilation_cache", True)
        monitoring.unregister_event_duration_listener(listen)
    assert summary["status"] == "ok" and "comparison" in summary
    assert summary["dynamic"]["steps"] == 5
    for name in NEWTON + STEP:
        assert compiles[f"jit({name})"] == 1, (name, dict(compiles))


def test_solve_and_gradient_compile_each_piece_once():
    """The README pattern on a small beam: the plain solve compiles each Newton piece once;
    a solve at a new load or parameter value compiles nothing; the eager gradient reuses
    the solve's pieces and adds two small ones that hold no host callback (so the
    persistent cache keeps them: never the traced adjoint ``_cotangents``); a second
    gradient compiles nothing; ``je.forces`` outside jit is one program. Counted with
    ``jax.monitoring`` (each compilation or persistent-cache load is one event), so the
    test does not depend on the machine's load."""
    import jax.numpy as jnp
    from jax import monitoring

    import jaxelastic as je
    from jaxelastic import loads

    events: list[str] = []

    def listen(event, duration, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            events.append(str(kw.get("fun_name", "")))

    mesh = je.rectangle(4, 1, size=(2.0, 0.5))  # 2D: the same pieces, compiled faster
    clamp = loads.fix(mesh, loads.nodes_on_plane(mesh, 0, 0.0))
    g = jnp.asarray(loads.gravity_load(mesh, density=1000.0, g=[0, -9.81]))
    psi = je.materials.neo_hookean
    lame = functools.partial(je.Lame.from_E_nu, dim=2)
    pot = je.Potential(mesh=mesh, params=lame(1e6, 0.3), f_ext=g, psi=psi)
    params2 = lame(2e6, 0.3)
    jax.clear_caches()
    monitoring.register_event_duration_secs_listener(listen)
    try:
        je.forces(psi, mesh.points, mesh, pot.params)
        forces = list(events)
        je.solve(pot, clamp)
        first = list(events)
        je.solve(pot.replace(f_ext=2.0 * g, params=params2), clamp)
        second = events[len(first) :]

        def tip(E):
            p = lame(E, jnp.asarray(0.3))
            return je.solve(pot.replace(params=p), clamp).x[:, 1].min()

        grad = jax.grad(tip)
        grad(jnp.asarray(1e6))
        n_grad = len(events)
        grad(jnp.asarray(3e6))
        regrad = events[n_grad:]
        in_grad = Counter(events[len(first) : n_grad])
    finally:
        monitoring.unregister_event_duration_listener(listen)
    assert forces == ["jit(_nodal_forces)"], forces
    counts = Counter(first)
    for name in (*NEWTON, "_upper"):
        assert counts[f"jit({name})"] == 1, (name, counts)
    assert not [e for e in second if e.startswith("jit(_")], second
    assert not [e for e in regrad if e.startswith("jit(_")], regrad
    for name in (*NEWTON, "_upper", "_cotangents"):
        assert in_grad[f"jit({name})"] == 0, (name, in_grad)
    assert in_grad["jit(_exact_upper)"] == 1 and in_grad["jit(_host_pullback)"] == 1, in_grad


def test_fit_objective_compiles_once_and_holds_no_host_callback():
    """A load-path fit of a small specimen: the compiled loss and gradient holds no host
    callback (``linear="auto"`` is device CG there, jaxelastic.fitting.fit_linear), so JAX's
    persistent cache keeps it; a second evaluation at new parameter values, from the first
    one's solutions, compiles nothing; and its gradient matches central differences."""
    import jax.numpy as jnp
    import numpy as np
    from jax import monitoring

    import jaxelastic as je
    from jaxelastic import fitting as F
    from jaxelastic import loads
    from jaxelastic.fitting import objective as O

    mesh = je.rectangle(2, 1, size=(2.0, 1.0))
    left, right = loads.nodes_on_plane(mesh, 0, 0.0), loads.nodes_on_plane(mesh, 0, 2.0)
    bc = loads.combine(loads.fix(mesh, left), loads.fix(mesh, right, displacement=[0.2, 0.0]))
    pot = je.Potential(mesh, je.Lame.from_E_nu(100.0, 0.3, dim=2), psi=je.materials.neo_hookean)
    e = jnp.asarray([1.0, 0.0])
    obs = (F.Reaction(jnp.asarray(right), e, jnp.asarray([3.0, 6.0]), 1.0),)
    case = F.LoadPathCase(pot, bc, [0.5, 1.0], obs)
    obj = F.make_objective([case], F.Material(80.0, 0.25))
    assert obj.solvers[0].linear.kind == "cg"
    warms = obj.initial_warms()
    args = (obj.z0, obj.pz, obj.cases, warms, obj.solvers, obj.adjoint)
    assert "callback" not in O._value_and_grad.lower(*args).as_text()
    events: list[str] = []

    def listen(event, duration, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            events.append(str(kw.get("fun_name", "")))

    z1 = obj.z0 + jnp.asarray([0.05, -0.02])
    monitoring.register_event_duration_secs_listener(listen)
    try:
        (f0, auxs), _ = obj.value_and_grad(obj.z0, warms)
        n_first = len(events)
        warm1 = tuple(a.warm for a in auxs)
        (f1, _), g1 = obj.value_and_grad(z1, warm1)
        again = events[n_first:]
    finally:
        monitoring.unregister_event_duration_listener(listen)
    assert not again, again
    assert float(f1) != float(f0)
    h = 1e-5
    for j in range(2):
        dz = jnp.zeros(2).at[j].set(h)
        fp = float(obj.value_and_grad(z1 + dz, warm1, check=False)[0][0])
        fm = float(obj.value_and_grad(z1 - dz, warm1, check=False)[0][0])
        np.testing.assert_allclose(float(g1[j]), (fp - fm) / (2 * h), rtol=1e-5)


_DEFAULT_CACHE_CHILD = """
import os, sys, jax
jax.config.update("jax_enable_x64", True)
import jaxelastic as je
assert jax.config.jax_compilation_cache_dir is None, "set at import"
je.rectangle(2, 1)  # the first mesh: the library's default cache, before any compile
print(jax.config.jax_compilation_cache_dir, jax.config.jax_compilation_cache_max_size)
"""


@pytest.mark.parametrize("switch", ["", "0"])
def test_library_enables_the_default_cache_lazily(tmp_path, switch):
    """A fresh process: nothing at import; the first mesh enables JAX's persistent cache
    in $JAXELASTIC_CACHE_DIR without JAX's size limit (whose eviction scan reads every
    entry at every write; the library prunes once per process instead);
    JAXELASTIC_CACHE=0 leaves it off; a cache the user configured (as this test session
    does) is kept."""
    from jaxelastic.cache import ensure_persistent_cache

    assert ensure_persistent_cache() is None  # the session's own cache stays
    env = dict(os.environ, JAXELASTIC_CACHE_DIR=str(tmp_path / "c"), JAXELASTIC_CACHE=switch)
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    p = subprocess.run(
        [sys.executable, "-c", _DEFAULT_CACHE_CHILD], env=env, capture_output=True, text=True
    )
    assert p.returncode == 0, p.stderr[-2000:]
    path, size = p.stdout.split()
    if switch == "0":
        assert path == "None"
    else:
        assert path == str(tmp_path / "c") and int(size) == -1  # JAX: no size limit
        assert os.path.isdir(path)


def test_prune_keeps_the_most_recently_written_entries(tmp_path):
    """The cache is pruned to its size limit by deleting the least recently written
    entries (with their access-time files); other files stay; a missing directory is
    nothing to prune."""
    from jaxelastic.cache import prune_cache

    for i in range(6):
        (tmp_path / f"k{i}-cache").write_bytes(b"x" * 100)
        (tmp_path / f"k{i}-atime").write_bytes(b"t")
        os.utime(tmp_path / f"k{i}-cache", ns=(10**18 + i * 10**9, 10**18 + i * 10**9))
    (tmp_path / "other").write_bytes(b"y" * 1000)
    assert prune_cache(str(tmp_path), 350) == 3
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == ["k3-atime", "k3-cache", "k4-atime", "k4-cache", "k5-atime", "k5-cache", "other"]
    assert prune_cache(str(tmp_path), 10**6) == 0
    assert prune_cache(str(tmp_path / "missing"), 0) == 0


def test_sparsity_pattern_kept_on_disk(tmp_path, monkeypatch):
    """Large meshes keep their host sparsity pattern next to the persistent cache: a
    second build loads the same arrays (the twist n = 29 analysis took 4.3 s, its load
    0.5 s); a corrupt file is built again; at most DISK_KEEP files are kept."""
    import dataclasses

    import numpy as np

    import jaxelastic as je
    from jaxelastic.solvers.host import pattern as P

    monkeypatch.setattr(P, "DISK_MIN_SLOTS", 0)
    monkeypatch.setattr(P, "DISK_KEEP", 2)
    monkeypatch.setattr(P, "_disk_folder", lambda: str(tmp_path))
    builds = []
    build = P.SparsityPattern.build
    monkeypatch.setattr(
        P.SparsityPattern, "build", classmethod(lambda cls, *a: builds.append(1) or build(*a))
    )
    mesh = je.box(3, 2, 2)
    cells, n = np.asarray(mesh.cells), mesh.points.shape[0]
    fixed = np.zeros(n * 3, bool)
    fixed[:6] = True
    a = P.SparsityPattern.build_cached(cells, n, 3, fixed)
    b = P.SparsityPattern.build_cached(cells, n, 3, fixed)
    assert len(builds) == 1
    for f in dataclasses.fields(a):
        assert np.array_equal(getattr(a, f.name), getattr(b, f.name)), f.name
    (path,) = tmp_path.glob("*.npz")
    path.write_bytes(b"broken")
    P.SparsityPattern.build_cached(cells, n, 3, fixed)
    assert len(builds) == 2
    for k in range(3):
        fixed[6 + k] = True
        P.SparsityPattern.build_cached(cells, n, 3, fixed)
    assert len(list(tmp_path.glob("*.npz"))) == 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__, "-q", "-n", "0"]))
