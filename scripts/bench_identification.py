"""Benchmark of identification over a load path: forward levels, loss and gradient, a fit.

Problem: the plate-with-hole specimen of :mod:`jaxelastic.fitting.specimens` (P1 tets,
one eighth of the plate by symmetry, ``--n`` cells around the hole, radially and through
the half-thickness; the default 32,16,5 has 3,366 nodes, about 10k dofs), neo-Hookean,
pulled in ``--levels`` load levels (20 by default), observed by its support force and the
in-plane displacements of 30 DIC points on the top face (noise-free synthetic data at
E = 1000, ν = 0.3).

Timed (the fits first, including their compilation; then the pieces, compiled once,
warm medians of ``--repeats`` calls):

* ``forward``: the predictions of every level (:meth:`LoadPathCase.predictions`, the
  levels solved in order with warm starts from the previous level);
* ``value_and_grad``: the χ² misfit and its gradient with respect to (E, ν) (the forward
  levels plus one adjoint solve per level), from the previous evaluation's solutions at
  the same point and at a new point about 1 % away (what an optimiser iteration costs),
  and from the rest shape;
* ``linearize``: the residuals and their Jacobian with respect to (E, ν) (the forward
  levels plus, per level, one linear solve with two right-hand sides: the forward-mode
  tangents), at the same new point: one Levenberg–Marquardt evaluation;
* ``fit``: :func:`jaxelastic.fitting.fit` of (E, ν) from (700, 0.2), including
  compilation, with its Gauss–Newton uncertainty, by Levenberg–Marquardt
  (``optimizer="lm"``, which needs no further pass for the uncertainty: it reuses its
  Jacobian at the optimum) and by the default L-BFGS (``--optimizers``). The data are
  noise-free, so the χ² at the optimum is round-off: Levenberg–Marquardt stops with
  ``LMSettings(atol=1e-10)``, where the undamped Gauss–Newton step predicts a decrease
  of ½χ² below 1e-10 (the parameters within about 1e-5 standard errors of the optimum).

Timings on a shared machine are noisy: compare the ratios within one run.

Usage::

    python scripts/bench_identification.py --repeats 1 --out out/bench_identification
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


LM_SETTINGS_ATOL = 1e-10
"""``LMSettings.atol`` of the Levenberg–Marquardt fit of noise-free data [½χ²]."""


def _fit(case, optimizer: str) -> dict:
    from jaxelastic import fitting as F

    opt = F.LMSettings(atol=LM_SETTINGS_ATOL) if optimizer == "lm" else optimizer
    t0, c0 = time.perf_counter(), time.process_time()
    res = F.fit([case], F.Material(700.0, 0.2), optimizer=opt)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    assert res.uncertainty is not None
    return dict(
        wall_s=wall,
        cpu_s=cpu,  # all threads: on a loaded machine, wall time is at least cpu_s / cores
        iterations=int(res.iterations),
        evaluations=int(res.evaluations),
        newton_steps=int(np.sum(res.newton_steps)),
        converged=bool(res.converged),
        stop_reason=res.stop_reason,
        E=float(res.E),
        nu=float(res.nu),
        standard_errors=res.standard_errors,
    )


def run(n, levels: int, repeats: int, optimizers: tuple[str, ...]) -> dict:
    """Long because: the timings are one sequence of steps on shared compiled functions."""
    import jax

    import jaxelastic as je
    from jaxelastic import fitting as F

    t0 = time.perf_counter()
    mesh, case = _setup(n, levels)
    t_setup = time.perf_counter() - t0
    # the fits first, each in a process that has compiled nothing of it yet
    fits = {name: _fit(case, name) for name in optimizers}
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
    t0 = time.perf_counter()
    obj.linearize(z1, (warm,))
    t_lin_first = time.perf_counter() - t0
    t_lin = _median_time(lambda: obj.linearize(z1, (warm,)), repeats)
    _, _, auxs = obj.linearize(z1, (warm,))
    steps_lin = int(auxs[0].newton_steps)
    t_fwd_step = _median_time(
        lambda: jax.block_until_ready(fwd(obj.pz.psi_params(z1), warm)), repeats
    )
    out = dict(
        mesh=dict(n=list(n), nodes=mesh.n_nodes, tets=mesh.n_cells, dofs=3 * mesh.n_nodes),
        levels=levels,
        setup_s=t_setup,
        forward=dict(
            first_incl_compile_s=t_fwd_first,
            warm_s=t_fwd,
            from_rest_s=t_fwd_cold,
            new_point_s=t_fwd_step,
        ),
        value_and_grad=dict(
            first_incl_compile_s=t_vg_first,
            warm_s=t_vg,
            from_rest_s=t_vg_cold,
            new_point_s=t_vg_step,
            new_point_newton_steps=steps_step,
        ),
        linearize=dict(
            first_incl_compile_s=t_lin_first, new_point_s=t_lin, new_point_newton_steps=steps_lin
        ),
        ratio_value_and_grad_to_forward=t_vg / t_fwd,
        ratio_from_rest=t_vg_cold / t_fwd_cold,
        ratio_new_point=dict(value_and_grad=t_vg_step / t_fwd_step, linearize=t_lin / t_fwd_step),
        fit=fits,
    )
    return out


def _print(result: dict) -> None:
    f, v, lin = result["forward"], result["value_and_grad"], result["linearize"]
    rn = result["ratio_new_point"]
    print(f"{result['mesh']['dofs']} dofs, {result['levels']} levels")
    print("| | s | ratio to forward | Newton steps |")
    print("|---|---|---|---|")
    rows = [
        ("forward levels, same point", f["warm_s"], None, None),
        ("forward levels, from rest", f["from_rest_s"], None, None),
        (
            "loss + gradient, same point",
            v["warm_s"],
            result["ratio_value_and_grad_to_forward"],
            None,
        ),
        ("forward levels, new point", f["new_point_s"], None, None),
        (
            "loss + gradient, new point",
            v["new_point_s"],
            rn["value_and_grad"],
            v["new_point_newton_steps"],
        ),
        (
            "residuals + Jacobian, new point",
            lin["new_point_s"],
            rn["linearize"],
            lin["new_point_newton_steps"],
        ),
    ]
    for name, t, ratio, steps in rows:
        r = "" if ratio is None else f"{ratio:.2f}"
        print(f"| {name} | {t:.2f} | {r} | {'' if steps is None else steps} |")
    if result["fit"]:
        print()
        print(
            "| fit | s incl. compile | CPU s | iterations | evaluations | Newton steps | stop "
            "| E | nu |"
        )
        print("|---|---|---|---|---|---|---|---|---|")
        for name, r in result["fit"].items():
            print(
                f"| {name} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | {r['iterations']} | "
                f"{r['evaluations']} | "
                f"{r['newton_steps']} | {r['stop_reason']} | {r['E']:.6g} | {r['nu']:.6g} |"
            )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/bench_identification")
    ap.add_argument("--n", default="32,16,5", help="cells around, radial, thickness")
    ap.add_argument("--levels", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument(
        "--optimizers",
        default="lm,lbfgs",
        help="fits to run, comma-separated: 'lm' (Levenberg–Marquardt), 'lbfgs' (the default)",
    )
    ap.add_argument("--no-fit", action="store_true", help="skip the fits")
    args = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxelastic.io import write_json

    n = tuple(int(a) for a in args.n.split(","))
    optimizers = () if args.no_fit else tuple(o for o in args.optimizers.split(",") if o)
    result = run(n, args.levels, args.repeats, optimizers)
    result["machine"] = dict(platform=platform.platform(), cpus=os.cpu_count())
    os.makedirs(args.out, exist_ok=True)
    write_json(os.path.join(args.out, "bench_identification.json"), result, nonfinite="string")
    _print(result)
    print(f"wrote {args.out}/bench_identification.json", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
