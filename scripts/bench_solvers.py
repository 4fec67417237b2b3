"""Solver benchmark: the JAX-FEM "twist" hyperelasticity problem, a backward-Euler step,
and the cost of each optional part of a scene.

Twist: unit cube ``box(n, n, n)`` (6n³ tets), face x = 1 clamped, face x = 0 given
u_x = 0 and half of a 60° rotation about the x axis through (y, z) = (0.5, 0.5); user ψ
isochoric neo-Hookean ``μ/2 (J^(−2/3) I_C − 3) + κ/2 (J − 1)²`` with E = 10, ν = 0.3,
κ = E/(3(1 − 2ν)); converged to a relative residual of 1e-8. Each (n, linear solver) runs
in a fresh subprocess so its peak RSS and cold (compile-including) time are its own.

Reported per run: cold wall time (first solve, including tracing and XLA compilation),
warm wall time (second solve, same compiled code), Newton and linear iterations, peak RSS,
and a per-phase split of one warm Newton iteration (energy+gradient, element Hessians,
linear solve).

``--element`` (default ``p1``): ``p2`` runs the twist on ``box(n, n, n, order=2)``
(tet10; n = 9–10 has about the dofs of P1 n = 19), ``p2fbar`` the same with the F-bar
formulation, ``composite`` the composite F-bar tets (tet4x8, same nodes as P2).

Usage::

    python scripts/bench_solvers.py                      # n = 10, 19, 29; cg and direct
    python scripts/bench_solvers.py --sizes 10 --solvers cg,direct,amg --out out/bench
    python scripts/bench_solvers.py --element p2 --sizes 5,9 --solvers direct,amg
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
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
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import loads

    mesh = je.box(n, n, n, **ELEMENTS[element])
    E, nu = 10.0, 0.3
    mu = E / (2 * (1 + nu))
    kappa = E / (3 * (1 - 2 * nu))
    th = np.pi / 3

    def u(X):
        y, z = X[:, 1], X[:, 2]
        return np.stack(
            [
                0 * y,
                (0.5 + (y - 0.5) * np.cos(th) - (z - 0.5) * np.sin(th) - y) / 2,
                (0.5 + (y - 0.5) * np.sin(th) + (z - 0.5) * np.cos(th) - z) / 2,
            ],
            1,
        )

    bc = loads.combine(
        loads.fix(mesh, loads.nodes_on_plane(mesh, 0, 1.0)),
        loads.fix(mesh, loads.nodes_on_plane(mesh, 0, 0.0), displacement=u),
    )

    def psi_iso(F, p):
        J = je.kinematics.det(F)
        return p.mu / 2 * (J ** (-2.0 / 3.0) * jnp.sum(F * F) - 3) + p.lam / 2 * (J - 1) ** 2

    pot = je.Potential(mesh=mesh, params=je.Lame(mu, kappa), psi=psi_iso)
    return mesh, pot, bc


def _phase_split(pot, x, bc, linear):
    """Time the parts of one Newton iteration at configuration x (warm, median of 3)."""
    import jax
    import jax.numpy as jnp

    from jaxelastic import potential as P
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
    if linear is None:
        mesh = pot.mesh

        @jax.jit
        def lin(Ke, rhs):
            def H(v):
                ve = v[mesh.cells].reshape(mesh.n_cells, -1)
                out = jnp.einsum("cij,cj->ci", Ke, ve).reshape(mesh.cells.shape + (-1,))
                from jaxelastic.energy import assemble

                return fm * assemble(mesh, out * 1.0) + (1 - fm) * v

            M = block_jacobi(P.node_hessian_blocks(pot, Ke), free)
            return cg(lambda v: H(fm * v), rhs, M, tol=1e-6 * jnp.linalg.norm(rhs), max_iter=5000)

        t_lin, res = timeit(lin, Ke, rhs)
        its = int(res.iterations)
    else:
        Ke_np = np.asarray(Ke)
        md = np.zeros(x.shape[0])
        t0 = time.perf_counter()
        _, its, _ = linear(Ke_np, md, np.asarray(rhs), 1e-6)
        t_lin = time.perf_counter() - t0
    return dict(energy_grad=t_vg, element_hessians=t_ke, linear_solve=t_lin, linear_its=int(its))


def worker(n: int, solver: str, element: str = "p1") -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxelastic.solvers.host import HostLinearSolver
    from jaxelastic.solvers.newton import NewtonSettings, solve

    mesh, pot, bc = _twist_problem(n, element)
    linear = None if solver == "cg" else HostLinearSolver.for_problem(mesh, bc, solver)
    settings = NewtonSettings(rtol=1e-8, max_steps=50)
    t0 = time.perf_counter()
    solve(pot, bc, settings=settings, linear=linear, throw=False)
    t_cold = time.perf_counter() - t0
    warm = solve(pot, bc, settings=settings, linear=linear, throw=False)
    phases = _phase_split(pot, warm.x, bc, linear)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # MiB on Linux
    return dict(
        n=n,
        element=element,
        mesh_element=mesh.element,
        tets=int(mesh.n_cells),
        dofs=int(mesh.n_dofs),
        solver=solver,
        status=int(warm.status),
        cold_s=t_cold,
        warm_s=float(warm.wall_time),
        newton=int(warm.steps),
        linear_its=int(warm.linear_iterations),
        residual=float(warm.residual),
        peak_rss_mib=rss,
        phases=phases,
    )


def be_step_worker() -> dict:
    """Time one backward-Euler step of the default scene (cold and warm)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import dynamics, loads, materials
    from jaxelastic.solvers.newton import make_linear

    mesh = je.box(20, 3, 3, size=(2.0, 0.25, 0.25))
    params = je.Lame(*je.lame(1e7, 0.3))
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
        step = jax.jit(dynamics.step, static_argnames=("integ", "settings", "linear"))
        linear = make_linear(mesh, bc, "auto")  # what the default scene uses
        t0 = time.perf_counter()
        st1, r = step(base, st, bc, integ, linear=linear)
        jax.block_until_ready(st1)
        cold = time.perf_counter() - t0
        ts = []
        for _ in range(5):
            t0 = time.perf_counter()
            st1, r = step(base, st, bc, integ, linear=linear)
            jax.block_until_ready(st1)
            ts.append(time.perf_counter() - t0)
        out[name] = dict(cold_s=cold, warm_s=float(np.median(ts)), newton=int(r.steps))
    return out


def parts_worker() -> dict:
    """Show that optional parts cost nothing when switched off (same mesh, static solve)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import loads, materials
    from jaxelastic import potential as P

    mesh = je.box(40, 10, 10, size=(4.0, 1.0, 1.0))
    params = je.Lame(*je.lame(1e6, 0.3))
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


def _atomic_write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.replace(tmp, path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--sizes", default="10,19,29")
    ap.add_argument("--solvers", default="cg,direct")
    ap.add_argument("--out", default="out/bench_solvers")
    ap.add_argument("--skip-extras", action="store_true", help="skip BE step and parts")
    ap.add_argument("--element", default="p1", choices=sorted(ELEMENTS), help="twist element")
    ap.add_argument("--worker", nargs="+", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        kind = a.worker[0]
        if kind == "twist":
            res = worker(int(a.worker[1]), a.worker[2], *a.worker[3:4])
        elif kind == "be":
            res = be_step_worker()
        else:
            res = parts_worker()
        print(json.dumps(res))
        return 0

    rows = []
    hdr = (
        f"{'n':>3} {'tets':>7} {'dofs':>7} {'solver':>7} {'status':>6} {'cold s':>8} "
        f"{'warm s':>8} {'newton':>6} {'lin its':>7} {'RSS MiB':>8} "
        f"{'E+g s':>7} {'Ke s':>7} {'lin s':>7}"
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
                f"{r['n']:>3} {r['tets']:>7} {r['dofs']:>7} {solver:>7} {r['status']:>6} "
                f"{r['cold_s']:>8.2f} {r['warm_s']:>8.2f} {r['newton']:>6} {r['linear_its']:>7} "
                f"{r['peak_rss_mib']:>8.0f} {ph['energy_grad']:>7.3f} "
                f"{ph['element_hessians']:>7.3f} {ph['linear_solve']:>7.3f}"
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
    _atomic_write(Path(a.out) / "bench_solvers.json", json.dumps(result, indent=2))
    print(f"\nwrote {Path(a.out) / 'bench_solvers.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
