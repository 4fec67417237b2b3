"""Time to a first result: whole processes, split into where the time goes.

Each case runs in a fresh process, twice: with an empty persistent compilation cache (a new
directory in ``$JAXELASTIC_CACHE_DIR``) and again on the cache the first run filled
("warm"). Cases (``--cases``, comma-separated):

* ``readme``: the example at the top of ``README.md`` (1,920-tet beam, one solve, one
  ``jax.grad`` through it), with the times *to the solve* and *to the gradient*;
* ``default``: ``jaxelastic run`` (the default scene);
* ``twist10``, ``twist29``: ``jaxelastic run twist --set mesh.n=[n,n,n]``;
* ``bracket``: ``jaxelastic run`` of the linear P1 L-bracket scene of
  ``scripts/bench_bracket.py`` (``--bracket-scene FILE``; skipped without it);
* ``fit``: a Mooney–Rivlin (c10, c01) fit of a small 2D specimen (``rectangle(4, 4)``,
  a uniaxial and a shear load case, synthetic targets; ``jaxelastic.fitting.fit``).

Each run is split (all in wall seconds of the child process, from its start):

* ``import``: module imports (``importlib``'s ``_find_and_load``, outermost calls only,
  compile time inside subtracted), and before it the interpreter's own start-up
  (``startup``: from the parent's spawn to the child's first line);
* ``trace``: tracing and lowering (``jax.monitoring`` events
  ``jaxpr_trace_duration`` + ``jaxpr_to_mlir_module_duration``; nested traces of inner
  ``jit``s are counted inside their outer one too, so this may overstate a little);
* ``compile``: XLA compilation (``backend_compile_duration`` less the cache loads);
* ``cache_load``: persistent-cache loads (``cache_retrieval_time_sec``);
* ``host_setup``: the host linear solvers' sparsity analysis
  (``HostLinearSolver.shared``); ``host_linear``: their factorisations and solves;
* ``outputs``: VTU/PVD, PNG, summaries and the reports of ``jaxelastic.scene.run``;
* ``solve``: the rest — device execution and Python between the compiled pieces.

The hooks are set up in the child by this script only (the library carries no timing
code). Also reported: the number of XLA compilations, persistent-cache hits, peak RSS
(``os.wait4``) and CPU time. ``--repeat N`` runs each (case, cache) pair N times,
interleaving the cases; the table shows the minimum wall time of the N runs and the split
of that run.

Usage::

    python scripts/bench_first_result.py [--cases readme,default,twist10,twist29,fit]
        [--repeat 3] [--bracket-scene bracket_linear-p1.toml] [--out out/bench/first.json]
        [--compare ../old-checkout]     # paired: each case before/after, interleaved

The ``jaxelastic`` imported by the children is the one on ``$PYTHONPATH`` (set it to
another checkout to measure that one with the same script).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CASES = ("readme", "default", "twist10", "twist29", "bracket", "fit")
BUCKETS = (
    "startup",
    "import",
    "trace",
    "compile",
    "cache_load",
    "host_setup",
    "host_linear",
    "outputs",
    "solve",
)

# ----------------------------------------------------------------------------------------
# the child
# ----------------------------------------------------------------------------------------


class _Clock:
    """Exclusive wall time per bucket: a stack of open sections; the time of a nested
    section, or of a compile event inside one, is taken out of the enclosing section."""

    def __init__(self):
        self.t = {b: 0.0 for b in BUCKETS}
        self.stack: list[list[float]] = []  # [start, child seconds]
        self.n = dict(compiles=0, cache_hits=0, traces=0)
        self.marks: dict[str, float] = {}

    def enter(self):
        self.stack.append([time.perf_counter(), 0.0])

    def leave(self, bucket: str):
        start, child = self.stack.pop()
        el = time.perf_counter() - start
        self.t[bucket] += el - child
        if self.stack:
            self.stack[-1][1] += el

    def event(self, bucket: str, seconds: float):
        self.t[bucket] += seconds
        if self.stack:
            self.stack[-1][1] += seconds


def _wrap(clock: _Clock, owner, name: str, bucket: str) -> None:
    fn = getattr(owner, name, None)
    if fn is None or getattr(fn, "_bench_wrapped", False):
        return
    is_class_method = isinstance(owner.__dict__.get(name), classmethod)
    raw = fn.__func__ if is_class_method else fn

    def wrapped(*a, **kw):
        clock.enter()
        try:
            return raw(*a, **kw)
        finally:
            clock.leave(bucket)

    wrapped._bench_wrapped = True  # type: ignore[attr-defined]
    setattr(owner, name, classmethod(wrapped) if is_class_method else wrapped)


def _install(clock: _Clock) -> None:
    """Hooks: imports, jax.monitoring events (the library and jax are not imported yet)."""
    import importlib._bootstrap as boot

    orig = boot._find_and_load
    depth = [0]

    def find_and_load(name, import_):
        if depth[0]:
            return orig(name, import_)
        depth[0] += 1
        clock.enter()
        try:
            return orig(name, import_)
        finally:
            depth[0] -= 1
            clock.leave("import")

    boot._find_and_load = find_and_load  # type: ignore[assignment]

    from jax import monitoring

    retrieval = [0.0]

    def on_duration(event: str, seconds: float, **kw) -> None:
        if event in (
            "/jax/core/compile/jaxpr_trace_duration",
            "/jax/core/compile/jaxpr_to_mlir_module_duration",
        ):
            clock.event("trace", seconds)
            clock.n["traces"] += event.endswith("trace_duration")
        elif event == "/jax/core/compile/backend_compile_duration":
            clock.n["compiles"] += 1
            load, retrieval[0] = retrieval[0], 0.0
            clock.event("cache_load", load)
            clock.event("compile", max(seconds - load, 0.0))
        elif event == "/jax/compilation_cache/cache_retrieval_time_sec":
            retrieval[0] += seconds  # inside the backend_compile_duration that follows

    def on_event(event: str, **kw) -> None:
        if event == "/jax/compilation_cache/cache_hits":
            clock.n["cache_hits"] += 1

    monitoring.register_event_duration_secs_listener(on_duration)
    monitoring.register_event_listener(on_event)


def _hook_library(clock: _Clock) -> None:
    from jaxelastic.solvers.host import assembled

    H = assembled.HostLinearSolver
    _wrap(clock, H, "shared", "host_setup")
    for name in ("factor", "factor_upper", "apply", "factor_solve", "factor_solve_upper"):
        _wrap(clock, H, name, "host_linear")
    _wrap(clock, H, "factor_cg_upper", "host_linear")
    import jaxelastic.io.vtk as vtk
    import jaxelastic.scene.run as run

    for name in (
        "write_static_vtu",
        "static_figure",
        "dynamic_figures",
        "finish_summary",
        "state_stress_fields",
        "reaction_report",
        "probe_report",
        "displacement_report",
        "elastic_energy",
        "run_header",
    ):
        _wrap(clock, run, name, "outputs")
    for name in ("write", "close"):
        _wrap(clock, vtk.TimeSeriesWriter, name, "outputs")


def _readme(clock: _Clock) -> None:
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    import jaxelastic as je
    from jaxelastic import loads

    _hook_library(clock)

    def psi(F, p):
        J = je.kinematics.det(F)
        return p.mu / 2 * (J ** (-2 / 3) * jnp.sum(F * F) - 3) + p.lam / 2 * (J - 1) ** 2

    mesh = je.box(20, 4, 4, size=(5.0, 1.0, 1.0))
    params = je.Lame.from_E_nu(1e6, 0.3)
    je.first_piola(psi)
    je.forces(psi, mesh.points, mesh, params)
    clamp = loads.fix(mesh, loads.nodes_on_plane(mesh, 0, 0.0))
    g = loads.gravity_load(mesh, density=1000.0, g=[0, 0, -9.81])
    pot = je.Potential(mesh=mesh, params=params, f_ext=jnp.asarray(g), psi=psi)
    res = je.solve(pot, clamp)
    print(je.Status(int(res.status)).name, int(res.stats["steps"]), float(res.stats["residual"]))
    clock.marks["to_solve"] = time.time()

    def tip(E):
        return je.solve(pot.replace(params=je.Lame.from_E_nu(E, 0.3)), clamp).x[:, 2].min()

    print(jax.grad(tip)(1e6))
    clock.marks["to_gradient"] = time.time()


def _fit(clock: _Clock) -> None:
    import jax
    import jax.numpy as jnp
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    import jaxelastic as je
    from jaxelastic import loads as L
    from jaxelastic.fitting import Fixed, LoadCase, Positive, fit

    _hook_library(clock)
    MR = je.materials.MooneyRivlin
    mesh = je.rectangle(4, 4, size=(1.0, 1.0))
    X = np.asarray(mesh.points)
    bottom = L.nodes_on_plane(mesh, 1, 0.0)
    origin = np.flatnonzero(np.all(np.isclose(X, 0.0), axis=1))
    top = L.facets_where(mesh, lambda c: np.isclose(c[:, 1], 1.0))
    bcs = [
        L.combine(L.fix(mesh, bottom, components=(1,)), L.fix(mesh, origin)),
        L.fix(mesh, bottom),
    ]
    fs = [jnp.asarray(L.traction_load(mesh, top, t)) for t in ((0.0, 0.6), (0.3, 0.0))]
    truth = MR(c10=0.4, c01=0.1, kappa=5.0)
    psi = je.materials.mooney_rivlin
    cases = []
    for bc, f in zip(bcs, fs, strict=True):
        pot = je.Potential(mesh=mesh, params=truth, f_ext=f, psi=psi)
        cases.append(LoadCase(pot=pot.replace(params=None), bc=bc, observed=je.solve(pot, bc).x))
    clock.marks["to_targets"] = time.time()
    res = fit(
        cases, MR(0.2, 0.3, 5.0), transforms=MR(Positive(), Positive(), Fixed()), max_iter=100
    )
    print(res.params, res.iterations, res.stop_reason)
    clock.marks["to_fit"] = time.time()


def _cli(clock: _Clock, argv: list[str]) -> None:
    from jaxelastic.cli import main

    _hook_library(clock)
    rc = main(argv)
    if rc != 0:
        raise SystemExit(f"jaxelastic {' '.join(argv)} exited with {rc}")
    clock.marks["done"] = time.time()


def _child(case: str, result: str, argv: list[str]) -> int:
    t_first = time.time()
    t0 = time.perf_counter()
    clock = _Clock()
    _install(clock)
    if case == "readme":
        _readme(clock)
    elif case == "fit":
        _fit(clock)
    else:
        _cli(clock, argv)
    wall = time.perf_counter() - t0
    spawn = float(os.environ["BENCH_SPAWN_EPOCH"])
    t = dict(clock.t)
    t["startup"] = t_first - spawn
    t["solve"] = wall - sum(v for k, v in t.items() if k not in ("startup", "solve"))
    marks = {k: v - spawn for k, v in clock.marks.items()}
    Path(result).write_text(json.dumps(dict(split=t, marks=marks, counts=clock.n)))
    sys.stdout.flush()
    os._exit(0)  # as the jaxelastic console script does: no interpreter teardown


# ----------------------------------------------------------------------------------------
# the parent
# ----------------------------------------------------------------------------------------


def _argv(case: str, out: str, bracket: str | None) -> list[str]:
    common = ["--out", out, "--no-progress"]
    if case == "default":
        return ["run", *common]
    if case.startswith("twist"):
        n = int(case[5:])
        return ["run", "twist", *common, "--set", f"mesh.n=[{n},{n},{n}]"]
    if case == "bracket":
        assert bracket is not None
        return ["run", bracket, *common]
    return []


def run_case(
    case: str, cache: str, tmp: str, bracket: str | None, pythonpath: str | None = None
) -> dict:
    """One case in a fresh child process: its split, counts, wall, CPU and peak RSS
    (``pythonpath``: the child's ``$PYTHONPATH``, default this process's)."""
    result = os.path.join(tmp, "result.json")
    out = os.path.join(tmp, f"out_{case}")
    cmd = [sys.executable, __file__, "--_child", case, result, "--", *_argv(case, out, bracket)]
    env = dict(os.environ, JAXELASTIC_CACHE_DIR=cache)
    if pythonpath is not None:
        env["PYTHONPATH"] = pythonpath
    with (
        open(os.path.join(tmp, "stdout"), "w+") as fo,
        open(os.path.join(tmp, "stderr"), "w+") as fe,
    ):
        t0 = time.perf_counter()
        env["BENCH_SPAWN_EPOCH"] = repr(time.time())
        p = subprocess.Popen(cmd, env=env, cwd=tmp, stdout=fo, stderr=fe)
        _, status, ru = os.wait4(p.pid, 0)
        wall = time.perf_counter() - t0
        p.returncode = os.waitstatus_to_exitcode(status)
        fo.seek(0)
        fe.seek(0)
        out_s, err_s = fo.read(), fe.read()
    if p.returncode != 0:
        raise RuntimeError(f"{case} failed ({p.returncode}):\n{out_s}\n{err_s[-3000:]}")
    r = json.loads(Path(result).read_text())
    r.update(
        case=case,
        wall_s=wall,
        cpu_s=ru.ru_utime + ru.ru_stime,
        peak_rss_mb=ru.ru_maxrss / 1024,
        stdout=out_s[-400:],
    )
    return r


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--_child"]:
        case, result, _, *rest = argv[1:]
        return _child(case, result, rest)
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--cases", default="readme,default,twist10,twist29,fit")
    p.add_argument("--repeat", type=int, default=1)
    p.add_argument("--bracket-scene", default=None)
    p.add_argument("--out", default=str(ROOT / "out" / "bench" / "first_result.json"))
    p.add_argument("--label", default="", help="a label stored in the JSON (e.g. the commit)")
    p.add_argument(
        "--compare",
        default=None,
        metavar="PATH",
        help="also run every case with PYTHONPATH=PATH (another checkout, label 'before'), "
        "interleaved with the current one (label 'after'): paired figures from one run",
    )
    a = p.parse_args(argv)
    cases = [c for c in a.cases.split(",") if c]
    for c in cases:
        if c not in CASES and not (c.startswith("twist") and c[5:].isdigit()):
            p.error(f"unknown case {c!r} (one of {', '.join(CASES)})")
    if "bracket" in cases and not a.bracket_scene:
        print("bracket: no --bracket-scene, skipped", file=sys.stderr)
        cases.remove("bracket")
    bracket = os.path.abspath(a.bracket_scene) if a.bracket_scene else None
    runs: dict[tuple[str, str], list[dict]] = {}
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="bench_first_") as tmp:
        variants = [("after", None)]
        if a.compare:
            variants.insert(0, ("before", os.path.abspath(a.compare)))
        for i in range(a.repeat):
            for case in cases:
                order = variants if i % 2 == 0 else variants[::-1]
                for label, path in order:
                    cache = os.path.join(tmp, f"cache_{case}_{label}_{i}")
                    shutil.rmtree(cache, ignore_errors=True)
                    for setting in ("empty", "warm"):
                        r = run_case(case, cache, tmp, bracket, path)
                        key = (case, setting if not a.compare else f"{setting} {label}")
                        runs.setdefault(key, []).append(r)
                        _progress(key, i, r)
    rows = []
    for (case, setting), rs in runs.items():
        best = min(rs, key=lambda r: r["wall_s"])
        rows.append(
            dict(
                case=case,
                setting=setting,
                wall_s_min=best["wall_s"],
                wall_s_all=[round(r["wall_s"], 2) for r in rs],
                cpu_s_min=min(r["cpu_s"] for r in rs),
                split=best["split"],
                marks=best["marks"],
                counts=best["counts"],
                peak_rss_mb=max(r["peak_rss_mb"] for r in rs),
            )
        )
    _print(rows)
    result = dict(
        machine=f"{os.cpu_count()} cores, {platform.platform()}, "
        f"python {platform.python_version()}",
        date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        load_average=[load0, os.getloadavg()],
        label=a.label,
        pythonpath=os.environ.get("PYTHONPATH", ""),
        rows=rows,
    )
    os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
    Path(a.out).write_text(json.dumps(result, indent=1))
    print(f"wrote {a.out} (load average {load0[0]:.1f} -> {os.getloadavg()[0]:.1f})")
    return 0


def _progress(key: tuple[str, str], i: int, r: dict) -> None:
    print(
        f"  {key[0]:8s} {key[1]:12s} run {i + 1}: {r['wall_s']:6.2f} s wall, "
        f"{r['cpu_s']:6.2f} s CPU, {r['counts']['compiles']} compilations, "
        f"{r['counts']['cache_hits']} cache hits",
        flush=True,
    )


def _print(rows: list[dict]) -> None:
    head = ["wall", *BUCKETS, "XLA n", "hits", "RSS MB"]
    print(f"\n{'case':8s} {'cache':12s} " + " ".join(f"{h:>8s}" for h in head))
    for r in rows:
        s = r["split"]
        cells = [f"{r['wall_s_min']:8.2f}", *(f"{s[b]:8.2f}" for b in BUCKETS)]
        cells += [f"{r['counts']['compiles']:8d}", f"{r['counts']['cache_hits']:8d}"]
        cells.append(f"{r['peak_rss_mb']:8.0f}")
        print(f"{r['case']:8s} {r['setting']:12s} " + " ".join(cells))
        if r["marks"]:
            print(f"{'':22s}" + ", ".join(f"{k} {v:.2f} s" for k, v in r["marks"].items()))


if __name__ == "__main__":
    sys.exit(main())
