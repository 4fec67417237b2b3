"""Device multigrid vs host AMG vs block-Jacobi CG on the neo-Hookean twist.

Twist (:func:`jaxelastic.verification.twist`): unit cube ``box(n, n, n)`` (6n³ tets, 3(n+1)³
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

Sharded (``--devices 1,4``): for a device count D > 1 the run gets D host CPU devices
(``XLA_FLAGS=--xla_force_host_platform_device_count=D``), shards the twist with
``je.shard(pot, bc, devices=D)`` and solves the sharded problem (``multilevel`` and ``cg``;
the host ``amg`` refuses sharded problems and is skipped). It also reports the difference
of its answer from the first device count's run of the same solver (max |Δx| / max |u|),
and the bytes one CG iteration moves between devices, read from the compiled HLO (per
device: the buffers of its collective-permutes and all-reduces): the multigrid application
(``M``), the Newton operator's product (``A``) and CG's three scalar reductions, against
one all-reduce of the whole node vector (``/repl``: what XLA's replicated layout moves
per product).

Usage::

    python scripts/bench_multilevel.py                         # n = 19, 29; amg, multilevel, cg
    python scripts/bench_multilevel.py --sizes 10 --solvers amg,multilevel --repeat 1
    python scripts/bench_multilevel.py --sizes 10,29 --solvers multilevel,cg --devices 1,4
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
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


_ITEMSIZE = dict(f64=8, f32=4, s32=4, u32=4, s64=8, pred=1)


def collective_bytes(fn, *args) -> dict:
    """``{op: (count, per-device bytes)}`` of the collectives in ``jit(fn)``'s compiled HLO."""
    import jax

    text = jax.jit(fn).lower(*args).compile().as_text()
    out: dict = {}
    pat = r"= \(?((?:[a-z0-9]+\[[0-9,]*\]\S*(?:, )?)+)\)? "
    pat += r"(all-reduce|collective-permute|all-gather|all-to-all|reduce-scatter)(?:-start)?\("
    for m in re.finditer(pat, text):
        size = 0
        for t, dims in re.findall(r"([a-z0-9]+)\[([0-9,]*)\]", m.group(1)):
            count = 1
            for x in dims.split(","):
                count *= int(x) if x else 1
            size += count * _ITEMSIZE.get(t, 8)
        c, b = out.get(m.group(2), (0, 0))
        out[m.group(2)] = (c + 1, b + size)
    return out


def _total(c: dict) -> int:
    return int(sum(b for _, b in c.values()))


def communication(pot, bc, linear) -> dict:
    """Bytes per CG iteration and per Newton step (setup) of a sharded solve, per device."""
    import jax
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic.mechanics import potential as pm
    from jaxelastic.solvers.multilevel import sharded_preconditioner

    x = pot.mesh.points
    Ke = jax.jit(lambda p, x: pm.elastic_element_hessians(p, x, True))(pot, x)
    free = ~bc.mask
    fm = free.astype(x.dtype)
    r = fm * jnp.sin(x)

    def A(pot, Ke, fm, v):
        return fm * pm.element_hessian_vp(pot, Ke, fm * v) + (1 - fm) * v

    a = collective_bytes(A, pot, Ke, fm, r)
    out = dict(node_vector_bytes=int(x.size * x.dtype.itemsize), A_bytes=_total(a))
    out["cg_scalars_bytes"] = 3 * x.dtype.itemsize
    m_bytes = 0
    if isinstance(linear, je.Multilevel):
        h, halo = je.solvers.init_linear(linear, pot.mesh, bc)[1].hierarchy, pot.mesh.halo

        def M1(h, Ke, free, r):
            return sharded_preconditioner(h, halo, Ke, None, free)(r)

        def M2(h, Ke, free, r):
            M = sharded_preconditioner(h, halo, Ke, None, free)
            return M(r), M(2.0 * r + 1.0)

        one, two = (_total(collective_bytes(f, h, Ke, free, r)) for f in (M1, M2))
        m_bytes = two - one
        lv1 = h.coarse[0] if h.coarse else None
        out["coarse_vector_bytes"] = int(lv1.n * lv1.b * 8) if lv1 is not None else 0
        out["setup_bytes_per_newton_step"] = int(2 * one - two)
    out["M_bytes"] = int(m_bytes)
    it = out["A_bytes"] + m_bytes + out["cg_scalars_bytes"]
    out["cg_iteration_bytes"] = int(it)
    out["cg_iteration_vs_replicated"] = it / out["node_vector_bytes"]
    return out


def worker(n: int, solver: str, repeat: int, devices: int = 1, save: str | None = None) -> dict:
    """One (size, solver, devices) run in this process."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    import jaxelastic as je
    from jaxelastic import verification as benchmarks

    b = benchmarks.twist(n)
    mesh, pot, bc = b.mesh, b.pot, b.bc
    part = None
    if devices > 1:
        pot, bc, part = je.shard(pot, bc, devices=devices)
        mesh = pot.mesh
    t0 = time.perf_counter()
    linear, lstate = je.solvers.init_linear(_linear(solver), mesh, bc)
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
    if isinstance(linear, je.Multilevel) and lstate.hierarchy is not None:
        levels = lstate.hierarchy.describe()
    extra = {}
    if part is not None:
        extra = dict(partition=part.stats(), comm=communication(pot, bc, linear))
    if save:
        x = np.asarray(res.x)
        np.save(save, part.to_natural(x) if part is not None else x)
    return dict(
        n=n,
        dofs=int(b.mesh.n_dofs),
        tets=int(b.mesh.n_cells),
        solver=solver,
        devices=devices,
        **extra,
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


def _run_subprocess(
    n: int, solver: str, repeat: int, timeout: float, devices: int = 1, save: str = ""
) -> dict:
    cmd = [sys.executable, __file__, "--worker", str(n), solver, "--repeat", str(repeat)]
    cmd += ["--worker-devices", str(devices), "--worker-save", save]
    env = dict(os.environ)
    if devices > 1:
        flag = f"--xla_force_host_platform_device_count={devices}"
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " " + flag).strip()
    try:
        out = subprocess.run(
            cmd, capture_output=True, text=True, timeout=timeout, check=False, env=env
        )
    except subprocess.TimeoutExpired:
        return dict(n=n, solver=solver, devices=devices, error=f"timeout after {timeout:.0f} s")
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
    if out.returncode != 0 or not lines:
        err = out.stderr.strip().splitlines()[-1:]
        return dict(n=n, solver=solver, devices=devices, error=err)
    return json.loads(lines[-1])


def _table(rows: list[dict]) -> str:
    head = (
        f"{'n':>3} {'dofs':>7} {'solver':>14} {'dev':>3} {'newton':>6} {'lin its':>7} "
        f"{'its/amg':>7} {'setup s':>7} {'compile s':>9} {'warm s':>7} {'warm/amg':>8} "
        f"{'RSS MiB':>8} {'vs 1 dev':>8} {'B/CG it':>8} {'/repl':>6}"
    )
    lines = [head, "-" * len(head)]
    amg = {r["n"]: r for r in rows if r.get("solver") == "amg" and "error" not in r}
    for r in rows:
        dev = r.get("devices", 1)
        if "error" in r:
            lines.append(f"{r['n']:>3} {'':>7} {r['solver']:>14} {dev:>3}  error: {r['error']}")
            continue
        ref = amg.get(r["n"])
        ri = f"{r['linear_its'] / ref['linear_its']:.2f}" if ref else "-"
        rt = f"{r['warm_s'] / ref['warm_s']:.2f}" if ref else "-"
        diff = f"{r['diff_vs_1']:.1e}" if "diff_vs_1" in r else "-"
        comm = r.get("comm", {})
        cb = f"{comm['cg_iteration_bytes']:>8}" if comm else f"{'-':>8}"
        cr = f"{comm['cg_iteration_vs_replicated']:.2f}" if comm else "-"
        lines.append(
            f"{r['n']:>3} {r['dofs']:>7} {r['solver']:>14} {dev:>3} {r['newton']:>6} "
            f"{r['linear_its']:>7} {ri:>7} {r['setup_s']:>7.2f} {r['compile_s']:>9.1f} "
            f"{r['warm_s']:>7.2f} {rt:>8} {r['peak_rss_mib']:>8.0f} {diff:>8} {cb} {cr:>6}"
        )
    return "\n".join(lines)


def _twist_points(n: int):
    """Rest points of ``box(n, n, n)`` (node ``i + (n+1)(j + (n+1)k)`` at ``(i, j, k)/n``),
    without importing JAX in the parent."""
    import numpy as np

    t = np.linspace(0.0, 1.0, n + 1)
    Z, Y, X = np.meshgrid(t, t, t, indexing="ij")
    return np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="19,29", help="comma-separated twist sizes n")
    ap.add_argument("--solvers", default="amg,multilevel,cg", help=f"subset of {SOLVERS}")
    ap.add_argument("--repeat", type=int, default=3, help="warm solves (the minimum is kept)")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per run")
    ap.add_argument("--out", default="out/bench/multilevel.json", help="JSON output path")
    ap.add_argument(
        "--devices", default="1", help="comma-separated device counts (>1: sharded, host CPUs)"
    )
    ap.add_argument("--worker", nargs=2, metavar=("N", "SOLVER"), help=argparse.SUPPRESS)
    ap.add_argument("--worker-devices", type=int, default=1, help=argparse.SUPPRESS)
    ap.add_argument("--worker-save", default="", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        n, solver = int(args.worker[0]), args.worker[1]
        row = worker(n, solver, args.repeat, args.worker_devices, args.worker_save or None)
        print(json.dumps(row))
        return
    solvers = [s for s in args.solvers.split(",") if s]
    bad = [s for s in solvers if s not in SOLVERS]
    if bad:
        ap.error(f"unknown solver(s) {bad}; choose from {SOLVERS}")
    device_counts = [int(d) for d in args.devices.split(",") if d]
    rows = []
    import numpy as np  # the parent runs no JAX

    with tempfile.TemporaryDirectory() as tmp:
        for n in (int(s) for s in args.sizes.split(",") if s):
            for s in solvers:
                ref = None
                for dev in device_counts:
                    if dev > 1 and s in ("amg", "multilevel-sa"):
                        continue  # host AMG refuses sharded problems; SA: one device only
                    save = str(Path(tmp) / f"x_{n}_{s}_{dev}.npy")
                    row = _run_subprocess(n, s, args.repeat, args.timeout, dev, save)
                    if "error" not in row:
                        x = np.load(save)
                        if ref is None:
                            ref = x
                        else:  # relative to the first device count's displacement
                            X = _twist_points(n)
                            u = np.max(np.abs(ref - X))
                            row["diff_vs_1"] = float(np.max(np.abs(x - ref)) / u)
                    rows.append(row)
                    print(json.dumps(row), flush=True)
    print(_table(rows))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    from jaxelastic.io import write_json  # atomic; imported late: the parent runs no JAX

    write_json(out, dict(benchmark="twist", rtol=1e-8, runs=rows), indent=2)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
