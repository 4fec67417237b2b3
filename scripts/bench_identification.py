"""Benchmark of identification over a load path: forward levels, loss and gradient, a fit.

Problem: the plate-with-hole specimen of :mod:`jaxelastic.fitting.specimens` (P1 tets,
one eighth of the plate by symmetry, ``--n`` cells around the hole, radially and through
the half-thickness; the default 32,16,5 has 3,366 nodes, about 10k dofs), neo-Hookean,
pulled in ``--levels`` load levels (20 by default), observed by its support force and the
in-plane displacements of 30 DIC points on the top face (noise-free synthetic data at
E = 1000, ν = 0.3).

Timed (compiled once, then warm medians of ``--repeats`` calls):

* ``forward``: the predictions of every level (:meth:`LoadPathCase.predictions`, the
  levels solved in order with warm starts from the previous level);
* ``value_and_grad``: the χ² misfit and its gradient with respect to (E, ν) (the forward
  levels plus one adjoint solve per level), from the previous evaluation's solutions at
  the same point and at a new point about 1 % away (what an optimiser iteration costs),
  and from the rest shape;
* ``fit``: :func:`jaxelastic.fitting.fit` of (E, ν) from (700, 0.2), including
  compilation, with its Gauss–Newton uncertainty.

Timings on a shared machine are noisy: compare the ratios within one run.

Usage::

    python scripts/bench_identification.py --out out/bench_identification
    python scripts/bench_identification.py --n 8,4,1 --levels 5 --out /tmp/bi   # smoke test
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np


def _median_time(fn, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def _setup(n, levels: int):
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import fitting as F
    from jaxelastic import materials as M
    from jaxelastic.fitting import specimens as S

    mesh = S.plate_with_hole(*n)
    test = S.hole_test(mesh, 0.3)
    truth = M.Lame.from_E_nu(1000.0, 0.3, dim=3)
    pot = je.Potential(mesh, truth, psi=M.neo_hookean)
    factors = np.linspace(1.0 / levels, 1.0, levels)
    pts = S.dic_points(test, 30, 0, margin=0.3)
    _, data = S.synthetic_measurements(test, pot, factors, pts, 0.0, 0, F.FIT_SOLVER)
    e = jnp.asarray([1.0, 0.0, 0.0])
    sf = 0.01 * float(np.sqrt(np.mean(data["force"] ** 2)))
    su = 0.01 * float(np.sqrt(np.mean(data["displacements"] ** 2)))
    obs = (
        F.Reaction(jnp.asarray(test.pulled), e, jnp.asarray(data["force"]), sf),
        F.Points.at(mesh, pts, data["displacements"], su, components=("x", "y")),
    )
    return mesh, F.LoadPathCase(pot, test.bc, factors, obs)


def run(n, levels: int, repeats: int, do_fit: bool) -> dict:
    """Long because: the timings are one sequence of steps on shared compiled functions."""
    import jax

    import jaxelastic as je
    from jaxelastic import fitting as F

    t0 = time.perf_counter()
    mesh, case = _setup(n, levels)
    t_setup = time.perf_counter() - t0
    obj = F.make_objective([case], F.Material(700.0, 0.2))
    solver = obj.solvers[0]
    p = obj.pz.psi_params(obj.z0)
    # the case and the solver are arguments, as in the objective (not constants of the
    # compiled program, which XLA compiles into a slower program: 1.0 against 0.5 s for 4
    # levels at this size)
    predict = jax.jit(lambda p, w, c, s: c.predictions(p, w, s, je.ImplicitAdjoint()))
    fwd = lambda p, w: predict(p, w, case, solver)  # noqa: E731
    w0 = case.initial_warm()
    t0 = time.perf_counter()
    _, aux = jax.block_until_ready(fwd(p, w0))
    t_fwd_first = time.perf_counter() - t0
    warm = aux.warm
    t_fwd = _median_time(lambda: jax.block_until_ready(fwd(p, warm)), repeats)
    t_fwd_cold = _median_time(lambda: jax.block_until_ready(fwd(p, w0)), repeats)
    t0 = time.perf_counter()
    obj.value_and_grad(obj.z0, (warm,))
    t_vg_first = time.perf_counter() - t0
    t_vg = _median_time(lambda: obj.value_and_grad(obj.z0, (warm,)), repeats)
    t_vg_cold = _median_time(lambda: obj.value_and_grad(obj.z0, (w0,)), repeats)
    # an optimiser iteration: a new point (E, ν each about 1 % away) from the solutions
    # at the previous one
    z1 = obj.z0 + 0.01
    t_vg_step = _median_time(lambda: obj.value_and_grad(z1, (warm,)), repeats)
    (_, auxs), _ = obj.value_and_grad(z1, (warm,))
    steps_step = int(auxs[0].newton_steps)
    out = dict(
        mesh=dict(n=list(n), nodes=mesh.n_nodes, tets=mesh.n_cells, dofs=3 * mesh.n_nodes),
        levels=levels,
        setup_s=t_setup,
        forward=dict(first_incl_compile_s=t_fwd_first, warm_s=t_fwd, from_rest_s=t_fwd_cold),
        value_and_grad=dict(
            first_incl_compile_s=t_vg_first,
            warm_s=t_vg,
            from_rest_s=t_vg_cold,
            new_point_s=t_vg_step,
            new_point_newton_steps=steps_step,
        ),
        ratio_value_and_grad_to_forward=t_vg / t_fwd,
        ratio_from_rest=t_vg_cold / t_fwd_cold,
    )
    if do_fit:
        t0 = time.perf_counter()
        res = F.fit([case], F.Material(700.0, 0.2))
        assert res.uncertainty is not None
        out["fit"] = dict(
            wall_s=time.perf_counter() - t0,
            iterations=int(res.iterations),
            stop_reason=res.stop_reason,
            E=float(res.E),
            nu=float(res.nu),
            standard_errors=res.standard_errors,
            evaluations=int(np.asarray(res.newton_steps).shape[0]),
        )
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/bench_identification")
    ap.add_argument("--n", default="32,16,5", help="cells around, radial, thickness")
    ap.add_argument("--levels", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-fit", action="store_true", help="skip the full fit")
    args = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxelastic.io import write_json

    n = tuple(int(a) for a in args.n.split(","))
    result = run(n, args.levels, args.repeats, not args.no_fit)
    result["machine"] = dict(platform=platform.platform(), cpus=os.cpu_count())
    os.makedirs(args.out, exist_ok=True)
    write_json(os.path.join(args.out, "bench_identification.json"), result, nonfinite="string")
    f, v = result["forward"], result["value_and_grad"]
    print(
        f"{result['mesh']['dofs']} dofs, {args.levels} levels: forward {f['warm_s']:.2f} s "
        f"(from rest {f['from_rest_s']:.2f} s), loss+gradient {v['warm_s']:.2f} s "
        f"(ratio {result['ratio_value_and_grad_to_forward']:.2f}; from rest "
        f"{result['ratio_from_rest']:.2f}); at a new point {v['new_point_s']:.2f} s "
        f"({v['new_point_newton_steps']} Newton steps)"
    )
    if "fit" in result:
        r = result["fit"]
        print(
            f"fit: {r['wall_s']:.1f} s incl. compile, {r['iterations']} iterations "
            f"({r['stop_reason']}), E = {r['E']:.6g}, nu = {r['nu']:.6g}"
        )
    print(f"wrote {args.out}/bench_identification.json", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
