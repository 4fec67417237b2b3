"""Halo exchange for a mesh sharded over devices: local tables and the ghost-node traffic.

A sharded mesh (:func:`jaxelastic.shard`) keeps the global padded layout of
:mod:`jaxelastic.parallel.partition`: shard ``s`` owns nodes ``[s·n_own, (s+1)·n_own)`` and
cells ``[s·c_loc, (s+1)·c_loc)``. A :class:`Halo` adds what a shard needs to work on its
cells alone under ``jax.shard_map``:

* its cells in *local* node numbering ``[owned (n_own) | ghosts (n_ghost)]``
  (``local_cells``) and the local node → cell-slot table (``local_incidence``);
* per neighbour shift δ (shard ``o`` talks to ``(o + δ) mod S``; only shifts with
  neighbours exist), the owned nodes ``o`` sends (``send``) and where the receiver's ghost
  slots sit in what it receives (``recv``, ``ghost_src``).

Inside the mapped function (:meth:`Halo.map`) each shard calls :meth:`Halo.gather`
(owned values → owned + ghost values, one ``lax.ppermute`` per shift carrying only the
interface nodes), :meth:`Halo.scatter_add` (the transpose: ghost contributions are sent back
and added to their owners) and :meth:`Halo.psum`.

Every table has a leading shard axis ``S`` and is placed with ``NamedSharding(mesh,
P(axis))``; inside :meth:`Halo.map` the leading axis is gone (the "local view").
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.sharding import PartitionSpec as P

from ..mesh.core import Mesh
from .partition import Partition

__all__ = ["Halo", "build_halo", "node_slots"]


@dataclasses.dataclass(frozen=True)
class Halo:
    """Halo tables of a sharded mesh (a JAX pytree; see the module docstring).

    Attributes:
        local_cells: ``(S, c_loc, k)`` int32 cells in local node numbering (``[0, n_own)``
            owned, ``[n_own, n_own + n_ghost)`` ghosts); padded cells list local node 0.
        local_incidence: ``(S, n_own + n_ghost, v)`` int32 local node → flat cell slot
            ``c·k + a`` of the shard's real cells, padded with ``c_loc·k``.
        send: per shift, ``(S, m_δ)`` int32 owned local indices shard ``o`` sends to
            ``(o + δ) mod S`` (padding: ``n_own``, out of range).
        recv: per shift, ``(S, m_δ)`` int32 ghost slots ``[0, n_ghost)`` of what shard
            ``r`` receives from ``(r − δ) mod S``, in the same order (padding: ``n_ghost``).
        ghost_src: ``(S, n_ghost)`` int32 row of each ghost slot in the concatenation of the
            received buffers (unused slots: 0).
        n_shards, n_own, n_ghost, c_loc: static sizes; axis: the mesh axis name (static);
        device_mesh: the :class:`jax.sharding.Mesh` (static); shifts: the δ's (static);
        local: True for the per-shard view inside :meth:`map` (static).
    """

    local_cells: jax.Array
    local_incidence: jax.Array
    send: tuple
    recv: tuple
    ghost_src: jax.Array
    n_shards: int = dataclasses.field(metadata=dict(static=True), default=1)
    n_own: int = dataclasses.field(metadata=dict(static=True), default=0)
    n_ghost: int = dataclasses.field(metadata=dict(static=True), default=0)
    c_loc: int = dataclasses.field(metadata=dict(static=True), default=0)
    axis: str = dataclasses.field(metadata=dict(static=True), default="shards")
    device_mesh: object = dataclasses.field(metadata=dict(static=True), default=None)
    shifts: tuple = dataclasses.field(metadata=dict(static=True), default=())
    local: bool = dataclasses.field(metadata=dict(static=True), default=False)

    @property
    def n_local(self) -> int:
        """Local node count ``n_own + n_ghost``."""
        return self.n_own + self.n_ghost

    def sharding(self, replicated: bool = False) -> jax.sharding.NamedSharding:
        """``NamedSharding`` of the device mesh along the first axis (or replicated)."""
        mesh = self.device_mesh
        assert isinstance(mesh, jax.sharding.Mesh)
        return jax.sharding.NamedSharding(mesh, P() if replicated else P(self.axis))

    def exchange_bytes(self, width: int, itemsize: int = 8) -> int:
        """Bytes one :meth:`gather` (or :meth:`scatter_add`) moves between devices in total
        for ``width`` numbers per node: ``Σ_δ S·m_δ·width·itemsize`` (padding included)."""
        return int(sum(s.shape[-1] for s in self.send) * self.n_shards * width * itemsize)

    # -------------------------------------------------------------- inside shard_map

    def _perm(self, delta: int, back: bool = False):
        S = self.n_shards
        pairs = [(o, (o + delta) % S) for o in range(S)]
        return [(b, a) for a, b in pairs] if back else pairs

    def _check_local(self, what: str) -> None:
        if not self.local:
            raise ValueError(
                f"Halo.{what} runs inside Halo.map (per shard, under shard_map); outside, "
                "call halo.map(fn, *arrays, out_specs=...) with fn(local_halo, *blocks)"
            )

    def gather(self, x_own: jax.Array) -> jax.Array:
        """Owned values ``(n_own, ...)`` → local values ``(n_own + n_ghost, ...)``: ghost
        rows filled from their owners (one ``ppermute`` per shift, interface nodes only)."""
        self._check_local("gather")
        if not self.shifts:
            return jnp.concatenate(
                [x_own, jnp.zeros((self.n_ghost,) + x_own.shape[1:], x_own.dtype)]
            )
        bufs = []
        for i, delta in enumerate(self.shifts):
            out = x_own.at[self.send[i]].get(mode="fill", fill_value=0)
            bufs.append(lax.ppermute(out, self.axis, self._perm(delta)))
        allr = jnp.concatenate(bufs) if len(bufs) > 1 else bufs[0]
        return jnp.concatenate([x_own, allr[self.ghost_src]])

    def scatter_add(self, f_loc: jax.Array) -> jax.Array:
        """Local values ``(n_own + n_ghost, ...)`` → owned sums ``(n_own, ...)``: each ghost
        row is sent back to its owner and added there (the transpose of :meth:`gather`)."""
        self._check_local("scatter_add")
        f_own, g = f_loc[: self.n_own], f_loc[self.n_own :]
        for i, delta in enumerate(self.shifts):
            back = g.at[self.recv[i]].get(mode="fill", fill_value=0)
            back = lax.ppermute(back, self.axis, self._perm(delta, back=True))
            f_own = f_own.at[self.send[i]].add(back, mode="drop")
        return f_own

    def psum(self, a):
        """Sum over shards (``lax.psum`` on the mesh axis)."""
        self._check_local("psum")
        return lax.psum(a, self.axis)

    # -------------------------------------------------------------- outside

    def map(self, fn: Callable, *args, out_specs):
        """Run ``fn(local_halo, *blocks)`` on every shard under ``jax.shard_map``.

        Args:
            fn: per-shard function; ``local_halo`` is this halo's local view (tables
                without the shard axis); each array leaf of ``args`` with at least one
                dimension arrives as its shard's block along axis 0, scalars replicated.
            args: pytrees of sharded arrays (global padded layout) and scalars.
            out_specs: ``PartitionSpec`` pytree of the outputs (``P(halo.axis)`` for
                sharded blocks, ``P()`` for replicated values such as a psum).
        """
        if self.local:
            raise ValueError("Halo.map is called on the global halo, not inside Halo.map")

        def spec(a):
            return P(self.axis) if jnp.ndim(a) >= 1 else P()

        in_specs = (jax.tree_util.tree_map(lambda _: P(self.axis), self),) + tuple(
            jax.tree_util.tree_map(spec, a) for a in args
        )

        def body(h, *blocks):
            loc = jax.tree_util.tree_map(lambda t: t[0], h)
            return fn(dataclasses.replace(loc, local=True), *blocks)

        mesh = self.device_mesh
        assert isinstance(mesh, jax.sharding.Mesh)
        mapped = jax.shard_map(body, mesh=mesh, in_specs=in_specs, out_specs=out_specs)
        return mapped(self, *args)

    def map_mesh(self, fn: Callable, mesh: Mesh, *args, out_specs):
        """:meth:`map` for mesh kernels: ``fn(local_halo, local_mesh, points, *blocks)``.

        ``local_mesh`` is the shard's :class:`~jaxelastic.mesh.Mesh` over its local nodes
        ``[owned | ghosts]``: ``cells``/``incidence`` are the local tables, ``dN`` and
        ``weights`` its cell blocks, ``halo`` None, and its ``points`` are **zeros**
        ``(n_local, dim)``: pass gathered *displacements* as positions (F = I + ∇u is all
        the kernels need; gathering the rest points too would double the traffic).
        ``points`` is the shard's owned block of the rest points ``(n_own, dim)``.
        """

        def body(hl, pts, dN, w, *blocks):
            loc = Mesh(
                points=jnp.zeros((hl.n_local, pts.shape[1]), pts.dtype),
                cells=hl.local_cells,
                dN=dN,
                weights=w,
                incidence=hl.local_incidence,
                halo=None,
                element=mesh.element,
                formulation=mesh.formulation,
            )
            return fn(hl, loc, pts, *blocks)

        return self.map(body, mesh.points, mesh.dN, mesh.weights, *args, out_specs=out_specs)

    def displacements(self, x_own: jax.Array, points_own: jax.Array) -> jax.Array:
        """Local displacements ``(n_local, dim)`` of owned positions: ``u = x − X`` on the
        owned block (in the rest points' dtype, as
        :func:`~jaxelastic.mechanics.kinematics.displacements`), then :meth:`gather`."""
        u = x_own - points_own
        return self.gather(u if u.dtype == points_own.dtype else u.astype(points_own.dtype))


jax.tree_util.register_dataclass(
    Halo,
    data_fields=["local_cells", "local_incidence", "send", "recv", "ghost_src"],
    meta_fields=[
        "n_shards",
        "n_own",
        "n_ghost",
        "c_loc",
        "axis",
        "device_mesh",
        "shifts",
        "local",
    ],
)


def node_slots(cells: np.ndarray, n_rows: int, real: np.ndarray | None = None, width=None):
    """``(n_rows, v)`` int32 node → flat cell-slot table (``c·k + a``) over the cells with
    ``real`` True, padded with ``n_cells·k`` (the layout of ``Mesh.incidence``).

    Args:
        cells: ``(n_cells, k)`` node indices in ``[0, n_rows)``.
        n_rows: number of nodes (rows).
        real: ``(n_cells,)`` bool, the cells to list (default all).
        width: at least this many columns (to stack tables of several shards).
    """
    c, k = cells.shape
    flat = cells.ravel().astype(np.int64)
    slots = np.arange(c * k)
    if real is not None:
        keep = np.repeat(np.asarray(real, dtype=bool), k)
        flat, slots = flat[keep], slots[keep]
    order = np.argsort(flat, kind="stable")
    counts = np.bincount(flat, minlength=n_rows)
    v = max(int(counts.max()) if counts.size else 0, 1, int(width or 0))
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = np.arange(flat.size) - np.repeat(starts, counts)
    table = np.full((n_rows, v), c * k, dtype=np.int32)
    table[flat[order], rank] = slots[order]
    return table


def build_halo(part: Partition, device_mesh, axis: str) -> Halo:
    """Host-side :class:`Halo` tables of ``part`` (NumPy arrays; :func:`jaxelastic.shard`
    places them on the devices).

    Args:
        part: the :class:`~jaxelastic.parallel.partition.Partition`.
        device_mesh: a :class:`jax.sharding.Mesh` with ``part.n_shards`` devices on ``axis``.
        axis: its axis name.
    """
    S, n_own, c_loc = part.n_shards, part.n_own, part.c_loc
    ghosts = part.ghosts
    n_ghost = max([g.size for g in ghosts] + [0])
    k = part.padded_cells.shape[1]
    # local numbering and cell tables
    local_cells = np.empty((S, c_loc, k), dtype=np.int32)
    tables = []
    for s in range(S):
        lookup = np.full(part.n_padded_nodes, -1, dtype=np.int64)
        lookup[s * n_own : (s + 1) * n_own] = np.arange(n_own)
        lookup[ghosts[s]] = n_own + np.arange(ghosts[s].size)
        blk = part.padded_cells[s * c_loc : (s + 1) * c_loc]
        real = part.cell_real[s * c_loc : (s + 1) * c_loc]
        loc = lookup[blk]
        assert (loc[real] >= 0).all()
        loc[~real] = 0
        local_cells[s] = loc
        tables.append(node_slots(loc, n_own + n_ghost, real))
    v = max(t.shape[1] for t in tables)
    local_incidence = np.full((S, n_own + n_ghost, v), c_loc * k, dtype=np.int32)
    for s, t in enumerate(tables):
        local_incidence[s, :, : t.shape[1]] = t
    # shifts: shard o sends to r = (o + δ) mod S the ghosts of r that o owns
    owner_of = [g // n_own for g in ghosts]
    shifts, send, recv = [], [], []
    ghost_src = np.zeros((S, n_ghost), dtype=np.int32)
    offset = 0
    for delta in range(1, S):
        lists = []
        for o in range(S):
            r = (o + delta) % S
            slots = np.flatnonzero(owner_of[r] == o)
            lists.append((o, r, slots))
        m = max(sl.size for _, _, sl in lists)
        if m == 0:
            continue
        snd = np.full((S, m), n_own, dtype=np.int32)
        rcv = np.full((S, m), n_ghost, dtype=np.int32)
        for o, r, sl in lists:
            snd[o, : sl.size] = ghosts[r][sl] - o * n_own
            rcv[r, : sl.size] = sl
            ghost_src[r, sl] = offset + np.arange(sl.size)
        shifts.append(delta)
        send.append(snd)
        recv.append(rcv)
        offset += m
    return Halo(
        local_cells=local_cells,  # pyright: ignore[reportArgumentType]
        local_incidence=local_incidence,  # pyright: ignore[reportArgumentType]
        send=tuple(send),
        recv=tuple(recv),
        ghost_src=ghost_src,  # pyright: ignore[reportArgumentType]
        n_shards=S,
        n_own=n_own,
        n_ghost=int(n_ghost),
        c_loc=c_loc,
        axis=axis,
        device_mesh=device_mesh,
        shifts=tuple(shifts),
    )
