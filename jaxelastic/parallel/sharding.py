"""One mesh over many devices: :func:`shard` a potential and its Dirichlet data.

``pot_s, bc_s, part = je.shard(pot, bc, devices=4)`` partitions the mesh
(:mod:`jaxelastic.parallel.partition`: METIS or a space-filling curve), renumbers and pads
every node and cell array into the *global padded layout* (shard ``s`` owns nodes
``[s·n_own, (s+1)·n_own)`` and cells ``[s·c_loc, (s+1)·c_loc)``), places each with
``NamedSharding(device_mesh, P("shards"))`` along its first axis (scalars replicated), and
attaches a :class:`~jaxelastic.parallel.halo.Halo` to the mesh. The result is an ordinary
:class:`~jaxelastic.mechanics.potential.Potential` / :class:`~jaxelastic.loads.Dirichlet` pair:

* ``je.solve(pot_s, bc_s)`` works unchanged (``linear="cg"``, ``"multilevel"``; ``"auto"``
  picks a device solver; the host ``"direct"``/``"amg"`` refuse at once), and so do
  dynamics steps and gradients through the solve;
* the energy kernels (energy, forces, HVP, element Hessians, assembly) run per shard under
  ``shard_map`` and exchange only interface ("ghost") nodes with ``lax.ppermute``;
* ``part.to_natural(sol.x)`` gives the answer in the original numbering,
  ``part.to_padded(a)`` takes a natural node or cell field (e.g. ``x0``) into the padded one.

Padding: padded nodes copy a real node of their shard (same rest point, no cell), carry no
mass or load and are Dirichlet-fixed at their rest point; padded cells have zero weights
and shape-function gradients (F = I) and contribute nothing.

On one machine without several accelerators, JAX can split the CPU into host devices:
start Python with ``XLA_FLAGS=--xla_force_host_platform_device_count=4`` (set before
``jax`` is imported).
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from ..loads import Dirichlet
from ..mechanics.potential import Potential
from ..mesh import Mesh
from .halo import Halo, build_halo, node_slots
from .partition import METHODS, Partition, partition_mesh

__all__ = [
    "shard",
    "Partition",
    "device_mesh",
    "AXIS",
    "is_sharded",
    "collective_bytes",
]

AXIS = "shards"
"""Name of the device-mesh axis :func:`shard` creates (a given mesh keeps its own)."""

_NODE_FIELDS = ("f_ext", "mass", "x_tilde", "x_prev")
_ZERO_ON_PADDING = ("f_ext", "mass")


def device_mesh(devices) -> jax.sharding.Mesh:
    """A one-axis :class:`jax.sharding.Mesh` named :data:`AXIS`.

    Args:
        devices: a device count N (the first N of ``jax.devices()``), a sequence of
            devices, or a one-axis :class:`jax.sharding.Mesh` (returned as is).

    Raises:
        ValueError: N < 1, more devices than JAX sees (the message says how to get host
            CPU devices), or a mesh with more than one axis.
    """
    if isinstance(devices, jax.sharding.Mesh):
        if len(devices.axis_names) != 1:
            raise ValueError(
                f"shard: the device mesh must have one axis, got axes {devices.axis_names}; "
                "make one with jax.make_mesh((N,), ('shards',))"
            )
        return devices
    if isinstance(devices, (int, np.integer)):
        n, avail = int(devices), jax.devices()
        if n < 1:
            raise ValueError(f"shard: devices must be >= 1, got {n}")
        if n > len(avail):
            raise ValueError(
                f"shard: {n} devices requested but JAX sees {len(avail)} "
                f"({avail[0].platform}). On a CPU-only machine start Python with "
                f"XLA_FLAGS=--xla_force_host_platform_device_count={n} in the environment "
                "(set before jax is imported) to split the CPU into host devices; across "
                "machines, call jax.distributed.initialize() first"
            )
        devs = avail[:n]
    elif isinstance(devices, Sequence):
        devs = list(devices)
        if not devs:
            raise ValueError("shard: the device list is empty")
    else:
        raise TypeError(
            f"shard: devices must be a count, a list of devices or a jax.sharding.Mesh, got "
            f"{type(devices).__name__}"
        )
    return jax.sharding.Mesh(np.asarray(devs), (AXIS,))


def is_sharded(mesh) -> bool:
    """Whether ``mesh`` is sharded over several devices: it has a halo
    (:func:`shard`), or its points are placed on more than one device (the plain XLA
    layout, e.g. ``dataclasses.replace(pot_s.mesh, halo=None)``)."""
    if getattr(mesh, "halo", None) is not None:
        return True
    pts = getattr(mesh, "points", None)
    if pts is None or isinstance(pts, Tracer):
        return False
    sharding = getattr(pts, "sharding", None)
    return sharding is not None and len(sharding.device_set) > 1


def _host(a, name: str) -> np.ndarray:
    if isinstance(a, Tracer):
        raise ValueError(
            f"shard: {name} is traced (inside jit/vmap/grad); shard the concrete potential "
            "once, outside any transformation, then jit or differentiate the sharded one"
        )
    return np.asarray(a)


def _put(a: np.ndarray, dtype, sharding) -> jax.Array:
    return jax.device_put(np.asarray(a).astype(dtype), sharding)


def _check(pot: Potential, bc: Dirichlet) -> None:
    if not isinstance(pot, Potential):
        raise TypeError(f"shard: pot must be a je.Potential, got {type(pot).__name__}")
    if not isinstance(bc, Dirichlet):
        raise TypeError(f"shard: bc must be je.Dirichlet data, got {type(bc).__name__}")
    if getattr(pot.mesh, "halo", None) is not None:
        raise ValueError("shard: this potential is already sharded (its mesh has a halo)")
    if pot.contact is not None:
        raise ValueError(
            "shard: contact terms are not supported on a sharded potential yet (their "
            "contact-node lists use the natural numbering); solve contact scenes on one device"
        )
    if pot.pressure is not None:
        raise ValueError(
            "shard: pressure terms are not supported on a sharded potential yet (their facet "
            "lists use the natural numbering); solve pressure scenes on one device"
        )
    if pot.stiffness_damping is not None and pot.x_prev is None:
        raise ValueError("shard: stiffness damping needs x_prev")


def shard(
    pot: Potential, bc: Dirichlet, devices=None, *, method: str = "auto"
) -> tuple[Potential, Dirichlet, Partition]:
    """Partition ``pot``'s mesh over devices and place every array on its shard.

    Long because: every field of the potential, the mesh and the Dirichlet data is
    renumbered, padded and placed here, in one pass a reader can check against the layout.

    Args:
        pot: a concrete :class:`~jaxelastic.mechanics.potential.Potential` (no contact term).
        bc: its :class:`~jaxelastic.loads.Dirichlet` data.
        devices: a device count N (first N of ``jax.devices()``; default all), a list of
            devices, or a one-axis :class:`jax.sharding.Mesh`.
        method: cell partitioning, ``"auto"`` (METIS when pymetis is installed, else a
            Morton curve), ``"metis"`` or ``"sfc"``
            (:func:`~jaxelastic.parallel.partition.partition_cells`).

    Returns:
        ``(pot_s, bc_s, partition)``: the sharded potential and Dirichlet data in the global
        padded layout (``pot_s.mesh.halo`` set), and the
        :class:`~jaxelastic.parallel.partition.Partition` (``to_natural``/``to_padded``,
        ``stats()``).

    Raises:
        ValueError: more devices than JAX sees (naming ``XLA_FLAGS``), fewer cells than
            devices, an already sharded or traced potential, a contact term, an unknown
            method.
        TypeError: arguments of the wrong kind.
    """
    _check(pot, bc)
    if method not in METHODS:
        raise ValueError(f"shard: method must be one of {METHODS}, got {method!r}")
    dmesh = device_mesh(len(jax.devices()) if devices is None else devices)
    axis = str(dmesh.axis_names[0])
    S = int(dmesh.devices.size)
    mesh = pot.mesh
    pts = _host(mesh.points, "mesh.points")
    cells = _host(mesh.cells, "mesh.cells")
    if S > cells.shape[0]:
        raise ValueError(f"shard: {cells.shape[0]} cells cannot be split over {S} devices")
    part = partition_mesh(pts, cells, S, method)
    row, rep = NamedSharding(dmesh, P(axis)), NamedSharding(dmesh, P())
    dt = mesh.points.dtype

    halo = build_halo(part, dmesh, axis)
    halo = jax.tree_util.tree_map(lambda a: _put(a, np.int32, row), halo)
    assert isinstance(halo, Halo)
    cell_real = part.cell_real

    def cell_field(a, zero: bool):
        out = _host(a, "a mesh cell field")[part.cell_source]
        if zero:
            out[~cell_real] = 0
        return out

    incidence = node_slots(part.padded_cells, part.n_padded_nodes, cell_real)
    mesh_s = Mesh(
        points=_put(pts[part.node_source], dt, row),
        cells=_put(part.padded_cells, np.int32, row),
        dN=_put(cell_field(mesh.dN, True), dt, row),
        weights=_put(cell_field(mesh.weights, True), dt, row),
        incidence=_put(incidence, np.int32, row),
        halo=halo,
        element=mesh.element,
        formulation=mesh.formulation,
    )
    n_cells = cells.shape[0]

    def param(leaf):
        if isinstance(leaf, Tracer):
            _host(leaf, "a material parameter")
        shape = np.shape(leaf)
        if len(shape) >= 1 and shape[0] == n_cells:
            dtype = leaf.dtype if isinstance(leaf, jax.Array) else np.asarray(leaf).dtype
            return _put(np.asarray(leaf)[part.cell_source], dtype, row)
        if isinstance(leaf, jax.Array):
            return jax.device_put(leaf, rep)
        return leaf

    fields = {}
    for name in _NODE_FIELDS:
        a = getattr(pot, name)
        if a is None:
            continue
        h = _host(a, name)[part.node_source]
        if name in _ZERO_ON_PADDING:
            h[~part.node_real] = 0
        fields[name] = _put(h, a.dtype, row)
    for name in ("inertia_weight", "mass_damping", "stiffness_damping"):
        a = getattr(pot, name)
        if isinstance(a, jax.Array):
            fields[name] = jax.device_put(a, rep)
    params = jax.tree_util.tree_map(param, pot.params)
    pot_s = dataclasses.replace(pot, mesh=mesh_s, params=params, **fields)

    mask = _host(bc.mask, "bc.mask")[part.node_source]
    mask[~part.node_real] = True
    values = _host(bc.values, "bc.values")[part.node_source]
    values[~part.node_real] = pts[part.node_source][~part.node_real]
    bc_s = Dirichlet(
        mask=_put(mask, bool, row), values=_put(values, jnp.result_type(bc.values), row)
    )
    return pot_s, bc_s, part


# ----------------------------------------------------------------- communication volume

_COLLECTIVES = ("collective-permute", "all-reduce", "all-gather", "reduce-scatter", "all-to-all")
_BYTES = {"f64": 8, "f32": 4, "s32": 4, "u32": 4, "pred": 1, "s64": 8, "u64": 8, "f16": 2}
_SHAPE = re.compile(r"\b(f64|f32|s32|u32|pred|s64|u64|f16)\[([0-9,]*)\]")
_CALLS = re.compile(r"(?:calls|to_apply|body|condition|branch_computations)=\{?([%\w.\-, ]+)\}?")


def _shape_bytes(text: str) -> int:
    total = 0
    for dt, dims in _SHAPE.findall(text):
        total += _BYTES[dt] * int(np.prod([int(d) for d in dims.split(",") if d] or [1]))
    return total


def _group_size(line: str) -> int:
    m = re.search(r"replica_groups=\[(\d+),(\d+)\]", line)
    if m:
        return int(m.group(2))
    m = re.search(r"replica_groups=\{\{([0-9,]*)\}", line)
    return len(m.group(1).split(",")) if m else 1


def _computations(hlo: str) -> dict[str, list[str]]:
    comps: dict[str, list[str]] = {}
    name = None
    for line in hlo.splitlines():
        head = re.match(r"^(?:ENTRY )?(%[\w.\-]+) .*\{\s*$", line)
        if head and not line.startswith(" "):
            name = head.group(1)
            comps[name] = []
        elif line.startswith("}"):
            name = None
        elif name is not None:
            comps[name].append(line)
    return comps


def collective_bytes(hlo: str, *, loop_body: bool = False) -> dict:
    """Per-device operand bytes of the collectives in compiled HLO text
    (``jax.jit(f).lower(...).compile().as_text() or ""``).

    Counts ``collective-permute``, ``all-reduce``, ``all-gather``, ``reduce-scatter`` and
    ``all-to-all`` (and their async ``-start`` halves): the operand size each device sends
    into one op (for an all-gather the result divided by the group size).

    Args:
        hlo: the compiled module's text.
        loop_body: count only inside ``while`` bodies (and what they call): one iteration
            of a loop, e.g. of CG.

    Returns:
        ``{kind: {"ops": n, "bytes": b}, "total": {"ops": n, "bytes": b}}``.
    """
    comps = _computations(hlo)
    if loop_body:
        body = re.compile(r"body=(%[\w.\-]+)")
        todo = [b for lines in comps.values() for ln in lines for b in body.findall(ln)]
        keep: set[str] = set()
        while todo:
            c = todo.pop()
            if c in keep or c not in comps:
                continue
            keep.add(c)
            for ln in comps[c]:
                for grp in _CALLS.findall(ln):
                    todo += [g.strip() for g in grp.split(",") if g.strip().startswith("%")]
        lines = [ln for c in keep for ln in comps[c]]
    else:
        lines = [ln for v in comps.values() for ln in v]
    out = {k: {"ops": 0, "bytes": 0} for k in _COLLECTIVES + ("total",)}
    for ln in lines:
        m = re.match(r"\s*(?:ROOT )?%[\w.\-]+ = (.*?) ([a-z\-]+)\(", ln)
        if not m:
            continue
        kind = m.group(2).removesuffix("-start")
        if kind not in _COLLECTIVES:
            continue
        b = _shape_bytes(m.group(1))
        if kind == "all-gather":
            b //= max(_group_size(ln), 1)
        out[kind]["ops"] += 1
        out[kind]["bytes"] += b
        out["total"]["ops"] += 1
        out["total"]["bytes"] += b
    return {k: v for k, v in out.items() if v["ops"] or k == "total"}
