"""float32 vs float64: kernel and Newton-solve times on the twist benchmark.

For each size ``n`` of the twist (``jaxelastic.verification.twist``, unit cube, 6n³ tets,
isochoric neo-Hookean, half of a 60° turn), in both precisions (float64 with x64 on;
float32 = float32 arrays with x64 still on, as ``[solver] precision = "float32"`` does):

* ``energy``, ``forces``, ``element_hessians``: the kernels, each ``jax.jit``-ed with the
  mesh as an argument (nothing constant-folded), min of ``--repeat`` warm calls;
* ``solve``: the whole ``je.solve`` (Newton, ``linear`` as given, ``rtol`` as given), min of
  ``--repeat`` warm calls (compile excluded: the first call), with its Newton steps, linear
  iterations, status and the residual floor;
* the relative displacement difference of the float32 solution from the float64 one,
  ``‖u₃₂ − u₆₄‖ / ‖u₆₄‖``.

The table gives the times and the f64/f32 speed-ups; the JSON (``--out``, default
``out/bench/precision.json``) holds every number and the peak RSS of the process
(``resource.getrusage``, so the largest size dominates). On a machine shared with other
jobs the timings are noisy: the min of the repeats is the least noisy figure.

Usage::

    python scripts/bench_precision.py [--sizes 6,10,16] [--repeat 3] [--rtol 1e-5]
                                      [--linear auto] [--out out/bench/precision.json]
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxelastic as je  # noqa: E402
from jaxelastic.io import write_json  # noqa: E402
from jaxelastic.verification import torsion as twist  # noqa: E402

DTYPES = {"float64": jnp.float64, "float32": jnp.float32}


def _min_time(fn, repeat: int) -> float:
    """Min wall time [s] of ``repeat`` warm calls of ``fn`` (after one warm-up call)."""
    jax.block_until_ready(fn())
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - t0)
    return float(best)


def _kernels(b, repeat: int) -> dict:
    """Min times [s] of energy, forces and element Hessians at a sheared state."""
    psi, mesh, params = b.pot.psi, b.pot.mesh, b.pot.params
    X = mesh.points
    x = X + jnp.asarray(0.05, X.dtype) * X[:, [1, 2, 0]]  # a smooth non-trivial state
    en = jax.jit(lambda x, m, p: je.energy(psi, x, m, p))
    fo = jax.jit(lambda x, m, p: je.forces(psi, x, m, p))
    ke = jax.jit(lambda x, m, p: je.mechanics.element_hessians(psi, x, m, p))
    return {
        "energy": _min_time(lambda: en(x, mesh, params), repeat),
        "forces": _min_time(lambda: fo(x, mesh, params), repeat),
        "element_hessians": _min_time(lambda: ke(x, mesh, params), repeat),
    }


def _solve(b, linear: str, rtol: float, repeat: int) -> tuple[dict, np.ndarray]:
    """The warm solve time and statistics, and the solution (float64 copy)."""
    solver = je.solvers.prepare_solver(je.Newton(rtol=rtol, linear=linear), b.pot.mesh, b.bc)
    t0 = time.perf_counter()
    res = je.solve(b.pot, b.bc, solver=solver, throw=False)
    first = time.perf_counter() - t0
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        res = je.solve(b.pot, b.bc, solver=solver, throw=False)
        best = min(best, time.perf_counter() - t0)
    row = dict(
        solve=float(best),
        first_call=float(first),
        status=je.Status(int(res.status)).name,
        steps=int(res.stats["steps"]),
        linear_iterations=int(res.stats["linear_iterations"]),
        residual=float(res.stats["residual"]),
        residual_floor=float(res.stats["residual_floor"]),
    )
    return row, np.asarray(res.x, dtype=np.float64)


def _peak_rss_mb() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / 1024 / 1024 if sys.platform == "darwin" else r / 1024  # bytes on macOS


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="6,10,16", help="twist sizes n (6n³ tets)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--rtol", type=float, default=1e-5, help="Newton rtol (both precisions)")
    ap.add_argument("--linear", default="auto", help="linear solver of the Newton solve")
    ap.add_argument("--out", default=os.path.join("out", "bench", "precision.json"))
    a = ap.parse_args(argv)
    sizes = [int(s) for s in a.sizes.split(",")]
    rows = []
    hdr = (
        f"{'n':>4} {'dofs':>7} {'prec':>8} {'energy ms':>10} {'forces ms':>10} "
        f"{'hess ms':>9} {'solve s':>8} {'steps':>5} {'status':>10} {'rel diff':>9}"
    )
    print(hdr)
    for n in sizes:
        ref = None
        for name in ("float64", "float32"):
            b = twist(n, dtype=DTYPES[name])
            k = _kernels(b, a.repeat)
            s, x = _solve(b, a.linear, a.rtol, a.repeat)
            X = np.asarray(b.pot.mesh.points, dtype=np.float64)
            if ref is None:
                ref, X64 = x, X
                rel = 0.0
            else:
                rel = float(np.linalg.norm(x - ref) / np.linalg.norm(ref - X64))
            row = dict(n=n, n_dofs=b.pot.mesh.n_dofs, precision=name, **k, **s, rel_diff=rel)
            rows.append(row)
            print(
                f"{n:>4} {row['n_dofs']:>7} {name:>8} {1e3 * k['energy']:>10.2f} "
                f"{1e3 * k['forces']:>10.2f} {1e3 * k['element_hessians']:>9.2f} "
                f"{s['solve']:>8.3f} {s['steps']:>5} {s['status']:>10} {rel:>9.1e}"
            )
    speedups = []
    for n in sizes:
        r64, r32 = (next(r for r in rows if r["n"] == n and r["precision"] == p) for p in DTYPES)
        sp = {k: r64[k] / r32[k] for k in ("energy", "forces", "element_hessians", "solve")}
        speedups.append(dict(n=n, **sp))
        print(
            f"n = {n}: f64/f32 time  energy {sp['energy']:.2f}x  forces {sp['forces']:.2f}x  "
            f"element Hessians {sp['element_hessians']:.2f}x  solve {sp['solve']:.2f}x"
        )
    out = dict(
        benchmark="twist",
        rtol=a.rtol,
        linear=a.linear,
        repeat=a.repeat,
        machine=f"{os.cpu_count()} cores, {platform.processor() or platform.machine()}, "
        f"jax {jax.__version__}, {jax.default_backend()}",
        load_average=list(os.getloadavg()),
        peak_rss_mb=_peak_rss_mb(),
        rows=rows,
        speedup_f64_over_f32=speedups,
    )
    os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
    write_json(a.out, out)
    print(f"peak RSS {out['peak_rss_mb']:.0f} MB; wrote {a.out}")
    return out


if __name__ == "__main__":
    main()
