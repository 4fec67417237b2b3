"""Benchmark the host linear-algebra path: element Hessians → CSR assembly → solve.

Two 3D problems linearised at rest, isochoric neo-Hookean (``materials.isochoric_neo_hookean``)
``ψ = μ/2 (J^(-2/3) tr(FᵀF) − 3) + κ/2 (J − 1)²`` with E = 10, ν = 0.3:

* ``twist``: unit cube ``box(n, n, n)``, faces x = 0 and x = 1 clamped, the x = 1 face
  turned by a small angle about the cube's axis (the first Newton step of the twist
  scene: the right-hand side is the lifting ``−K_fd u_d``);
* ``cantilever``: ``box(4n, n, n, size=(4, 1, 1))`` clamped at x = 0 under its own weight
  (bending-dominated: the hard case for Jacobi-CG, DESIGN §4).

For each size it times the jitted element Hessians (compile and steady state), the
sparsity analysis (building a :class:`~jaxelastic.solvers.host.HostLinearSolver`), the
host assembly, and for each back end (AMG; the direct back ends PARDISO, CHOLMOD,
cholespy, SuperLU that import, the last two only up to ``--slow-max-dofs``) ``setup``
(host assembly + first factorisation with the symbolic analysis / AMG setup),
``refactor`` (a later Newton step's numeric factorisation from the upper data / AMG
Galerkin refresh) and the solve to ``--rtol``, with the peak resident memory of each stage
(psutil, sampled), and ``direct_over_amg`` (best direct setup+solve over AMG's). It also
times AMG hierarchy reuse over a sequence of five matrices along a twisting path. Prints a
table and writes ``bench_linear.json`` (atomically) to ``--out``.

The library's only Krylov loop is the device CG (``jaxelastic.solvers.linear.krylov``); the
host back ends only factorise and apply. To time the host side alone, this measurement
script has its own small NumPy PCG (:func:`pcg`): the AMG rows run it with one V-cycle
(``HostLinearSolver.apply``) per iteration, the ``cg-jacobi`` baseline with the inverse
diagonal; the direct rows are one exact ``apply``.

OpenBLAS threads are capped at 1 unless ``OPENBLAS_NUM_THREADS`` is set: with more
threads than free cores, OpenBLAS's spinning threads made every CG vector dot ~10x slower
in our runs (the machine's load average is recorded in the JSON).

    python scripts/bench_linear.py                 # n = 10, 19, 29
    python scripts/bench_linear.py --sizes 10,14,19,24,29 --problems twist --no-reuse
    python scripts/bench_linear.py --sizes 10,19 --out out/bench_linear
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import psutil  # noqa: E402

import jaxelastic  # noqa: E402
from jaxelastic.io import write_json  # noqa: E402
from jaxelastic.materials import Lame, isochoric_neo_hookean  # noqa: E402
from jaxelastic.solvers.host import HostLinearSolver, available_direct_backends  # noqa: E402

E_YOUNG, NU = 10.0, 0.3
MU = E_YOUNG / (2.0 * (1.0 + NU))
KAPPA = E_YOUNG / (3.0 * (1.0 - 2.0 * NU))


_hessians = jax.jit(
    lambda x, mesh, p: jaxelastic.mechanics.element_hessians(isochoric_neo_hookean, x, mesh, p)
)
_hessians_psd = jax.jit(
    lambda x, mesh, p: jaxelastic.mechanics.element_hessians(
        isochoric_neo_hookean, x, mesh, p, project=True
    )
)


class PeakRSS:
    """Context manager sampling this process's RSS every ``dt`` s; ``.peak_mb`` after."""

    def __init__(self, dt: float = 0.02):
        self.dt = dt
        self.proc = psutil.Process()
        self.peak = 0

    def _run(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, self.proc.memory_info().rss)
            self._stop.wait(self.dt)

    def __enter__(self):
        self.peak = self.proc.memory_info().rss
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()
        self.peak = max(self.peak, self.proc.memory_info().rss)

    @property
    def peak_mb(self) -> float:
        return self.peak / 2**20


def timed(fn, *args):
    """``(result, wall seconds, cpu seconds, peak RSS MiB)`` of one call."""
    with PeakRSS() as pk:
        c0, t0 = time.process_time(), time.perf_counter()
        out = fn(*args)
        t, c = time.perf_counter() - t0, time.process_time() - c0
    return out, t, c, pk.peak_mb


def build_problem(kind: str, n: int):
    """Mesh, Dirichlet mask ``(n_dofs,)``, prescribed values ``(n_dofs,)``, load ``(n_dofs,)``."""
    if kind == "twist":
        mesh = jaxelastic.box(n, n, n)
        X = np.asarray(mesh.points)
        left, right = X[:, 0] == 0.0, X[:, 0] == 1.0
        fixed = np.repeat(left | right, 3)
        ud = np.zeros_like(X)  # small rotation (0.01 rad) of the x = 1 face about its axis
        th = 0.01
        y, z = X[:, 1] - 0.5, X[:, 2] - 0.5
        ud[right, 1] = (np.cos(th) * y - np.sin(th) * z - y)[right]
        ud[right, 2] = (np.sin(th) * y + np.cos(th) * z - z)[right]
        load = np.zeros_like(X)
    elif kind == "cantilever":
        mesh = jaxelastic.box(4 * n, n, n, size=(4.0, 1.0, 1.0))
        X = np.asarray(mesh.points)
        fixed = np.repeat(X[:, 0] == 0.0, 3)
        ud = np.zeros_like(X)
        vol = np.zeros(mesh.n_nodes)  # lumped nodal volume: gravity −z with ρg = 1e-2
        np.add.at(vol, np.asarray(mesh.cells).ravel(), np.repeat(np.asarray(mesh.volumes) / 4, 4))
        load = np.zeros_like(X)
        load[:, 2] = -1e-2 * vol
    else:
        raise ValueError(kind)
    return mesh, fixed, ud.reshape(-1), load.reshape(-1)


def rhs(K_full, fixed, ud, load):
    """Right-hand side of the eliminated system for the free increments:
    ``b_f = f_f − K_fd u_d``, ``b_d = 0`` (the fixed dofs are known)."""
    b = load - K_full @ np.where(fixed, ud, 0.0)
    b[fixed] = 0.0
    return b


def twisted(X: np.ndarray, angle: float) -> np.ndarray:
    """Cross-sections x = const of the unit cube turned by ``angle·x`` about its axis."""
    th = angle * X[:, 0]
    y, z = X[:, 1] - 0.5, X[:, 2] - 0.5
    out = X.copy()
    out[:, 1] = 0.5 + np.cos(th) * y - np.sin(th) * z
    out[:, 2] = 0.5 + np.sin(th) * y + np.cos(th) * z
    return out


def pcg(K, b, M, rtol: float, maxiter: int = 2000):
    """Measurement utility: PCG on ``K x = b`` (``(n,)``) to ``‖b − Kx‖ ≤ rtol·‖b‖``.

    Returns ``(x, iterations, converged, relative true residual)``.
    """
    nb = float(np.linalg.norm(b))
    x = np.zeros_like(b)
    r = b.copy()
    z = M(r)
    p = z.copy()
    rz = float(r @ z)
    it = 0
    while it < maxiter and np.linalg.norm(r) > rtol * nb:
        Kp = K @ p
        alpha = rz / float(p @ Kp)
        x += alpha * p
        r -= alpha * Kp
        it += 1
        z = M(r)
        rz, rz_old = float(r @ z), rz
        p = z + (rz / rz_old) * p
    res = float(np.linalg.norm(b - K @ x)) / max(nb, 1e-300)
    return x, it, bool(res <= 1.01 * rtol), res


def host_solve(host: HostLinearSolver, K, b, rtol: float):
    """Solve with the host back end after :meth:`HostLinearSolver.factor`: one exact
    ``apply`` (direct) or the script's PCG with one V-cycle per iteration (AMG)."""
    shape = host.shape
    if host.exact:
        x = host.apply(b.reshape(shape), 0).reshape(-1)
        res = float(np.linalg.norm(b - K @ x)) / max(float(np.linalg.norm(b)), 1e-300)
        return x, 1, bool(res <= rtol), res
    return pcg(K, b, lambda r: host.apply(r.reshape(shape), 0).reshape(-1), rtol)


def run_solver(kind, opts, Ke, K, b, mesh, fixed, rtol, host=None):
    """One row: ``kind`` ``"amg"``/``"direct"`` (a HostLinearSolver, ``host`` if given) or
    ``"cg-jacobi"`` (the script's PCG with the inverse diagonal)."""
    md = np.zeros(mesh.n_nodes)
    if kind == "cg-jacobi":
        t0 = time.perf_counter()
        inv = 1.0 / K.diagonal()
        t_up, c_up, m_up = time.perf_counter() - t0, 0.0, 0.0
        t_re = t_up
        (x, it, ok, res), t_so, c_so, m_so = timed(pcg, K, b, lambda r: inv * r, rtol, 20000)
        info = {}
    else:
        if host is None:
            host = HostLinearSolver(mesh.cells, mesh.points, fixed.reshape(-1, 3), kind, **opts)
        status, t_up, c_up, m_up = timed(host.factor, Ke, md, 0)
        # a Newton step after the first: numeric refactorisation (the symbolic analysis is
        # kept) / AMG Galerkin refresh; upper data precomputed, as the device provides it
        up = host.pattern.upper_data(Ke)
        _, t_re, _, _ = timed(host.factor_upper, up, md, 0)
        (x, it, ok, res), t_so, c_so, m_so = timed(host_solve, host, K, b, rtol)
        info = {
            k: (float(v) if isinstance(v, np.floating) else v) for k, v in host.last_info.items()
        }
        info["factor_status"] = int(status)
    return dict(
        refactor_s=t_re,
        setup_s=t_up,
        setup_cpu_s=c_up,
        solve_s=t_so,
        solve_cpu_s=c_so,
        peak_rss_mb=max(m_up, m_so),
        iterations=it,
        converged=ok,
        residual=res,
        **info,
    ), x


def reuse_study(mesh, fixed, params, rtol, b, angles=(0.0, 0.1, 0.2, 0.3, 0.4)):
    """Total AMG factor+solve time over Hessians at a sequence of twisted states."""
    X = np.asarray(mesh.points)
    kes = [np.asarray(_hessians_psd(jnp.asarray(twisted(X, a)), mesh, params)) for a in angles]
    md = np.zeros(mesh.n_nodes)
    out = {}
    modes = {
        "rebuild every update": dict(reuse=1),
        "galerkin refresh (reuse=5)": dict(reuse=5, refresh="galerkin"),
        "frozen hierarchy (reuse=5)": dict(reuse=5, refresh="none"),
    }
    for name, opts in modes.items():
        host = HostLinearSolver(mesh.cells, X, fixed.reshape(-1, 3), "amg", **opts)
        steps = []
        for Ke in kes:
            _, t_up, c_up, _ = timed(host.factor, Ke, md, 0)
            K = host.assemble(Ke)
            (_, it, ok, _), t_so, c_so, _ = timed(host_solve, host, K, b, rtol)
            steps.append(
                dict(setup_s=t_up, solve_s=t_so, cpu_s=c_up + c_so, iterations=it, converged=ok)
            )
        out[name] = dict(
            total_s=sum(st["setup_s"] + st["solve_s"] for st in steps),
            total_cpu_s=sum(st["cpu_s"] for st in steps),
            iterations=[st["iterations"] for st in steps],
            converged=all(st["converged"] for st in steps),
            steps=steps,
        )
    return out


def bench_case(kind, n, args):
    mesh, fixed, ud, load = build_problem(kind, n)
    rec = dict(
        problem=kind, n=n, n_cells=mesh.n_cells, n_dofs=mesh.n_dofs, n_fixed=int(fixed.sum())
    )
    params = Lame(jnp.asarray(MU), jnp.asarray(KAPPA))
    x0 = mesh.points
    Ke, t, c, m = timed(lambda: _hessians(x0, mesh, params).block_until_ready())
    rec["hessians_first_call_s"] = t  # includes compilation
    Ke, t, c, m = timed(lambda: _hessians(x0, mesh, params).block_until_ready())
    rec.update(hessians_s=t, hessians_cpu_s=c, hessians_peak_rss_mb=m)
    Ke = np.asarray(Ke)
    # the sparsity analysis is the construction of a HostLinearSolver (kept for the AMG row)
    amg, t, c, m = timed(HostLinearSolver, mesh.cells, mesh.points, fixed.reshape(-1, 3), "amg")
    P = amg.pattern
    rec.update(pattern_s=t, pattern_peak_rss_mb=m, nnz=P.nnz)
    K_full = P.assemble_full(Ke)
    b = rhs(K_full, fixed, ud, load)
    del K_full
    times = []
    for _ in range(3):
        K, t, c, m = timed(amg.assemble, Ke)
        times.append(t)
    rec.update(assemble_s=min(times), assemble_peak_rss_mb=m)
    solvers = {}
    runs = [("amg", "amg", {})]
    if mesh.n_dofs <= args.direct_max_dofs:
        for be in args.direct_backends.split(","):
            if be not in available_direct_backends():
                print(f"  (direct back end {be!r} is not importable here: skipped)")
                continue
            if be in ("cholespy", "splu") and mesh.n_dofs > args.slow_max_dofs:
                continue
            runs.append((f"direct-{be}", "direct", dict(backend=be)))
    if n <= args.cg_max_n:
        runs.append(("cg-jacobi", "cg-jacobi", {}))
    xs = {}
    for name, kind_, opts in runs:
        host = amg if kind_ == "amg" else None
        res, xs[name] = run_solver(kind_, opts, Ke, K, b, mesh, fixed, args.rtol, host)
        solvers[name] = res
        print(
            f"  {kind:10s} n={n:3d} {name:16s} setup {res['setup_s']:8.2f}s  refactor "
            f"{res['refactor_s']:7.2f}s  solve "
            f"{res['solve_s']:7.2f}s  it {res['iterations']:5d}  res {res['residual']:.1e}  "
            f"rss {res['peak_rss_mb']:7.0f} MiB",
            flush=True,
        )
    ref = next((xs[k] for k in xs if k.startswith("direct")), None)
    best_direct = min(
        (s["setup_s"] + s["solve_s"] for k, s in solvers.items() if k.startswith("direct")),
        default=None,
    )
    amg_total = solvers["amg"]["setup_s"] + solvers["amg"]["solve_s"]
    rec["direct_over_amg"] = None if best_direct is None else best_direct / amg_total
    if ref is not None:
        for k, x in xs.items():
            solvers[k]["rel_diff_to_direct"] = float(
                np.linalg.norm(x - ref) / max(np.linalg.norm(ref), 1e-300)
            )
    rec["solvers"] = solvers
    if kind == "twist" and not args.no_reuse:
        rec["amg_reuse"] = reuse_study(mesh, fixed, params, args.rtol, b)
        for name, r in rec["amg_reuse"].items():
            print(
                f"  {kind:10s} n={n:3d} AMG {name:28s} total {r['total_s']:7.2f}s "
                f"it {r['iterations']}",
                flush=True,
            )
    return rec


def print_table(records):
    hdr = (
        f"{'problem':10s} {'n':>3s} {'cells':>8s} {'dofs':>8s} {'nnz':>10s} {'hess s':>7s} "
        f"{'patt s':>7s} {'asm s':>6s} | {'solver':16s} {'setup s':>8s} {'refac s':>8s} "
        f"{'solve s':>8s} "
        f"{'iters':>6s} {'resid':>8s} {'RSS MiB':>8s}"
    )
    print(hdr)
    print("-" * len(hdr))
    for r in records:
        left = (
            f"{r['problem']:10s} {r['n']:3d} {r['n_cells']:8d} {r['n_dofs']:8d} "
            f"{r['nnz']:10d} {r['hessians_s']:7.2f} {r['pattern_s']:7.2f} "
            f"{r['assemble_s']:6.2f}"
        )
        for name, s in r["solvers"].items():
            print(
                f"{left} | {name:16s} {s['setup_s']:8.2f} {s['refactor_s']:8.2f} "
                f"{s['solve_s']:8.2f} "
                f"{s['iterations']:6d} {s['residual']:8.1e} {s['peak_rss_mb']:8.0f}"
            )
            left = " " * len(left)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="10,19,29", help="comma-separated n (default 10,19,29)")
    ap.add_argument("--problems", default="twist,cantilever")
    ap.add_argument("--out", default="out/bench_linear")
    ap.add_argument("--rtol", type=float, default=1e-8)
    ap.add_argument(
        "--direct-max-dofs",
        type=int,
        default=100_000,
        help="skip the direct solvers above this many dofs (their fill grows ~n_dofs^(4/3))",
    )
    ap.add_argument("--direct-backends", default="pardiso,cholmod,cholespy,splu")
    ap.add_argument(
        "--slow-max-dofs",
        type=int,
        default=30_000,
        help="skip cholespy and SuperLU above this many dofs (71 s / 92 s at 81k dofs)",
    )
    ap.add_argument("--cg-max-n", type=int, default=10, help="run cg-jacobi for n <= this")
    ap.add_argument("--no-reuse", action="store_true", help="skip the AMG reuse study")
    args = ap.parse_args(argv)
    sizes = [int(s) for s in args.sizes.split(",") if s]
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "bench_linear.json")
    meta = dict(
        command=" ".join(["python", "scripts/bench_linear.py", *(argv or sys.argv[1:])]),
        python=platform.python_version(),
        jax=jax.__version__,
        cpu_count=os.cpu_count(),
        openblas_threads=os.environ.get("OPENBLAS_NUM_THREADS"),
        loadavg_start=os.getloadavg(),
        rtol=args.rtol,
    )
    records = []
    for n in sizes:
        for kind in args.problems.split(","):
            records.append(bench_case(kind, n, args))
            meta["loadavg_now"] = os.getloadavg()
            meta["max_rss_mb"] = psutil.Process().memory_info().rss / 2**20
            write_json(path, dict(meta=meta, results=records), indent=1, nonfinite="string")
    print()
    print_table(records)
    print(f"\nload average at start {meta['loadavg_start']}, end {os.getloadavg()}")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
