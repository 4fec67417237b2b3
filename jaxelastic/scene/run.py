"""Running a scene: :func:`run_scene` (``jaxelastic run SCENE --out DIR``).

Static scenes: :func:`jaxelastic.solve_incremental` (``load_steps`` increments with
cut-back). Dynamic scenes: :func:`jaxelastic.dynamics.simulate` (one compiled step per time
step, progress bar, energies per step) with a callback that writes the VTU series every
``[output].every`` steps and stops once the body has settled; with ``compare_static`` also
the static solution of the final load. Outputs: :mod:`jaxelastic.scene.outputs`.
"""

from __future__ import annotations

import math
import os
import time
import warnings
from typing import Any

import jax.numpy as jnp
import numpy as np

from .. import dynamics
from ..io import TimeSeriesWriter
from ..loads import Dirichlet
from ..solvers import Solution, SolveError, solve_incremental
from .build import Built, build
from .load import load_scene
from .outputs import (
    dynamic_figures,
    elastic_energy,
    log,
    prepare_out,
    probe_report,
    reaction_report,
    remove_stale,
    run_header,
    static_figure,
    write_static_vtu,
    write_summary,
)
from .schema import DynamicIntegrator, StaticIntegrator

__all__ = ["run_scene", "static_solve"]


# ----------------------------------------------------------------------------------------
# statics
# ----------------------------------------------------------------------------------------


def static_solve(
    built: Built, *, bc: Dirichlet | None = None, what: str = "static solve"
) -> tuple[Any, list[dict], Solution]:
    """Newton with ``[integrator].load_steps`` increments and cut-back on failure.

    Args:
        built: the built scene (its potential's mass is ignored).
        bc: fixed Dirichlet data (the dynamic comparison); default ``built.bc_fn(s)`` at
            each load factor ``s``.
        what: names the solve in the error message.
    Returns:
        ``(x (n_nodes, dim), per-increment stats, solution of the last increment)``.
    Raises:
        SolveError: the load stepping stalled.
    """
    cfg = built.scene.spec.integrator
    n = cfg.load_steps if isinstance(cfg, StaticIntegrator) else 1
    path = built.bc_fn if bc is None else (lambda s: bc)
    sol = solve_incremental(
        built.potential.replace(mass=None),
        path(1.0),
        x0=built.x0,
        solver=built.solver,
        steps=n,
        path=path,
        throw=False,
    )
    stats = [
        dict(
            status=h["status"],
            newton_steps=h["steps"],
            linear_iterations=h["linear_iterations"],
            residual=h["residual"],
            wall_time=h["wall_time"],
            load_factor=h["s"],
            accepted=h["accepted"],
        )
        for h in sol.stats["increments"]
    ]
    if not bool(sol.ok):
        s = sol.stats["load_factor"]
        raise SolveError(sol, what=f"{what} (stalled at load factor {s:.4g})")
    return sol.x, stats, sol


def _run_static(built: Built, out: str, progress: bool, summary: dict) -> None:
    ocfg = built.scene.spec.output
    log(progress, "static solve (the first solve includes compilation) ...")
    t0 = time.perf_counter()
    x, stats, sol = static_solve(built)
    summary["timings"]["solve_incl_compile"] = time.perf_counter() - t0
    steps = int(sol.stats["steps"])
    summary["static"] = dict(
        load_steps=stats,
        newton_steps=sum(s["newton_steps"] for s in stats),
        linear_iterations=sum(s["linear_iterations"] for s in stats),
        final_residual=stats[-1]["residual"],
        residual_history=np.asarray(sol.stats["residual_history"])[: steps + 1].tolist(),
        elastic_energy=elastic_energy(built, x),
        max_displacement=float(np.linalg.norm(np.asarray(x) - built.x0, axis=1).max()),
        **reaction_report(built, x, built.bc),
    )
    summary["probes"] = probe_report(built, x)
    t0 = time.perf_counter()
    if ocfg.vtu:
        summary["outputs"]["pvd"] = write_static_vtu(built, out, 1.0, x)
    if ocfg.png:
        summary["outputs"]["png"].append(static_figure(built, out, x))
    summary["timings"]["outputs"] = time.perf_counter() - t0


# ----------------------------------------------------------------------------------------
# dynamics
# ----------------------------------------------------------------------------------------


class _Monitor:
    """The ``simulate`` callback of a dynamic scene: keeps the last state and the tip
    displacement, writes the VTU series every ``[output].every`` steps, and stops once
    kinetic < settle_tol × elastic energy for ``settle_steps`` consecutive steps."""

    def __init__(self, built: Built, writer: TimeSeriesWriter | None, n_steps: int):
        self.built, self.writer, self.n_steps = built, writer, n_steps
        cfg = built.scene.spec.integrator
        assert isinstance(cfg, DynamicIntegrator)  # the monitor of a dynamic scene
        self.cfg = cfg
        self.every = built.scene.spec.output.every
        self.state = dynamics.init_state(built.x0, built.v0)
        self.records: list[dict] = []
        self.tip_u = [np.zeros(built.mesh.dim)]
        self.n = self.below = self.last_written = 0
        self.settled_at: float | None = None
        self.t_out = 0.0

    def write(self, t: float, state) -> None:
        assert self.writer is not None  # called only when there is a writer
        t0 = time.perf_counter()
        self.writer.write(t, state.x, velocity=np.asarray(state.v))
        self.t_out += time.perf_counter() - t0
        self.last_written = self.n

    def __call__(self, state, solution, record) -> bool:
        self.n += 1
        self.state = state
        self.records.append(record)
        tip, X = self.built.tip, np.asarray(self.built.x0)
        self.tip_u.append(np.asarray(state.x)[tip] - X[tip])
        ratio = record["kinetic"] / max(abs(record["elastic"]), np.finfo(float).tiny)
        self.below = self.below + 1 if ratio < self.cfg.settle_tol else 0
        done = self.cfg.settle and self.below >= self.cfg.settle_steps
        if self.writer is not None and (self.n % self.every == 0 or done or self.n == self.n_steps):
            self.write(record["t"], state)
        if done:
            self.settled_at = record["t"]
        return done


def _simulate(built: Built, out: str, progress: bool, summary: dict):
    """Run the time steps; returns ``(monitor, failure or None)``."""
    pot, integ, cfg = built.potential, built.integrator, built.scene.spec.integrator
    assert integ is not None and isinstance(cfg, DynamicIntegrator)  # a dynamic scene
    n_steps = max(1, math.ceil(cfg.duration / integ.h - 1e-9))
    writer = None
    if built.scene.spec.output.vtu:
        writer = TimeSeriesWriter(out, "dynamic", built.mesh, built.psi, built.params)
    mon = _Monitor(built, writer, n_steps)
    if writer is not None:
        mon.write(0.0, mon.state)
    log(progress, f"{n_steps} time steps of h = {integ.h:g} s (the first includes compilation)")
    bc = built.bc_fn if built.time_dependent else built.bc
    failure = None
    t0 = time.perf_counter()
    try:
        dynamics.simulate(
            pot, mon.state, bc, integ, n_steps, solver=built.solver, callback=mon, progress=progress
        )
    except SolveError as e:
        failure = e
        st = e.solution.stats
        summary["failed_step"] = dict(
            step=mon.n + 1,
            t=(mon.n + 1) * integ.h,
            status=e.status.name,
            newton_steps=int(st["steps"]),
            linear_iterations=int(st["linear_iterations"]),
            residual=float(st["residual"]),
        )
    summary["timings"]["time_loop_total"] = time.perf_counter() - t0
    if writer is not None:
        if mon.last_written != mon.n:
            mon.write(mon.records[-1]["t"], mon.state)
        writer.close()
        remove_stale(out, "dynamic", len(writer.steps))
        summary["outputs"]["pvd"] = writer.pvd_path
        summary["outputs"]["vtu_files"] = len(writer.steps)
    return mon, failure


def _per_step(built: Built, records: list[dict]) -> dict:
    """Columns of the step records; ``t`` and the energies start with the initial state."""
    v0, m = np.asarray(built.v0), np.asarray(built.potential.mass)
    ke0 = 0.5 * float(np.sum(m[:, None] * v0**2))
    e0 = elastic_energy(built, built.x0)
    cols = ("newton_steps", "linear_iterations", "residual", "line_search_cutbacks", "wall_time")
    per: dict[str, list] = {"t": [0.0], "kinetic": [ke0], "elastic": [e0], "external": [0.0]}
    per |= {k: [] for k in cols}
    for r in records:
        for k in per:
            per[k].append(r[k])
    per["total"] = [a + b + c for a, b, c in zip(per["kinetic"], per["elastic"], per["external"])]  # noqa: B905
    return per


def _dynamic_summary(built: Built, mon: _Monitor, per: dict, summary: dict) -> None:
    walls = per["wall_time"]
    steady = float(np.median(walls[1:])) if len(walls) > 1 else float("nan")
    summary["timings"].update(
        first_step_incl_compile=walls[0] if walls else None,
        compile_estimate=(walls[0] - steady) if len(walls) > 1 else None,
        step_median=steady,
        steps_total=float(sum(walls)),
    )
    X = np.asarray(built.x0)
    summary["dynamic"] = dict(
        steps=mon.n,
        t_end=per["t"][-1],
        settled=mon.settled_at is not None,
        settle_time=mon.settled_at,
        kinetic_over_elastic=per["kinetic"][-1] / max(abs(per["elastic"][-1]), 1e-300),
        newton_steps_total=int(sum(per["newton_steps"])),
        linear_iterations_total=int(sum(per["linear_iterations"])),
        final_residual=per["residual"][-1] if mon.n else None,
        tip=dict(
            node=built.tip,
            rest_position=X[built.tip].tolist(),
            source="probe 0" if built.probes else "node farthest from the Dirichlet nodes",
            displacement=mon.tip_u[-1].tolist(),
        ),
        per_step=per,
    )
    summary["probes"] = probe_report(built, mon.state.x)


def _compare_static(built: Built, out: str, progress: bool, mon: _Monitor, summary: dict):
    """The static solution at the final load and its distance to the dynamic one."""
    log(progress, "static solve of the same load (includes compilation) ...")
    t_end, tip, X = mon.records[-1]["t"] if mon.records else 0.0, built.tip, np.asarray(built.x0)
    bc = built.bc_fn(t_end)
    t0 = time.perf_counter()
    x_static, stats, _ = static_solve(built, bc=bc, what="static comparison solve")
    summary["timings"]["static_solve_incl_compile"] = time.perf_counter() - t0
    u_s = np.asarray(x_static) - X
    dist = np.linalg.norm(np.asarray(mon.state.x) - np.asarray(x_static), axis=1)
    umax = float(np.linalg.norm(u_s, axis=1).max())
    tip_s = float(np.linalg.norm(u_s[tip]))
    summary["static"] = dict(
        **stats[-1],
        elastic_energy=elastic_energy(built, x_static),
        tip_displacement=u_s[tip].tolist(),
        max_displacement=umax,
        probes=probe_report(built, x_static),
        **reaction_report(built, x_static, bc),
    )
    summary["comparison"] = dict(
        max_nodal_distance=float(dist.max()),
        tip_distance=float(dist[tip]),
        tip_deflection_static=tip_s,
        relative_to_tip_deflection=float(dist.max()) / max(tip_s, 1e-300),
        relative_to_max_displacement=float(dist.max()) / max(umax, 1e-300),
    )
    if built.scene.spec.output.vtu:
        t0 = time.perf_counter()
        write_static_vtu(built, out, t_end, x_static)
        mon.t_out += time.perf_counter() - t0
    return x_static


def _run_dynamic(built: Built, out: str, progress: bool, summary: dict) -> None:
    mon, failure = _simulate(built, out, progress, summary)
    per = _per_step(built, mon.records)
    _dynamic_summary(built, mon, per, summary)
    x_static = None
    cfg = built.scene.spec.integrator
    assert isinstance(cfg, DynamicIntegrator)  # a dynamic scene
    if cfg.compare_static and failure is None:
        x_static = _compare_static(built, out, progress, mon, summary)
    if built.scene.spec.output.png and mon.n:
        t0 = time.perf_counter()
        paths = dynamic_figures(built, out, per, mon.tip_u, mon.state.x, x_static)
        summary["outputs"]["png"] += paths
        mon.t_out += time.perf_counter() - t0
    summary["timings"]["outputs"] = mon.t_out
    if failure is not None:
        raise failure


# ----------------------------------------------------------------------------------------
# run
# ----------------------------------------------------------------------------------------


def run_scene(scene, out_dir, progress: bool = True) -> dict:
    """Solve a scene and write its outputs into ``out_dir``; returns the summary dict.

    Writes (each file atomically): ``summary.json`` (the scene, timings, Newton and CG
    iterations and energies per step, final residual, probes, static/dynamic difference);
    with ``[output].vtu`` a ParaView series ``dynamic.pvd`` + ``dynamic_NNNN.vtu`` and/or
    ``static.pvd`` + ``static_0000.vtu`` (displacement, velocity, J, Green strain, P,
    von Mises stress, energy density); with ``[output].png`` ``final_shape.png`` and, for
    dynamics, ``tip_displacement.png`` and ``energy.png``. ``out_dir`` is created; a
    path that is a file is refused, and so is an input file (scene, mesh) that an output
    would overwrite.

    Args:
        scene: a :class:`~jaxelastic.scene.load.Scene`, a TOML path, a shipped name or a
            dict; out_dir: output directory; progress: progress bar and messages.
    Raises:
        SceneError: invalid scene or output directory.
        SolveError: a Newton solve failed (``summary.json`` is still written, with
            ``"status": "failed"`` and the error).
    """
    t_start = time.perf_counter()
    scene = load_scene(scene)
    out = prepare_out(out_dir, scene)
    if jnp.zeros(()).dtype != jnp.float64:
        warnings.warn(
            "running a scene in float32: enable float64 with "
            'jax.config.update("jax_enable_x64", True) (the CLI does)',
            UserWarning,
            stacklevel=2,
        )
    t0 = time.perf_counter()
    built = build(scene)
    summary = run_header(built, out)
    summary["timings"]["build"] = time.perf_counter() - t0
    path = os.path.join(out, "summary.json")
    try:
        (_run_static if scene.static else _run_dynamic)(built, out, progress, summary)
    except SolveError as e:
        summary.update(status="failed", error=str(e))
        summary["timings"]["total"] = time.perf_counter() - t_start
        write_summary(path, summary)
        raise
    summary["status"] = "ok"
    summary["timings"]["total"] = time.perf_counter() - t_start
    return write_summary(path, summary)
