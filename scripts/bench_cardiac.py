"""Cardiac mechanics verification (Land et al. 2015, *Proc. R. Soc. A* 471:20150641).

**Problem 1**: the Guccione beam [0, 10] × [0, 1] × [0, 1] mm, C = 2 kPa, b_f = 8, b_t = 2,
b_fs = 4, fibres along x, the face x = 0 clamped, a follower pressure of 0.004 kPa on the
bottom face z = 0 (an open surface whose rim moves: ``loads.pressure_load(...,
follower=True)``). Output: the deformed z of the material point (10, 0.5, 1); the
participating codes report ≈ 4.15–4.17 mm. Each case is one Newton solve from rest at the
full pressure (``--load``: a multiple of it) with the Newton tangent ``--tangent``
(``auto``: the true, non-symmetric tangent solved by GMRES; ``symmetric``: the
quasi-Newton; see ``docs/guide/pressure.md``); the table gives the Newton steps, the GMRES
(or linear) iterations and the last residuals (quadratic convergence: each about the
square of the one before, relative to the first).

**Problems 2 and 3**: the truncated thick ellipsoid (:func:`jaxelastic.mesh.truncated_ellipsoid`,
endocardium radii 7 and 17 mm, epicardium 10 and 20 mm, base plane z = 5 mm), the base
**fixed** in all components, an endocardial pressure on the deformed wall (the rim on the
base is fixed, so the pressure is the conservative ``−p V`` of the cavity closed by the
base plane: ``origin = (0, 0, 5)``). Problem 2: isotropic Guccione, C = 10 kPa,
b_f = b_t = b_fs = 1, p = 10 kPa. Problem 3: C = 2 kPa, b_f = 8, b_t = 2, b_fs = 4, helix
fibres from +90° (endocardium) to −90° (epicardium) at the cell centroids or, with
``--fibres quadrature``, at the quadrature points (:func:`jaxelastic.materials.helix_basis`),
active tension S_a = T_a f0⊗f0 with T_a = 60 kPa
(:func:`jaxelastic.materials.with_active_tension`), p = 15 kPa. Outputs: the deformed z of
the endocardial apex (0, 0, −17) and the epicardial apex (0, 0, −20).
Problem 2 is ramped by ``je.solve_incremental``; problem 3 ramps the pressure and T_a
together in equal increments (one ``je.solve`` each from the last converged state). Mesh
level n: ``truncated_ellipsoid(4n, 8n, n)``.

Incompressibility by the penalty κ of :func:`jaxelastic.materials.guccione` (``--kappa``,
a list: the result approaches the incompressible one as κ grows). Prints a table, writes
``bench_cardiac.json`` and, for the ventricle, ``bench_cardiac.png`` (apex z against the
number of nodes, with the consensus values). The time includes compilation; the memory is
the process's peak resident set size so far (it only grows through the run).

Usage::

    python scripts/bench_cardiac.py --problems 1 --meshes 1:standard,1:fbar,2:fbar --kappa 1000
    python scripts/bench_cardiac.py --problems 2,3 --ventricle 1:1:fbar,1:2:standard,2:2:fbar \
        --out out/cardiac
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
APEX_CONSENSUS = {2: (-26.5, -28.2), 3: (-12.0, -15.2)}
"""Deformed z [mm] of the (endocardial, epicardial) apex reported by the participating
codes for problems 2 and 3 (REFERENCES.md; a reading of the paper's figure for problem 3
gives ≈ −12.5 / −15.5)."""
PROBLEM = {
    2: dict(C=10.0, bf=1.0, bt=1.0, bfs=1.0, pressure=10.0, Ta=0.0),
    3: dict(C=2.0, bf=8.0, bt=2.0, bfs=4.0, pressure=15.0, Ta=60.0),
}
"""Guccione constants [kPa, –], the endocardial pressure and the active tension [kPa]."""


def beam(
    n: int,
    formulation: str,
    kappa: float,
    max_steps: int = 200,
    tangent: str = "auto",
    load: float = 1.0,
) -> dict:
    """Problem 1 on a P2 ``box(10n, n, n)`` mesh with the given formulation, Newton
    ``tangent`` and ``load`` times the benchmark's pressure."""
    import jaxelastic as je
    from jaxelastic import loads as L
    from jaxelastic import materials as M

    m = je.box(10 * n, n, n, size=(10.0, 1.0, 1.0), order=2, formulation=formulation)
    X = np.asarray(m.points)
    tip = int(np.argmin(np.linalg.norm(X - [10.0, 0.5, 1.0], axis=1)))
    if np.linalg.norm(X[tip] - [10.0, 0.5, 1.0]) > 1e-12:
        raise SystemExit("the mesh has no node at (10, 0.5, 1)")
    bottom = L.facets_where(m, lambda Y: Y[:, 2] < 1e-9)
    term = L.pressure_load(m, bottom, 0.004 * load, follower=True)
    p = M.per_cell_basis(M.guccione_params(kappa=kappa), m.n_cells)
    pot = je.Potential(m, p, psi=M.guccione, pressure=term)
    bc = L.fix(m, L.nodes_on_plane(m, 0, 0.0))
    t0 = time.perf_counter()
    solver = je.Newton(rtol=1e-8, max_steps=max_steps, tangent=tangent)
    res = je.solve(pot, bc, solver=solver, throw=False)
    z = float(res.x[tip, 2])
    k = int(res.stats["steps"])
    hist = np.asarray(res.stats["residual_history"])[: k + 1]
    return {
        "n": n,
        "formulation": formulation,
        "kappa": kappa,
        "tangent": tangent,
        "load": load,
        "linear_iterations": int(res.stats["linear_iterations"]),
        "linear_unconverged": int(res.stats["linear_unconverged"]),
        "residual_history": [float(v) for v in hist],
        "n_nodes": int(m.n_nodes),
        "status": res.reason,
        "ok": bool(res.ok),
        "newton_steps": int(res.stats["steps"]),
        "z": z,
        "wall_s": time.perf_counter() - t0,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }


def ventricle(
    problem: int,
    n: int,
    order: int,
    formulation: str,
    kappa: float,
    steps: int = 5,
    fibres: str = "cells",
) -> dict:
    """Problem 2 or 3 on ``truncated_ellipsoid(4n, 8n, n)`` (see the module)."""
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import loads as L
    from jaxelastic import materials as M
    from jaxelastic.mesh import ellipsoid_surfaces, truncated_ellipsoid
    from jaxelastic.solvers import prepare_solver

    c = PROBLEM[problem]
    t0 = time.perf_counter()
    m = truncated_ellipsoid(4 * n, 8 * n, n, order=order, formulation=formulation)
    surf = ellipsoid_surfaces(m)
    apex = {"endo": 0, "epi": n * (1 + 32 * n * n)}  # the apex nodes of layers 0 and n
    term = L.pressure_load(m, surf["endocardium"], c["pressure"], origin=[0.0, 0.0, 5.0])
    f0, s0 = M.helix_basis(m, at=fibres)
    passive = M.guccione_params(
        C=c["C"], bf=c["bf"], bt=c["bt"], bfs=c["bfs"], kappa=kappa, f0=f0, s0=s0
    )
    bc = L.fix(m, np.unique(surf["base"]))
    solver = je.Newton(rtol=1e-8, max_steps=100)
    if c["Ta"] == 0.0:
        pot = je.Potential(m, passive, psi=M.guccione, pressure=term)
        res = je.solve_incremental(pot, bc, solver=solver, steps=steps, throw=False)
        ok, reason, s_done = bool(res.ok), res.reason, float(res.stats["load_factor"])
        newton = [int(i["steps"]) for i in res.stats["increments"]]
        x = res.x
    else:  # T_a is a material parameter: ramped with the pressure, one solve per increment
        psi = M.with_active_tension(M.guccione)

        def at(s: float):
            act = M.ActiveTension(passive, jnp.asarray(s * c["Ta"]), f0)
            return je.Potential(m, act, psi=psi, pressure=term.scaled(s))

        prepared = prepare_solver(solver, m, bc)
        x, ok, reason, s_done, newton = m.points, True, "converged", 0.0, []
        for k in range(1, steps + 1):
            res = je.solve(at(k / steps), bc, x0=x, solver=prepared, throw=False)
            newton.append(int(res.stats["steps"]))
            if not res.ok:
                ok, reason = False, res.reason
                break
            x, s_done = res.x, k / steps
    X = np.asarray(x)
    return {
        "problem": problem,
        "level": n,
        "mesh": f"{4 * n}x{8 * n}x{n}",
        "order": order,
        "formulation": formulation,
        "kappa": kappa,
        "fibres": fibres,
        "n_nodes": int(m.n_nodes),
        "n_cells": int(m.n_cells),
        "status": reason,
        "ok": ok,
        "load_factor": s_done,
        "newton_steps": newton,
        "z_endo": float(X[apex["endo"], 2]),
        "z_epi": float(X[apex["epi"], 2]),
        "wall_s": time.perf_counter() - t0,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }


def _element(order: int, formulation: str) -> str:
    return f"P{order}" + ("" if formulation == "standard" else f"+{formulation}")


def plot(rows: list, path: str) -> None:
    """Apex z against the number of nodes per problem and element, with the consensus."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    probs = sorted({r["problem"] for r in rows})
    fig, axes = plt.subplots(1, len(probs), figsize=(5.5 * len(probs), 4.2), squeeze=False)
    for ax, prob in zip(axes[0], probs, strict=True):
        sub = [r for r in rows if r["problem"] == prob and r["ok"]]
        for key in sorted({(r["order"], r["formulation"], r["kappa"]) for r in sub}):
            pts = sorted(
                (r["n_nodes"], r["z_endo"], r["z_epi"])
                for r in sub
                if (r["order"], r["formulation"], r["kappa"]) == key
            )
            nn, ze, zp = (np.array(a) for a in zip(*pts, strict=True))
            label = f"{_element(key[0], key[1])}, κ={key[2]:g}"
            (line,) = ax.plot(nn, ze, "o-", label=f"{label}: endo")
            ax.plot(nn, zp, "s--", color=line.get_color(), label=f"{label}: epi")
        for z, name in zip(APEX_CONSENSUS[prob], ("endo", "epi"), strict=True):
            ax.axhline(z, color="k", lw=0.8, ls=":")
            ax.annotate(f"consensus {name} {z}", (0.02, z), xycoords=("axes fraction", "data"))
        ax.set_xscale("log")
        ax.set_xlabel("nodes")
        ax.set_ylabel("deformed apex z [mm]")
        ax.set_title(f"Land et al. 2015, problem {prob}")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--problems", default="1", help="which of 1, 2, 3 (comma-separated)")
    ap.add_argument("--meshes", default="1:standard,1:fbar", help="problem 1: n:formulation,...")
    ap.add_argument(
        "--ventricle",
        default="1:1:fbar,1:2:standard,1:2:fbar",
        help="problems 2, 3: level:order:formulation,... (mesh truncated_ellipsoid(4n, 8n, n))",
    )
    ap.add_argument("--steps", type=int, default=5, help="problems 2, 3: load increments")
    ap.add_argument(
        "--fibres",
        default="cells",
        choices=("cells", "quadrature"),
        help="problem 3: helix fibres at the cell centroids or the quadrature points",
    )
    ap.add_argument("--kappa", default="1000", help="penalty values [kPa], comma-separated")
    ap.add_argument(
        "--tangent",
        default="auto",
        help="problem 1: Newton tangents, comma-separated (auto, exact, symmetric)",
    )
    ap.add_argument("--load", type=float, default=1.0, help="problem 1: multiple of 0.004 kPa")
    ap.add_argument("--out", default=None, help="directory for bench_cardiac.json/.png")
    a = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    problems = {int(p) for p in a.problems.split(",")}
    kappas = [float(k) for k in a.kappa.split(",")]
    out: dict = {"consensus": CONSENSUS, "apex_consensus": APEX_CONSENSUS}
    rows = []
    if 1 in problems:
        print(
            f"Land et al. 2015 problem 1 (pressure {0.004 * a.load:g} kPa): z of (10, 0.5, 1), "
            f"consensus {CONSENSUS} mm at 0.004 kPa"
        )
        print(
            f"{'mesh':>12} {'kappa':>8} {'tangent':>9} {'nodes':>6} {'status':>8} {'steps':>5} "
            f"{'linear':>6} {'z [mm]':>8} {'s':>6}  last relative residuals"
        )
        for spec in a.meshes.split(","):
            n, form = spec.split(":")
            for kappa in kappas:
                for tangent in a.tangent.split(","):
                    r = beam(int(n), form, kappa, tangent=tangent, load=a.load)
                    rows.append(r)
                    label = f"{10 * int(n)}x{n}x{n} {form}"
                    status = "ok" if r["ok"] else "FAILED"
                    h = np.asarray(r["residual_history"])
                    tail = " ".join(f"{v:.1e}" for v in h[-5:] / h[0])
                    print(
                        f"{label:>12} {kappa:8g} {tangent:>9} {r['n_nodes']:6d} {status:>8} "
                        f"{r['newton_steps']:5d} {r['linear_iterations']:6d} {r['z']:8.4f} "
                        f"{r['wall_s']:6.1f}  {tail}",
                        flush=True,
                    )
        out["problem1"] = rows
    vrows = []
    for prob in sorted(problems & {2, 3}):
        print(
            f"Land et al. 2015 problem {prob}: apex z (endo, epi), consensus "
            f"{APEX_CONSENSUS[prob]} mm; base fixed"
        )
        print(
            f"{'mesh':>16} {'kappa':>7} {'nodes':>6} {'status':>9} {'Newton':>16} "
            f"{'endo':>8} {'epi':>8} {'s':>6} {'MB':>6}"
        )
        for spec in a.ventricle.split(","):
            n, order, form = spec.split(":")
            for kappa in kappas:
                fibres = a.fibres if prob == 3 else "cells"
                r = ventricle(prob, int(n), int(order), form, kappa, a.steps, fibres)
                vrows.append(r)
                label = f"{r['mesh']} {_element(r['order'], form)}"
                label += " qp" if fibres == "quadrature" else ""
                status = "ok" if r["ok"] else f"s={r['load_factor']:.2f}"
                steps = "+".join(map(str, r["newton_steps"]))
                print(
                    f"{label:>16} {kappa:7g} {r['n_nodes']:6d} {status:>9} {steps:>16} "
                    f"{r['z_endo']:8.3f} {r['z_epi']:8.3f} {r['wall_s']:6.1f} "
                    f"{r['peak_rss_mb']:6.0f}",
                    flush=True,
                )
    if vrows:
        out["ventricle"] = vrows
    if a.out:
        os.makedirs(a.out, exist_ok=True)
        with open(os.path.join(a.out, "bench_cardiac.json"), "w") as f:
            json.dump(out, f, indent=1)
        if vrows:
            plot(vrows, os.path.join(a.out, "bench_cardiac.png"))
    return 0 if all(r["ok"] for r in rows + vrows) else 1


if __name__ == "__main__":
    sys.exit(main())
