"""Cardiac mechanics verification (Land et al. 2015, *Proc. R. Soc. A* 471:20150641).

Problem 1 only (problems 2 and 3, the ventricle, are not here yet): the Guccione beam
[0, 10] × [0, 1] × [0, 1] mm, C = 2 kPa, b_f = 8, b_t = 2, b_fs = 4, fibres along x, the
face x = 0 clamped, a follower pressure of 0.004 kPa on the bottom face z = 0 (an open
surface whose rim moves: ``loads.pressure_load(..., follower=True)``, quasi-Newton). Output:
the deformed z of the material point (10, 0.5, 1); the participating codes report
≈ 4.15–4.17 mm. Incompressibility by the penalty κ of :func:`jaxelastic.materials.guccione`
(``--kappa``, a list: the result approaches the incompressible one as κ grows).

Each case is one Newton solve from rest at the full pressure (load increments from a
converged state stall: see ``docs/guide/pressure.md``). Prints a table, writes JSON.

Usage::

    python scripts/bench_cardiac.py --meshes 1:standard,1:fbar,2:fbar --kappa 1000 --out out/cardiac
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time

import numpy as np

CONSENSUS = (4.15, 4.17)
"""Deformed z [mm] of (10, 0.5, 1) reported by the participating codes (REFERENCES.md)."""


def beam(n: int, formulation: str, kappa: float, max_steps: int = 200) -> dict:
    """Problem 1 on a P2 ``box(10n, n, n)`` mesh with the given formulation."""
    import jaxelastic as je
    from jaxelastic import loads as L
    from jaxelastic import materials as M

    m = je.box(10 * n, n, n, size=(10.0, 1.0, 1.0), order=2, formulation=formulation)
    X = np.asarray(m.points)
    tip = int(np.argmin(np.linalg.norm(X - [10.0, 0.5, 1.0], axis=1)))
    if np.linalg.norm(X[tip] - [10.0, 0.5, 1.0]) > 1e-12:
        raise SystemExit("the mesh has no node at (10, 0.5, 1)")
    bottom = L.facets_where(m, lambda Y: Y[:, 2] < 1e-9)
    term = L.pressure_load(m, bottom, 0.004, follower=True)
    p = M.per_cell_basis(M.guccione_params(kappa=kappa), m.n_cells)
    pot = je.Potential(m, p, psi=M.guccione, pressure=term)
    bc = L.fix(m, L.nodes_on_plane(m, 0, 0.0))
    t0 = time.perf_counter()
    res = je.solve(pot, bc, solver=je.Newton(rtol=1e-8, max_steps=max_steps), throw=False)
    z = float(res.x[tip, 2])
    return {
        "n": n,
        "formulation": formulation,
        "kappa": kappa,
        "n_nodes": int(m.n_nodes),
        "status": res.reason,
        "ok": bool(res.ok),
        "newton_steps": int(res.stats["steps"]),
        "z": z,
        "wall_s": time.perf_counter() - t0,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--meshes", default="1:standard,1:fbar", help="n:formulation,...")
    ap.add_argument("--kappa", default="1000", help="penalty values [kPa], comma-separated")
    ap.add_argument("--out", default=None, help="directory for bench_cardiac.json")
    a = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    rows = []
    print(f"Land et al. 2015 problem 1: z of (10, 0.5, 1), consensus {CONSENSUS} mm")
    print(
        f"{'mesh':>12} {'kappa':>8} {'nodes':>6} {'status':>12} {'steps':>5} {'z [mm]':>8} {'s':>6}"
    )
    for spec in a.meshes.split(","):
        n, form = spec.split(":")
        for kappa in (float(k) for k in a.kappa.split(",")):
            r = beam(int(n), form, kappa)
            rows.append(r)
            label = f"{10 * int(n)}x{n}x{n} {form}"
            status = "ok" if r["ok"] else "FAILED"
            print(
                f"{label:>12} {kappa:8g} {r['n_nodes']:6d} {status:>12} "
                f"{r['newton_steps']:5d} {r['z']:8.4f} {r['wall_s']:6.1f}",
                flush=True,
            )
    if a.out:
        os.makedirs(a.out, exist_ok=True)
        with open(os.path.join(a.out, "bench_cardiac.json"), "w") as f:
            json.dump({"consensus": CONSENSUS, "problem1": rows}, f, indent=1)
    return 0 if all(r["ok"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
