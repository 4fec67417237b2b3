"""Benchmark of differentiable solves: forward solve, ``value_and_grad`` w.r.t. (E, ν), and a fit.

Problem: a 3D neo-Hookean cantilever ``box(24, 6, 6)`` of size 4 × 1 × 1 m (5,184 tets,
1,225 nodes, the size of JAX-FEM's inverse-problem cantilever), clamped at x = 0, dead
end traction at x = 4 (bending: t = (0, 0, −2 kPa); a second, stretching case
t = (20 kPa, 0, 0) is used by the fit), E = 1 MPa, ν = 0.3 (tip deflection ≈ 0.35 m).

Timed per linear solver (``cg``: matrix-free block-Jacobi PCG inside jit for Newton and
adjoint; ``direct``: sparse Cholesky on the host; ``amg``: AMG-preconditioned CG on the
host; in the split, the host solvers' adjoint is a factorisation + solve (direct) or
AMG-preconditioned SciPy CG to the adjoint tolerance):

* ``forward``: one :func:`jaxelastic.solve` from the rest shape at
  (E, ν) = (3E*, ν* − 0.15) (Newton to a relative residual 1e-10);
* ``value_and_grad``: the same solve plus the adjoint, of the loss
  ``‖x*(E, ν) − x_obs‖² / ‖x_obs − X‖²`` (x_obs: the solution at the true parameters);
* the split of the backward pass: one element-Hessian evaluation and the adjoint linear
  solve at the solution (iterations and time);
* ``fit``: :func:`jaxelastic.fitting.fit` from (3E*, ν* − 0.15) on the bending and
  stretching cases (all nodes observed, ``--fit-linear`` solver), run twice: including
  compilation, then warm.

Warm times are medians of ``--repeats`` calls of the compiled function; the compile time
is the first call minus the warm median. Timings on a shared machine are noisy: compare the
ratios within one run.

Usage::

    python scripts/bench_fit.py --out out/bench_fit
    python scripts/bench_fit.py --n 8,2,2 --repeats 2 --solvers cg --out /tmp/bf   # smoke test
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from jaxelastic.io import write_atomic, write_json

JAXFEM = dict(tets=5184, value_and_grad=1.19, forward=0.85)
TORCHFEM = dict(tets=4320, backward=1.95)
TARGET = dict(value_and_grad=0.3, ratio=1.5)
E_TRUE, NU_TRUE = 1.0e6, 0.3


def problem(n=(24, 6, 6), size=(4.0, 1.0, 1.0)):
    """Mesh, Dirichlet data and the bending / stretching load vectors of the cantilever."""
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import loads

    mesh = je.box(*n, size=size)
    length = size[0]
    bc = loads.fix(mesh, loads.nodes_on_plane(mesh, 0, 0.0))
    end = loads.facets_where(mesh, lambda X: np.isclose(X[:, 0], length))
    f_bend = jnp.asarray(loads.traction_load(mesh, end, (0.0, 0.0, -2.0e3)))
    f_stretch = jnp.asarray(loads.traction_load(mesh, end, (2.0e4, 0.0, 0.0)))
    return mesh, bc, f_bend, f_stretch


def _timed(fn, *args, repeats: int):
    """(first call [s], warm median [s], all warm times, output of the last call)."""
    import jax

    t = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return first, float(np.median(times)), times, out


def _amg_cg(host, K, b, rtol: float) -> int:
    """SciPy CG on the assembled K, preconditioned by the host AMG V-cycle; iterations."""
    import scipy.sparse.linalg as spla

    n = K.shape[0]
    count = [0]

    def M(r):
        count[0] += 1
        return host.apply(np.asarray(r).reshape(b.shape)).reshape(-1)

    spla.cg(K, b.reshape(-1), rtol=rtol, M=spla.LinearOperator((n, n), matvec=M))
    return count[0]


def _host_adjoint(kind: str, mesh, bc, Ke, rhs, repeats: int):
    """(median time [s], iterations) of the adjoint solve with a host back end at the
    solution: factorise (direct) / build the hierarchy (AMG) and solve; AMG as the
    preconditioner of a SciPy CG to the adjoint tolerance."""
    import jax.numpy as jnp

    import jaxelastic as je

    host = je.solvers.HostLinearSolver.for_problem(mesh, bc, kind)
    Ks = np.asarray(0.5 * (Ke + jnp.swapaxes(Ke, 1, 2)))
    md = np.zeros(mesh.n_nodes)
    b = np.asarray(rhs)
    rtol = je.ImplicitAdjoint().rtol
    ts, its = [], 1
    for _ in range(max(repeats, 1)):
        t = time.perf_counter()
        host.factor(Ks, md)
        if kind == "direct":
            host.apply(b)
        else:
            its = _amg_cg(host, host.assemble(Ks), b, rtol)
        ts.append(time.perf_counter() - t)
    return float(np.median(ts)), int(its)


def bench_solver(kind: str, mesh, bc, f_bend, x_obs, repeats: int) -> dict:
    """Forward, value_and_grad and the backward split for one linear solver."""
    import jax
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic.materials import Lame
    from jaxelastic.mechanics import potential as P
    from jaxelastic.solvers.linear import block_jacobi, cg

    solver = je.solvers.prepare_solver(je.Newton(rtol=1e-10, linear=kind), mesh, bc)
    X = mesh.points
    scale = jnp.sum((x_obs - X) ** 2)

    def pot_of(th):
        return je.Potential(
            mesh=mesh,
            params=Lame.from_E_nu(th[0], th[1]),
            f_ext=f_bend,
            psi=je.materials.neo_hookean,
        )

    def forward(th):
        return je.solve(pot_of(th), bc, x0=X, solver=solver, throw=False)

    def loss(th):
        r = je.solve(pot_of(th), bc, x0=X, solver=solver, throw=False)
        return jnp.sum((r.x - x_obs) ** 2) / scale, r

    th0 = jnp.array([3.0 * E_TRUE, NU_TRUE - 0.15])
    fwd = jax.jit(forward)
    vg = jax.jit(jax.value_and_grad(loss, has_aux=True))
    f_first, f_warm, f_all, res = _timed(fwd, th0, repeats=repeats)
    if int(res.status) != je.Status.SUCCESS:
        raise RuntimeError(f"{kind}: forward solve failed: {je.Status(int(res.status)).name}")
    v_first, v_warm, v_all, ((val, _), g) = _timed(vg, th0, repeats=repeats)
    if not bool(jnp.all(jnp.isfinite(g))):
        raise RuntimeError(f"{kind}: non-finite gradient {g}")

    # split of the backward pass at the solution: element Hessians + adjoint solve
    x = res.x
    pot = pot_of(th0)
    ke = jax.jit(lambda pot, x: P.elastic_element_hessians(pot, x, False))
    _, t_ke, _, Ke = _timed(ke, pot, x, repeats=repeats)
    free = ~bc.mask
    fm = free.astype(x.dtype)
    rhs = fm * 2.0 * (x - x_obs) / scale  # the loss's cotangent of x
    adj = je.ImplicitAdjoint()

    @jax.jit
    def adjoint_cg(pot, Ke, rhs):
        M = block_jacobi(P.node_hessian_blocks(pot, Ke), free)

        def A(v):
            return fm * P.element_hessian_vp(pot, Ke, fm * v) + (1.0 - fm) * v

        tol = adj.rtol * jnp.linalg.norm(rhs)
        return cg(A, rhs, M, tol=tol, max_iter=adj.max_iter)

    if kind == "cg":
        _, t_adj, _, ares = _timed(adjoint_cg, pot, Ke, rhs, repeats=repeats)
        adj_its = int(ares.stats["iterations"])
    else:
        t_adj, adj_its = _host_adjoint(kind, mesh, bc, Ke, rhs, repeats)
    return dict(
        solver=kind,
        forward_warm=f_warm,
        forward_compile=f_first - f_warm,
        forward_all=f_all,
        value_and_grad_warm=v_warm,
        value_and_grad_compile=v_first - v_warm,
        value_and_grad_all=v_all,
        backward=v_warm - f_warm,
        ratio=v_warm / f_warm,
        newton_steps=int(res.stats["steps"]),
        newton_linear_iterations=int(res.stats["linear_iterations"]),
        element_hessians=t_ke,
        adjoint_solve=t_adj,
        adjoint_iterations=adj_its,
        loss=float(val),
        grad=[float(a) for a in g],
    )


def bench_fit(mesh, bc, f_bend, f_stretch, obs, linear: str) -> dict:
    """A full (E, ν) fit on the bending + stretching cases, all nodes observed: run twice,
    the first including compilation, the second warm (same compiled functions)."""
    import jaxelastic as je
    from jaxelastic.fitting import LoadCase, Material, fit

    cases = [
        LoadCase(
            pot=je.Potential(mesh=mesh, params=None, f_ext=f, psi=je.materials.neo_hookean),
            bc=bc,
            observed=o,
        )
        for f, o in zip((f_bend, f_stretch), obs, strict=True)
    ]
    solver = je.Newton(rtol=1e-11, linear=linear)
    walls = []
    for _ in range(2):
        t = time.perf_counter()
        r = fit(cases, Material(E=3.0 * E_TRUE, nu=NU_TRUE - 0.15), max_iter=60, solver=solver)
        walls.append(time.perf_counter() - t)
    its = int(r.iterations)
    return dict(
        linear=linear,
        wall_incl_compile=walls[0],
        wall_warm=walls[1],
        iterations=its,
        warm_per_iteration=walls[1] / max(its, 1),
        converged=bool(r.converged),
        stop_reason=r.stop_reason,
        E=float(r.E),
        nu=float(r.nu),
        E_rel_error=abs(r.E - E_TRUE) / E_TRUE,
        nu_rel_error=abs(r.nu - NU_TRUE) / NU_TRUE,
        loss=float(r.loss),
        newton_steps_total=int(np.sum(r.newton_steps)),
        newton_steps_first_iterate=[int(a) for a in np.asarray(r.newton_steps)[0]],
        newton_steps_last_iterate=[int(a) for a in np.asarray(r.newton_steps)[-1]],
    )


def _table(rows, fit_row, n_cells) -> str:
    head = (
        f"{'solver':8s} {'forward s':>10s} {'v&g s':>8s} {'v&g/fwd':>8s} {'backward s':>10s} "
        f"{'Newton':>6s} {'lin its':>7s} {'Ke s':>7s} {'adjoint s':>9s} {'adj its':>7s} "
        f"{'compile fwd/v&g s':>18s}"
    )
    lines = [f"cantilever: {n_cells} tets", head, "-" * len(head)]
    for r in rows:
        lines.append(
            f"{r['solver']:8s} {r['forward_warm']:10.3f} {r['value_and_grad_warm']:8.3f} "
            f"{r['ratio']:8.2f} {r['backward']:10.3f} {r['newton_steps']:6d} "
            f"{r['newton_linear_iterations']:7d} {r['element_hessians']:7.3f} "
            f"{r['adjoint_solve']:9.3f} {r['adjoint_iterations']:7d} "
            f"{r['forward_compile']:8.1f}/{r['value_and_grad_compile']:.1f}"
        )
    lines.append(
        f"targets: value_and_grad <= {TARGET['value_and_grad']} s and <= {TARGET['ratio']}x "
        f"forward; JAX-FEM {JAXFEM['value_and_grad']} s (forward {JAXFEM['forward']} s) on "
        f"{JAXFEM['tets']} tets; torch-fem backward {TORCHFEM['backward']} s on "
        f"{TORCHFEM['tets']} tets"
    )
    if fit_row:
        f = fit_row
        lines.append(
            f"fit ({f['linear']}, bend + stretch): {f['iterations']} iterations, "
            f"{f['wall_warm']:.1f} s warm ({f['warm_per_iteration']:.2f} s/iteration), "
            f"{f['wall_incl_compile']:.1f} s incl. compile; "
            f"E err {f['E_rel_error']:.1e}, nu err {f['nu_rel_error']:.1e}"
        )
    return "\n".join(lines)


def _plot(rows, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.2))
    names = [r["solver"] for r in rows] + ["JAX-FEM"]
    fwd = [r["forward_warm"] for r in rows] + [JAXFEM["forward"]]
    vg = [r["value_and_grad_warm"] for r in rows] + [JAXFEM["value_and_grad"]]
    xs = np.arange(len(names))
    ax.bar(xs - 0.2, fwd, 0.4, label="forward solve")
    ax.bar(xs + 0.2, vg, 0.4, label="value_and_grad")
    ax.axhline(TARGET["value_and_grad"], color="k", ls="--", lw=0.8, label="target 0.3 s")
    ax.set_xticks(xs, names)
    ax.set_ylabel("warm time [s]")
    ax.set_title("3D neo-Hookean cantilever, ~5k tets (warm, median)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    try:
        write_atomic(path, lambda tmp: fig.savefig(tmp, format="png", dpi=120))
    finally:
        plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/bench_fit")
    ap.add_argument("--n", default="24,6,6", help="cells per axis (default: %(default)s)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--solvers", default="cg,direct,amg")
    ap.add_argument("--no-fit", action="store_true", help="skip the full fit")
    ap.add_argument("--fit-linear", default="cg", help="linear solver of the fit")
    args = ap.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic.materials import Lame

    n = tuple(int(a) for a in args.n.split(","))
    mesh, bc, f_bend, f_stretch = problem(n)
    params = Lame.from_E_nu(E_TRUE, NU_TRUE)
    obs = []
    for f in (f_bend, f_stretch):
        pot = je.Potential(mesh=mesh, params=params, f_ext=f, psi=je.materials.neo_hookean)
        obs.append(je.solve(pot, bc, solver=je.Newton(rtol=1e-12, linear="direct")).x)
    tip = float(jnp.max(jnp.abs(obs[0][:, 2] - mesh.points[:, 2])))
    print(
        f"mesh {n}: {mesh.n_cells} tets, {mesh.n_nodes} nodes; tip deflection {tip:.4f} m",
        file=sys.stderr,
    )
    rows = []
    for kind in args.solvers.split(","):
        print(f"timing {kind} ...", file=sys.stderr, flush=True)
        rows.append(bench_solver(kind, mesh, bc, f_bend, obs[0], args.repeats))
    fit_row = None
    if not args.no_fit:
        print("fitting ...", file=sys.stderr, flush=True)
        fit_row = bench_fit(mesh, bc, f_bend, f_stretch, obs, args.fit_linear)
    print(_table(rows, fit_row, mesh.n_cells))
    os.makedirs(args.out, exist_ok=True)
    result = dict(
        problem=dict(
            n=n,
            n_cells=mesh.n_cells,
            n_nodes=mesh.n_nodes,
            E=E_TRUE,
            nu=NU_TRUE,
            tip_deflection=tip,
            start=dict(E=3 * E_TRUE, nu=NU_TRUE - 0.15),
        ),
        jax=jax.__version__,
        devices=[str(d) for d in jax.devices()],
        cpu_count=os.cpu_count(),
        solvers=rows,
        fit=fit_row,
        references=dict(jaxfem=JAXFEM, torchfem=TORCHFEM, target=TARGET),
        note="warm = median of repeated calls of the compiled function; shared machine, noisy",
    )
    write_json(os.path.join(args.out, "bench_fit.json"), result, indent=1, nonfinite="string")
    _plot(rows, os.path.join(args.out, "bench_fit.png"))
    print(f"wrote {args.out}/bench_fit.json and bench_fit.png", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
