"""Building a validated :class:`~jaxelastic.scene.load.Scene` into arrays and a potential.

:func:`build` turns the scene into a mesh (generated, or read from a file and optionally
lifted to P2 / the composite F-bar element), ψ, parameters, Dirichlet data, a
:class:`~jaxelastic.mechanics.potential.Potential` holding only the parts the scene needs (no
mass in statics, no ``f_ext`` without loads), a bound :class:`~jaxelastic.Newton` solver and an
integrator. Problems only visible with the mesh (a selection matching no node, an unknown
group, a user function failing) are :class:`~jaxelastic.scene.errors.SceneError` s naming
the key.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import dynamics, loads
from ..io import MeshData, read_mesh
from ..loads import Dirichlet
from ..materials import (
    BUILTIN,
    DIRECTION_KEYS,
    FAMILIES,
    FAMILY_TYPES,
    ActiveTension,
    Guccione,
    Lame,
    check_guccione,
    helix_basis,
    lame,
    with_active_tension,
)
from ..mechanics.potential import Potential
from ..mechanics.quadrature_fields import AtQuadrature, first_point_params, is_at_quadrature
from ..mesh import (
    Mesh,
    MeshError,
    boundary_facets,
    box,
    cook_membrane,
    rectangle,
    to_quadratic,
    with_formulation,
)
from ..mesh.elements import edge_table
from ..solvers import CG, Newton, PreparedSolver, prepare_solver
from ..solvers.newton import is_quadratic
from . import memory
from .callables import CallableSpecError, import_callable, n_positional
from .cavity import Cavities, build_pressure
from .contact import build_contact
from .load import Scene, load_scene
from .schema import (
    DynamicIntegrator,
    FibreCellData,
    FibreRegion,
    FibreRule,
    RotateDisplacement,
    Selector,
    SolverSpec,
    axis_index,
)
from .where import WhereError, where_mask

__all__ = [
    "Built",
    "build",
    "newton_of",
    "lift_file_mesh",
    "empty_mesh_counts",
    "select_nodes",
    "select_facets",
    "scene_dtype",
    "linear_solver_name",
    "Sharded",
    "check_devices",
    "padded_dirichlet",
]


class Built(NamedTuple):
    """A scene turned into arrays and functions (everything a run needs).

    Attributes:
        scene: the :class:`~jaxelastic.scene.load.Scene`.
        mesh: the rest mesh; mesh_data: the :class:`~jaxelastic.io.MeshData` of a mesh
            file (named sets), or None for a generator.
        psi: the strain-energy density; params: ``Lame(mu, lam)``, or the parameter type
            of a rubber/tissue model (e.g. ``MooneyRivlin``; HGO fibres per cell).
        potential: base :class:`~jaxelastic.mechanics.potential.Potential` (``mass`` only in
            dynamics, ``f_ext`` only with loads or gravity).
        bc: Dirichlet data with the full prescribed displacement (statics) or at t = 0.
        bc_fn: ``s ↦ Dirichlet``: in statics ``s`` is the load factor in [0, 1], in
            dynamics the time [s].
        time_dependent: whether ``bc_fn`` changes with time (dynamics).
        solver: :class:`~jaxelastic.Newton` from ``[solver]``, its linear solver bound to
            the mesh and the Dirichlet pattern.
        integrator: :class:`~jaxelastic.dynamics.Integrator`, or None (statics).
        x0: ``(n_nodes, dim)`` initial positions (the rest shape); v0: initial velocities
            ``(n_nodes, dim)`` (zero on Dirichlet dofs), or None (statics).
        probes: ``(node, point)`` per ``[output].probes`` entry (nearest node).
        tip: node whose displacement is plotted over time (first probe, or the node
            farthest from the Dirichlet nodes).
        supports: ``(key, mask)`` per ``[[dirichlet]]`` entry, the mask ``(n_nodes, dim)``
            bool of the dofs it prescribes (the reaction of each support is reported).
    """

    scene: Scene
    mesh: Mesh
    mesh_data: MeshData | None
    psi: Callable
    params: Any
    potential: Potential
    bc: Dirichlet
    bc_fn: Callable[[float], Dirichlet]
    time_dependent: bool
    solver: PreparedSolver
    integrator: dynamics.Integrator | None
    x0: jax.Array
    v0: jax.Array | None
    probes: list
    tip: int
    shard: Sharded | None = None
    cavities: Cavities | None = None  # [[cavity]]: volumes per load step (jaxelastic.scene.cavity)
    supports: tuple = ()


class Sharded(NamedTuple):
    """The solve-side arrays of a scene with ``[solver] devices = N > 1``
    (:func:`jaxelastic.shard`): the same problem renumbered into the global padded layout
    and placed on N devices. :class:`Built`'s other fields stay in the natural numbering
    (outputs, probes, VTU); a run solves with these and maps the solution back with
    ``partition.to_natural``.

    Attributes:
        potential: the sharded :class:`~jaxelastic.mechanics.potential.Potential` (padded nodes and
            cells); bc: its Dirichlet data at the full load (statics) or t = 0;
        bc_fn: ``s ↦`` sharded Dirichlet data (as :attr:`Built.bc_fn`);
        solver: the Newton solver bound to the sharded mesh;
        x0: ``(S·n_own, dim)`` padded rest positions; v0: padded initial velocities or None;
        partition: the :class:`~jaxelastic.parallel.partition.Partition`;
        devices: the devices used (``str`` of each);
        rest: ``(S·n_own, dim)`` NumPy padded rest positions (where padded nodes are fixed).
    """

    potential: Potential
    bc: Dirichlet
    bc_fn: Callable[[float], Dirichlet]
    solver: PreparedSolver
    x0: jax.Array
    v0: jax.Array | None
    partition: Any
    devices: tuple
    rest: np.ndarray


# ----------------------------------------------------------------------------------------
# mesh
# ----------------------------------------------------------------------------------------


def _read_file_mesh(scene: Scene) -> tuple[Mesh, MeshData]:
    """Read ``[mesh].file``, check the memory estimate of its lifted size, lift it."""
    m = scene.spec.mesh
    assert m.file is not None  # called for a mesh file
    try:
        md = read_mesh(m.file)
    except MeshError as e:
        empty = empty_mesh_counts(m.file)
        if empty is not None:
            raise scene.error(
                f"[mesh].file: the mesh {m.file!r} is empty ({empty[0]} points, {empty[1]} "
                "cells): export the volume mesh (triangles or tetrahedra) into it"
            ) from None
        raise scene.error(f"[mesh].file: {e}") from None
    el = md.mesh.element_type
    size = memory.file_mesh_size(
        md.mesh.n_nodes, md.mesh.n_cells, el.dim, el.n_nodes, m.order, m.formulation
    )
    memory.check(scene, size)
    try:
        return lift_file_mesh(md, m.order, m.formulation)
    except (MeshError, ValueError) as e:
        raise scene.error(f"[mesh].file: {e}") from None


def empty_mesh_counts(path: str) -> tuple[int, int] | None:
    """``(points, cells)`` of a VTU file whose pieces hold no cell (meshio cannot parse an
    empty VTU: "need at least one array to concatenate"), else None.

    Reads only the ``<Piece NumberOfPoints=... NumberOfCells=...>`` attributes.
    """
    if not path.lower().endswith((".vtu", ".pvtu")):
        return None
    import xml.etree.ElementTree as ET

    points = cells = 0
    try:
        for _, el in ET.iterparse(path, events=("start",)):
            if el.tag == "Piece":
                points += int(el.get("NumberOfPoints", "0"))
                cells += int(el.get("NumberOfCells", "0"))
            el.clear()
    except (ET.ParseError, OSError, ValueError):
        return None
    return (points, cells) if cells == 0 else None


def scene_dtype(scene: Scene) -> np.dtype:
    """The float dtype of a scene's arrays, from ``[solver] precision``: float32 or float64
    (float32 when x64 is disabled, whatever is asked: JAX has no float64 then)."""
    want = np.float32 if scene.spec.solver.precision == "float32" else np.float64
    return np.dtype(jax.dtypes.canonicalize_dtype(want))


def _with_dtype(mesh: Mesh, dtype) -> Mesh:
    """``mesh`` with its float arrays (points, shape-function gradients, weights) in
    ``dtype`` (computed in the generator's precision, then rounded once)."""
    if mesh.points.dtype == dtype:
        return mesh
    return dataclasses.replace(
        mesh,
        points=mesh.points.astype(dtype),
        dN=mesh.dN.astype(dtype),
        weights=mesh.weights.astype(dtype),
    )


def _cast(tree, dtype):
    """Every float array leaf of ``tree`` in ``dtype`` (other leaves unchanged)."""

    def leaf(a):
        if hasattr(a, "dtype") and jnp.issubdtype(a.dtype, jnp.floating):
            return jnp.asarray(a, dtype)
        return a

    return jax.tree_util.tree_map(leaf, tree)


def _make_mesh(scene: Scene) -> tuple[Mesh, MeshData | None]:
    m = scene.spec.mesh
    if m.file is not None:
        return _read_file_mesh(scene)
    kw: dict[str, Any] = dict(order=m.order or 1, formulation=m.formulation)
    n = m.n
    try:
        if m.generator == "cook":
            assert isinstance(n, int)  # MeshSpec: one integer for "cook"
            return cook_membrane(n, **kw), None
        fn = box if m.generator == "box" else rectangle
        # MeshSpec: n per axis, size and origin filled in for "box" / "rectangle"
        assert isinstance(n, tuple) and m.size is not None and m.origin is not None
        return fn(*n, size=tuple(m.size), origin=tuple(m.origin), **kw), None
    except (MeshError, ValueError) as e:
        raise scene.error(f"[mesh]: {e}") from None


def lift_file_mesh(md: MeshData, order: int | None, form: str) -> tuple[Mesh, MeshData]:
    """Apply ``[mesh] order/formulation`` to a mesh read from a file.

    A P1 file becomes P2 (``order = 2``) or composite (``order`` 1/unset with F-bar/B-bar)
    by :func:`~jaxelastic.mesh.to_quadratic`, which keeps the P1 node numbers: point sets
    gain the mid-edge nodes of edges with both ends in the set, facet sets become the
    quadratic facets with the same corners.

    Args:
        md: the mesh file's data; order: 1, 2 or None (keep the file's); form: formulation.
    Raises:
        MeshError: ``order = 1`` for a P2 file, or a tagged facet set with interior facets.
    """
    mesh = md.mesh
    el = mesh.element_type
    p1 = el.n_nodes == el.dim + 1
    if order == 1 and not p1:
        raise MeshError(f"order = 1 but the file holds {el.name} cells (P2 files stay P2)")
    if p1 and (order == 2 or form != "standard"):
        q = to_quadratic(mesh, composite=order != 2, formulation=form)
        return q, _lift_sets(md, q)
    if form != mesh.formulation:
        mesh = with_formulation(mesh, form)
        md = dataclasses.replace(md, mesh=mesh)
    return mesh, md


def _lift_sets(md: MeshData, q: Mesh) -> MeshData:
    """The named sets of a P1 file's ``md`` on its lifted mesh ``q`` (same P1 numbers)."""
    el = md.mesh.element_type
    cells = np.asarray(q.cells)
    ends = cells[:, : el.dim + 1][:, edge_table(el)].reshape(-1, 2)  # (c·e, 2)
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

    return dataclasses.replace(
        md,
        mesh=q,
        point_sets={k: lift_points(s) for k, s in md.point_sets.items()},
        facet_sets={k: lift_facets(s) for k, s in md.facet_sets.items()},
        node_map=np.concatenate([md.node_map, np.full(q.n_nodes - md.mesh.n_nodes, -1)]),
    )


# ----------------------------------------------------------------------------------------
# material
# ----------------------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnums=0)
def _psi_and_P(psi, F, params):
    return jnp.asarray(psi(F, params)), jax.grad(psi)(F, params)


def _user_callable(scene: Scene, key: str, spec: str) -> Callable:
    try:
        return import_callable(spec, scene.base_dir)
    except CallableSpecError as e:
        raise scene.error(f"{key}: {e}") from None


def _family_params(scene: Scene, mesh: Mesh, md: MeshData | None):
    """The parameter pytree of a rubber/tissue model from its ``[material]`` keys (HGO
    fibre directions per cell, ``(n_cells, ·)``: see :func:`_fibre_field`)."""
    m = scene.spec.material
    dtype = jnp.zeros(()).dtype
    fields = FAMILY_TYPES[m.model]._fields
    raw: dict = {}  # the mesh file's cell data, read once if a fibre key asks for it
    vals = {
        k: _as_param(
            _fibre_field(scene, k, getattr(m, k), mesh, md, raw)
            if k in _FIBRE_KEYS
            else getattr(m, k),
            dtype,
        )
        for k in fields
    }
    params = FAMILY_TYPES[m.model](**vals)
    if isinstance(params, Guccione):  # a per-cell basis (cell data, regions) checked here
        try:
            check_guccione(params)
        except ValueError as e:
            raise scene.error(f"[material]: {e}") from None
    return params


_FIBRE_KEYS = DIRECTION_KEYS


def _as_param(v, dtype):
    """A parameter leaf in ``dtype`` (a per-quadrature-point field keeps its wrapper)."""
    if is_at_quadrature(v):
        return AtQuadrature(jnp.asarray(v.values, dtype))
    return jnp.asarray(v, dtype)


def _fibre_field(scene: Scene, key: str, spec, mesh: Mesh, md: MeshData | None, raw: dict):
    """``[material].<key>`` (an HGO fibre direction) as a per-cell ``(n_cells, ·)`` array,
    or (a rule with ``at = "quadrature"``) an ``AtQuadrature`` of ``(n_cells, n_q, 3)``.

    A vector is broadcast as given (ψ normalises it); ``{ cell_data = ... }`` and where
    regions give normalised ``(n_cells, 3)`` rows (2D directions padded with z = 0).

    Args:
        spec: a vector (tuple of floats), a :class:`~jaxelastic.scene.schema.FibreCellData`,
            a :class:`~jaxelastic.scene.schema.FibreRule` or a tuple of
            :class:`~jaxelastic.scene.schema.FibreRegion`.
        raw: cache of the mesh file's volume cell data (filled on first use).
    """
    if isinstance(spec, FibreCellData):
        a = _cell_data_fibres(scene, f"[material].{key}.cell_data", spec.cell_data, mesh, md, raw)
    elif isinstance(spec, FibreRule):
        rule = _rule_fibres(scene, key, spec, mesh)
        if isinstance(rule, AtQuadrature):
            return rule  # unit rows already
        a = rule
    elif spec and isinstance(spec[0], FibreRegion):
        a = _region_fibres(scene, key, spec, mesh)
    else:
        return np.broadcast_to(np.asarray(spec, float), (mesh.n_cells, len(spec)))
    if a.shape[1] == 2:
        a = np.concatenate([a, np.zeros((a.shape[0], 1))], axis=1)
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def _rule_fibres(scene: Scene, key: str, rule: FibreRule, mesh: Mesh):
    """Directions of the helix rule at the cell centroids (the corners' mean),
    ``(n_cells, 3)``, or at the quadrature points (``rule.at``), an ``AtQuadrature`` of
    ``(n_cells, n_q, 3)``: the fibre (``"helix"``) or the sheet normal (``"transmural"``)."""
    if mesh.dim != 3:
        raise scene.error(
            f"[material].{key}: rule = {rule.rule!r} needs a 3D mesh (an ellipsoidal "
            f"ventricle), the mesh is {mesh.dim}D"
        )
    f0, s0 = helix_basis(
        mesh,
        at=rule.at,
        endo=rule.endo_radii,
        epi=rule.epi_radii,
        alpha_endo=rule.endo,
        alpha_epi=rule.epi,
    )
    a = f0 if rule.rule == "helix" else s0
    return a if isinstance(a, AtQuadrature) else np.asarray(a)


def _region_fibres(scene: Scene, key: str, regions, mesh: Mesh) -> np.ndarray:
    """Per-cell directions ``(n_cells, 2|3)`` from where regions of the cell centroids."""
    cells = np.asarray(mesh.cells)[:, : mesh.dim + 1]  # the corners (P2/composite too)
    centroids = np.asarray(mesh.points)[cells].mean(axis=1)
    width = max(len(r.direction) for r in regions)
    out = np.zeros((mesh.n_cells, width))
    done = np.zeros(mesh.n_cells, dtype=bool)
    for i, r in enumerate(regions):
        if r.where is None:
            mask = np.ones(mesh.n_cells, dtype=bool)
        else:
            try:
                mask = where_mask(r.where, centroids)
            except WhereError as e:
                raise scene.error(f"[material].{key}[{i}].where: {e} in {r.where!r}") from None
            if not mask.any():
                raise scene.error(
                    f"[material].{key}[{i}].where: {r.where!r} matches no cell centroid"
                )
        d = np.zeros(width)
        d[: len(r.direction)] = r.direction
        out[mask & ~done] = d
        done |= mask
    return out


def _cell_data_fibres(scene, where: str, name: str, mesh: Mesh, md, raw: dict) -> np.ndarray:
    """The ``(n_cells, 3)`` (2D: or ``(n_cells, 2)``) cell-data array ``name`` of the mesh
    file, checked finite with nonzero rows (``where``: the key, for the messages)."""
    if md is None:
        raise scene.error(
            f"{where}: a generated mesh has no cell data (use [mesh].file, one vector, or "
            "where regions)"
        )
    if not raw:
        raw.update(_file_cell_data(scene, where, md.source))
    if name not in raw:
        names = ", ".join(sorted(raw)) or "none"
        raise scene.error(
            f"{where}: the mesh file {md.source!r} has no cell data {name!r} (its cell data "
            f"on the volume cells: {names})"
        )
    a, n = raw[name], mesh.n_cells
    shapes = ((n, 3), (n, 2)) if mesh.dim == 2 else ((n, 3),)
    if a.shape not in shapes:
        raise scene.error(
            f"{where}: cell data {name!r} of {md.source!r} has shape {a.shape}, expected "
            f"(n_cells, 3) = ({n}, 3)"
        )
    a = np.asarray(a, dtype=float)
    bad = np.flatnonzero(~np.isfinite(a).all(axis=1) | ~(np.abs(a) > 0).any(axis=1))
    if bad.size:
        raise scene.error(
            f"{where}: cell data {name!r} of {md.source!r} has zero or non-finite rows "
            f"(cells {', '.join(map(str, bad[:5]))}{', ...' if bad.size > 5 else ''}): every "
            "cell needs a nonzero fibre direction"
        )
    return a


def _file_cell_data(scene: Scene, where: str, path: str) -> dict:
    """Cell-data arrays of the volume cells of mesh file ``path``, in the cell order of
    :func:`~jaxelastic.io.read_mesh` (its volume blocks concatenated in file order).

    :class:`~jaxelastic.io.MeshData` keeps no cell data, so the file is read again with
    meshio. Returns ``{name: (n_cells, ...) array}``, possibly empty (arrays whose shapes
    differ across the volume blocks are left out).
    """
    import meshio

    try:
        m = meshio.read(path)
    except (Exception, SystemExit) as e:  # noqa: BLE001 — meshio may sys.exit on errors
        raise scene.error(f"{where}: cannot read the cell data of {path!r} ({e})") from None
    dims = [b.dim if len(b.data) else -1 for b in m.cells]
    vol = [i for i, d in enumerate(dims) if d == max(dims)]
    out = {}
    for name, per_block in m.cell_data.items():
        if len(per_block) != len(m.cells):
            continue
        try:
            out[name] = np.concatenate([np.asarray(per_block[i]) for i in vol])
        except ValueError:
            continue
    return out


def _material(scene: Scene, mesh: Mesh, md: MeshData | None = None) -> tuple[Callable, Any]:
    """ψ and its parameters from ``[material]``, checked at F = I (finite ψ and P).

    Args:
        scene: the scene; mesh: the rest mesh; md: its file's data (HGO fibre directions
            from cell data), or None for a generator.
    """
    m = scene.spec.material
    model = m.model
    dim = mesh.dim
    if model in FAMILIES:
        psi = FAMILIES[model]
        params = _family_params(scene, mesh, md)
        if m.active_tension is not None:  # [material].active_tension: along f0
            psi = with_active_tension(psi)
            Ta = jnp.asarray(m.active_tension, jnp.zeros(()).dtype)
            params = ActiveTension(params, Ta, params.f0)
        first = jax.tree_util.tree_map(lambda v: v[0] if v.ndim else v, first_point_params(params))
        _check_at_identity(scene, psi, first, dim)  # one cell's parameters
        return psi, params
    psi = BUILTIN[model] if ":" not in model else _user_callable(scene, "[material].model", model)
    if m.E is not None:
        try:
            mu, lam = lame(m.E, m.nu, dim=dim, plane=m.plane or "strain")
        except ValueError as e:
            raise scene.error(f"[material]: {e}") from None
    else:
        mu, lam = m.mu, m.lam
    dtype = jnp.zeros(()).dtype
    params = Lame(jnp.asarray(mu, dtype), jnp.asarray(lam, dtype))
    _check_at_identity(scene, psi, params, dim)
    return psi, params


def _check_at_identity(scene: Scene, psi, params, dim: int) -> None:
    """Raise the scene's error unless ψ and P are finite at F = I."""
    model = scene.spec.material.model
    dtype = jnp.zeros(()).dtype  # the parameters' dtype (cast to [solver] precision later)
    try:
        F = jnp.asarray(np.eye(dim), dtype)
        val, P = _psi_and_P(psi, F, params)  # one small compile, not op-by-op dispatch
    except Exception as e:  # noqa: BLE001 — user code: report any failure with the key
        raise scene.error(
            f"[material].model {model!r} fails at F = I in {dim}D ({type(e).__name__}: {e})"
        ) from None
    if val.shape != () or not bool(jnp.isfinite(val)) or not bool(jnp.all(jnp.isfinite(P))):
        raise scene.error(
            f"[material].model {model!r} must return a finite scalar at F = I, got "
            f"shape {val.shape}, value {val}"
        )


# ----------------------------------------------------------------------------------------
# selections
# ----------------------------------------------------------------------------------------


def _group_nodes(scene: Scene, key: str, name: str, mesh: Mesh, md: MeshData | None):
    if md is None:
        raise scene.error(
            f"{key}.group: a generated mesh has no named groups (use plane/box/where)"
        )
    if name in md.point_sets:
        return md.point_sets[name]
    if name in md.facet_sets:
        return np.unique(md.facet_sets[name])
    if name in md.cell_sets:
        return np.unique(np.asarray(mesh.cells)[md.cell_sets[name]])
    names = sorted({*md.point_sets, *md.facet_sets, *md.cell_sets})
    raise scene.error(
        f"{key}.group: the mesh has no group {name!r} (groups: {', '.join(names) or 'none'})"
    )


def select_nodes(
    scene: Scene, key: str, sel: Selector, mesh: Mesh, md: MeshData | None
) -> np.ndarray:
    """Node indices ``(m,)`` of a selector (``key`` names it in messages).

    Raises:
        SceneError: the selection matches no node, or a group/where problem.
    """
    if sel.plane is not None:
        p = sel.plane
        idx = loads.nodes_on_plane(mesh, axis_index(p.axis), p.value, p.tol)
    elif sel.box is not None:
        idx = loads.nodes_in_box(mesh, list(sel.box.lo), list(sel.box.hi))
    elif sel.where is not None:
        try:
            idx = np.flatnonzero(where_mask(sel.where, np.asarray(mesh.points)))
        except (WhereError, ValueError, IndexError, TypeError) as e:
            raise scene.error(f"{key}.where: cannot evaluate {sel.where!r}: {e}") from None
    else:
        assert sel.group is not None  # a Selector has exactly one of plane, box, where, group
        idx = _group_nodes(scene, key, sel.group, mesh, md)
    idx = np.asarray(idx, dtype=np.int64)
    if idx.size == 0:
        raise scene.error(f"{key} selects no nodes")
    return idx


def select_facets(
    scene: Scene, key: str, sel: Selector, mesh: Mesh, md: MeshData | None
) -> np.ndarray:
    """Boundary facets ``(m, nodes per facet)`` of a selector: a facet group, or the
    facets whose nodes all match."""
    if sel.group is not None:
        if md is None:
            raise scene.error(
                f"{key}.group: a generated mesh has no named groups (use plane/box/where)"
            )
        if sel.group not in md.facet_sets:
            raise scene.error(
                f"{key}.group: the mesh has no facet group {sel.group!r} (facet groups: "
                f"{', '.join(sorted(md.facet_sets)) or 'none'})"
            )
        facets = md.facet_sets[sel.group]
    else:
        mask = np.zeros(mesh.n_nodes, dtype=bool)
        mask[select_nodes(scene, key, sel, mesh, md)] = True
        facets = loads.facets_where(mesh, lambda X: mask)
    if len(facets) == 0:
        raise scene.error(f"{key} selects no boundary facets (all nodes of a facet must match)")
    return np.asarray(facets)


# ----------------------------------------------------------------------------------------
# Dirichlet data and loads
# ----------------------------------------------------------------------------------------


def _rotation(axis: int, angle_deg: float, dim: int) -> np.ndarray:
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    if dim == 2:
        return np.array([[c, -s], [s, c]])
    i, j = [a for a in range(3) if a != axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def _displacement_fn(scene: Scene, key: str, spec, dim: int):
    """``(u(Xs, t) -> (m, dim), time_dependent)`` for one Dirichlet entry."""
    if spec is None:
        return (lambda Xs, t: np.zeros_like(Xs)), False
    if isinstance(spec, str):
        fn = _user_callable(scene, key, spec)
        if n_positional(fn) >= 2:
            return (lambda Xs, t: fn(Xs, t)), True
        return (lambda Xs, t: fn(Xs)), False
    if isinstance(spec, RotateDisplacement):
        r = spec.rotate
        R = _rotation(axis_index(r.axis), r.angle_deg, dim)
        c = np.asarray(r.center if r.center is not None else [0.0] * dim, dtype=float)
        return (lambda Xs, t: r.scale * ((Xs - c) @ R.T + c - Xs)), False
    u = np.asarray(spec, dtype=float)
    return (lambda Xs, t: np.broadcast_to(u, Xs.shape)), False


def _dirichlet(scene: Scene, mesh: Mesh, md) -> tuple[Callable[[float], Dirichlet], bool]:
    """``(s ↦ Dirichlet, time_dependent)``: ``s`` is the load factor (statics) or time."""
    X = np.asarray(mesh.points)
    entries = []
    time_dep = False
    for i, d in enumerate(scene.spec.dirichlet):
        key = f"[dirichlet][{i}]"
        idx = select_nodes(scene, f"{key}.nodes", d.nodes, mesh, md)
        comps = None if d.components is None else [axis_index(a) for a in d.components]
        u, dep = _displacement_fn(scene, f"{key}.displacement", d.displacement, mesh.dim)
        time_dep |= dep or d.ramp_time is not None
        entries.append((key, idx, comps, u, d.ramp_time))
    static = scene.static

    def bc_fn(s: float) -> Dirichlet:
        if not entries:
            return loads.no_dirichlet(mesh)
        parts = []
        for key, idx, comps, u, ramp in entries:
            factor = s if static else (1.0 if ramp is None else min(s / ramp, 1.0))
            try:
                disp = factor * np.asarray(u(X[idx], None if static else s), dtype=float)
                parts.append(loads.fix(mesh, idx, comps, disp))
            except Exception as e:  # noqa: BLE001 — user functions: name the key
                raise scene.error(f"{key}.displacement: {type(e).__name__}: {e}") from None
        return loads.combine(*parts)

    return bc_fn, time_dep


def _external_forces(scene: Scene, mesh: Mesh, md) -> np.ndarray | None:
    """``(n_nodes, dim)`` tractions + point loads + gravity, or None without loads."""
    spec = scene.spec
    parts = []
    for i, t in enumerate(spec.traction):
        facets = select_facets(scene, f"[traction][{i}].facets", t.facets, mesh, md)
        if t.traction is not None:
            parts.append(loads.traction_load(mesh, facets, list(t.traction)))
        else:
            _, area = loads.facet_normals(mesh.points, facets)
            parts.append(loads.traction_load(mesh, facets, np.asarray(t.total_force) / area.sum()))
    for i, p in enumerate(spec.point_load):
        idx = select_nodes(scene, f"[point_load][{i}].nodes", p.nodes, mesh, md)
        force = p.force if p.force is not None else np.asarray(p.total_force) / idx.size
        parts.append(loads.point_load(mesh, idx, np.asarray(force)))
    if spec.gravity is not None:
        parts.append(loads.gravity_load(mesh, spec.material.density, list(spec.gravity.g)))
    return sum(parts[1:], parts[0]) if parts else None


# ----------------------------------------------------------------------------------------
# solver, initial state, probes
# ----------------------------------------------------------------------------------------


def newton_of(s: SolverSpec) -> Newton:
    """The :class:`~jaxelastic.Newton` of a ``[solver]`` table (linear solver unbound)."""
    linear: Any = s.linear
    if linear == "cg":
        linear = CG(preconditioner=s.preconditioner, max_iter=s.cg_max_iter)
    return Newton(
        rtol=s.rtol,
        atol=s.atol,
        max_steps=s.max_steps,
        xtol=s.xtol,
        hessian=s.hessian,
        linear=linear,
        ls_max=s.ls_max,
        armijo=s.armijo,
        require_positive_J=s.require_positive_J,
    )


def linear_solver_name(linear, state=None) -> str:
    """What a linear solver is, for the summary: its kind and, where its state
    (:class:`~jaxelastic.solvers.LinearState`) has one, the back end it resolved to
    (``"direct (cholespy)"``, ``"amg (pyamg)"``, ``"cg (block_jacobi)"``); read from the
    objects' attributes, so a new back end is named without a change here."""
    if isinstance(linear, str):
        return linear
    kind = str(getattr(linear, "kind", type(linear).__name__.lower()))
    if isinstance(linear, CG):
        return f"cg ({linear.preconditioner})"
    host = None if state is None else state.host  # HostLinearSolver of Direct / AMG
    inner = getattr(host, "backend", None)  # its DirectSolver / AMGSolver / ...
    for attr in ("name", "backend", "library"):
        v = getattr(inner, attr, None)
        if isinstance(v, str) and v:
            return f"{kind} ({v})"
    if inner is not None:
        if kind == "amg" or "amg" in type(inner).__name__.lower():
            return f"{kind} (pyamg)"
        return f"{kind} ({type(inner).__name__})"
    return kind


def _initial_velocity(scene: Scene, X: np.ndarray, bc: Dirichlet, dtype) -> jax.Array:
    integ = scene.spec.integrator
    assert isinstance(integ, DynamicIntegrator)  # called for dynamic scenes only
    iv = integ.initial_velocity
    key = "[integrator].initial_velocity"
    if iv is None:
        v0 = np.zeros_like(X)
    elif isinstance(iv, str):
        fn = _user_callable(scene, key, iv)
        try:
            v0 = np.asarray(fn(X), dtype=float)
        except Exception as e:  # noqa: BLE001 — user code: report any failure with the key
            raise scene.error(f"{key}: {type(e).__name__}: {e}") from None
        if v0.shape != X.shape or not np.isfinite(v0).all():
            raise scene.error(
                f"{key}: must return finite values of shape {X.shape}, got {v0.shape}"
            )
    else:
        v0 = np.broadcast_to(np.asarray(iv, dtype=float), X.shape).copy()
    v0 = np.where(np.asarray(bc.mask), 0.0, v0)
    _check_speed(scene, key, X, v0)
    return jnp.asarray(v0, dtype)


SPEED_MAX_BODIES = 1e6
"""An initial velocity that would carry a node this many body sizes in the scene's
duration is refused (it overflows the energies long before; wrong units are the usual
cause)."""


def _check_speed(scene: Scene, key: str, X: np.ndarray, v0: np.ndarray) -> None:
    """Refuse an initial velocity whose kinetic energy overflows or that would move a node
    by more than :data:`SPEED_MAX_BODIES` body sizes within the duration, naming the key."""
    size = float(np.linalg.norm(np.ptp(X, axis=0))) or 1.0
    duration = float(getattr(scene.spec.integrator, "duration", 0.0) or 0.0)
    speed = float(np.max(np.hypot.reduce(v0, axis=1), initial=0.0))  # (no overflow)
    if not np.isfinite(speed) or speed * duration > SPEED_MAX_BODIES * size:
        raise scene.error(
            f"{key}: a speed of {speed:.3g} m/s would carry the body {speed * duration:.3g} m "
            f"in the {duration:g} s of the run, more than {SPEED_MAX_BODIES:.0e} times its "
            f"size ({size:.3g} m; its kinetic energy overflows float64 before): check the "
            "units (m/s)"
        )


def _tip_node(mesh: Mesh, bc: Dirichlet) -> int:
    # cKDTree comes from the compiled scipy.spatial._ckdtree, which has no stubs
    from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]

    X = np.asarray(mesh.points)
    fixed = np.flatnonzero(np.asarray(bc.mask).any(axis=1))
    if fixed.size == 0:
        return int(np.argmax(np.linalg.norm(X - X.mean(axis=0), axis=1)))
    dist, _ = cKDTree(X[fixed]).query(X)
    return int(np.argmax(dist))


PROBE_MAX_DISTANCE = 0.5
"""A probe point farther than this fraction of the rest body's diagonal from every node
is refused (it would be reported at the nearest node: almost always a typo or a unit
slip)."""


def _probes(scene: Scene, X: np.ndarray) -> list:
    out = []
    diag = float(np.linalg.norm(np.ptp(X, axis=0))) if X.size else 0.0
    for i, p in enumerate(scene.spec.output.probes):
        dist = np.linalg.norm(X - np.asarray(p), axis=1)
        node = int(np.argmin(dist))
        if dist[node] > PROBE_MAX_DISTANCE * diag:
            raise scene.error(
                f"[output].probes[{i}] = {list(p)} lies {dist[node]:.3g} from the nearest node "
                f"(the body's diagonal is {diag:.3g}): give points on or inside the body, in "
                "the mesh's units"
            )
        out.append((node, list(p)))
    return out


# ----------------------------------------------------------------------------------------
# [solver] devices: sharding
# ----------------------------------------------------------------------------------------

HOST_DEVICES_FLAG = "--xla_force_host_platform_device_count"
"""The XLA flag that splits the host CPU into N devices (set in ``XLA_FLAGS`` before JAX
starts)."""


def check_devices(n: int) -> list:
    """The first ``n`` devices JAX sees (``jax.devices()``, every process's in a
    multi-process run).

    Raises:
        ValueError: fewer than ``n`` devices, with how to get more (the XLA flag for host
            CPU devices, or one process per GPU under ``jax.distributed``).
    """
    devs = jax.devices()
    if len(devs) < n:
        kind = devs[0].platform
        raise ValueError(
            f"{n} devices asked for, but JAX sees {len(devs)} ({kind}): for host CPU devices "
            f"start with XLA_FLAGS={HOST_DEVICES_FLAG}={n} in the environment (before JAX "
            "starts); for several GPUs or hosts, launch one process per device and call "
            "jaxelastic.parallel.distributed.initialize_from_env() (see the guide 'Many "
            "devices and hosts')"
        )
    return list(devs[:n])


def padded_dirichlet(sh: Sharded, bc: Dirichlet) -> Dirichlet:
    """Natural Dirichlet data ``bc`` in the padded layout of a sharded scene, placed like
    its ``sh.bc``: padded nodes fixed at their rest position."""
    return _padded_dirichlet(sh.partition, bc, sh.rest, sh.bc)


def _padded_dirichlet(part, bc: Dirichlet, X_pad: np.ndarray, like: Dirichlet) -> Dirichlet:
    """Natural Dirichlet data in the padded layout of ``part``, placed like ``like``:
    padded nodes fixed at their rest position ``X_pad`` (their place in the layout)."""
    real = np.asarray(part.node_real)[:, None]
    mask = np.asarray(part.to_padded(np.asarray(bc.mask)))
    values = np.asarray(part.to_padded(np.asarray(bc.values)))
    mask = np.where(real, mask, True)
    values = np.where(real, values, X_pad).astype(values.dtype)
    return Dirichlet(
        mask=jax.device_put(mask, like.mask.sharding),
        values=jax.device_put(values, like.values.sharding),
    )


def _shard(scene: Scene, pot: Potential, bc_fn, bc: Dirichlet, v0) -> Sharded:
    """The :class:`Sharded` parts of a scene with ``[solver] devices > 1``."""
    from ..parallel.sharding import shard

    n = scene.spec.solver.devices
    key = "[solver].devices"  # (host linear solvers and [fit] are refused by the schema)
    try:
        devices = check_devices(n)
    except ValueError as e:
        raise scene.error(f"{key}: {e}") from None
    try:
        pot_s, bc_s, part = shard(pot, bc, devices=devices)
    except (ValueError, TypeError, NotImplementedError) as e:
        raise scene.error(f"{key} = {n}: cannot shard this scene: {e}") from None
    X_pad = np.asarray(part.to_padded(np.asarray(pot.mesh.points)))
    x0 = pot_s.mesh.points

    def sharded_bc(s: float) -> Dirichlet:
        return _padded_dirichlet(part, bc_fn(s), X_pad, bc_s)

    v0_s = None
    if v0 is not None:
        pad = np.asarray(part.to_padded(np.asarray(v0)))
        pad[~np.asarray(part.node_real)] = 0.0
        v0_s = jax.device_put(pad, x0.sharding)
    return Sharded(
        potential=pot_s,
        bc=bc_s,
        bc_fn=sharded_bc,
        solver=prepare_solver(newton_of(scene.spec.solver), pot_s.mesh, bc_s),
        x0=x0,
        v0=v0_s,
        partition=part,
        devices=tuple(str(d) for d in devices),
        rest=X_pad,
    )


# ----------------------------------------------------------------------------------------
# build
# ----------------------------------------------------------------------------------------


def build(scene) -> Built:
    """Turn a scene (a :class:`~jaxelastic.scene.load.Scene`, a path, a shipped name or a
    dict) into arrays.

    The :class:`~jaxelastic.mechanics.potential.Potential` holds only what the scene needs: no mass
    in statics, no ``f_ext`` without loads or gravity, no pressure without ``[[pressure]]``.

    Long because: each table of the scene is one step here, in the order its arrays need.

    Raises:
        SceneError: a mesh too large for the memory (:func:`~jaxelastic.scene.memory.check`,
            before the mesh is generated), an empty mesh file, problems only visible with
            the mesh (a selection that matches no node, an unknown group, wrong vector
            lengths for a mesh file's dimension, a user function returning the wrong shape,
            a material failing at F = I).
    """
    scene = load_scene(scene)
    memory.check(scene)  # a generator's size is known before anything is allocated
    mesh, md = _make_mesh(scene)
    if scene.dim is None:
        problem = scene.spec.dim_problem(mesh.dim)
        if problem is not None:
            raise scene.error(problem)
    # everything is built in the generator's precision (selections, probes and loads on
    # the float64 rest shape: the same nodes in either precision), then rounded once to
    # [solver] precision
    psi, params = _material(scene, mesh, md)
    bc_fn64, time_dep = _dirichlet(scene, mesh, md)
    f_ext = _external_forces(scene, mesh, md)
    dtype = scene_dtype(scene)
    X = np.asarray(mesh.points)
    probes = _probes(scene, X)
    tip = probes[0][0] if probes else _tip_node(mesh, bc_fn64(1.0 if scene.static else 0.0))
    mesh = _with_dtype(mesh, dtype)
    if md is not None:
        md = dataclasses.replace(md, mesh=_with_dtype(md.mesh, dtype))
    params = _cast(params, dtype)

    def bc_fn(s: float) -> Dirichlet:
        return _cast(bc_fn64(s), dtype)

    pot = Potential(
        mesh=mesh,
        params=params,
        f_ext=None if f_ext is None else jnp.asarray(f_ext, dtype),
        psi=psi,
    )
    integrator, v0 = None, None
    bc = bc_fn(1.0 if scene.static else 0.0)
    if not scene.static:
        integ = scene.spec.integrator
        assert isinstance(integ, DynamicIntegrator)  # not scene.static
        mass = loads.lumped_mass(mesh, scene.spec.material.density)
        pot = pot.replace(mass=jnp.asarray(mass, dtype))
        integrator = dynamics.Integrator(
            h=integ.h, method=integ.method, alpha=integ.alpha, beta=integ.beta
        )
        v0 = _initial_velocity(scene, X, bc, dtype)
    pot = build_contact(scene, pot)  # [[obstacle]]: barrier contact (else unchanged)
    # [[pressure]] / [[cavity]]: the pressure term and the cavities (else unchanged, None)
    pot, cavities = build_pressure(scene, pot, bc, md, select_facets)
    if isinstance(params, ActiveTension) and cavities is not None and cavities.volumes is not None:
        raise scene.error(
            "[material].active_tension is ramped with the load factor of [integrator].load_steps;"
            " a [[cavity]] with a prescribed volume steps the volume instead: give the cavity a "
            "pressure ([[pressure]] cavity = ...) or leave active_tension out"
        )
    sharded = None
    if scene.spec.solver.devices > 1:  # [solver] devices: solve on the padded layout
        sharded = _shard(scene, pot, bc_fn, bc, v0)
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
        solver=prepare_solver(newton_of(scene.spec.solver), mesh, bc, quadratic=is_quadratic(pot))
        if sharded is None
        else sharded.solver,
        integrator=integrator,
        x0=mesh.points,
        v0=v0,
        probes=probes,
        tip=tip,
        shard=sharded,
        cavities=cavities,
        supports=_supports(scene, mesh, md),
    )


def _supports(scene: Scene, mesh: Mesh, md) -> tuple:
    """``(key, mask (n_nodes, dim))`` of each ``[[dirichlet]]`` entry's prescribed dofs."""
    out = []
    for i, d in enumerate(scene.spec.dirichlet):
        key = f"[dirichlet][{i}]"
        idx = select_nodes(scene, f"{key}.nodes", d.nodes, mesh, md)
        mask = np.zeros(mesh.points.shape, bool)
        comps = range(mesh.dim) if d.components is None else [axis_index(a) for a in d.components]
        mask[np.ix_(np.asarray(idx), np.asarray(list(comps), dtype=np.int64))] = True
        out.append((key, mask))
    return tuple(out)
