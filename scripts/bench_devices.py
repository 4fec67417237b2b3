"""Device benchmark: the neo-Hookean twist at growing size on whatever devices JAX sees.

The JAX-FEM twist (:func:`jaxelastic.verification.twist`: unit cube ``box(n, n, n)``,
6n³ P1 tets, 3(n+1)³ dofs, face x = 1 clamped, face x = 0 turned by 30°, isochoric
neo-Hookean) solved by Newton with the device linear solver (``--linear``: the device
multigrid ``multilevel`` when the library has it, else ``cg``), in float32 and float64
(``--precisions``; float32 meshes with x64 enabled, so only the scene is float32).

Each (n, precision) runs in a fresh subprocess (its own peak device memory and RSS; an
out-of-memory run loses only itself) with everything passed to ``jit`` as arguments and
the solver bound outside jit. Reported per run: setup time (mesh + solver binding, host),
compile time (``jit(...).lower(...).compile()``), the first (cold, compiled) solve and the
min of ``--repeat`` warm solves, Newton steps and linear iterations, warm time per Newton
iteration, status and final residual, peak device memory (``device.memory_stats()``:
``peak_bytes_in_use``, where the backend has it; CPU has not) and peak RSS.

Runs go precision by precision (float32 first: the ≈ 1M-dof target is float32), sizes
growing (default n = 10, 30, 50, 69: 4k, 89k, 398k and 1.03M dofs) until ``--max-dofs``
or until the predicted time of the next run (:func:`_predict`) would not fit in what is
left of ``--budget-s``; each subprocess is also killed at the remaining budget. A run
whose cold solve takes over 10 s is timed warm once instead of ``--repeat`` times.

Usage::

    python scripts/bench_devices.py                                  # GPU run, ≤ 1.1M dofs
    python scripts/bench_devices.py --max-dofs 5000 --budget-s 300   # CPU smoke run
    python scripts/bench_devices.py --sizes 10,20 --precisions float32 --out out/bench/dev.json
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

DEFAULT_SIZES = "10,30,50,69"


def dofs(n: int) -> int:
    """Dofs of the P1 twist on ``box(n, n, n)``: 3(n+1)³."""
    return 3 * (n + 1) ** 3


def _peak_device_bytes(device) -> int | None:
    try:
        stats = device.memory_stats()
    except Exception:  # noqa: BLE001 — backends without allocator statistics
        return None
    if not stats:
        return None
    return int(stats.get("peak_bytes_in_use", stats.get("bytes_in_use", 0)))


def child(n: int, precision: str, linear: str, repeat: int, rtol: float) -> dict:
    """One (n, precision) run, in this process; returns its record."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import verification as benchmarks

    dtype = jnp.float32 if precision == "float32" else jnp.float64
    if linear == "auto-device":
        linear = "multilevel" if hasattr(je, "Multilevel") else "cg"
    t0 = time.perf_counter()
    b = benchmarks.twist(n, dtype=dtype)
    params = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), b.pot.params)
    pot = b.pot.replace(params=params)  # the benchmark's constants are float64
    t_mesh = time.perf_counter() - t0
    t0 = time.perf_counter()
    solver = je.solvers.prepare_solver(je.Newton(rtol=rtol, linear=linear), b.mesh, b.bc)
    t_bind = time.perf_counter() - t0
    dev = jax.devices()[0]
    pot, bc = jax.device_put((pot, b.bc), dev)

    def solve(pot, bc):
        r = je.solve(pot, bc, solver=solver, throw=False)
        return r.x, r.status, r.stats

    t0 = time.perf_counter()
    compiled = jax.jit(solve).lower(pot, bc).compile()
    t_compile = time.perf_counter() - t0
    t0 = time.perf_counter()
    x, status, stats = jax.block_until_ready(compiled(pot, bc))
    t_cold = time.perf_counter() - t0
    warm = []
    for _ in range(repeat if t_cold < 10.0 else 1):  # big runs: one warm solve
        t0 = time.perf_counter()
        x, status, stats = jax.block_until_ready(compiled(pot, bc))
        warm.append(time.perf_counter() - t0)
    steps = int(stats["steps"])
    t_warm = min(warm)
    return dict(
        n=n,
        dofs=int(b.mesh.n_dofs),
        tets=int(b.mesh.n_cells),
        precision=precision,
        linear=linear,
        rtol=rtol,
        status=je.Status(int(status)).name,
        newton_steps=steps,
        linear_iterations=int(stats["linear_iterations"]),
        residual=float(stats["residual"]),
        residual_floor=float(stats.get("residual_floor", float("nan"))),
        mesh_s=t_mesh,
        bind_s=t_bind,
        compile_s=t_compile,
        cold_s=t_cold,
        warm_s=t_warm,
        per_newton_s=t_warm / max(steps, 1),
        peak_device_mb=(lambda v: None if v is None else v / 2**20)(_peak_device_bytes(dev)),
        rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        backend=jax.default_backend(),
        device=str(dev),
        device_kind=getattr(dev, "device_kind", ""),
        jax=jax.__version__,
    )


def _predict(row: dict, n: int) -> float:
    """Predicted wall time [s] of the run at ``n`` from an earlier ``row``: start-up and
    compilation as before, the size-dependent parts (mesh, binding, solves) scaled by the
    dof ratio to the power 1.2 (iteration counts grow slowly with n)."""
    scaled = row["mesh_s"] + row["bind_s"] + row["cold_s"] + 3 * row["warm_s"]
    fixed = max(row["wall_s"] - scaled, 0.0)
    return fixed + scaled * (dofs(n) / row["dofs"]) ** 1.2


def _table(rows: list[dict]) -> str:
    head = (
        f"{'n':>3} {'dofs':>9} {'prec':>7} {'linear':>10} {'status':>18} {'newton':>6} "
        f"{'lin its':>7} {'compile s':>9} {'warm s':>8} {'s/newton':>8} {'dev MiB':>8} "
        f"{'RSS MiB':>8}"
    )
    out = [head]
    for r in rows:
        if "error" in r:
            out.append(f"{r['n']:>3} {dofs(r['n']):>9} {r['precision']:>7} {'':>10} {r['error']}")
            continue
        dev = "-" if r["peak_device_mb"] is None else f"{r['peak_device_mb']:.0f}"
        out.append(
            f"{r['n']:>3} {r['dofs']:>9} {r['precision']:>7} {r['linear']:>10} "
            f"{r['status']:>18} {r['newton_steps']:>6} {r['linear_iterations']:>7} "
            f"{r['compile_s']:>9.1f} {r['warm_s']:>8.3f} {r['per_newton_s']:>8.3f} "
            f"{dev:>8} {r['rss_mb']:>8.0f}"
        )
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default=DEFAULT_SIZES, help="twist n values (box(n, n, n))")
    ap.add_argument("--max-dofs", type=int, default=1_100_000)
    ap.add_argument("--precisions", default="float32,float64")
    ap.add_argument("--linear", default="auto-device", help="multilevel, cg (default: best)")
    ap.add_argument("--budget-s", type=float, default=420.0, help="wall-clock budget, all runs")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--rtol64", type=float, default=1e-8)
    ap.add_argument("--rtol32", type=float, default=1e-5)
    ap.add_argument("--out", default="out/bench/devices.json")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.child:  # n,precision: one run, JSON on the last stdout line
        n, precision = args.child.split(",")
        rtol = args.rtol32 if precision == "float32" else args.rtol64
        print(json.dumps(child(int(n), precision, args.linear, args.repeat, rtol)))
        return 0

    start = time.perf_counter()
    sizes = [int(s) for s in args.sizes.split(",") if s and dofs(int(s)) <= args.max_dofs]
    precisions = [p for p in args.precisions.split(",") if p]
    rows: list[dict] = []
    last: dict[str, dict] = {}  # precision -> its last successful run
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    for prec in precisions:  # float32 first by default: the ~1M-dof target is float32
        for n in sizes:
            left = args.budget_s - (time.perf_counter() - start)
            if prec in last:
                guess = _predict(last[prec], n)
                if guess > left:
                    print(f"skip n={n} {prec}: predicted {guess:.0f} s > {left:.0f} s left")
                    continue
            if left < 5:
                print(f"skip n={n} {prec}: budget spent")
                continue
            cmd = [sys.executable, __file__, "--child", f"{n},{prec}", "--linear", args.linear]
            cmd += ["--repeat", str(args.repeat), "--rtol64", str(args.rtol64)]
            cmd += ["--rtol32", str(args.rtol32)]
            t0 = time.perf_counter()
            try:
                p = subprocess.run(cmd, capture_output=True, text=True, timeout=left, env=env)
                wall = time.perf_counter() - t0
                if p.returncode != 0:
                    lines = (p.stderr or p.stdout).strip().splitlines() or ["?"]
                    errs = [s for s in lines if "Error" in s and not s.startswith(" ")]
                    tail = (errs or lines)[-1][:300]
                    row = dict(n=n, precision=prec, error=f"exit {p.returncode}: {tail}")
                else:
                    row = json.loads(p.stdout.strip().splitlines()[-1])
                    row["wall_s"] = wall
                    last[prec] = row
            except subprocess.TimeoutExpired:
                wall = time.perf_counter() - t0
                row = dict(n=n, precision=prec, error=f"killed at the budget after {wall:.0f} s")
            rows.append(row)
            print(_table([row]).splitlines()[-1], flush=True)
    res = dict(
        budget_s=args.budget_s,
        elapsed_s=time.perf_counter() - start,
        max_dofs=args.max_dofs,
        runs=rows,
    )
    print()
    print(_table(rows))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    from jaxelastic.io import write_json  # atomic; imported late: the parent runs no JAX

    write_json(out, res)
    print(f"wrote {out} ({res['elapsed_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
