"""Device multigrid vs host AMG vs block-Jacobi CG on the neo-Hookean twist.

Twist (:func:`jaxelastic.benchmarks.twist`): unit cube ``box(n, n, n)`` (6n³ tets, 3(n+1)³
dofs; n = 19 ≈ 24k dofs, n = 29 ≈ 81k dofs), Newton to a relative residual of 1e-8. Each
(n, linear solver) runs in a fresh subprocess, so its peak RSS and its compile are its own.

Solvers: ``amg`` (``je.AMG()``: PyAMG smoothed aggregation on the host through a callback,
one V-cycle per CG iteration), ``multilevel`` (``je.Multilevel()``: aggregation multigrid
on the device, no callback), ``multilevel-sa`` (``je.Multilevel(smooth=True, degree=3)``:
smoothed aggregation on the device) and ``cg`` (``je.CG()``: block-Jacobi PCG).

Reported per run: Newton steps, total linear (CG) iterations, setup seconds (binding the
linear solver: pattern analysis / hierarchy construction on the host), cold seconds (first
solve: tracing, compilation and the solve), warm seconds (min over ``--repeat`` further
solves), compile seconds (cold − warm), peak RSS, and the ratios to ``amg`` measured in
the same run.

Usage::

    python scripts/bench_multilevel.py                         # n = 19, 29; amg, multilevel, cg
    python scripts/bench_multilevel.py --sizes 10 --solvers amg,multilevel --repeat 1
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

SOLVERS = ("amg", "multilevel", "multilevel-sa", "cg")


def _linear(name: str):
    import jaxelastic as je

    return {
        "amg": lambda: je.AMG(),
        "multilevel": lambda: je.Multilevel(),
        "multilevel-sa": lambda: je.Multilevel(smooth=True, degree=3),
        "cg": lambda: je.CG(),
    }[name]()


def worker(n: int, solver: str, repeat: int) -> dict:
    """One (size, solver) run in this process."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxelastic as je
    from jaxelastic import benchmarks

    b = benchmarks.twist(n)
    mesh, pot, bc = b.mesh, b.pot, b.bc
    t0 = time.perf_counter()
    linear = je.solvers.bind_linear(_linear(solver), mesh, bc)
    setup = time.perf_counter() - t0
    newton = je.Newton(rtol=1e-8, max_steps=50, linear=linear)
    t0 = time.perf_counter()
    je.solve(pot, bc, solver=newton, throw=False)
    cold = time.perf_counter() - t0
    warm, res = float("inf"), None
    for _ in range(max(1, repeat)):
        t0 = time.perf_counter()
        res = je.solve(pot, bc, solver=newton, throw=False)
        warm = min(warm, time.perf_counter() - t0)
    assert res is not None
    steps = int(res.stats["steps"])
    levels = None
    if isinstance(linear, je.Multilevel) and linear.hierarchy is not None:
        levels = linear.hierarchy.describe()
    return dict(
        n=n,
        dofs=int(mesh.n_dofs),
        tets=int(mesh.n_cells),
        solver=solver,
        status=int(res.status),
        newton=steps,
        linear_its=int(res.stats["linear_iterations"]),
        linear_history=[int(i) for i in res.stats["linear_history"][:steps]],
        setup_s=setup,
        cold_s=cold,
        warm_s=warm,
        compile_s=max(cold - warm, 0.0),
        peak_rss_mib=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        levels=levels,
    )


def _run_subprocess(n: int, solver: str, repeat: int, timeout: float) -> dict:
    cmd = [sys.executable, __file__, "--worker", str(n), solver, "--repeat", str(repeat)]
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=False)
    except subprocess.TimeoutExpired:
        return dict(n=n, solver=solver, error=f"timeout after {timeout:.0f} s")
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
    if out.returncode != 0 or not lines:
        return dict(n=n, solver=solver, error=out.stderr.strip().splitlines()[-1:])
    return json.loads(lines[-1])


def _table(rows: list[dict]) -> str:
    head = (
        f"{'n':>3} {'dofs':>7} {'solver':>14} {'newton':>6} {'lin its':>7} {'its/amg':>7} "
        f"{'setup s':>7} {'compile s':>9} {'warm s':>7} {'warm/amg':>8} {'RSS MiB':>8}"
    )
    lines = [head, "-" * len(head)]
    amg = {r["n"]: r for r in rows if r.get("solver") == "amg" and "error" not in r}
    for r in rows:
        if "error" in r:
            lines.append(f"{r['n']:>3} {'':>7} {r['solver']:>14}  error: {r['error']}")
            continue
        ref = amg.get(r["n"])
        ri = f"{r['linear_its'] / ref['linear_its']:.2f}" if ref else "-"
        rt = f"{r['warm_s'] / ref['warm_s']:.2f}" if ref else "-"
        lines.append(
            f"{r['n']:>3} {r['dofs']:>7} {r['solver']:>14} {r['newton']:>6} "
            f"{r['linear_its']:>7} {ri:>7} {r['setup_s']:>7.2f} {r['compile_s']:>9.1f} "
            f"{r['warm_s']:>7.2f} {rt:>8} {r['peak_rss_mib']:>8.0f}"
        )
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="19,29", help="comma-separated twist sizes n")
    ap.add_argument("--solvers", default="amg,multilevel,cg", help=f"subset of {SOLVERS}")
    ap.add_argument("--repeat", type=int, default=3, help="warm solves (the minimum is kept)")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per run")
    ap.add_argument("--out", default="out/bench/multilevel.json", help="JSON output path")
    ap.add_argument("--worker", nargs=2, metavar=("N", "SOLVER"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(int(args.worker[0]), args.worker[1], args.repeat)))
        return
    solvers = [s for s in args.solvers.split(",") if s]
    bad = [s for s in solvers if s not in SOLVERS]
    if bad:
        ap.error(f"unknown solver(s) {bad}; choose from {SOLVERS}")
    rows = []
    for n in (int(s) for s in args.sizes.split(",") if s):
        for s in solvers:
            rows.append(_run_subprocess(n, s, args.repeat, args.timeout))
            print(json.dumps(rows[-1]), flush=True)
    print(_table(rows))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    from jaxelastic.io import write_json  # atomic; imported late: the parent runs no JAX

    write_json(out, dict(benchmark="twist", rtol=1e-8, runs=rows), indent=2)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
