"""Building and running a validated :class:`~jaxelastic.scenes.Scene` (see that module).

:func:`build` turns the scene into a mesh, ψ, parameters, Dirichlet data, a
:class:`~jaxelastic.potential.Potential` holding only the parts the scene needs (no mass in
statics, no ``f_ext`` without loads), Newton settings and an integrator. :func:`run_scene`
solves it (static: Newton with optional load steps; dynamic: one jitted step per time
step in a host loop with a progress bar, stopping early once the body has settled) and
writes the outputs: a ParaView time series, PNG pictures and ``summary.json``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fnmatch
import functools
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
from ._where import WhereError, where_mask
from .energy import energy
from .io import MeshData, TimeSeriesWriter, _write_atomic, read_mesh
from .loads import Dirichlet
from .materials import BUILTIN, Lame, lame
from .mesh import (
    Mesh,
    MeshError,
    boundary_facets,
    box,
    cook_membrane,
    rectangle,
    to_quadratic,
    with_formulation,
)
from .potential import Potential
from .quadratic import _edge_table
from .scenes import (
    _V,
    Built,
    Scene,
    SceneError,
    _axis_index,
    _check_dims,
    _import_callable,
    _n_positional,
    load_scene,
)
from .solvers.continuation import solve_incremental
from .solvers.newton import (
    NewtonResult,
    NewtonSettings,
    SolveError,
    Status,
    make_linear,
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
# build
# ----------------------------------------------------------------------------------------


def _make_mesh(v: _V, scene: Scene) -> tuple[Mesh, MeshData | None]:
    m = scene["mesh"]
    form = m.get("formulation", "standard")
    if "file" in m:
        try:
            md = read_mesh(m["file"])
            return _lift_file_mesh(md, m.get("order"), form)
        except (MeshError, ValueError) as e:
            raise v.err(f"[mesh].file: {e}") from None
    gen = m["generator"]
    kw = dict(order=m.get("order", 1), formulation=form)
    try:
        if gen == "cook":
            return cook_membrane(m["n"], **kw), None
        fn = box if gen == "box" else rectangle
        return fn(*m["n"], size=tuple(m["size"]), origin=tuple(m["origin"]), **kw), None
    except (MeshError, ValueError) as e:
        raise v.err(f"[mesh]: {e}") from None


def _lift_file_mesh(md: MeshData, order, form: str) -> tuple[Mesh, MeshData]:
    """Apply ``[mesh] order/formulation`` to a mesh read from a file. A P1 file becomes P2
    (``order = 2``) or composite (``order`` 1/unset with F-bar/B-bar) by :func:`to_quadratic`,
    which keeps the P1 node numbers: point sets gain the mid-edge nodes of edges with both
    ends in the set, facet sets become the quadratic facets with the same corners."""
    mesh = md.mesh
    el = mesh.element_type
    p1 = el.n_nodes == el.dim + 1
    if order == 1 and not p1:
        raise MeshError(f"order = 1 but the file holds {el.name} cells (P2 files stay P2)")
    if p1 and (order == 2 or form != "standard"):
        q = to_quadratic(mesh, composite=order != 2, formulation=form)
        cells = np.asarray(q.cells)
        ends = cells[:, : el.dim + 1][:, _edge_table(el)].reshape(-1, 2)  # (c·e, 2)
        mids = cells[:, el.dim + 1 :].reshape(-1)  # the mid-node of each of those edges

        def lift_points(idx):
            inset = np.zeros(q.n_nodes, dtype=bool)
            inset[idx] = True
            return np.unique(np.concatenate([idx, mids[inset[ends].all(axis=1)]]))

        bf = boundary_facets(q)
        key = {tuple(sorted(f[: el.dim])): f for f in bf}

        def lift_facets(f1):
            try:
                return np.array([key[tuple(sorted(f))] for f in f1]).reshape(-1, bf.shape[1])
            except KeyError:
                raise MeshError("a tagged facet set holds interior facets") from None

        md = dataclasses.replace(
            md,
            mesh=q,
            point_sets={k: lift_points(s) for k, s in md.point_sets.items()},
            facet_sets={k: lift_facets(s) for k, s in md.facet_sets.items()},
            node_map=np.concatenate([md.node_map, np.full(q.n_nodes - mesh.n_nodes, -1)]),
        )
        return q, md
    if form != mesh.formulation:
        mesh = with_formulation(mesh, form)
        md = dataclasses.replace(md, mesh=mesh)
    return mesh, md


@functools.partial(jax.jit, static_argnums=0)
def _psi_and_P(psi, F, params):
    return jnp.asarray(psi(F, params)), jax.grad(psi)(F, params)


def _material(v: _V, scene: Scene, dim: int):
    m = scene["material"]
    model = m["model"]
    psi = (
        BUILTIN[model]
        if ":" not in model
        else _import_callable(v, "[material].model", model, scene.base_dir)
    )
    if "E" in m:
        try:
            mu, lam = lame(m["E"], m["nu"], dim=dim, plane=m.get("plane", "strain"))
        except ValueError as e:
            raise v.err(f"[material]: {e}") from None
    else:
        mu, lam = m["mu"], m["lam"]
    dtype = jnp.zeros(()).dtype
    params = Lame(jnp.asarray(mu, dtype), jnp.asarray(lam, dtype))
    try:
        F = jnp.asarray(np.eye(dim), dtype)
        val, P = _psi_and_P(psi, F, params)  # one small compile, not op-by-op dispatch
    except Exception as e:  # noqa: BLE001 — user code: report any failure with the key
        raise v.err(
            f"[material].model {model!r} fails at F = I in {dim}D ({type(e).__name__}: {e})"
        ) from None
    if val.shape != () or not bool(jnp.isfinite(val)) or not bool(jnp.all(jnp.isfinite(P))):
        raise v.err(
            f"[material].model {model!r} must return a finite scalar at F = I, got "
            f"shape {val.shape}, value {val}"
        )
    return psi, params


def _select_nodes(v: _V, key: str, sel, mesh: Mesh, md: MeshData | None) -> np.ndarray:
    X = np.asarray(mesh.points)
    if "plane" in sel:
        p = sel["plane"]
        idx = loads.nodes_on_plane(mesh, _axis_index(p["axis"]), p["value"], p.get("tol"))
    elif "box" in sel:
        idx = loads.nodes_in_box(mesh, sel["box"]["lo"], sel["box"]["hi"])
    elif "where" in sel:
        try:
            idx = np.flatnonzero(where_mask(sel["where"], X))
        except (WhereError, ValueError, IndexError, TypeError) as e:
            raise v.err(f"{key}.where: cannot evaluate {sel['where']!r}: {e}") from None
    else:
        name = sel["group"]
        if md is None:
            raise v.err(f"{key}.group: a generated mesh has no named groups (use plane/box/where)")
        if name in md.point_sets:
            idx = md.point_sets[name]
        elif name in md.facet_sets:
            idx = np.unique(md.facet_sets[name])
        elif name in md.cell_sets:
            idx = np.unique(np.asarray(mesh.cells)[md.cell_sets[name]])
        else:
            names = sorted({*md.point_sets, *md.facet_sets, *md.cell_sets})
            raise v.err(
                f"{key}.group: the mesh has no group {name!r} (groups: "
                f"{', '.join(names) or 'none'})"
            )
    idx = np.asarray(idx, dtype=np.int64)
    if idx.size == 0:
        raise v.err(f"{key} selects no nodes")
    return idx


def _select_facets(v: _V, key: str, sel, mesh: Mesh, md: MeshData | None) -> np.ndarray:
    if "group" in sel:
        name = sel["group"]
        if md is None:
            raise v.err(f"{key}.group: a generated mesh has no named groups (use plane/box/where)")
        if name not in md.facet_sets:
            raise v.err(
                f"{key}.group: the mesh has no facet group {name!r} (facet groups: "
                f"{', '.join(sorted(md.facet_sets)) or 'none'})"
            )
        facets = md.facet_sets[name]
    else:
        mask = np.zeros(mesh.n_nodes, dtype=bool)
        mask[_select_nodes(v, key, sel, mesh, md)] = True
        facets = loads.facets_where(mesh, lambda X: mask)
    if len(facets) == 0:
        raise v.err(f"{key} selects no boundary facets (all nodes of a facet must match)")
    return np.asarray(facets)


def _rotation(axis: int, angle_deg: float, dim: int) -> np.ndarray:
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    if dim == 2:
        return np.array([[c, -s], [s, c]])
    i, j = [a for a in range(3) if a != axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def _displacement_fn(v: _V, key: str, spec, base_dir: str, dim: int):
    """``(u(Xs, t) -> (m, dim), time_dependent)`` for one Dirichlet entry."""
    if spec is None:
        return (lambda Xs, t: np.zeros_like(Xs)), False
    if isinstance(spec, str):
        fn = _import_callable(v, key, spec, base_dir)
        if _n_positional(fn) >= 2:
            return (lambda Xs, t: fn(Xs, t)), True
        return (lambda Xs, t: fn(Xs)), False
    if isinstance(spec, dict) or hasattr(spec, "keys"):
        r = spec["rotate"]
        R = _rotation(_axis_index(r["axis"]), r["angle_deg"], dim)
        c = np.asarray(r.get("center", [0.0] * dim), dtype=float)
        scale = r["scale"]
        return (lambda Xs, t: scale * ((Xs - c) @ R.T + c - Xs)), False
    u = np.asarray(spec, dtype=float)
    return (lambda Xs, t: np.broadcast_to(u, Xs.shape)), False


def _dirichlet(v: _V, scene: Scene, mesh: Mesh, md):
    X = np.asarray(mesh.points)
    dim = mesh.dim
    entries = []
    time_dep = False
    for i, d in enumerate(scene["dirichlet"]):
        key = f"[dirichlet][{i}]"
        idx = _select_nodes(v, f"{key}.nodes", d["nodes"], mesh, md)
        comps = d.get("components")
        comps = None if comps is None else [_axis_index(a) for a in comps]
        u, dep = _displacement_fn(
            v, f"{key}.displacement", d.get("displacement"), scene.base_dir, dim
        )
        ramp = d.get("ramp_time")
        time_dep |= dep or ramp is not None
        entries.append((key, idx, comps, u, ramp))
    static = scene.static

    def bc_fn(s: float) -> Dirichlet:
        if not entries:
            return loads.no_dirichlet(mesh)
        parts = []
        for key, idx, comps, u, ramp in entries:
            factor = s if static else (1.0 if ramp is None else min(s / ramp, 1.0))
            t = None if static else s
            try:
                disp = factor * np.asarray(u(X[idx], t), dtype=float)
                parts.append(loads.fix(mesh, idx, comps, disp))
            except SceneError:
                raise
            except Exception as e:  # noqa: BLE001 — user functions: name the key
                raise v.err(f"{key}.displacement: {type(e).__name__}: {e}") from None
        return loads.combine(*parts)

    return bc_fn, time_dep


def _external_forces(v: _V, scene: Scene, mesh: Mesh, md) -> np.ndarray | None:
    f = None

    def add(g):
        nonlocal f
        f = g if f is None else f + g

    for i, t in enumerate(scene["traction"]):
        key = f"[traction][{i}]"
        facets = _select_facets(v, f"{key}.facets", t["facets"], mesh, md)
        if "traction" in t:
            add(loads.traction_load(mesh, facets, t["traction"]))
        else:
            _, area = loads.facet_normals(mesh.points, facets)
            add(loads.traction_load(mesh, facets, np.asarray(t["total_force"]) / area.sum()))
    for i, p in enumerate(scene["point_load"]):
        key = f"[point_load][{i}]"
        idx = _select_nodes(v, f"{key}.nodes", p["nodes"], mesh, md)
        force = p["force"] if "force" in p else np.asarray(p["total_force"]) / idx.size
        add(loads.point_load(mesh, idx, force))
    if "gravity" in scene.data:
        add(loads.gravity_load(mesh, scene["material"]["density"], scene["gravity"]["g"]))
    return f


def _tip_node(mesh: Mesh, bc: Dirichlet) -> int:
    from scipy.spatial import cKDTree

    X = np.asarray(mesh.points)
    fixed = np.flatnonzero(np.asarray(bc.mask).any(axis=1))
    if fixed.size == 0:
        return int(np.argmax(np.linalg.norm(X - X.mean(axis=0), axis=1)))
    dist, _ = cKDTree(X[fixed]).query(X)
    return int(np.argmax(dist))


def build(scene) -> Built:
    """Turn a scene (a :class:`~jaxelastic.scenes.Scene`, path, name or dict) into arrays.

    Raises:
        SceneError: problems only visible with the mesh (a selection that matches no
            node, an unknown group, wrong vector lengths for a mesh file's dimension, a
            user function returning the wrong shape, a material failing at F = I).
    """
    scene = load_scene(scene)
    v = _V(scene.label)
    mesh, md = _make_mesh(v, scene)
    dim = mesh.dim
    if scene.dim is None:
        if dim == 3 and "plane" in scene["material"]:
            raise v.err("[material].plane applies to 2D meshes only")
        _check_dims(v, scene._dim_checks, dim)
    psi, params = _material(v, scene, dim)
    bc_fn, time_dep = _dirichlet(v, scene, mesh, md)
    f_ext = _external_forces(v, scene, mesh, md)
    integ = scene["integrator"]
    dtype = mesh.points.dtype
    solver_opts = dict(scene["solver"])
    linear_kind = solver_opts.pop("linear", "auto")
    settings = NewtonSettings(**solver_opts)
    X = np.asarray(mesh.points)
    pot = Potential(
        mesh=mesh,
        params=params,
        f_ext=None if f_ext is None else jnp.asarray(f_ext, dtype),
        psi=psi,
    )
    if scene.static:
        bc = bc_fn(1.0)
        integrator, v0 = None, None
    else:
        bc = bc_fn(0.0)
        pot = pot.replace(
            mass=jnp.asarray(loads.lumped_mass(mesh, scene["material"]["density"]), dtype)
        )
        integrator = dynamics.Integrator(
            h=integ["h"], method=integ["method"], alpha=integ["alpha"], beta=integ["beta"]
        )
        iv = integ.get("initial_velocity")
        key = "[integrator].initial_velocity"
        if iv is None:
            v0 = np.zeros_like(X)
        elif isinstance(iv, str):
            fn = _import_callable(v, key, iv, scene.base_dir)
            try:
                v0 = np.asarray(fn(X), dtype=float)
            except Exception as e:  # noqa: BLE001
                raise v.err(f"{key}: {type(e).__name__}: {e}") from None
            if v0.shape != X.shape or not np.isfinite(v0).all():
                raise v.err(f"{key}: must return finite values of shape {X.shape}, got {v0.shape}")
        else:
            v0 = np.broadcast_to(np.asarray(iv, dtype=float), X.shape).copy()
        v0 = jnp.asarray(np.where(np.asarray(bc.mask), 0.0, v0), dtype)
    probes = []
    for p in scene["output"]["probes"]:
        node = int(np.argmin(np.linalg.norm(X - np.asarray(p), axis=1)))
        probes.append((node, list(p)))
    tip = probes[0][0] if probes else _tip_node(mesh, bc)
    return Built(
        scene=scene,
        mesh=mesh,
        mesh_data=md,
        psi=psi,
        params=params,
        potential=pot,
        bc=bc,
        bc_fn=bc_fn,
        time_dependent=time_dep,
        settings=settings,
        linear=make_linear(mesh, bc, linear_kind),
        integrator=integrator,
        x0=mesh.points,
        v0=v0,
        probes=probes,
        tip=tip,
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
