"""Hertz indentation with barrier contact: a rigid sphere pressed into a block.

A quarter of a unit block (symmetry planes x = 0, y = 0) on a mesh graded towards the
contact point, its base pushed up by δ into a fixed rigid sphere of radius R that touches
the top face at the barrier's reach. The total contact force (×4) is compared with Hertz,
``F = (4/3) E* √R δ^{3/2}``, ``E* = E/(1 − ν²)`` (REFERENCES "Contact"; valid for δ ≪ R
and a block much larger than the contact radius ``a = √(Rδ)``), and the exponent is
fitted on a log–log scale.

    .venv/bin/python scripts/contact_hertz.py --n 16 --out out/bench/contact_hertz.json
"""

from __future__ import annotations

import argparse
import pathlib
import resource
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxelastic as je  # noqa: E402
from jaxelastic import contact as jc  # noqa: E402

E, NU, R = 1e6, 0.3, 1.0


def graded_block(n: int, size: float = 1.0, power: float = 3.0, order: int = 1) -> je.Mesh:
    """Cube of side ``size`` [m], ``6n³`` tets (P1 or P2) graded towards the corner
    (0, 0, size) of the contact (``x → size·(x/size)^p``)."""
    m = je.box(n, n, n)
    X = np.asarray(m.points)
    Y = size * np.stack([X[:, 0] ** power, X[:, 1] ** power, 1.0 - (1.0 - X[:, 2]) ** power], 1)
    graded = je.from_arrays(Y, np.asarray(m.cells))
    return graded if order == 1 else je.to_quadratic(graded)  # straight-sided tet10


def hertz_force(delta):
    """Hertz load [N] of a rigid sphere (R) indenting an elastic half-space by δ [m]."""
    return 4.0 / 3.0 * E / (1 - NU**2) * np.sqrt(R) * np.asarray(delta) ** 1.5


def run(
    n: int = 16,
    deltas=(0.0025, 0.005, 0.01, 0.015, 0.02),
    dhat: float = 1e-4,
    size: float = 1.0,
    order: int = 1,
) -> dict:
    """Indent to each δ in turn; returns δ, F (full body), Hertz F, errors, min distance."""
    mesh = graded_block(n, size, order=order)
    top = size
    mu, lam = je.lame(E, NU)
    pot = je.Potential(mesh, je.Lame(mu, lam), psi=je.materials.neo_hookean)
    sphere = jc.Sphere(jnp.array([0.0, 0.0, top + R + dhat]), R)
    pot = jc.with_contact(pot, [sphere], dhat=dhat)
    c = pot.contact
    X = np.asarray(mesh.points)
    tol = 1e-9
    sym_x = je.loads.fix(mesh, np.where(X[:, 0] < tol)[0], components=(0,))
    sym_y = je.loads.fix(mesh, np.where(X[:, 1] < tol)[0], components=(1,))
    base = np.where(X[:, 2] < tol)[0]
    solver = je.Newton(rtol=1e-9, linear="direct")
    x = mesh.points
    rows, t0 = [], time.perf_counter()
    for d in deltas:
        lift = je.loads.fix(mesh, base, components=(2,), displacement=[0.0, 0.0, d + dhat])
        bc = je.loads.combine(sym_x, sym_y, lift)
        sol = je.solve(pot, bc, x0=x, solver=solver)
        x = sol.x
        F = -4.0 * float(c.forces(x)[:, 2].sum())
        rows.append(
            dict(
                delta=d,
                force=F,
                hertz=float(hertz_force(d)),
                min_distance=float(c.min_distance(x)),
                newton_steps=int(sol.stats["steps"]),
            )
        )
    F, H = np.array([r["force"] for r in rows]), np.array([r["hertz"] for r in rows])
    slope = float(np.polyfit(np.log(deltas), np.log(F), 1)[0])
    return dict(
        n=n,
        size=size,
        order=order,
        tets=int(mesh.n_cells),
        dofs=int(mesh.n_dofs),
        dhat=dhat,
        rows=rows,
        rel_error=(F / H - 1).tolist(),
        exponent=slope,
        min_distance=min(r["min_distance"] for r in rows),
        wall_time=time.perf_counter() - t0,
        peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="+", default=[8, 12, 16])
    ap.add_argument("--size", type=float, default=1.0, help="block side [m] (quarter)")
    ap.add_argument("--order", type=int, default=1, help="1 (tet4) or 2 (tet10)")
    ap.add_argument("--delta", type=float, nargs="+", default=[0.0025, 0.005, 0.01, 0.015, 0.02])
    ap.add_argument("--out", default="out/bench/contact_hertz.json")
    args = ap.parse_args()
    results = []
    print(f"{'n':>4} {'tets':>7} {'delta':>8} {'F [N]':>10} {'Hertz':>10} {'err':>7} {'min d':>9}")
    for n in args.n:
        r = run(n, tuple(args.delta), size=args.size, order=args.order)
        results.append(r)
        for row, e in zip(r["rows"], r["rel_error"], strict=True):
            print(
                f"{n:4d} {r['tets']:7d} {row['delta']:8.4f} {row['force']:10.2f} "
                f"{row['hertz']:10.2f} {e:+7.2%} {row['min_distance']:9.2e}"
            )
        print(f"     exponent {r['exponent']:.3f} (Hertz 1.5), wall {r['wall_time']:.1f} s")
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    je.io.write_json(out, results)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
