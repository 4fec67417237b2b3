"""Cost of the differentiable rest geometry, and inverse elastostatics: ratios in one run.

Problem: a neo-Hookean cantilever clamped at x = 0 sagging under its own weight (3D
``box(--n)`` of 4 × 1 × 1 m, E = 1 MPa, ν = 0.3, ρ = 1000 kg/m³, g = 9.81 m/s²), the
loss its compliance ``f·(x − X)``. Timed per linear solver (warm medians of ``--repeats``
calls, interleaved round by round, of compiled functions taking the potential, the
Dirichlet data and the points as arguments; ``direct``: the host sparse Cholesky, ``cg``:
the matrix-free PCG):

* ``forward``: today's solve, the mesh built once by ``from_arrays``;
* ``with_points``: the geometry-differentiable path without a gradient: the rest
  quantities and the gravity load recomputed from the points (``mesh.with_points(X)``)
  before the same solve (target ≤ 1.2 × forward);
* ``shape_grad``: value and gradient of the compliance with respect to every rest point
  (target ≤ 3 × forward);
* ``param_grad``: value and gradient with respect to (μ, λ), for comparison.

Then the inverse problem on the 2D cantilever ``rectangle(--n2)`` under gravity (sag about
a quarter of its length): the rest shape recovered by the direct method and by the fixed
point, iterations, wall time (including compilation) and the round-trip error.

Timings on a shared machine are noisy: compare the ratios within one run.

Usage::

    python scripts/bench_shape.py --out out/bench_shape
    python scripts/bench_shape.py --n 6,2,2 --n2 8,2 --repeats 2 --out /tmp/bs   # smoke test
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import numpy as np

from jaxelastic.io import write_json

TARGET = dict(with_points=1.2, shape_grad=3.0)


def _interleaved_times(cases: dict, repeats: int) -> dict:
    """``name -> (first call [s], median warm call [s])``, the warm calls interleaved
    round by round (one call of every case per round), so that the load of a shared
    machine drifting during the run affects every case alike."""
    import jax

    first = {}
    for name, fn in cases.items():
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        first[name] = time.perf_counter() - t0
    times: dict = {name: [] for name in cases}
    for _ in range(repeats):
        for name, fn in cases.items():
            t0 = time.perf_counter()
            jax.block_until_ready(fn())
            times[name].append(time.perf_counter() - t0)
    return {name: (first[name], statistics.median(times[name])) for name in cases}


def cost_rows(n, repeats: int, solvers) -> list[dict]:
    """One row per (solver, path): warm median, first call and the ratio to ``forward``."""
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import loads as L
    from jaxelastic import materials as M

    mesh = je.box(*n, size=(4.0, 1.0, 1.0))
    bc = L.fix(mesh, L.nodes_on_plane(mesh, 0, 0.0))
    params = je.Lame.from_E_nu(1.0e6, 0.3)
    g = (0.0, 0.0, -9.81)

    def weight(m):
        return L.gravity_load(m, 1000.0, g)

    pot = je.Potential(mesh=mesh, params=params, f_ext=jnp.asarray(weight(mesh)), psi=M.neo_hookean)
    rows = []
    for kind in solvers:
        rows += _cost_of(kind, pot, bc, weight, repeats)
    return rows


def _cost_of(kind: str, pot, bc, weight, repeats: int) -> list[dict]:
    """The four timed paths of one linear solver, compiled, the potential, the Dirichlet
    data and the points passed as arguments (never closed over)."""
    import jax
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import loads as L

    mesh = pot.mesh
    prepared = je.solvers.prepare_solver(je.Newton(rtol=1e-10, linear=kind), mesh, bc)

    def moved(pot, bc, X):
        m = pot.mesh.with_points(X)
        return pot.replace(mesh=m, f_ext=weight(m)), L.with_rest_points(bc, pot.mesh.points, X)

    def forward(pot, bc):
        return je.solve(pot, bc, solver=prepared).x

    def compliance(X, pot, bc):
        p, b = moved(pot, bc, X)
        return jnp.sum(p.f_ext * (je.solve(p, b, solver=prepared).x - X))

    def compliance_params(params, pot, bc):
        x = je.solve(pot.replace(params=params), bc, solver=prepared).x
        return jnp.sum(pot.f_ext * (x - pot.mesh.points))

    fwd = jax.jit(forward)
    wp = jax.jit(lambda pot, bc, X: forward(*moved(pot, bc, X)))
    sg = jax.jit(jax.value_and_grad(compliance))
    pg = jax.jit(jax.value_and_grad(compliance_params))
    X = mesh.points
    cases = {
        "forward": lambda: fwd(pot, bc),
        "with_points": lambda: wp(pot, bc, X),
        "shape_grad": lambda: sg(X, pot, bc),
        "param_grad": lambda: pg(pot.params, pot, bc),
    }
    timed = _interleaved_times(cases, repeats)
    base = timed["forward"][1]
    return [
        dict(
            solver=kind,
            path=name,
            warm_s=warm,
            first_s=first,
            ratio=warm / base,
            target=TARGET.get(name),
            cells=mesh.n_cells,
            dofs=mesh.n_dofs,
        )
        for name, (first, warm) in timed.items()
    ]


def inverse_rows(n2) -> list[dict]:
    """The 2D sagging cantilever's rest shape by both methods."""
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import loads as L
    from jaxelastic import materials as M

    mesh = je.rectangle(*n2, size=(4.0, 0.5))
    params = je.Lame.from_E_nu(1000.0, 0.3)

    def weight(m):
        return L.gravity_load(m, 1.0, (0.0, -1.0))

    bc0 = L.fix(mesh, L.nodes_on_plane(mesh, 0, 0.0))
    pot0 = je.Potential(mesh=mesh, params=params, f_ext=weight(mesh), psi=M.neo_hookean)
    x_hat = je.solve(pot0, bc0, solver=je.Newton(rtol=1e-12)).x
    seen = je.from_arrays(np.asarray(x_hat), np.asarray(mesh.cells))
    bc = L.fix(seen, L.nodes_on_plane(seen, 0, 0.0))
    pot = je.Potential(mesh=seen, params=params, f_ext=weight(seen), psi=M.neo_hookean)
    sag = float(jnp.max(jnp.abs(x_hat - mesh.points)))
    rows = []
    for method in ("direct", "fixed_point"):
        res = je.unloaded_shape(pot, bc, x_hat, loads=weight, method=method, max_steps=200)
        err = float(jnp.max(jnp.abs(res.x - mesh.points)))
        h = np.asarray(res.stats["residual_history"])
        rows.append(
            dict(
                method=method,
                status=je.Status(int(res.status)).name,
                iterations=int(res.stats["steps"]),
                wall_s=float(res.stats["wall_time"]),
                round_trip=float(res.stats["round_trip"]),
                rest_error=err / sag,
                history=[float(v) for v in h],
                sag=sag,
                dofs=mesh.n_dofs,
            )
        )
    return rows


def table(cost: list[dict], inverse: list[dict]) -> str:
    lines = [
        "| solver | path | warm [s] | first call [s] | × forward | target |",
        "|---|---|---|---|---|---|",
    ]
    for r in cost:
        tgt = f"≤ {r['target']}" if r["target"] else ""
        lines.append(
            f"| {r['solver']} | {r['path']} | {r['warm_s']:.3f} | {r['first_s']:.2f} | "
            f"{r['ratio']:.2f} | {tgt} |"
        )
    lines += [
        "",
        "| method | status | iterations | wall [s] (with compile) | round trip "
        "| rest error / sag |",
        "|---|---|---|---|---|---|",
    ]
    for r in inverse:
        lines.append(
            f"| {r['method']} | {r['status']} | {r['iterations']} | {r['wall_s']:.1f} | "
            f"{r['round_trip']:.1e} | {r['rest_error']:.1e} |"
        )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", default="12,3,3", help="box cells nx,ny,nz (3D cost)")
    ap.add_argument("--n2", default="16,4", help="rectangle cells nx,ny (2D inverse)")
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--solvers", default="direct,cg")
    ap.add_argument("--out", default="out/bench_shape")
    args = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    n = tuple(int(v) for v in args.n.split(","))
    n2 = tuple(int(v) for v in args.n2.split(","))
    cost = cost_rows(n, args.repeats, args.solvers.split(","))
    inverse = inverse_rows(n2)
    text = table(cost, inverse)
    sys.stdout.write(text)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "bench_shape.md"), "w", encoding="utf-8") as fh:
        fh.write(text)
    meta = dict(n=n, n2=n2, repeats=args.repeats, command=" ".join(sys.argv))
    write_json(
        os.path.join(args.out, "bench_shape.json"), dict(meta=meta, cost=cost, inverse=inverse)
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
