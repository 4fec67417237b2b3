"""Cost of contact per Newton iteration vs the elastic element Hessians.

The ``drop`` scene's body (a 0.2 m stable neo-Hookean cube, lagged friction μ = 0.5 on the
ground, d̂ = 1e-3 m) on a finer mesh (``6n³`` tets; n = 20: 48k), placed so that its base
sits inside the barrier's reach (every base node active). Timed, each jitted, min of 3:

* ``elastic Ke``: the element Hessians Newton builds every iteration (exact, by
  contraction: :func:`jaxelastic.mechanics.hessians.element_hessians`) — the reference;
* ``barrier``: what contact adds per Newton iteration: Π_c and ∂Π_c/∂x (one line-search
  trial), the per-node Hessian blocks folded into Ke
  (:meth:`~jaxelastic.contact.Contact.add_hessian_blocks`) and the CCD step bound;
* with ``--self`` (self-contact on): the host broad phase (``Contact.refreshed(x,
  force=True)``, a full rebuild: an upper bound, as Newton rebuilds only when a node has
  used half its motion bound) and the barrier with the self-contact pairs; ``pairs``
  times the self-contact part alone (pair energy, gradient, Hessians of the closest
  slots, their node blocks and one coupling product, CCD; it is inside ``barrier``).

The target is barrier (+ broad phase) ≤ 1× the elastic element Hessians. Prints a table
and writes JSON (``--out``) with the peak RSS.

    .venv/bin/python scripts/bench_contact.py --n 20 [--self] --out out/bench/bench_contact.json
"""

from __future__ import annotations

import argparse
import resource
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxelastic as je  # noqa: E402
from jaxelastic import contact as jc  # noqa: E402
from jaxelastic.mechanics import element_hessians  # noqa: E402

DHAT = 1e-3


def best(fn, *args, repeat: int = 3) -> float:
    """Min wall time [s] of ``repeat`` calls after a warm-up (compile) call."""
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return min(times)


def drop_body(n: int, self_contact: bool):
    """The drop scene's potential at ``6n³`` tets with its contact term, and a state
    ``x`` whose base is 0.3 d̂ above the ground (plus a small random perturbation)."""
    mesh = je.box(n, n, n, size=(0.2, 0.2, 0.2), origin=(0.0, 0.0, 0.05))
    mu, lam = je.materials.lame(1e5, 0.3)
    mass = jnp.asarray(je.loads.lumped_mass(mesh, 1000.0))
    f = jnp.asarray(je.loads.gravity_load(mesh, 1000.0, [0.0, 0.0, -9.81]))
    pot = je.Potential(
        mesh, je.Lame(mu, lam), f_ext=f, mass=mass, psi=je.materials.stable_neo_hookean
    )
    ground = jc.HalfSpace(jnp.zeros(3), jnp.array([0.0, 0.0, 1.0]), friction=0.5)
    kw = dict(self_contact=True) if self_contact else {}
    c = jc.make_contact(pot, [ground], dhat=DHAT, **kw)
    x = mesh.points - jnp.array([0.0, 0.0, 0.05 - 0.3 * DHAT])
    h = 0.2 / n
    x = x + 1e-3 * h * jax.random.uniform(jax.random.PRNGKey(0), x.shape, x.dtype)
    c = c.lag(x)  # friction lagged at this state (as every time step does)
    return pot, c, x


@jax.jit
def _elastic(pot, x):
    return element_hessians(pot.psi, x, pot.mesh, pot.params)


@jax.jit
def _barrier(pot, c, x, Ke, step):
    e, g = c.energy(x), c.gradient(x)
    Kc = c.add_hessian_blocks(Ke, pot.mesh, x, project=True)
    return e, g, Kc, c.ccd_step(x, step)


@jax.jit
def _pairs(c, x, v, step):
    """The self-contact part alone: pair energy and gradient, pair Hessians (the K
    closest slots; node-diagonal blocks and the coupling operator applied once), CCD."""
    sc = c.self_contact
    e, g = sc.energy(x, c.dhat, c.kappa), sc.gradient(x, c.dhat, c.kappa)
    hs = sc.pair_hessians(x, c.dhat, c.kappa)
    Hv = sc.coupling(x, c.dhat, c.kappa, hessians=hs)(v)
    return e, g, sc.node_blocks(x, c.dhat, c.kappa), Hv, sc.ccd_step(x, step)


@jax.jit
def _fold_only(pot, Ke):  # a copy of Ke: the part of "barrier" that only moves memory
    return Ke + 0.0


def run(n: int, self_contact: bool) -> dict:
    pot, c, x = drop_body(n, self_contact)
    Ke = _elastic(pot, x)
    step = -1e-2 * DHAT * jnp.ones_like(x)
    t_el = best(_elastic, pot, x)
    t_bar = best(_barrier, pot, c, x, Ke, step)
    row = dict(
        n=n,
        tets=int(pot.mesh.n_cells),
        dofs=int(pot.mesh.n_dofs),
        contact_nodes=int(c.nodes.size),
        active_nodes=int(jnp.sum(jnp.any(c.distances(x) < c.dhat, axis=0))),
        self_contact=self_contact,
        elastic_Ke_s=t_el,
        barrier_s=t_bar,
        ke_copy_s=best(_fold_only, pot, Ke),
    )
    if self_contact:
        t0 = time.perf_counter()
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            c.refreshed(np.asarray(x), force=True)
            times.append(time.perf_counter() - t0)
        row["broad_phase_s"] = min(times)
        row["self_pairs_s"] = best(_pairs, c, x, step, step)
        sc = c.self_contact
        row["capacity"] = list(sc.capacity)
        row["candidates"] = list(sc.counts)
    total = t_bar + row.get("broad_phase_s", 0.0)
    row["ratio"] = total / t_el
    row["min_distance"] = float(c.min_distance(x))
    row["energy_finite"] = bool(jnp.isfinite(c.energy(x)))
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="+", default=[20])
    ap.add_argument("--self", action="store_true", help="self-contact on (broad phase too)")
    ap.add_argument("--out", default="out/bench/bench_contact.json")
    args = ap.parse_args()
    rows = []
    print(
        f"{'tets':>7} {'active':>7} {'elastic Ke [s]':>15} {'barrier [s]':>12} "
        f"{'broad [s]':>10} {'pairs [s]':>10} {'ratio':>6}"
    )
    for n in args.n:
        try:
            r = run(n, args.self)
        except Exception as e:  # self-contact not available: report and go on
            if not args.self:
                raise
            print(f"n = {n}: self-contact skipped ({type(e).__name__}: {e})")
            r = dict(n=n, self_contact=True, skipped=f"{type(e).__name__}: {e}")
            rows.append(r)
            continue
        rows.append(r)
        bp, sp = r.get("broad_phase_s"), r.get("self_pairs_s")
        print(
            f"{r['tets']:7d} {r['active_nodes']:7d} {r['elastic_Ke_s']:15.4f} "
            f"{r['barrier_s']:12.4f} {'-' if bp is None else f'{bp:.4f}':>10} "
            f"{'-' if sp is None else f'{sp:.4f}':>10} {r['ratio']:6.2f}"
        )
        if args.self:
            print(f"        candidates {r['candidates']} in buffers {r['capacity']}")
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak RSS {rss:.0f} MB")
    je.io.write_json(args.out, dict(rows=rows, peak_rss_mb=rss))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
