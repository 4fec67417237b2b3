"""The twist solved on every device of a multi-process JAX job: the script each process runs.

Every process runs this same script. :func:`jaxelastic.parallel.distributed.initialize_from_env`
reads where it sits (``JAX_COORDINATOR_ADDRESS`` / ``JAX_NUM_PROCESSES`` /
``JAX_PROCESS_ID``, or a SLURM job step), every process builds the same twist
(:func:`jaxelastic.verification.twist`), :func:`jaxelastic.shard` splits it over all the
devices of the job (every process's), Newton + CG solves it, and process 0 writes the
natural-order solution (``x.npy``) and ``result.json`` (steps, CG iterations, times, the
partition) into ``--out``.

Two processes on one machine, one CPU device each (what ``tests/test_multiprocess.py``
does)::

    for i in 0 1; do
      JAX_COORDINATOR_ADDRESS=127.0.0.1:12345 JAX_NUM_PROCESSES=2 JAX_PROCESS_ID=$i \\
        python scripts/distributed_twist.py --n 4 --out out/mp &
    done; wait

On a SLURM cluster, one process per GPU: ``srun --ntasks-per-node=4 --gpus-per-task=1
python scripts/distributed_twist.py --n 29 --out out/mp`` (see docs/guide/distributed.md).

``--single`` solves the same problem in one process without sharding (the reference).
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=4, help="twist cells per edge (6 n^3 tets)")
    ap.add_argument("--out", default="out/distributed_twist", help="output directory")
    ap.add_argument("--linear", default="cg", choices=("cg", "multilevel", "auto"))
    ap.add_argument("--hessian", default="element", choices=("element", "hvp"))
    ap.add_argument("--rtol", type=float, default=1e-10, help="Newton relative tolerance")
    ap.add_argument("--method", default="auto", help="partition method (auto, metis, sfc)")
    ap.add_argument("--single", action="store_true", help="one process, no sharding")
    ap.add_argument("--timeout", type=int, default=120, help="connect timeout [s]")
    args = ap.parse_args(argv)

    import jax

    from jaxelastic.parallel.distributed import host_array, initialize_from_env

    info = (
        None if args.single else initialize_from_env(timeout_s=args.timeout)
    )  # first: before anything else uses JAX
    jax.config.update("jax_enable_x64", True)
    import numpy as np

    import jaxelastic as je
    from jaxelastic import verification as benchmarks
    from jaxelastic.io import write_json

    b = benchmarks.twist(args.n)
    linear = {"cg": je.CG(), "multilevel": je.Multilevel(), "auto": "auto"}[args.linear]
    solver = je.Newton(linear=linear, rtol=args.rtol, hessian=args.hessian)
    part = None
    t0 = time.perf_counter()
    if args.single:
        pot, bc = b.pot, b.bc
    else:
        pot, bc, part = je.shard(b.pot, b.bc, devices=len(jax.devices()), method=args.method)
    t_shard = time.perf_counter() - t0
    t0 = time.perf_counter()
    sol = je.solve(pot, bc, solver=solver)
    t_cold = time.perf_counter() - t0
    t0 = time.perf_counter()
    sol = je.solve(pot, bc, solver=solver)
    t_warm = time.perf_counter() - t0
    x = host_array(sol.x)  # a collective: every process gathers the whole array
    if part is not None:
        x = part.to_natural(x, kind="nodes")
    rank = 0 if info is None else info.process_id
    result = dict(
        n=args.n,
        processes=1 if info is None else info.num_processes,
        process_id=rank,
        devices=[str(d) for d in jax.devices()],
        sharded=part is not None,
        partition=None if part is None else part.stats(dim=3, itemsize=8),
        newton_steps=int(sol.stats["steps"]),
        linear_iterations=int(sol.stats["linear_iterations"]),
        residual=float(sol.stats["residual"]),
        shard_s=t_shard,
        cold_s=t_cold,
        warm_s=t_warm,
        peak_rss_mib=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    )
    if rank == 0:
        os.makedirs(args.out, exist_ok=True)
        np.save(os.path.join(args.out, "x.npy"), np.asarray(x))
        write_json(os.path.join(args.out, "result.json"), result)
    print(
        f"process {rank}: {result['processes']} process(es), {len(jax.devices())} devices, "
        f"{result['newton_steps']} Newton steps, {result['linear_iterations']} CG iterations, "
        f"cold {t_cold:.2f} s, warm {t_warm:.3f} s",
        flush=True,
    )
    if info is not None and info.num_processes > 1:
        jax.distributed.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
