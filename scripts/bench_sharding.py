"""Sharding the twist over 1, 2 and 4 host devices: time, iterations, communication volume.

Twist (:func:`jaxelastic.verification.twist`, ``box(n, n, n)``: 6n³ tets, 3(n+1)³ dofs;
n = 10 / 19 / 29 ≈ 4k / 24k / 81k dofs), Newton (rtol 1e-8) with a device linear solver
(``--linear cg``: block-Jacobi PCG, or ``multilevel``). Each (n, devices) runs in a fresh
subprocess started with ``XLA_FLAGS=--xla_force_host_platform_device_count=D``; D = 1 is
the plain unsharded solve, D ≥ 2 is ``je.shard(pot, bc, devices=D)``.

Reported per run: Newton steps and CG iterations, cold (compile + solve) and warm (min of
``--repeat``) solve seconds, peak RSS, the partition (cells, owned, ghost and interface
nodes per shard) and the communication, read from the *compiled* HLO of the kernels a
Newton step runs (``jit(...).lower(...).compile().as_text()``: every ``all-reduce``,
``all-gather``, ``collective-permute``, ``reduce-scatter``, ``all-to-all``):

* per CG iteration: the operator ``element_hessian_vp`` (halo gather + scatter-add) and
  the two dot products of PCG (one scalar all-reduce each);
* per Newton step: forces, element Hessians, the preconditioner blocks and one energy
  (each line-search trial evaluates one), plus ``its/step`` CG iterations.

Bytes are *per device*: the sum of the buffers the device's collectives carry (for a
``collective-permute`` what it sends, for an ``all-reduce`` its operand). The contrast is
the replicated layout (cells sharded, nodes replicated): one all-reduce of the whole node
vector ``3·n_nodes·8`` bytes per operator application. ``projection`` extrapolates the
halo to N devices from the measured ghost counts, assuming shards of a 3D mesh whose
interface grows like the surface of a cube of their volume (ghosts ∝ (n_nodes/N)^(2/3)).

On a 2-core machine host devices share the same two cores, so sharding cannot speed
anything up here: the figures are the cost of the layout and its communication.

Usage::

    python scripts/bench_sharding.py                                  # n = 10, 19, 29; D = 1, 2, 4
    python scripts/bench_sharding.py --sizes 10 --devices 1,2 --repeat 1
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import subprocess
import sys
import time
from pathlib import Path

COLLECTIVES = ("all-reduce", "all-gather", "collective-permute", "reduce-scatter", "all-to-all")
_DTYPE_BYTES = {"f64": 8, "f32": 4, "s32": 4, "u32": 4, "s64": 8, "u64": 8, "pred": 1, "f16": 2}
_OP = re.compile(
    r"=\s*(?P<shape>\([^=]*?\)|[a-z]\w*\[[\d,]*\](?:\{[^}]*\})?)\s+"
    r"(?P<op>" + "|".join(COLLECTIVES) + r")(?P<start>-start)?\("
)
_ARRAY = re.compile(r"([a-z]\w*)\[([\d,]*)\]")


def _shape_bytes(shape: str) -> int:
    total = 0
    for dt, dims in _ARRAY.findall(shape):
        n = 1
        for d in filter(None, dims.split(",")):
            n *= int(d)
        total += n * _DTYPE_BYTES.get(dt, 8)
    return total


def hlo_collectives(hlo_text: str) -> dict:
    """Count the collectives of compiled (SPMD-partitioned) HLO text and their per-device
    buffer bytes: ``{op: {"count": c, "bytes": b}}`` plus ``"total"`` (an async
    ``*-start`` counts once, with half its tuple: operand and result)."""
    out: dict = {op: dict(count=0, bytes=0) for op in COLLECTIVES}
    for m in _OP.finditer(hlo_text):
        b = _shape_bytes(m.group("shape"))
        if m.group("start"):
            b //= 2
        out[m.group("op")]["count"] += 1
        out[m.group("op")]["bytes"] += b
    out["total"] = dict(
        count=sum(v["count"] for v in out.values()), bytes=sum(v["bytes"] for v in out.values())
    )
    return out


def _compiled_collectives(fn, *args) -> dict:
    import jax

    return hlo_collectives(jax.jit(fn).lower(*args).compile().as_text())


def _communication(pot, x) -> dict:
    """Collectives of the kernels one Newton step and one CG iteration run."""
    import jax
    import jax.numpy as jnp

    from jaxelastic.mechanics import potential as P

    Ke = jax.jit(lambda p, y: P.elastic_element_hessians(p, y, False))(pot, x)
    kern = dict(
        hvp=_compiled_collectives(lambda p, k, v: P.element_hessian_vp(p, k, v), pot, Ke, x),
        dot=_compiled_collectives(lambda a, b: jnp.vdot(a, b), x, x),
        forces=_compiled_collectives(lambda p, y: P.gradient(p, y), pot, x),
        energy=_compiled_collectives(lambda p, y: P.value(p, y), pot, x),
        hessians=_compiled_collectives(
            lambda p, y: P.elastic_element_hessians(p, y, False), pot, x
        ),
        blocks=_compiled_collectives(lambda p, k: P.node_hessian_blocks(p, k), pot, Ke),
    )
    cg = {k: kern["hvp"]["total"][k] + 2 * kern["dot"]["total"][k] for k in ("count", "bytes")}
    step = {
        k: sum(kern[n]["total"][k] for n in ("forces", "energy", "hessians", "blocks"))
        for k in ("count", "bytes")
    }
    return dict(kernels=kern, per_cg_iteration=cg, per_newton_step_without_cg=step)


def worker(n: int, devices: int, linear: str, repeat: int, method: str) -> dict:
    """One (size, device count) run in this process (started with the XLA flag)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    import jaxelastic as je
    from jaxelastic import verification as benchmarks

    b = benchmarks.twist(n)
    pot, bc, part = b.pot, b.bc, None
    t0 = time.perf_counter()
    if devices > 1:
        pot, bc, part = je.shard(b.pot, b.bc, devices=devices, method=method)
    shard_s = time.perf_counter() - t0
    lin = je.CG() if linear == "cg" else je.Multilevel()
    newton = je.Newton(rtol=1e-8, max_steps=50, linear=lin)
    t0 = time.perf_counter()
    res = je.solve(pot, bc, solver=newton, throw=False)
    cold = time.perf_counter() - t0
    warm = float("inf")
    for _ in range(max(1, repeat)):
        t0 = time.perf_counter()
        res = je.solve(pot, bc, solver=newton, throw=False)
        warm = min(warm, time.perf_counter() - t0)
    x = np.asarray(res.x)
    if part is not None:
        x = part.to_natural(x, kind="nodes")
    steps, its = int(res.stats["steps"]), int(res.stats["linear_iterations"])
    comm = _communication(pot, res.x)
    rec = dict(
        n=n,
        dofs=int(b.mesh.n_dofs),
        tets=int(b.mesh.n_cells),
        devices=devices,
        linear=linear,
        status=int(res.status),
        newton=steps,
        cg_its=its,
        shard_s=shard_s,
        cold_s=cold,
        warm_s=warm,
        peak_rss_mib=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        replicated_bytes=int(3 * b.mesh.n_nodes * 8),
        partition=None if part is None else part.stats(dim=3, itemsize=8),
        communication=comm,
    )
    cg, st = comm["per_cg_iteration"]["bytes"], comm["per_newton_step_without_cg"]["bytes"]
    rec["bytes_per_newton_step"] = st + (its / max(steps, 1)) * cg
    rec["x_digest"] = [float(np.abs(x).sum()), float(x[-1, 1])]
    np.save(f"/tmp/bench_sharding_x_{os.getpid()}.npy", x)
    rec["x_file"] = f"/tmp/bench_sharding_x_{os.getpid()}.npy"
    return rec


def _run(n: int, d: int, args) -> dict:
    env = dict(os.environ)
    env["XLA_FLAGS"] = (
        env.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={d}"
    ).strip()
    cmd = [sys.executable, __file__, "--worker", str(n), str(d), "--linear", args.linear]
    cmd += ["--repeat", str(args.repeat), "--method", args.method]
    try:
        out = subprocess.run(
            cmd, capture_output=True, text=True, timeout=args.timeout, check=False, env=env
        )
    except subprocess.TimeoutExpired:
        return dict(n=n, devices=d, error=f"timeout after {args.timeout:.0f} s")
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
    if out.returncode != 0 or not lines:
        return dict(n=n, devices=d, error=out.stderr.strip().splitlines()[-3:])
    return json.loads(lines[-1])


def _projection(rows: list[dict], targets=(8, 16, 64, 256)) -> list[dict]:
    """Per-shard halo at N devices from the measured ghosts, ghosts ∝ (n_nodes/N)^(2/3)."""
    out = []
    for n in sorted({r["n"] for r in rows}):
        meas = [r for r in rows if r["n"] == n and r.get("partition") and "error" not in r]
        if not meas:
            continue
        r = max(meas, key=lambda r: r["devices"])
        p, nodes = r["partition"], r["replicated_bytes"] // 24
        g = sum(p["ghost_nodes"]) / p["shards"]
        c = g / (nodes / p["shards"]) ** (2 / 3)
        for N in targets:
            own = nodes / N
            ghosts = c * own ** (2 / 3)
            out.append(
                dict(
                    n=n,
                    from_devices=p["shards"],
                    devices=N,
                    owned_nodes=own,
                    ghost_nodes=ghosts,
                    ghost_over_owned=ghosts / own,
                    halo_bytes_per_shard=ghosts * 24,
                    halo_over_replicated=ghosts * 24 / r["replicated_bytes"],
                )
            )
    return out


def _table(rows: list[dict]) -> str:
    head = (
        f"{'n':>3} {'dofs':>6} {'D':>2} {'newton':>6} {'CG its':>6} {'cold s':>7} {'warm s':>7} "
        f"{'ghost/own':>9} {'coll/CG':>7} {'B/CG it':>9} {'B/Newton':>10} {'B/CG / repl':>11} "
        f"{'RSS MiB':>7}"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        if "error" in r:
            lines.append(f"{r['n']:>3} {'':>6} {r['devices']:>2}  error: {r['error']}")
            continue
        p = r["partition"]
        go = "-" if p is None else f"{max(p['ghost_nodes']) / max(p['owned_nodes']):.3f}"
        cg = r["communication"]["per_cg_iteration"]
        lines.append(
            f"{r['n']:>3} {r['dofs']:>6} {r['devices']:>2} {r['newton']:>6} {r['cg_its']:>6} "
            f"{r['cold_s']:>7.1f} {r['warm_s']:>7.2f} {go:>9} {cg['count']:>7} "
            f"{cg['bytes']:>9.0f} {r['bytes_per_newton_step']:>10.0f} "
            f"{cg['bytes'] / r['replicated_bytes']:>11.3f} {r['peak_rss_mib']:>7.0f}"
        )
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="10,19,29", help="comma-separated twist sizes n")
    ap.add_argument("--devices", default="1,2,4", help="comma-separated device counts")
    ap.add_argument("--linear", default="cg", choices=("cg", "multilevel"))
    ap.add_argument("--method", default="auto", help="partition method: auto, metis, sfc")
    ap.add_argument("--repeat", type=int, default=3, help="warm solves (min is reported)")
    ap.add_argument("--timeout", type=float, default=1800.0, help="per run [s]")
    ap.add_argument("--out", default="out/bench/sharding.json")
    ap.add_argument("--worker", nargs=2, type=int, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        rec = worker(*args.worker, args.linear, args.repeat, args.method)
        print(json.dumps(rec), flush=True)
        return
    import numpy as np

    from jaxelastic.io import write_json

    rows = []
    for n in [int(s) for s in args.sizes.split(",")]:
        ref = None
        for d in [int(s) for s in args.devices.split(",")]:
            r = _run(n, d, args)
            if "x_file" in r:
                x = np.load(r.pop("x_file"))
                if ref is None:
                    ref = x
                r["max_rel_diff_vs_first"] = float(np.abs(x - ref).max() / np.abs(ref).max())
            rows.append(r)
            print(_table([r]).splitlines()[-1], flush=True)
    proj = _projection(rows)
    print("\n" + _table(rows))
    print("\nprojection (halo per shard from the measured ghosts, ghosts ~ (nodes/N)^(2/3)):")
    print(
        f"{'n':>3} {'N':>4} {'owned':>9} {'ghosts':>8} {'ghost/own':>9} {'halo kB':>8} {'/repl':>7}"
    )
    for p in proj:
        print(
            f"{p['n']:>3} {p['devices']:>4} {p['owned_nodes']:>9.0f} {p['ghost_nodes']:>8.0f} "
            f"{p['ghost_over_owned']:>9.3f} {p['halo_bytes_per_shard'] / 1e3:>8.2f} "
            f"{p['halo_over_replicated']:>7.4f}"
        )
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    write_json(
        args.out,
        dict(
            machine=dict(cpus=os.cpu_count(), load=os.getloadavg()),
            linear=args.linear,
            runs=rows,
            projection=proj,
        ),
    )
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
