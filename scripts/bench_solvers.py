"""Solver benchmark: the JAX-FEM "twist" hyperelasticity problem, a backward-Euler step,
and the cost of each optional part of a scene.

Twist (:func:`jaxelastic.verification.twist`): unit cube ``box(n, n, n)`` (6n³ tets), face
x = 1 clamped, face x = 0 given u_x = 0 and half of a 60° rotation about the x axis through
(y, z) = (0.5, 0.5); user ψ isochoric neo-Hookean ``μ/2 (J^(−2/3) I_C − 3) + κ/2 (J − 1)²``
with E = 10, ν = 0.3, κ = E/(3(1 − 2ν)); converged to a relative residual of 1e-8. Each
(n, linear solver) runs in a fresh subprocess so its peak RSS and cold (compile-including)
time are its own.

Reported per run: the linear solver (``auto`` resolves by size) and direct back end,
cold wall time (first solve, including tracing and XLA compilation), warm wall time (min
of 3 further solves, same compiled code), Newton and linear iterations, the host
factorisation time of the last Newton step (``factor s``: numeric Cholesky for direct,
hierarchy setup/refresh for AMG), peak RSS (VmHWM after the warm solves, before the phase
split), and a per-phase split of one warm Newton iteration (energy+gradient, element
Hessians, linear solve).

``--element`` (default ``p1``): ``p2`` runs the twist on ``box(n, n, n, order=2)``
(tet10; n = 9–10 has about the dofs of P1 n = 19), ``p2fbar`` the same with the F-bar
formulation, ``composite`` the composite F-bar tets (tet4x8, same nodes as P2).

``--breakdown``: instead, where the time of one warm solve goes, per Newton iteration
(element Hessians + rhs, host factorisation / AMG setup, host preconditioner or solve
applications, the whole linear-solve piece, the line search; see
:func:`breakdown_worker`).

Usage::

    python scripts/bench_solvers.py                      # n = 10, 19, 29; cg and direct
    python scripts/bench_solvers.py --breakdown --sizes 29 --solvers auto
    python scripts/bench_solvers.py --sizes 10 --solvers cg,direct,amg --out out/bench
    python scripts/bench_solvers.py --element p2 --sizes 5,9 --solvers direct,amg
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ELEMENTS = {
    "p1": {},
    "p2": {"order": 2},
    "p2fbar": {"order": 2, "formulation": "fbar"},
    "composite": {"order": 1, "formulation": "fbar"},
}


def _twist_problem(n: int, element: str = "p1"):
    """(mesh, pot, bc) of :func:`jaxelastic.verification.twist` for an element variant."""
    from jaxelastic import verification as benchmarks

    b = benchmarks.twist(n, **ELEMENTS[element])
    return b.mesh, b.pot, b.bc


def _phase_split(pot, x, bc, host):
    """Time the parts of one Newton iteration at configuration x (warm, median of 3).

    ``host``: None (device block-Jacobi CG) or a ``je.solvers.HostLinearSolver``.
    """
    import jax
    import jax.numpy as jnp

    from jaxelastic.mechanics import assemble
    from jaxelastic.mechanics import potential as P
    from jaxelastic.solvers.linear import block_jacobi, cg

    vg = jax.jit(lambda pot, x: (P.value(pot, x), P.gradient(pot, x)))
    ke = jax.jit(lambda pot, x: P.elastic_element_hessians(pot, x, False))

    def timeit(fn, *a):
        jax.block_until_ready(fn(*a))
        ts = []
        for _ in range(3):
            t = time.perf_counter()
            jax.block_until_ready(fn(*a))
            ts.append(time.perf_counter() - t)
        return float(np.median(ts)), fn(*a)

    t_vg, (_, g) = timeit(vg, pot, x)
    t_ke, Ke = timeit(ke, pot, x)
    free = ~bc.mask
    fm = free.astype(x.dtype)
    rhs = -g * fm
    if host is None:
        mesh = pot.mesh

        @jax.jit
        def lin(Ke, rhs):
            def H(v):
                ve = v[mesh.cells].reshape(mesh.n_cells, -1)
                out = jnp.einsum("cij,cj->ci", Ke, ve).reshape(mesh.cells.shape + (-1,))
                return fm * assemble(mesh, out * 1.0) + (1 - fm) * v

            M = block_jacobi(P.node_hessian_blocks(pot, Ke), free)
            return cg(lambda v: H(fm * v), rhs, M, tol=1e-6 * jnp.linalg.norm(rhs), max_iter=5000)

        t_lin, res = timeit(lin, Ke, rhs)
        its = int(res.stats["iterations"])
    else:
        # host back end: assemble + factorise (direct) / build the hierarchy (AMG), then one
        # application (the full solve for direct, one V-cycle for AMG)
        Ke_np = np.asarray(Ke)
        md = np.zeros(x.shape[0])
        t0 = time.perf_counter()
        host.factor(Ke_np, md)
        host.apply(np.asarray(rhs))
        t_lin = time.perf_counter() - t0
        its = 1
    return dict(energy_grad=t_vg, element_hessians=t_ke, linear_solve=t_lin, linear_its=int(its))


def worker(n: int, solver: str, element: str = "p1") -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxelastic as je
    from jaxelastic.solvers.host import map_large_blocks

    map_large_blocks()  # as the jaxelastic command does (docs/guide/linear-solvers.md)

    mesh, pot, bc = _twist_problem(n, element)
    t0 = time.perf_counter()
    # the linear solver's settings and state (what "auto" chose; the host back end with its
    # sparsity analysis), made once and passed to every solve
    newton = je.solvers.prepare_solver(je.Newton(rtol=1e-8, max_steps=50, linear=solver), mesh, bc)
    t_prepare = time.perf_counter() - t0
    kind = type(newton.newton.linear).__name__.lower()
    t0 = time.perf_counter()
    je.solve(pot, bc, solver=newton, throw=False)
    t_cold = time.perf_counter() - t0
    rss_cold = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # MiB on Linux
    warm_times = []
    for _ in range(3):  # min of 3 warm solves
        t0 = time.perf_counter()
        warm = je.solve(pot, bc, solver=newton, throw=False)
        warm_times.append(time.perf_counter() - t0)
    rss_warm = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    host = newton.linear_state.host  # the HostLinearSolver (direct / amg), or None
    info = dict(host.last_info) if host is not None else {}
    backend = info.get("backend", kind if kind != "direct" else "?")
    phases = _phase_split(pot, warm.x, bc, host)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # MiB on Linux
    return dict(
        n=n,
        element=element,
        mesh_element=mesh.element,
        tets=int(mesh.n_cells),
        dofs=int(mesh.n_dofs),
        solver=solver,
        kind=kind,
        backend=backend,
        factor_s=float(info.get("setup_time", float("nan"))),
        status=int(warm.status),
        prepare_s=t_prepare,
        cold_s=t_cold,
        warm_s=min(warm_times),
        warm_times_s=warm_times,
        peak_rss_after_cold_mib=rss_cold,
        peak_rss_after_warm_mib=rss_warm,
        newton=int(warm.stats["steps"]),
        linear_its=int(warm.stats["linear_iterations"]),
        residual=float(warm.stats["residual"]),
        peak_rss_mib=rss,
        phases=phases,
    )


def breakdown_worker(n: int, solver: str, element: str = "p1") -> dict:
    """Where one warm twist solve's time goes, per Newton iteration (host Newton loop).

    After a cold solve, one warm solve runs with timing wrappers around the three compiled
    pieces of :func:`jaxelastic.solvers.newton.minimize`'s Python loop (element Hessians + rhs;
    linear solve; line search + update, each synchronised) and around the host back end's
    calls (assembled data → factorisation / AMG setup; preconditioner or solve
    applications). The linear-solve piece minus the host calls is the device part: the
    segment-sum assembly of the CSR data, the host transfers and (AMG) the device CG.
    """
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxelastic as je
    from jaxelastic.solvers.newton import driver as N

    mesh, pot, bc = _twist_problem(n, element)
    newton = je.solvers.prepare_solver(je.Newton(rtol=1e-8, max_steps=50, linear=solver), mesh, bc)
    host = newton.linear_state.host
    log: list[dict] = []
    cur: dict = {}

    def timed(name, fn, sync=True):
        def wrapped(*a, **k):
            t = time.perf_counter()
            out = fn(*a, **k)
            if sync:
                jax.block_until_ready(out)
            cur[name] = cur.get(name, 0.0) + time.perf_counter() - t
            cur[name + "_calls"] = cur.get(name + "_calls", 0) + 1
            return out

        return wrapped

    pieces = ("_loop_prepare", "_loop_linear", "_host_linear_step", "_loop_finish")
    orig = {k: getattr(N, k) for k in pieces}
    if host is not None:  # before compiling: the callbacks capture the bound methods
        for meth, name in (
            ("factor_upper", "host_factor"),
            ("apply", "host_apply"),
            ("factor_cg_upper", "host_factor_cg"),
        ):
            setattr(host, meth, timed(name, getattr(host, meth), sync=False))
    je.solve(pot, bc, solver=newton, throw=False)  # cold: compile everything
    cur.clear()
    N._loop_prepare = timed("element_hessians_rhs", orig["_loop_prepare"])
    N._loop_linear = timed("linear_piece", orig["_loop_linear"])
    N._host_linear_step = timed("linear_piece", orig["_host_linear_step"])

    def update(*a, **k):
        out = timed("line_search_update", orig["_loop_finish"])(*a, **k)
        log.append(dict(cur))
        cur.clear()
        return out

    N._loop_finish = update
    t0 = time.perf_counter()
    sol = je.solve(pot, bc, solver=newton, throw=False)
    total = time.perf_counter() - t0
    for k, v in orig.items():
        setattr(N, k, v)
    keys = sorted({k for row in log for k in row if not k.endswith("_calls")})
    sums = {k: float(sum(r.get(k, 0.0) for r in log)) for k in keys}
    return dict(
        n=n,
        solver=solver,
        dofs=int(mesh.n_dofs),
        total_s=total,
        newton=int(sol.stats["steps"]),
        linear_its=int(sol.stats["linear_iterations"]),
        per_iteration=log,
        sums_s=sums,
        peak_rss_mib=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    )


def be_step_worker() -> dict:
    """Time one backward-Euler step of the default scene (cold and warm)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import dynamics, loads, materials

    mesh = je.box(20, 3, 3, size=(2.0, 0.25, 0.25))
    params = je.Lame.from_E_nu(1e7, 0.3)
    bc = loads.fix(mesh, loads.nodes_on_plane(mesh, 0, 0.0))
    mass = jnp.asarray(loads.lumped_mass(mesh, 1000.0))
    g = jnp.asarray(loads.gravity_load(mesh, 1000.0, [0, 0, -9.81]))
    out = {}
    variants = {
        "gravity+BE": dict(f_ext=g),
        "no gravity (pre-stretched)": dict(f_ext=None),
    }
    for name, kw in variants.items():
        base = je.Potential(mesh=mesh, params=params, mass=mass, psi=materials.neo_hookean, **kw)
        x0 = mesh.points if kw["f_ext"] is not None else mesh.points * 1.01
        st = dynamics.init_state(x0)
        integ = dynamics.Integrator(h=0.02)
        step = jax.jit(dynamics.step, static_argnames=("integ", "solver"))
        # what the default scene uses: "auto", bound once
        solver = je.solvers.prepare_solver(je.Newton(), mesh, bc)
        t0 = time.perf_counter()
        st1, r = step(base, st, bc, integ, solver=solver)
        jax.block_until_ready(st1)
        cold = time.perf_counter() - t0
        ts = []
        for _ in range(5):
            t0 = time.perf_counter()
            st1, r = step(base, st, bc, integ, solver=solver)
            jax.block_until_ready(st1)
            ts.append(time.perf_counter() - t0)
        out[name] = dict(cold_s=cold, warm_s=float(np.median(ts)), newton=int(r.stats["steps"]))
    return out


def parts_worker() -> dict:
    """Show that optional parts cost nothing when switched off (same mesh, static solve)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import loads, materials
    from jaxelastic.mechanics import potential as P

    mesh = je.box(40, 10, 10, size=(4.0, 1.0, 1.0))
    params = je.Lame.from_E_nu(1e6, 0.3)
    x = mesh.points * 1.001
    g = jnp.asarray(loads.gravity_load(mesh, 1000.0, [0, 0, -9.81]))
    mass = jnp.asarray(loads.lumped_mass(mesh, 1000.0))
    pots = {
        "elastic only": je.Potential(mesh=mesh, params=params, psi=materials.neo_hookean),
        "+ gravity": je.Potential(mesh=mesh, params=params, f_ext=g, psi=materials.neo_hookean),
        "+ gravity + inertia": je.Potential(
            mesh=mesh,
            params=params,
            f_ext=g,
            mass=mass,
            x_tilde=x,
            inertia_weight=jnp.asarray(2500.0),
            psi=materials.neo_hookean,
        ),
    }
    fns = {
        "gradient": jax.jit(P.gradient),
        "hvp": jax.jit(lambda p, x: P.hessian_vp(p, x, x)),
        "element_hessians": jax.jit(lambda p, x: P.elastic_element_hessians(p, x, False)),
    }
    out = {}
    for pname, pot in pots.items():
        row = {}
        for fname, fn in fns.items():
            jax.block_until_ready(fn(pot, x))
            ts = []
            for _ in range(20):
                t0 = time.perf_counter()
                jax.block_until_ready(fn(pot, x))
                ts.append(time.perf_counter() - t0)
            row[fname + "_ms"] = 1e3 * float(np.median(ts))
        out[pname] = row
    return out


def _run_sub(args: list[str]) -> dict:
    cmd = [sys.executable, __file__, "--worker", *args]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        return dict(error=proc.stderr[-2000:])
    return json.loads(proc.stdout.strip().splitlines()[-1])


_BREAKDOWN_KEYS = (
    ("element_hessians_rhs", "Ke+rhs"),
    ("host_factor", "factor/setup"),
    ("host_apply", "host apply"),
    ("host_factor_cg", "host set+CG"),
    ("linear_piece", "lin piece"),
    ("line_search_update", "line srch"),
)


def _breakdown_main(a) -> int:
    """``--breakdown``: one row per Newton iteration of one warm solve, seconds."""
    from jaxelastic.io import write_json

    rows = []
    for n in [int(s) for s in a.sizes.split(",")]:
        for solver in a.solvers.split(","):
            r = _run_sub(["breakdown", str(n), solver, a.element])
            rows.append(r)
            if "error" in r:
                print(f"{n:>3} {solver:>7} ERROR: {r['error'][-300:]}")
                continue
            print(
                f"\ntwist n = {n}, {solver}: warm solve {r['total_s']:.2f} s, {r['newton']} "
                f"Newton, {r['linear_its']} linear its, peak RSS {r['peak_rss_mib']:.0f} MiB"
            )
            print("  it " + " ".join(f"{h:>12}" for _, h in _BREAKDOWN_KEYS) + "  applies")
            for i, it in enumerate(r["per_iteration"]):
                vals = " ".join(f"{it.get(k, 0.0):>12.3f}" for k, _ in _BREAKDOWN_KEYS)
                print(f"  {i:>2} {vals}  {it.get('host_apply_calls', 0):>7}")
            tot = " ".join(f"{r['sums_s'].get(k, 0.0):>12.3f}" for k, _ in _BREAKDOWN_KEYS)
            print(f"  Σ  {tot}")
    Path(a.out).mkdir(parents=True, exist_ok=True)
    write_json(Path(a.out) / "bench_solvers_breakdown.json", dict(breakdown=rows), indent=2)
    print(f"\nwrote {Path(a.out) / 'bench_solvers_breakdown.json'}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--sizes", default="10,19,29")
    ap.add_argument("--solvers", default="cg,direct")
    ap.add_argument("--out", default="out/bench_solvers")
    ap.add_argument("--skip-extras", action="store_true", help="skip BE step and parts")
    ap.add_argument("--element", default="p1", choices=sorted(ELEMENTS), help="twist element")
    ap.add_argument(
        "--breakdown",
        action="store_true",
        help="instead: where one warm solve's time goes, per Newton iteration",
    )
    ap.add_argument("--worker", nargs="+", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        kind = a.worker[0]
        if kind == "twist":
            res = worker(int(a.worker[1]), a.worker[2], *a.worker[3:4])
        elif kind == "breakdown":
            res = breakdown_worker(int(a.worker[1]), a.worker[2], *a.worker[3:4])
        elif kind == "be":
            res = be_step_worker()
        else:
            res = parts_worker()
        print(json.dumps(res))
        return 0

    if a.breakdown:
        return _breakdown_main(a)
    rows = []
    hdr = (
        f"{'n':>3} {'tets':>7} {'dofs':>7} {'solver':>7} {'back end':>9} {'status':>6} "
        f"{'cold s':>8} {'warm s':>8} {'newton':>6} {'lin its':>7} {'RSS MiB':>8} "
        f"{'E+g s':>7} {'Ke s':>7} {'factor s':>8} {'lin s':>7}"
    )
    print(f"twist benchmark, element {a.element} (2-core CPU, float64; cold includes compilation)")
    print(hdr)
    for n in [int(s) for s in a.sizes.split(",")]:
        for solver in a.solvers.split(","):
            r = _run_sub(["twist", str(n), solver, a.element])
            r.setdefault("n", n)
            r.setdefault("element", a.element)
            r.setdefault("solver", solver)
            rows.append(r)
            if "error" in r:
                print(f"{n:>3} {solver:>7} ERROR: {r['error'][-300:]}")
                continue
            ph = r["phases"]
            print(
                f"{r['n']:>3} {r['tets']:>7} {r['dofs']:>7} {solver:>7} {r['backend']:>9} "
                f"{r['status']:>6} {r['cold_s']:>8.2f} {r['warm_s']:>8.2f} {r['newton']:>6} "
                f"{r['linear_its']:>7} {r['peak_rss_after_warm_mib']:>8.0f} "
                f"{ph['energy_grad']:>7.3f} {ph['element_hessians']:>7.3f} "
                f"{r['factor_s']:>8.3f} {ph['linear_solve']:>7.3f}",
                flush=True,
            )
    result = dict(twist=rows)
    if not a.skip_extras:
        be = _run_sub(["be"])
        result["backward_euler_step"] = be
        print("\nbackward-Euler step of the default scene (1,080 tets, h = 0.02 s, linear=auto):")
        for k, v in be.items():
            if isinstance(v, dict):
                print(
                    f"  {k:<28} cold {v['cold_s']:.2f} s, warm {v['warm_s'] * 1e3:.1f} ms, "
                    f"{v['newton']} Newton steps"
                )
        parts = _run_sub(["parts"])
        result["parts"] = parts
        print("\ncost of optional parts (24,000 tets; ms per call, warm):")
        for k, v in parts.items():
            if isinstance(v, dict):
                print(
                    f"  {k:<22} gradient {v['gradient_ms']:.2f}  hvp {v['hvp_ms']:.2f}  "
                    f"element Hessians {v['element_hessians_ms']:.2f} (built only when the "
                    "Newton settings need them)"
                )
    from jaxelastic.io import write_json  # here: the driver itself stays free of JAX

    Path(a.out).mkdir(parents=True, exist_ok=True)
    write_json(Path(a.out) / "bench_solvers.json", result, indent=2, nonfinite="string")
    print(f"\nwrote {Path(a.out) / 'bench_solvers.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
