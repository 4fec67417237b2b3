"""vmap over scenes: a batch of cantilevers solved by one compiled ``jax.vmap(je.solve)``
against a Python loop of the compiled single solve.

Problem: a 10 × 1.5 × 1.5 neo-Hookean cantilever, ``box(20, 3, 3)`` (1080 tets, 1008
dofs), clamped at x = 0, a dead shear traction on x = 10; a parameter sweep of Poisson's
ratio ν ∈ [0.2, 0.45] (``--sweep nu``) or of Young's modulus E ∈ [500, 2000]
(``--sweep E``) over the batch. Everything (mesh, Dirichlet data, loads) is a jit argument;
only the swept parameter is batched. The linear solver is the device one (``--linear``:
``multilevel`` when the library has it, else ``cg``), bound once outside jit.

Reported:

* loop: ``B`` calls of the compiled single solve (min of ``--repeat``), its throughput;
* batched: one call of the compiled ``vmap`` solve over all ``B`` members (min of
  ``--repeat``), throughput and the ratio batched / loop; agreement with the loop
  (max |Δx|), statuses, Newton steps and linear iterations (mean / max over members: a
  vmapped loop runs until its slowest member is done);
* chunked (``--chunks``): ``lax.map(solve, batch, batch_size=k)``, one compiled function
  that vmaps ``k`` members at a time;
* per batch size (``--sizes``): compile time, warm time per batch and per solve, peak RSS
  (``ru_maxrss`` after that size; sizes run in ascending order, so it is the peak of the
  largest batch so far) and XLA's ``compiled.memory_analysis()`` (temporary, argument and
  output bytes; what the batch size does to memory).

Usage::

    python scripts/bench_vmap.py                           # B = 64, sizes 1,4,16,64
    python scripts/bench_vmap.py --linear cg --chunks 4,16 --out out/bench/vmap.json
    python scripts/bench_vmap.py --batch 16 --sizes 1,16 --repeat 1   # quick check
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import numpy as np


def _rss_mb() -> float:
    """Peak resident set size of this process so far [MiB] (Linux: ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _memory(compiled) -> dict:
    """XLA's memory analysis of a compiled function [bytes] (empty where unsupported)."""
    try:
        m = compiled.memory_analysis()
    except Exception:  # noqa: BLE001 — not every backend implements it
        return {}
    if m is None:
        return {}
    keys = ("temp_size_in_bytes", "argument_size_in_bytes", "output_size_in_bytes")
    keys += ("generated_code_size_in_bytes",)
    return {k.removesuffix("_size_in_bytes"): int(getattr(m, k, 0)) for k in keys}


def _problem(precision: str):
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import loads
    from jaxelastic import materials as M

    dtype = jnp.float32 if precision == "float32" else jnp.float64
    mesh = je.box(20, 3, 3, (10.0, 1.5, 1.5), dtype=dtype)
    facets = loads.facets_where(mesh, lambda X: np.abs(X[:, 0] - 10.0) < 1e-9)
    f = jnp.asarray(loads.traction_load(mesh, facets, [0.0, 0.0, -0.2]), dtype)
    bc = loads.fix(mesh, loads.nodes_on_plane(mesh, 0, 0.0))
    pot = je.Potential(mesh=mesh, params=M.Lame(1.0, 1.0), f_ext=f, psi=M.neo_hookean)
    return mesh, pot, bc


def _timed(fn, repeat: int):
    """``(min wall time [s], last result)`` of ``repeat`` calls of ``fn()``."""
    import jax

    ts, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        ts.append(time.perf_counter() - t0)
    return min(ts), out


def run(args) -> dict:
    """Run the benchmark; returns its JSON record.

    Long because: one straight sequence of phases (setup, loop, batch sizes, chunks) that
    share the compiled functions and must run in this order."""
    import jax

    if args.precision == "float64":
        jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import materials as M

    linear = args.linear
    if linear == "auto-device":
        linear = "multilevel" if hasattr(je, "Multilevel") else "cg"
    mesh, pot, bc = _problem(args.precision)
    dtype = mesh.points.dtype
    solver = je.solvers.prepare_solver(je.Newton(rtol=args.rtol, linear=linear), mesh, bc)
    B = args.batch
    if args.sweep == "nu":
        values = np.linspace(0.2, 0.45, B)
    else:
        values = np.linspace(500.0, 2000.0, B)
    values = jnp.asarray(values, dtype)

    def one(v, pot, bc):
        E, nu = (1000.0, v) if args.sweep == "nu" else (v, 0.3)
        p = M.Lame.from_E_nu(jnp.asarray(E, dtype), jnp.asarray(nu, dtype))
        r = je.solve(pot.replace(params=p), bc, solver=solver, throw=False)
        return r.x, r.status, r.stats["steps"], r.stats["linear_iterations"]

    def compile_(fn, *a):
        t0 = time.perf_counter()
        c = jax.jit(fn).lower(*a).compile()
        return c, time.perf_counter() - t0

    res: dict = dict(
        problem=dict(
            mesh="box(20, 3, 3), 10 x 1.5 x 1.5",
            n_cells=int(mesh.n_cells),
            n_dofs=int(mesh.n_dofs),
            material="neo_hookean",
            sweep=args.sweep,
            range=[float(values[0]), float(values[-1])],
        ),
        linear=linear,
        precision=args.precision,
        rtol=args.rtol,
        batch=B,
        repeat=args.repeat,
        backend=jax.default_backend(),
        device=str(jax.devices()[0]),
        jax=jax.__version__,
    )

    # ---- loop of the compiled single solve
    single, c1 = compile_(one, values[0], pot, bc)
    res["single"] = dict(compile_s=c1, memory=_memory(single))
    t_loop, outs = _timed(lambda: [single(v, pot, bc) for v in values], args.repeat)
    res["loop"] = dict(time_s=t_loop, per_solve_s=t_loop / B, throughput=B / t_loop)
    res["loop"]["rss_mb"] = _rss_mb()
    x_loop = jnp.stack([o[0] for o in outs])

    # ---- batch sizes (ascending: ru_maxrss is then the peak of the largest so far)
    batched = jax.vmap(one, in_axes=(0, None, None))
    sizes = sorted({s for s in args.sizes if s <= B} | {B})
    res["sizes"] = []
    full = None
    for s in sizes:
        comp, cs = compile_(batched, values[:s], pot, bc)
        t, out = _timed(lambda comp=comp, s=s: comp(values[:s], pot, bc), args.repeat)
        row = dict(
            batch=s,
            compile_s=cs,
            time_s=t,
            per_solve_s=t / s,
            throughput=s / t,
            rss_mb=_rss_mb(),
            memory=_memory(comp),
        )
        res["sizes"].append(row)
        if s == B:
            full = (row, out)
    assert full is not None
    row, (xb, st, steps, lin) = full
    res["batched"] = dict(
        row,
        ratio=row["throughput"] / res["loop"]["throughput"],
        max_dx_vs_loop=float(jnp.max(jnp.abs(xb - x_loop))),
        statuses=sorted({int(s) for s in np.asarray(st)}),
        loop_statuses=sorted({int(o[1]) for o in outs}),
        steps_mean=float(np.mean(steps)),
        steps_max=int(np.max(steps)),
        linear_mean=float(np.mean(lin)),
        linear_max=int(np.max(lin)),
    )

    # ---- chunked vmap: lax.map with batch_size
    res["chunks"] = []
    for k in args.chunks:

        def chunked(vs, pot, bc, k=k):
            return jax.lax.map(lambda v: one(v, pot, bc), vs, batch_size=k)

        comp, cs = compile_(chunked, values, pot, bc)
        t, out = _timed(lambda comp=comp: comp(values, pot, bc), args.repeat)
        res["chunks"].append(
            dict(
                chunk=k,
                compile_s=cs,
                time_s=t,
                throughput=B / t,
                ratio=(B / t) / res["loop"]["throughput"],
                max_dx_vs_loop=float(jnp.max(jnp.abs(out[0] - x_loop))),
                rss_mb=_rss_mb(),
                memory=_memory(comp),
            )
        )
    return res


def _table(res: dict) -> str:
    def mb(row, key):
        v = row.get("memory", {}).get(key)
        return f"{v / 2**20:8.1f}" if v is not None else "       -"

    p = res["problem"]
    lines = [
        f"vmap over {res['batch']} cantilevers ({p['n_cells']} tets, {p['n_dofs']} dofs, "
        f"sweep {p['sweep']} {p['range'][0]:g}..{p['range'][1]:g}), linear={res['linear']}, "
        f"{res['precision']}, {res['backend']} ({res['device']})",
        f"loop of compiled single solves: {res['loop']['time_s']:.3f} s "
        f"({res['loop']['throughput']:.1f} solves/s; compile {res['single']['compile_s']:.1f} s)",
    ]
    b = res["batched"]
    lines.append(
        f"one vmapped solve:              {b['time_s']:.3f} s ({b['throughput']:.1f} solves/s)"
        f"  -> ratio {b['ratio']:.2f}; max|dx| vs loop {b['max_dx_vs_loop']:.1e}; "
        f"statuses {b['statuses']}; Newton steps mean/max {b['steps_mean']:.1f}/"
        f"{b['steps_max']}, linear its mean/max {b['linear_mean']:.0f}/{b['linear_max']}"
    )
    for c in res["chunks"]:
        lines.append(
            f"lax.map(batch_size={c['chunk']:>3}):       {c['time_s']:.3f} s "
            f"({c['throughput']:.1f} solves/s) -> ratio {c['ratio']:.2f}"
        )
    lines.append("")
    lines.append(
        "batch  compile s   time s   s/solve  solves/s  peak RSS MiB  XLA temp MiB  args MiB"
    )
    for r in res["sizes"]:
        lines.append(
            f"{r['batch']:>5}  {r['compile_s']:9.1f}  {r['time_s']:7.3f}  {r['per_solve_s']:8.4f}"
            f"  {r['throughput']:8.1f}  {r['rss_mb']:12.0f}  {mb(r, 'temp'):>12}"
            f"  {mb(r, 'argument'):>8}"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--sizes", default="1,4,16,64", help="batch sizes of the memory sweep")
    ap.add_argument("--chunks", default="", help="lax.map batch sizes, e.g. 4,16")
    ap.add_argument("--sweep", choices=("nu", "E"), default="nu")
    ap.add_argument("--linear", default="auto-device", help="cg, multilevel (default: best)")
    ap.add_argument("--precision", choices=("float64", "float32"), default="float64")
    ap.add_argument("--rtol", type=float, default=1e-8)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default="out/bench/vmap.json")
    args = ap.parse_args(argv)
    args.sizes = [int(s) for s in args.sizes.split(",") if s]
    args.chunks = [int(s) for s in args.chunks.split(",") if s]
    res = run(args)
    print(_table(res))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    from jaxelastic.io import write_json  # atomic

    write_json(out, res)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
