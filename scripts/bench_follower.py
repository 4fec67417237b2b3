"""Newton on a follower pressure: steps, line-search cut-backs and convergence.

The 6 × 1 × 1 neo-Hookean cantilever (μ = 100, λ = 150, 36 tets) clamped at x = 0 with a
follower pressure on its bottom face, an open surface whose rim moves (the problem of
``tests/test_follower_newton.py`` and ``tests/test_pressure.py``; see
``docs/guide/pressure.md``). Each row is one Newton solve (rtol 1e-10, at most 200 steps)
from rest or, for ``--ramp a:b``, the solve at ``b`` started from the converged state at
``a``; the table gives the status, the Newton steps, the line search's cut-backs, the
linear (GMRES) iterations of the steps, the last relative residuals and the tip height.

Usage::

    python scripts/bench_follower.py --pressures 1,2,4 --tangent auto,symmetric --ramp 1:2
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def cantilever(p: float):
    """The mesh, Dirichlet data and potential of the follower cantilever at pressure p."""
    import jaxelastic as je
    from jaxelastic import loads as L

    m = je.box(6, 1, 1, size=(6.0, 1.0, 1.0))
    bottom = L.facets_where(m, lambda X: X[:, 2] < 1e-9)
    term = L.pressure_load(m, bottom, p, follower=True)
    bc = L.fix(m, L.nodes_on_plane(m, 0, 0.0))
    return bc, je.Potential(m, je.Lame(100.0, 150.0), psi=je.neo_hookean, pressure=term)


def row(label: str, tangent: str, p: float, x0=None) -> tuple[str, object]:
    import jaxelastic as je

    bc, pot = cantilever(p)
    s = je.Newton(rtol=1e-10, max_steps=200, tangent=tangent)
    t0 = time.perf_counter()
    res = je.solve(pot, bc, solver=s, x0=x0, throw=False)
    wall = time.perf_counter() - t0
    k = int(res.stats["steps"])
    h = np.asarray(res.stats["residual_history"])[: k + 1]
    last = " ".join(f"{v:.1e}" for v in (h / h[0])[-4:])
    line = (
        f"{label:>10} {tangent:>9} {res.reason[:24]:>24} {k:5d} "
        f"{int(res.stats['line_search_cutbacks']):5d} {int(res.stats['linear_iterations']):6d} "
        f"{float(res.x[:, 2].max()):7.3f} {wall:6.1f}  {last}"
    )
    return line, res


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pressures", default="1,2,4", help="solves from rest (comma-separated)")
    ap.add_argument("--tangent", default="auto", help="Newton tangents (comma-separated)")
    ap.add_argument("--ramp", default="1:2", help="a:b: the solve at b from the state at a")
    a = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    print(
        f"{'p':>10} {'tangent':>9} {'status':>24} {'steps':>5} {'cuts':>5} {'linear':>6} "
        f"{'tip z':>7} {'s':>6}  last relative residuals"
    )
    for tangent in a.tangent.split(","):
        for p in a.pressures.split(","):
            print(row(p, tangent, float(p))[0], flush=True)
        if a.ramp:
            p0, p1 = (float(v) for v in a.ramp.split(":"))
            _, start = row("", tangent, p0)
            print(row(f"{p0:g}->{p1:g}", tangent, p1, x0=start.x)[0], flush=True)


if __name__ == "__main__":
    main()
