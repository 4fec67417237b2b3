"""Building a validated :class:`~jaxelastic.scenes.Scene` into arrays and a potential.

:func:`build` turns the scene into a mesh (generated, or read from a file and optionally
lifted to P2 / the composite F-bar element), ψ, parameters, Dirichlet data, a
:class:`~jaxelastic.potential.Potential` holding only the parts the scene needs (no mass in
statics, no ``f_ext`` without loads), Newton settings and an integrator.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from . import dynamics, loads
from ._where import WhereError, where_mask
from .io import MeshData, read_mesh
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
from .solvers.newton import (
    NewtonSettings,
    make_linear,
)

__all__ = ["build"]


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
