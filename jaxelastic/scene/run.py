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
from .. import plot as _plot
from ..io import TimeSeriesWriter
from ..loads import Dirichlet
from ..materials import ActiveTension
from ..parallel.distributed import host_array
from ..solvers import Solution, SolveError, SolveWarning, solve_incremental
from . import interrupt, memory
from .cavity import (
    cavity_pressures,
    cavity_report,
    pressure_schedule,
    pressure_volume_figure,
    pressures_at,
    volume_controlled_solve,
)
from .contact import contact_report, min_gap
from .interrupt import Interrupted
from .load import load_scene
from .outputs import (
    deformation_report,
    displacement_report,
    dynamic_figures,
    elastic_energy,
    finish_summary,
    log,
    prepare_out,
    probe_report,
    reaction_report,
    remove_stale,
    remove_temporaries,
    run_header,
    run_warnings,
    save_png,
    state_stress_fields,
    static_figure,
    vtu_compression,
    vtu_plane,
    write_static_vtu,
)
from .problem import Built, build, padded_dirichlet
from .schema import DynamicIntegrator, StaticIntegrator

__all__ = ["run_scene", "static_solve", "settle_ratio", "ROUNDOFF_ENERGY"]

ROUNDOFF_ENERGY = 1e-12
"""An energy at most this fraction of the run's energy scale (the largest kinetic +
|elastic| + |external| energy so far) counts as zero (see :func:`settle_ratio`)."""


def settle_ratio(kinetic: float, elastic: float, scale: float) -> float | None:
    """Kinetic over elastic energy, or None where the elastic energy is zero to round-off.

    A free body in rigid motion (or at rest without load) has no elastic energy: its ratio
    is undefined (the plain quotient is 1e29 or inf), so it is None (``null`` in
    ``summary.json``) when ``|elastic| <= ROUNDOFF_ENERGY * scale``.

    Args:
        kinetic, elastic: energies of a state [J]; scale: the run's energy scale [J].
    """
    if not abs(elastic) > ROUNDOFF_ENERGY * scale:
        return None
    return float(kinetic) / abs(float(elastic))


def _at_rest(kinetic: float, elastic: float, scale: float, tol: float) -> bool:
    """The settle test of one step: kinetic < tol × |elastic|; where the elastic energy is
    zero to round-off, kinetic must be zero to round-off too (no division)."""
    floor = ROUNDOFF_ENERGY * scale
    if abs(elastic) > floor:
        return kinetic < tol * abs(elastic)
    return kinetic <= floor


# ----------------------------------------------------------------------------------------
# statics
# ----------------------------------------------------------------------------------------


def static_solve(
    built: Built,
    *,
    bc: Dirichlet | None = None,
    what: str = "static solve",
    callback=None,
    pot=None,
) -> tuple[Any, list[dict], Solution]:
    """Newton with ``[integrator].load_steps`` increments and cut-back on failure.

    Args:
        built: the built scene (its potential's mass is ignored).
        bc: fixed Dirichlet data (the dynamic comparison); default ``built.bc_fn(s)`` at
            each load factor ``s``.
        what: names the solve in the error message.
        callback: ``callback(s, solution)`` after every converged increment (default:
            :func:`~jaxelastic.scene.interrupt.check`, which stops there on SIGINT/SIGTERM).
        pot: the static potential (default: the built one without mass; a dynamic scene's
            comparison passes :func:`~jaxelastic.dynamics.static_potential`, which reuses
            the time steps' compiled solve).
    Returns:
        ``(x (n_nodes, dim), per-increment stats, solution of the last increment)``.
    Raises:
        SolveError: the load stepping stalled.
    """
    cfg = built.scene.spec.integrator
    n = cfg.load_steps if isinstance(cfg, StaticIntegrator) else 1
    sh = built.shard
    if sh is None:
        path = built.bc_fn if bc is None else (lambda s: bc)
        x0, pot = built.x0, built.potential.replace(mass=None) if pot is None else pot
    else:  # [solver] devices > 1: solve on the padded layout, report in the natural one
        fixed = None if bc is None else sh_dirichlet(built, bc)
        path = sh.bc_fn if fixed is None else (lambda s: fixed)
        x0, pot = sh.x0, sh.potential.replace(mass=None) if pot is None else pot
    on_increment = callback or (lambda s, sol: interrupt.check())
    if bc is None and built.cavities is not None and built.cavities.volumes is not None:
        return volume_controlled_solve(built, n, on_increment)  # [[cavity]] volume = ...
    active = isinstance(pot.params, ActiveTension)  # [material].active_tension: ramped
    sol = solve_incremental(
        pot,
        path(1.0),
        x0=x0,
        solver=built.solver,
        steps=n,
        path=path,
        throw=False,
        callback=lambda s, so: on_increment(s, natural_solution(built, so)),
        params_path=pot.params.scaled if active else None,
    )
    sol = natural_solution(built, sol)
    stats = [
        dict(
            status=h["status"],
            newton_steps=h["steps"],
            linear_iterations=h["linear_iterations"],
            residual=h["residual"],
            wall_time=h["wall_time"],
            load_factor=h["s"],
            accepted=h["accepted"],
            min_J=h["min_J"],
            max_strain=h["max_strain"],
            achieved_rtol=h["achieved_rtol"],
            floor_limited=h["floor_limited"],
        )
        for h in sol.stats["increments"]
    ]
    if not bool(sol.ok):
        s = sol.stats["load_factor"]
        raise SolveError(sol, what=f"{what} (stalled at load factor {s:.4g})")
    return sol.x, stats, sol


def natural_solution(built: Built, sol: Solution) -> Solution:
    """``sol`` with ``x`` as a NumPy array in the natural node numbering (unchanged without
    ``[solver] devices``; gathered from every process in a multi-process run)."""
    if built.shard is None:
        return sol
    return sol._replace(x=natural(built, sol.x))


def natural(built: Built, a) -> np.ndarray:
    """A padded node field of a sharded scene ``(S·n_own, ...)`` as a natural NumPy array
    ``(n_nodes, ...)`` (a collective in a multi-process run: every process calls it)."""
    assert built.shard is not None  # a sharded scene
    return built.shard.partition.to_natural(host_array(a), kind="nodes")


def sh_dirichlet(built: Built, bc: Dirichlet) -> Dirichlet:
    """Natural Dirichlet data of a sharded scene in its padded, sharded layout."""
    assert built.shard is not None  # a sharded scene
    return padded_dirichlet(built.shard, bc)


def _static_report(built: Built, x, stats: list[dict], sol: Solution) -> dict:
    steps = int(sol.stats["steps"])
    return dict(
        load_steps=stats,
        newton_steps=sum(s["newton_steps"] for s in stats),
        linear_iterations=sum(s["linear_iterations"] for s in stats),
        final_residual=stats[-1]["residual"],
        residual_history=np.asarray(sol.stats["residual_history"])[: steps + 1].tolist(),
        elastic_energy=elastic_energy(built, x),
        **displacement_report(built, x),
        **reaction_report(built, x, built.bc),
        **_solve_quality(stats),
        deformation=deformation_report(built, x),
    )


def _solve_quality(records: list[dict]) -> dict:
    """How many accepted solves stopped at the round-off floor above the requested
    tolerance, and the largest relative residual reached (over ``records``)."""
    ok = [r for r in records if r.get("accepted", r.get("status") == "SUCCESS")]
    return dict(
        floor_limited_solves=sum(bool(r.get("floor_limited")) for r in ok),
        achieved_rtol_max=max((r["achieved_rtol"] for r in ok), default=None),
    )


def _run_deformation(built: Built, x, records: list[dict]) -> dict:
    """:func:`~jaxelastic.scene.outputs.deformation_report` of the final state, and the
    smallest J of any time step (``min_J_run``, its time and cell)."""
    rep = deformation_report(built, x)
    if records:
        i = int(np.argmin([r["min_J"] for r in records]))
        rep.update(min_J_run=records[i]["min_J"], min_J_run_t=records[i]["t"])
        if built.shard is None:  # (a sharded run numbers its cells in the padded layout)
            rep["min_J_run_cell"] = records[i]["min_J_cell"]
        rep["max_strain_run"] = max(r["max_strain"] for r in records)
    return rep


def _run_static(built: Built, out: str, progress: bool, summary: dict) -> None:
    ocfg = built.scene.spec.output
    log(progress, "static solve (the first solve includes compilation) ...")
    done: list[tuple[float, Solution]] = []

    def on_increment(s: float, sol: Solution) -> None:
        done.append((s, sol))
        interrupt.check()  # stop at this increment on SIGINT/SIGTERM

    t0 = time.perf_counter()
    try:
        x, stats, sol = static_solve(built, callback=on_increment)
    except KeyboardInterrupt as e:
        summary["timings"]["solve_incl_compile"] = time.perf_counter() - t0
        _static_partial(built, out, done, summary)
        raise Interrupted(_signame(e), _static_detail(built, done)) from None
    summary["timings"]["solve_incl_compile"] = time.perf_counter() - t0
    summary["static"] = _static_report(built, x, stats, sol)
    if built.potential.contact is not None:  # min distance over the converged increments
        gaps = [min_gap(built.potential, so.x, si) for si, so in done]
        summary["contact"] = contact_report(built.potential, x, 1.0, min(gaps, default=None))
    summary["probes"] = probe_report(built, x)
    if built.cavities is not None:  # [[cavity]]: volumes per load step, P–V plot
        steps = [(0.0, built.x0, None)]
        steps += [(si, so.x, so.stats.get("cavity_pressure")) for si, so in done]
        summary["cavities"] = cavity_report(built.cavities, steps)
    t0 = time.perf_counter()
    # the stresses once for the VTU and the picture (0.07-0.2 s per evaluation at 146k tets)
    fields = state_stress_fields(built, x) if ocfg.vtu else None
    if ocfg.vtu:
        summary["outputs"]["pvd"] = write_static_vtu(built, out, 1.0, x, fields=fields)
    if ocfg.png:
        interrupt.check("after the static solve")
        summary["outputs"]["png"].append(static_figure(built, out, x, fields=fields))
        if "cavities" in summary:
            pv = pressure_volume_figure(summary["cavities"], out, built.scene.name, save_png)
            summary["outputs"]["png"].append(pv)
    summary["timings"]["outputs"] = time.perf_counter() - t0


def _static_detail(built: Built, done: list) -> str:
    if not done:
        return "before the first load increment converged"
    return f"at load factor {done[-1][0]:.4g} ({len(done)} converged increment(s))"


def _static_partial(built: Built, out: str, done: list, summary: dict) -> None:
    """The summary entries and the VTU of the last converged increment of a stopped run."""
    with interrupt.shield():
        if not done:
            return
        s, sol = done[-1]
        summary["static"] = dict(
            load_factor=s,
            completed_increments=[
                dict(
                    load_factor=si,
                    newton_steps=int(so.stats["steps"]),
                    residual=float(so.stats["residual"]),
                )
                for si, so in done
            ],
            elastic_energy=elastic_energy(built, sol.x),
        )
        summary["probes"] = probe_report(built, sol.x)
        if built.scene.spec.output.vtu:
            summary["outputs"]["pvd"] = write_static_vtu(built, out, s, sol.x)


def _signame(e: BaseException) -> str:
    return e.signame if isinstance(e, Interrupted) else "KeyboardInterrupt"


# ----------------------------------------------------------------------------------------
# dynamics
# ----------------------------------------------------------------------------------------


class _Monitor:
    """The ``simulate`` callback of a dynamic scene: keeps the last state and the tip
    displacement, writes the VTU series every ``[output].every`` steps, stops once the
    settle test (:func:`_at_rest`) holds for ``settle_steps`` consecutive steps, and stops
    at the step boundary after a SIGINT/SIGTERM."""

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
        self.scale = 0.0  # the largest kinetic + |elastic| + |external| energy so far
        self.settled_at: float | None = None
        self.t_out = 0.0
        self.min_gap = math.inf  # contact: the smallest node–obstacle distance of any step
        # [[cavity]]: the states of the output frames, for the volumes after the run
        self.frames = [(0.0, np.asarray(built.x0))] if built.cavities is not None else None

    def write(self, t: float, state) -> None:
        assert self.writer is not None  # called only when there is a writer
        t0 = time.perf_counter()
        steps = self.writer.steps
        if not (steps and steps[-1][0] == float(t)):  # not written yet (an interrupted write)
            self.writer.write(t, state.x, velocity=np.asarray(state.v))
        self.t_out += time.perf_counter() - t0
        self.last_written = self.n

    def __call__(self, state, solution, record) -> bool:
        self.n += 1
        self.state = state
        self.records.append(record)
        if self.built.potential.contact is not None:
            self.min_gap = min(self.min_gap, min_gap(self.built.potential, state.x, state.t))
        tip, X = self.built.tip, np.asarray(self.built.x0)
        self.tip_u.append(np.asarray(state.x)[tip] - X[tip])
        ke, el = float(record["kinetic"]), float(record["elastic"])
        self.scale = max(self.scale, ke + abs(el) + abs(float(record["external"])))
        rest = _at_rest(ke, el, self.scale, self.cfg.settle_tol)
        self.below = self.below + 1 if rest else 0
        done = self.cfg.settle and self.below >= self.cfg.settle_steps
        stop = interrupt.requested() is not None
        last = self.n % self.every == 0 or done or stop or self.n == self.n_steps
        if self.writer is not None and last:
            self.write(record["t"], state)
        if self.frames is not None and last:
            self.frames.append((float(record["t"]), np.asarray(state.x)))
        if done:
            self.settled_at = record["t"]
        return done or stop


def _simulate(built: Built, out: str, progress: bool, summary: dict):
    """Run the time steps; returns ``(monitor, failure or None, Interrupted or None)``."""
    pot, integ, cfg = built.potential, built.integrator, built.scene.spec.integrator
    assert integ is not None and isinstance(cfg, DynamicIntegrator)  # a dynamic scene
    n_steps = max(1, math.ceil(cfg.duration / integ.h - 1e-9))
    writer = None
    if built.scene.spec.output.vtu:
        writer = TimeSeriesWriter(
            out, "dynamic", built.mesh, built.psi, built.params, plane=vtu_plane(built),
            contact=built.potential.contact, compression=vtu_compression(built),
        )  # fmt: skip
    mon = _Monitor(built, writer, n_steps)
    log(progress, f"{n_steps} time steps of h = {integ.h:g} s (the first includes compilation)")
    bc = built.bc_fn if built.time_dependent else built.bc
    state, callback = mon.state, mon
    if built.shard is not None:  # [solver] devices > 1: step on the padded layout
        sh = built.shard
        pot, bc = sh.potential, sh.bc_fn if built.time_dependent else sh.bc
        state, callback = dynamics.init_state(sh.x0, sh.v0), _NaturalStates(built, mon)

    failure = stopped = None
    t0 = time.perf_counter()
    try:
        if writer is not None:
            mon.write(0.0, mon.state)
        dynamics.simulate(
            pot,
            state,
            bc,
            integ,
            n_steps,
            solver=built.solver,
            callback=callback,
            progress=progress,
            pressure_at=pressure_schedule(built.scene),  # [[pressure]] ramp_time
        )
    except SolveError as e:
        failure = e
        summary["failed_step"] = _failed_step(e, mon.n, integ.h)
    except KeyboardInterrupt as e:  # a second signal, or Ctrl-C without the CLI's handlers
        stopped = Interrupted(_signame(e))
    if stopped is None and interrupt.requested() is not None:
        stopped = Interrupted(interrupt.requested() or "SIGINT")
    summary["timings"]["time_loop_total"] = time.perf_counter() - t0
    if stopped is not None:
        t = mon.records[-1]["t"] if mon.records else 0.0
        stopped.detail = f"after {mon.n} of {n_steps} time steps (t = {t:.6g} s)"
    with interrupt.shield():
        _close_series(mon, writer, out, summary)
    return mon, failure, stopped


class _NaturalStates:
    """The ``simulate`` callback of a sharded scene: the monitor sees each state in the
    natural numbering (gathered from every process in a multi-process run)."""

    def __init__(self, built: Built, mon: _Monitor):
        self.built, self.mon = built, mon

    def __call__(self, state, solution, record) -> bool:
        nat = {k: natural(self.built, getattr(state, k)) for k in ("x", "v", "x_prev", "v_prev")}
        return self.mon(state._replace(**nat), solution, record)


def _failed_step(e: SolveError, n_done: int, h: float) -> dict:
    st = e.solution.stats
    return dict(
        step=n_done + 1,
        t=(n_done + 1) * h,
        status=e.status.name,
        newton_steps=int(st["steps"]),
        linear_iterations=int(st["linear_iterations"]),
        residual=float(st["residual"]),
    )


def _close_series(mon: _Monitor, writer: TimeSeriesWriter | None, out: str, summary: dict):
    """Write the last state if it was not, the final ``.pvd``; drop stale VTU files."""
    if writer is None:
        return
    if mon.last_written != mon.n or not writer.steps:
        mon.write(mon.records[-1]["t"] if mon.records else 0.0, mon.state)
    writer.close()
    remove_stale(out, "dynamic", len(writer.steps))
    summary["outputs"]["pvd"] = writer.pvd_path
    summary["outputs"]["vtu_files"] = len(writer.steps)


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
    scale = max(
        abs(a) + abs(b) + abs(c)
        for a, b, c in zip(per["kinetic"], per["elastic"], per["external"], strict=True)
    )
    summary["dynamic"] = dict(
        steps=mon.n,
        t_end=per["t"][-1],
        settled=mon.settled_at is not None,
        settle_time=mon.settled_at,
        kinetic_over_elastic=settle_ratio(per["kinetic"][-1], per["elastic"][-1], scale),
        newton_steps_total=int(sum(per["newton_steps"])),
        linear_iterations_total=int(sum(per["linear_iterations"])),
        final_residual=per["residual"][-1] if mon.n else None,
        **displacement_report(built, mon.state.x),
        **_solve_quality(mon.records),
        deformation=_run_deformation(built, mon.state.x, mon.records),
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
    log(progress, "static solve of the same load ...")
    t_end, tip, X = mon.records[-1]["t"] if mon.records else 0.0, built.tip, np.asarray(built.x0)
    bc = built.bc_fn(t_end)
    t0 = time.perf_counter()
    assert built.integrator is not None  # a dynamic scene
    base = built.potential if built.shard is None else built.shard.potential
    schedule = pressure_schedule(built.scene)
    if schedule is not None:  # the pressures the body carried at the end
        assert base.pressure is not None  # a scene with [[pressure]] entries
        p_end = jnp.asarray(schedule(t_end), base.pressure.pressure.dtype)
        base = base.replace(pressure=base.pressure.replace(pressure=p_end))
    pot = dynamics.static_potential(base, built.integrator)  # the steps' compile
    x_static, stats, _ = static_solve(built, bc=bc, what="static comparison solve", pot=pot)
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


def _dynamic_cavities(built: Built, frames: list) -> dict:
    """The cavity report of a dynamic scene over its output frames ``(t, x)``: the time,
    each cavity's pressure (its ``[[pressure]]`` entries at that time) and volume."""
    cav, scene = built.cavities, built.scene
    assert cav is not None  # a scene with [[cavity]]
    steps = [(t, x, cavity_pressures(scene, cav, pressures_at(scene, t))) for t, x in frames]
    return cavity_report(cav, steps, variable="time")


def _run_dynamic(built: Built, out: str, progress: bool, summary: dict) -> None:
    mon, failure, stopped = _simulate(built, out, progress, summary)
    with interrupt.shield():
        per = _per_step(built, mon.records)
        _dynamic_summary(built, mon, per, summary)
        if built.potential.contact is not None and mon.n:
            pot, x, t = built.potential, mon.state.x, mon.state.t
            summary["contact"] = contact_report(pot, x, t, mon.min_gap)
        if mon.frames is not None:  # [[cavity]]: volumes and pressures per output frame
            summary["cavities"] = _dynamic_cavities(built, mon.frames)
    if stopped is not None:
        summary["timings"]["outputs"] = mon.t_out
        raise stopped
    x_static = None
    cfg = built.scene.spec.integrator
    assert isinstance(cfg, DynamicIntegrator)  # a dynamic scene
    if cfg.compare_static and failure is None:
        x_static = _compare_static(built, out, progress, mon, summary)
    if built.scene.spec.output.png and mon.n:
        interrupt.check("after the time steps")
        t0 = time.perf_counter()
        paths = dynamic_figures(built, out, per, mon.tip_u, mon.state.x, x_static)
        if "cavities" in summary:
            paths.append(
                pressure_volume_figure(summary["cavities"], out, built.scene.name, save_png)
            )
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
    iterations and energies per step, final residual, probes, static/dynamic difference,
    ``interrupted``); with ``[output].vtu`` a ParaView series ``dynamic.pvd`` +
    ``dynamic_NNNN.vtu`` and/or ``static.pvd`` + ``static_0000.vtu`` (displacement,
    velocity, J, Green strain, P, von Mises stress, energy density); with ``[output].png``
    ``final_shape.png`` and, for dynamics, ``tip_displacement.png`` and ``energy.png``.
    ``out_dir`` is created; a path that is a file is refused, and so is an input file
    (scene, mesh) that an output would overwrite. ``dynamic.kinetic_over_elastic`` is
    ``null`` where the elastic energy is zero to round-off (:func:`settle_ratio`).

    Interruptions (SIGINT/SIGTERM under :func:`~jaxelastic.scene.interrupt.handle_signals`,
    or Ctrl-C): the run stops at the next time step or load increment, writes the VTU of
    the last completed state, a ``.pvd`` listing only the files written and a summary with
    ``"status": "interrupted"``, ``"interrupted": true``, the signal and what was
    completed (no PNGs, no static comparison), removes temporaries, and raises
    :class:`~jaxelastic.scene.interrupt.Interrupted`.

    Args:
        scene: a :class:`~jaxelastic.scene.load.Scene`, a TOML path, a shipped name or a
            dict; out_dir: output directory; progress: progress bar and messages.
    Raises:
        SceneError: invalid scene or output directory, or a mesh too large for the memory
            (checked before anything is allocated, see :mod:`jaxelastic.scene.memory`).
        SolveError: a Newton solve failed (``summary.json`` is still written, with
            ``"status": "failed"`` and the error).
        Interrupted: stopped by a signal (the partial outputs are written).
    """
    t_start = time.perf_counter()
    scene = load_scene(scene)
    memory.check(scene)  # before the output directory is created
    out = prepare_out(out_dir, scene)
    if scene.spec.solver.precision == "float64" and jnp.zeros(()).dtype != jnp.float64:
        warnings.warn(
            'running a scene in float32 although [solver] precision = "float64": enable '
            'float64 with jax.config.update("jax_enable_x64", True) (the CLI does), or set '
            'precision = "float32"',
            UserWarning,
            stacklevel=2,
        )
    path = os.path.join(out, "summary.json")
    summary: dict[str, Any] = dict(scene=scene.to_dict(), scene_file=scene.source, timings={})
    try:
        t0 = time.perf_counter()
        if scene.spec.output.png:
            _plot.preload()  # matplotlib imports beside the build and the solve
        with interrupt.immediate():  # no step boundary inside a build
            built = build(scene)
        summary = run_header(built, out)
        summary["timings"]["build"] = time.perf_counter() - t0
        (_run_static if scene.static else _run_dynamic)(built, out, progress, summary)
    except SolveError as e:
        finish_summary(path, summary, t_start, status="failed", error=str(e), interrupted=False)
        raise
    except KeyboardInterrupt as e:
        raise _interrupted(e, out, path, summary, t_start) from None
    found = run_warnings(summary)
    for w in found:
        warnings.warn(f"scene {scene.name!r}: {w}", SolveWarning, stacklevel=2)
    return finish_summary(path, summary, t_start, status="ok", interrupted=False, warnings=found)


def _interrupted(e: KeyboardInterrupt, out: str, path: str, summary: dict, t_start: float):
    """Write the summary of a stopped run, remove temporaries; the Interrupted to raise."""
    stop = e if isinstance(e, Interrupted) else Interrupted(_signame(e))
    if not stop.detail:
        stop.detail = "during the build" if "mesh" not in summary else "before the first step"
    stop.out = out
    with interrupt.shield():
        fields = dict(status="interrupted", interrupted=True, signal=stop.signame)
        finish_summary(path, summary, t_start, completed=stop.detail, **fields)
        remove_temporaries(out)
    return stop
