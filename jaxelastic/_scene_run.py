"""Running a validated :class:`~jaxelastic.scenes.Scene` (see that module).

:func:`build` (in :mod:`jaxelastic._scene_build`, re-exported here) turns the scene into
arrays and a :class:`~jaxelastic.potential.Potential`. :func:`run_scene`
solves it (static: Newton with optional load steps; dynamic: one jitted step per time
step in a host loop with a progress bar, stopping early once the body has settled) and
writes the outputs: a ParaView time series, PNG pictures and ``summary.json``.
"""

from __future__ import annotations

import contextlib
import fnmatch
import json
import math
import os
import re
import sys
import time
import warnings
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from . import dynamics, loads
from . import plot as _plot
from ._scene_build import _lift_file_mesh, _tip_node, build  # noqa: F401
from .energy import energy
from .io import TimeSeriesWriter, _write_atomic
from .loads import Dirichlet
from .potential import Potential
from .scenes import (
    Built,
    Scene,
    SceneError,
    load_scene,
)
from .solvers.continuation import solve_incremental
from .solvers.newton import (
    NewtonResult,
    SolveError,
    Status,
    newton,
)

__all__ = ["build", "run_scene"]

# output file names (an input file with one of these names in --out is refused)
_OUTPUT_PATTERNS = (
    "summary.json",
    "dynamic.pvd",
    "dynamic_*.vtu",
    "static.pvd",
    "static_*.vtu",
    "final_shape.png",
    "tip_displacement.png",
    "energy.png",
)


# ----------------------------------------------------------------------------------------
# run
# ----------------------------------------------------------------------------------------


def _step_and_energies(base: Potential, state, bc, integ, settings, linear=None):
    """One time step plus the energies of the new state (one compiled function)."""
    new, res = dynamics.step(base, state, bc, integ, settings, linear)
    ke = dynamics.kinetic_energy(base.mass, new.v)
    el = energy(base.psi, new.x, base.mesh, base.params)
    ext = (
        jnp.zeros((), new.x.dtype)
        if base.f_ext is None
        else -jnp.sum(base.f_ext * (new.x - base.mesh.points))
    )
    return new, res, jnp.stack([ke, el, ext])


_step_jit = jax.jit(_step_and_energies, static_argnames=("integ", "settings", "linear"))
_newton_jit = jax.jit(newton, static_argnames=("settings", "linear"))
_energy_jit = jax.jit(energy, static_argnums=0)
_reaction_jit = jax.jit(loads.reaction_force, static_argnums=0)


def _elastic(built: Built, x) -> float:
    return float(_energy_jit(built.psi, x, built.mesh, built.params))


def _log(progress: bool, msg: str) -> None:
    if progress:
        print(f"[jaxelastic] {msg}", file=sys.stderr, flush=True)


def _prepare_out(out_dir, scene: Scene, built_inputs=()) -> str:
    out = os.path.abspath(os.fspath(out_dir))
    if os.path.exists(out) and not os.path.isdir(out):
        raise SceneError(f"--out {os.fspath(out_dir)!r} exists and is not a directory")
    inputs = [p for p in (scene.source, scene["mesh"].get("file"), *built_inputs) if p]
    for p in inputs:
        p = os.path.abspath(p)
        if os.path.dirname(p) == out and any(
            fnmatch.fnmatch(os.path.basename(p), pat) for pat in _OUTPUT_PATTERNS
        ):
            raise SceneError(
                f"refusing to write into {out!r}: the input {p!r} has the name of an output "
                "file and would be overwritten; choose another --out"
            )
    os.makedirs(out, exist_ok=True)
    return out


def _remove_stale(out: str, basename: str, count: int) -> None:
    """Delete ``basename_NNNN.vtu`` files with N ≥ count left by an earlier, longer run
    into the same directory (only names matching that exact pattern)."""
    pat = re.compile(rf"^{re.escape(basename)}_(\d{{4,}})\.vtu$")
    for name in os.listdir(out):
        m = pat.match(name)
        if m and int(m.group(1)) >= count:
            with contextlib.suppress(OSError):
                os.remove(os.path.join(out, name))


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.ndarray, jax.Array)):
        return _jsonable(np.asarray(x).tolist())
    if isinstance(x, (np.floating, float)):
        x = float(x)
        return x if math.isfinite(x) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.bool_,)):
        return bool(x)
    return x


def _write_json(path: str, obj) -> None:
    text = json.dumps(_jsonable(obj), indent=1, allow_nan=False)

    def write(tmp):
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text + "\n")

    _write_atomic(path, write)


def _save_png(fig, path: str) -> None:
    _write_atomic(path, lambda tmp: fig.savefig(tmp, format="png", dpi=130))


def _solve_stats(res: NewtonResult, wall: float) -> dict:
    return dict(
        status=Status(int(res.status)).name,
        newton_steps=int(res.steps),
        linear_iterations=int(res.linear_iterations),
        residual=float(res.residual),
        line_search_cutbacks=int(res.line_search_cutbacks),
        negative_curvature=int(res.negative_curvature),
        wall_time=wall,
    )


def _static_solve(built: Built, progress: bool, *, bc=None, what="static solve"):
    """Newton with ``load_steps`` increments and automatic cut-back on failure; returns
    ``(x, per-trial stats, last result)``.

    ``bc``: fixed Dirichlet data (the dynamic comparison); default ``built.bc_fn(s)`` at
    each load factor ``s``.
    """
    scene, pot = built.scene, built.potential
    static_pot = pot.replace(mass=None)
    n = scene["integrator"].get("load_steps", 1) if scene.static else 1
    bc_fn = built.bc_fn if bc is None else (lambda s: bc)
    inc = solve_incremental(
        static_pot,
        bc_fn,
        built.x0,
        steps=n,
        settings=built.settings,
        linear=built.linear,
        throw=False,
    )
    stats = []
    for h in inc.history:
        st = {k: h[k] for k in ("status", "newton_steps", "linear_iterations", "residual")}
        st.update(
            line_search_cutbacks=0,
            negative_curvature=0,
            wall_time=h["wall_time"],
            load_factor=h["s"],
            accepted=h["accepted"],
        )
        stats.append(st)
    if not inc.ok:
        raise SolveError(inc.last, what=f"{what} (stalled at load factor {inc.load_factor:.4g})")
    return inc.x, stats, inc.last


def _probe_report(built: Built, x) -> list:
    X = np.asarray(built.mesh.points)
    u = np.asarray(x) - X
    return [
        dict(
            point=p,
            node=node,
            node_position=X[node].tolist(),
            distance=float(np.linalg.norm(X[node] - np.asarray(p))),
            displacement=u[node].tolist(),
        )
        for node, p in built.probes
    ]


def _reaction(built: Built, x, bc: Dirichlet):
    pot = built.potential
    r = _reaction_jit(built.psi, x, built.mesh, built.params, bc, pot.f_ext)
    total = np.zeros(built.mesh.dim) if pot.f_ext is None else np.asarray(pot.f_ext).sum(0)
    return dict(reaction_force=np.asarray(r).tolist(), total_applied_load=total.tolist())


def _run_static(built: Built, out: str, progress: bool, summary: dict) -> None:
    scene = built.scene
    _log(progress, "static solve (the first solve includes compilation) ...")
    t0 = time.perf_counter()
    x, stats, res = _static_solve(built, progress)
    summary["timings"]["solve_incl_compile"] = time.perf_counter() - t0
    summary["static"] = dict(
        load_steps=stats,
        newton_steps=sum(s["newton_steps"] for s in stats),
        linear_iterations=sum(s["linear_iterations"] for s in stats),
        final_residual=stats[-1]["residual"],
        residual_history=np.asarray(res.residual_history)[: int(res.steps) + 1].tolist(),
        elastic_energy=_elastic(built, x),
        max_displacement=float(np.linalg.norm(np.asarray(x) - built.x0, axis=1).max()),
        **_reaction(built, x, built.bc),
    )
    summary["probes"] = _probe_report(built, x)
    t0 = time.perf_counter()
    if scene["output"]["vtu"]:
        with TimeSeriesWriter(out, "static", built.mesh, built.psi, built.params) as w:
            w.write(1.0, x)
        _remove_stale(out, "static", 1)
        summary["outputs"]["pvd"] = w.pvd_path
    if scene["output"]["png"]:
        fig = _plot.final_shape_figure(
            built.mesh, {"rest": built.x0, "static": x}, title=f"{scene.name}: static solution"
        )
        path = os.path.join(out, "final_shape.png")
        _save_png(fig, path)
        summary["outputs"]["png"].append(path)
    summary["timings"]["outputs"] = time.perf_counter() - t0


def _run_dynamic(built: Built, out: str, progress: bool, summary: dict) -> None:
    from tqdm.auto import tqdm

    scene, pot, integ = built.scene, built.potential, built.integrator
    cfg, ocfg = scene["integrator"], scene["output"]
    h = integ.h
    n_steps = max(1, math.ceil(cfg["duration"] / h - 1e-9))
    state = dynamics.init_state(built.x0, built.v0)
    X = np.asarray(built.x0)
    rec = {
        k: []
        for k in (
            "t",
            "newton_steps",
            "linear_iterations",
            "residual",
            "line_search_cutbacks",
            "wall_time",
            "kinetic",
            "elastic",
            "external",
            "total",
        )
    }
    tip_u = [np.zeros(built.mesh.dim)]
    e0 = _elastic(built, built.x0)
    ke0 = 0.5 * float(np.sum(np.asarray(pot.mass)[:, None] * np.asarray(built.v0) ** 2))
    for k, val in (("t", 0.0), ("kinetic", ke0), ("elastic", e0), ("external", 0.0)):
        rec[k].append(val)
    rec["total"].append(rec["kinetic"][0] + e0)
    writer = None
    t_out = 0.0
    if ocfg["vtu"]:
        t0 = time.perf_counter()
        writer = TimeSeriesWriter(out, "dynamic", built.mesh, built.psi, built.params)
        writer.write(0.0, state.x, velocity=np.asarray(state.v))
        t_out += time.perf_counter() - t0
    below = 0
    settled_at = None
    bc = built.bc_fn(h) if built.time_dependent else built.bc
    _log(progress, f"{n_steps} time steps of h = {h:g} s (the first step includes compilation)")
    bar = tqdm(total=n_steps, desc="time steps", unit="step", disable=not progress, mininterval=0.5)
    last_written = 0
    t_loop = time.perf_counter()
    failure = None
    for n in range(1, n_steps + 1):
        t_new = n * h
        if built.time_dependent:
            bc = built.bc_fn(t_new)
        t0 = time.perf_counter()
        new, res, en = _step_jit(pot, state, bc, integ, built.settings, built.linear)
        en = np.asarray(jax.block_until_ready(en))
        wall = time.perf_counter() - t0
        status = int(res.status)
        if status != Status.SUCCESS:
            failure = SolveError(res, what=f"time step {n} (to t = {t_new:g} s)")
            summary["failed_step"] = dict(step=n, t=t_new, **_solve_stats(res, wall))
            break
        state = new
        ke, el, ext = (float(a) for a in en)
        for k, val in (
            ("t", t_new),
            ("newton_steps", int(res.steps)),
            ("linear_iterations", int(res.linear_iterations)),
            ("residual", float(res.residual)),
            ("line_search_cutbacks", int(res.line_search_cutbacks)),
            ("wall_time", wall),
            ("kinetic", ke),
            ("elastic", el),
            ("external", ext),
            ("total", ke + el + ext),
        ):
            rec[k].append(val)
        tip_u.append(np.asarray(state.x)[built.tip] - X[built.tip])
        ratio = ke / max(abs(el), np.finfo(float).tiny)
        below = below + 1 if ratio < cfg["settle_tol"] else 0
        done = cfg["settle"] and below >= cfg["settle_steps"]
        if writer is not None and (n % ocfg["every"] == 0 or done or n == n_steps):
            t0 = time.perf_counter()
            writer.write(t_new, state.x, velocity=np.asarray(state.v))
            t_out += time.perf_counter() - t0
            last_written = n
        bar.set_postfix(
            t=f"{t_new:.3g}",
            newton=int(res.steps),
            cg=int(res.linear_iterations),
            KE_el=f"{ratio:.1e}",
            refresh=False,
        )
        bar.update(1)
        if done:
            settled_at = t_new
            bar.total = n  # settled early: show the bar complete
            bar.set_description("time steps (settled)", refresh=False)
            bar.refresh()
            break
    bar.close()
    loop_wall = time.perf_counter() - t_loop
    if writer is not None:
        if last_written != len(rec["t"]) - 1 and len(rec["t"]) > 1:
            writer.write(rec["t"][-1], state.x, velocity=np.asarray(state.v))
        writer.close()
        _remove_stale(out, "dynamic", len(writer.steps))
        summary["outputs"]["pvd"] = writer.pvd_path
        summary["outputs"]["vtu_files"] = len(writer.steps)
    walls = rec["wall_time"]
    steady = float(np.median(walls[1:])) if len(walls) > 1 else float("nan")
    summary["timings"].update(
        first_step_incl_compile=walls[0] if walls else None,
        compile_estimate=(walls[0] - steady) if len(walls) > 1 else None,
        step_median=steady,
        steps_total=float(sum(walls)),
        time_loop_total=loop_wall,
    )
    steps_taken = len(rec["t"]) - 1
    summary["dynamic"] = dict(
        steps=steps_taken,
        t_end=rec["t"][-1],
        settled=settled_at is not None,
        settle_time=settled_at,
        kinetic_over_elastic=rec["kinetic"][-1] / max(abs(rec["elastic"][-1]), 1e-300),
        newton_steps_total=int(sum(rec["newton_steps"][0:])),
        linear_iterations_total=int(sum(rec["linear_iterations"])),
        final_residual=rec["residual"][-1] if steps_taken else None,
        tip=dict(
            node=built.tip,
            rest_position=X[built.tip].tolist(),
            source="probe 0" if built.probes else "node farthest from the Dirichlet nodes",
            displacement=tip_u[-1].tolist(),
        ),
        per_step=rec,
    )
    summary["probes"] = _probe_report(built, state.x)
    x_static = None
    if cfg["compare_static"] and failure is None:
        _log(progress, "static solve of the same load (includes compilation) ...")
        t0 = time.perf_counter()
        x_static, stats, res = _static_solve(
            built, progress, bc=built.bc_fn(rec["t"][-1]), what="static comparison solve"
        )
        summary["timings"]["static_solve_incl_compile"] = time.perf_counter() - t0
        u_s = np.asarray(x_static) - X
        dist = np.linalg.norm(np.asarray(state.x) - np.asarray(x_static), axis=1)
        umax = float(np.linalg.norm(u_s, axis=1).max())
        tip_s = float(np.linalg.norm(u_s[built.tip]))
        summary["static"] = dict(
            **stats[-1],
            elastic_energy=_elastic(built, x_static),
            tip_displacement=u_s[built.tip].tolist(),
            max_displacement=umax,
            probes=_probe_report(built, x_static),
            **_reaction(built, x_static, built.bc_fn(rec["t"][-1])),
        )
        summary["comparison"] = dict(
            max_nodal_distance=float(dist.max()),
            tip_distance=float(dist[built.tip]),
            tip_deflection_static=tip_s,
            relative_to_tip_deflection=float(dist.max()) / max(tip_s, 1e-300),
            relative_to_max_displacement=float(dist.max()) / max(umax, 1e-300),
        )
        if writer is not None:
            t0 = time.perf_counter()
            with TimeSeriesWriter(out, "static", built.mesh, built.psi, built.params) as w:
                w.write(rec["t"][-1], x_static)
            _remove_stale(out, "static", 1)
            t_out += time.perf_counter() - t0
    if ocfg["png"] and steps_taken:
        t0 = time.perf_counter()
        shapes = {"rest": built.x0, f"dynamic, t = {rec['t'][-1]:.3g} s": state.x}
        if x_static is not None:
            shapes["static"] = x_static
        figs = {
            "final_shape.png": _plot.final_shape_figure(
                built.mesh, shapes, title=f"{scene.name}: final shape"
            ),
            "tip_displacement.png": _plot.tip_displacement_figure(
                rec["t"],
                np.asarray(tip_u),
                static=None if x_static is None else np.asarray(x_static)[built.tip] - X[built.tip],
                title=f"{scene.name}: displacement of node {built.tip} at "
                f"{np.round(X[built.tip], 4).tolist()}",
            ),
            "energy.png": _plot.energy_figure(
                rec["t"],
                {
                    "kinetic": rec["kinetic"],
                    "elastic": rec["elastic"],
                    r"load potential $-f_{ext} \cdot u$": rec["external"],
                    "total": rec["total"],
                },
                settle_tol=cfg["settle_tol"] if cfg["settle"] else None,
                title=f"{scene.name}: energies",
            ),
        }
        for name, fig in figs.items():
            path = os.path.join(out, name)
            _save_png(fig, path)
            summary["outputs"]["png"].append(path)
        t_out += time.perf_counter() - t0
    summary["timings"]["outputs"] = t_out
    if failure is not None:
        raise failure


def run_scene(scene, out_dir, progress: bool = True) -> dict:
    """Solve a scene and write its outputs into ``out_dir``; returns the summary dict.

    Writes (each file atomically): ``summary.json``; with ``[output].vtu`` a ParaView
    series ``dynamic.pvd`` + ``dynamic_NNNN.vtu`` (dynamics) and/or ``static.pvd`` +
    ``static_0000.vtu`` (displacement, velocity, J, stresses, energy density); with
    ``[output].png`` ``final_shape.png`` and, for dynamics, ``tip_displacement.png`` and
    ``energy.png``. ``out_dir`` is created; an existing file there is refused, and so is
    an input file (scene, mesh) that an output would overwrite.

    On a failed Newton solve the summary (with ``"status": "failed"`` and the error) is
    still written, then :class:`~jaxelastic.solvers.newton.SolveError` is raised.
    """
    t_start = time.perf_counter()
    scene = load_scene(scene)
    out = _prepare_out(out_dir, scene)
    if jnp.zeros(()).dtype != jnp.float64:
        warnings.warn(
            "running a scene in float32: enable float64 with "
            'jax.config.update("jax_enable_x64", True) (the CLI does)',
            UserWarning,
            stacklevel=2,
        )
    t0 = time.perf_counter()
    built = build(scene)
    summary: dict[str, Any] = dict(
        scene=scene.to_dict(),
        scene_file=scene.source,
        status="running",
        mesh=dict(
            dim=built.mesh.dim,
            n_nodes=built.mesh.n_nodes,
            n_cells=built.mesh.n_cells,
            element=built.mesh.element,
            formulation=built.mesh.formulation,
            n_dirichlet_dofs=int(np.asarray(built.bc.mask).sum()),
        ),
        material=dict(
            model=scene["material"]["model"],
            mu=float(built.params.mu),
            lam=float(built.params.lam),
            density=scene["material"].get("density"),
        ),
        solver=built.settings._asdict(),
        integrator=None if built.integrator is None else built.integrator._asdict(),
        timings=dict(build=time.perf_counter() - t0),
        outputs=dict(directory=out, summary=os.path.join(out, "summary.json"), png=[]),
    )
    summary_path = os.path.join(out, "summary.json")
    try:
        if scene.static:
            _run_static(built, out, progress, summary)
        else:
            _run_dynamic(built, out, progress, summary)
    except SolveError as e:
        summary["status"] = "failed"
        summary["error"] = str(e)
        summary["timings"]["total"] = time.perf_counter() - t_start
        _write_json(summary_path, summary)
        raise
    summary["status"] = "ok"
    summary["timings"]["total"] = time.perf_counter() - t_start
    _write_json(summary_path, summary)
    return _jsonable(summary)
