"""The device multigrid on a mesh sharded over devices: level 0 per shard, coarse replicated.

A mesh sharded over devices (:func:`jaxelastic.shard`, renumbered and padded) uses the
hierarchy of the one-device mesh (the aggregation follows the geometry, not the numbering:
:func:`~jaxelastic.solvers.multilevel.hierarchy.canonical_order`). :class:`ShardedHierarchy`
and :func:`sharded_preconditioner` keep level 0 per shard (partial sums of its own cells,
products with a halo exchange of interface values) and the coarse levels replicated on
every device (one ``psum`` of the level-1 matrix per Newton step and of the level-1 vector
per cycle), with the same iterates as one device.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from .cycle import (
    add_dead,
    block_inverse,
    chebyshev_smoother,
    ell_matvec,
    galerkin,
    lambda_max,
    level_chain,
    make_cycle,
    power_start,
)
from .hierarchy import Hierarchy, Level, ell_pattern, node_graph, pattern_of

__all__ = ["ShardedHierarchy", "build_sharded_hierarchy", "sharded_preconditioner"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True, eq=False, repr=False)
class ShardedHierarchy:
    """The hierarchy of a sharded mesh (:class:`~jaxelastic.parallel.halo.Halo`): level 0 as
    per-shard local tables (leading shard axis ``S``, sharded), the coarse levels as the
    :class:`Level` s of the one-device hierarchy (replicated). A pytree, equal only to
    itself.

    Shard ``s`` holds the rows of its local nodes ``[owned (n_own) | ghosts (n_ghost)]``
    of its own cells' part of the level-0 matrix (a partial sum: the level-0 matrix is the
    sum over shards); the level-0 product is ``scatter_add(A_s · gather(x))`` (interface
    values only cross devices), the Galerkin product ``Σ_s T_sᵀ A_s T_s`` is a per-shard
    partial sum and one ``psum``, the restriction a partial ``Tᵀr`` and one ``psum`` of the
    coarse vector; the coarse levels and the prolongation are computed on every shard.

    Attributes:
        coarse: tuple of :class:`Level`, levels 1, 2, … (replicated; empty when the
            mesh has at most ``max_coarse`` dofs: then the whole matrix is summed over the
            shards and factorised densely, as on one device).
        cols: ``(S, n_loc, w)`` int32 local ELL columns of the shard's level-0 rows.
        diag: ``(S, n_loc)`` int32 diagonal slot of each local row.
        el_perm, el_sorted: ``(S, c_loc·k·k)`` int32 local element-block → slot map, sorted.
        T: ``(S, n_loc, d, m)`` tentative prolongator rows of the local nodes.
        y_slot: ``(S, n_loc, w)`` int32 slot of ``A_s T`` (width ``wy``) each block adds into
            (``n_loc·wy``: dropped); ycols: ``(S, n_loc, wy)`` int32 its coarse nodes.
        c_slot: ``(S, n_loc, wy)`` int32 slot of the level-1 matrix (``n_1·w_1``: dropped).
        agg: ``(S, n_own)`` int32 aggregate of each owned node (``n_1``: none).
        r_perm, r_sorted: ``(S, n_own)`` int32 owned nodes sorted by aggregate.
        start: ``(S, n_own, d)`` int32 canonical dof index (power-iteration start; ``-1``:
            padding).
        glob: ``(S, n_loc)`` int32 padded global node of each local node (``S·n_own``: an
            unused ghost slot).
        n_shards, n_own, n_loc, w, wy, k, dim: static sizes.
    """

    coarse: tuple
    cols: jax.Array
    diag: jax.Array
    el_perm: jax.Array
    el_sorted: jax.Array
    T: jax.Array
    y_slot: jax.Array
    ycols: jax.Array
    c_slot: jax.Array
    agg: jax.Array
    r_perm: jax.Array
    r_sorted: jax.Array
    start: jax.Array
    glob: jax.Array
    n_shards: int = dataclasses.field(metadata=dict(static=True), default=1)
    n_own: int = dataclasses.field(metadata=dict(static=True), default=0)
    n_loc: int = dataclasses.field(metadata=dict(static=True), default=0)
    w: int = dataclasses.field(metadata=dict(static=True), default=0)
    wy: int = dataclasses.field(metadata=dict(static=True), default=0)
    k: int = dataclasses.field(metadata=dict(static=True), default=0)
    dim: int = dataclasses.field(metadata=dict(static=True), default=0)

    @property
    def sizes(self) -> tuple[int, ...]:
        """Dofs per level, fine (real and padded) to coarse."""
        return (self.n_shards * self.n_own * self.dim,) + tuple(
            int(lv.n * lv.b) for lv in self.coarse
        )

    def describe(self) -> str:
        """One line: level 0 per shard, then the replicated coarse levels."""
        parts = [f"{self.n_shards} x {self.n_own * self.dim} dofs (sharded, width {self.w})"]
        parts += [f"{lv.n * lv.b} dofs ({lv.n}x{lv.b}, replicated)" for lv in self.coarse]
        return " -> ".join(parts)

    def __repr__(self) -> str:
        return f"ShardedHierarchy({self.describe()})"


def _ghost_nodes(halo) -> np.ndarray:
    """``(S, n_ghost)`` padded global index of every ghost slot of a halo (``-1``: an
    unused slot), from its send/receive tables."""
    S, n_own, n_ghost = halo.n_shards, halo.n_own, halo.n_ghost
    out = np.full((S, n_ghost), -1, np.int64)
    for delta, snd, rcv in zip(halo.shifts, halo.send, halo.recv, strict=True):
        snd, rcv = np.asarray(snd), np.asarray(rcv)
        for r in range(S):
            o = (r - delta) % S
            ok = rcv[r] < n_ghost
            out[r, rcv[r][ok]] = o * n_own + snd[o][ok]
    return out


def _lookup(cols: np.ndarray) -> Callable:
    """Slot lookup ``(r, c) -> r·w + position`` of a self-padded ELL pattern ``(n, w)``
    (the first occurrence of each pair: the real slot)."""
    n, w = cols.shape
    keys = np.repeat(np.arange(n, dtype=np.int64), w) * n + cols.ravel().astype(np.int64)
    uniq, first = np.unique(keys, return_index=True)

    def lookup(r, c):
        q = np.asarray(r, np.int64) * n + np.asarray(c, np.int64)
        p = np.searchsorted(uniq, q)
        if q.size and not np.array_equal(uniq[np.minimum(p, uniq.size - 1)], q):
            raise AssertionError("pair outside the coarse sparsity pattern")
        return first[p]

    return lookup


def build_sharded_hierarchy(h: Hierarchy, halo, cells) -> ShardedHierarchy:
    """The :class:`ShardedHierarchy` of a hierarchy ``h`` built on the padded mesh.

    Long because: one pass per shard builds its local level-0 pattern and every slot map
    of its partial Galerkin product and restriction, which share their arrays.

    Args:
        h: :func:`~jaxelastic.solvers.multilevel.hierarchy.build_hierarchy` of the padded
            mesh (unsmoothed; its level-0 ``T`` and aggregates are in the padded numbering,
            its coarse levels those of the natural mesh, by
            :func:`~jaxelastic.solvers.multilevel.hierarchy.canonical_order`).
        halo: the mesh's :class:`~jaxelastic.parallel.halo.Halo` (host-readable tables).
        cells: ``(S·c_loc, k)`` padded connectivity.
    """
    lv0 = h.levels[0]
    S, n_own, n_ghost, c_loc = halo.n_shards, halo.n_own, halo.n_ghost, halo.c_loc
    n_loc, k, d = n_own + n_ghost, h.k, h.dim
    start = np.asarray(h.start).reshape(S, n_own, d)
    cells = np.asarray(cells, np.int64)
    local_cells = np.asarray(halo.local_cells, np.int64)
    ghosts = _ghost_nodes(halo)
    if len(h.levels) == 1:  # one level (a dense solve): no prolongator, no aggregates
        n1, w1 = 0, 1
        T0 = np.zeros((lv0.n, d, 1))
        agg_pad = np.zeros(lv0.n, np.int64)
        lookup1 = None
    else:
        lv1 = h.levels[1]
        if lv0.smooth or lv0.wp != 1:
            raise ValueError("the sharded Multilevel supports plain aggregation (smooth=False)")
        n1, w1 = lv1.n, lv1.w
        T0 = np.asarray(lv0.T)
        tslot = np.asarray(lv0.tslot)
        agg_pad = np.where(tslot < lv0.n, np.asarray(lv0.pcols)[:, 0], n1)  # wp = 1
        lookup1 = _lookup(np.asarray(lv1.cols))
    per, globs = [], []
    for s in range(S):
        glob = np.concatenate([s * n_own + np.arange(n_own), ghosts[s]])
        used = glob >= 0
        lc = local_cells[s]
        blk = cells[s * c_loc : (s + 1) * c_loc]
        real = ~(blk == blk[:, :1]).all(axis=1)  # a padded cell repeats one node
        G = node_graph(lc[real], n_loc)
        cols, w, deg, lookup = ell_pattern(G)
        el = lookup(np.repeat(lc, k, axis=1).ravel(), np.tile(lc, (1, k)).ravel())
        el_perm = np.argsort(el, kind="stable")
        diag = lookup(np.arange(n_loc), np.arange(n_loc)) - np.arange(n_loc) * w
        agg = np.where(used, agg_pad[np.where(used, glob, 0)], n1)
        T = np.where(used[:, None, None], T0[np.where(used, glob, 0)], 0.0)
        rows = np.repeat(np.arange(n_loc), w)
        cj = cols.ravel().astype(np.int64)
        ok = (np.arange(w)[None, :] < deg[:, None]).ravel() & (agg[cj] < n1)
        Yp = sp.csr_matrix(
            (np.ones(int(ok.sum()), np.int8), (rows[ok], agg[cj[ok]])), shape=(n_loc, n1 + 1)
        )
        ycols, wy, ydeg, ylookup = ell_pattern(pattern_of(Yp), pad_self=False)
        per.append((cols, w, diag, el, el_perm, T, agg, rows, cj, ok, ycols, wy, ydeg, ylookup))
        globs.append(np.where(used, glob, S * n_own))
    W = max(p[1] for p in per)
    WY = max(p[11] for p in per)
    out = {f: [] for f in ("cols", "diag", "el_perm", "el_sorted", "T", "y_slot", "ycols")}
    out.update(c_slot=[], agg=[], r_perm=[], r_sorted=[])
    for cols, w, diag, el, el_perm, T, agg, rows, cj, ok, ycols, wy, ydeg, yl in per:
        # re-slot into the common widths W, WY
        cw = np.repeat(np.arange(n_loc)[:, None], W, axis=1)
        cw[:, :w] = cols
        el_w = (el // w) * W + el % w
        y_slot = np.full(n_loc * w, n_loc * WY, np.int64)
        yr = yl(rows[ok], agg[cj[ok]])
        y_slot[ok] = (yr // wy) * WY + yr % wy
        ys = np.full((n_loc, W), n_loc * WY, np.int64)
        ys[:, :w] = y_slot.reshape(n_loc, w)
        yc = np.zeros((n_loc, WY), np.int64)
        yc[:, :wy] = ycols
        yreal = np.zeros((n_loc, WY), bool)
        yreal[:, :wy] = np.arange(wy)[None, :] < ydeg[:, None]
        yreal &= (agg < n1)[:, None]
        c_slot = np.full((n_loc, WY), n1 * w1, np.int64)
        ri, ui = np.nonzero(yreal)
        if lookup1 is not None:
            c_slot[ri, ui] = lookup1(agg[ri], yc[ri, ui])
        agg_own = agg[:n_own]
        r_perm = np.argsort(agg_own, kind="stable")
        out["cols"].append(cw)
        out["diag"].append(diag)
        out["el_perm"].append(el_perm)
        out["el_sorted"].append(el_w[el_perm])
        out["T"].append(T)
        out["y_slot"].append(ys)
        out["ycols"].append(yc)
        out["c_slot"].append(c_slot)
        out["agg"].append(agg_own)
        out["r_perm"].append(r_perm)
        out["r_sorted"].append(agg_own[r_perm])
    sharded = halo.sharding()
    replicated = halo.sharding(replicated=True)
    arrays = {}
    for name, vals in out.items():
        a = np.stack(vals)
        a = a.astype(np.int32) if np.issubdtype(a.dtype, np.integer) else a
        arrays[name] = jax.device_put(a, sharded)
    coarse = jax.device_put(tuple(h.levels[1:]), replicated)
    return ShardedHierarchy(
        coarse=coarse,
        **arrays,
        glob=jax.device_put(np.stack(globs).astype(np.int32), sharded),
        start=jax.device_put(start.astype(np.int32), sharded),
        n_shards=S,
        n_own=n_own,
        n_loc=n_loc,
        w=W,
        wy=WY,
        k=k,
        dim=d,
    )


def _local_view(tree):
    """The per-shard block of a pytree of ``(1, ...)`` blocks (inside ``shard_map``)."""
    return jax.tree_util.tree_map(lambda t: t[0], tree)


def sharded_preconditioner(
    sh: ShardedHierarchy,
    halo,
    Ke: jax.Array,
    md: jax.Array | None,
    free: jax.Array,
    *,
    degree: int = 4,
    lower: float = 1.0 / 30.0,
    power_iters: int = 15,
    cycle: str = "V",
    coarse_scale: float = 1.3,
) -> Callable[[jax.Array], jax.Array]:
    """:func:`~jaxelastic.solvers.multilevel.cycle.preconditioner` on a sharded mesh (same
    arguments, in the global padded layout; ``halo`` is the mesh's
    :class:`~jaxelastic.parallel.halo.Halo`).

    Long because: the per-shard setup (level-0 partial matrix, block Jacobi, power
    iteration, partial Galerkin product) and the per-shard cycle are closures over the same
    local operators, each run under one ``shard_map``.

    Communication per Newton step: the level-0 block-Jacobi diagonal (one scatter of
    ghost blocks), 2·(``power_iters`` + 1) halo exchanges and scalar ``psum`` s, and one
    ``psum`` of the level-1 matrix. Per application: two halo exchanges per level-0
    product (``2·degree`` products) and one ``psum`` of the level-1 vector.
    """
    dtype = Ke.dtype
    axis, mesh = halo.axis, halo.device_mesh
    Psh, Prep = jax.sharding.PartitionSpec(axis), jax.sharding.PartitionSpec()
    coarse = sh.coarse
    n_own, n_loc, w, wy, d = sh.n_own, sh.n_loc, sh.w, sh.wy, sh.dim
    lv1 = coarse[0] if coarse else None
    local = {f: getattr(sh, f) for f in ("cols", "diag", "el_perm", "el_sorted", "T")}
    local.update({f: getattr(sh, f) for f in ("y_slot", "ycols", "c_slot", "agg")})
    local.update({f: getattr(sh, f) for f in ("r_perm", "r_sorted", "start", "glob")})
    halo_spec = jax.tree_util.tree_map(lambda _: Psh, halo)
    local_spec = jax.tree_util.tree_map(lambda _: Psh, local)
    coarse_spec = jax.tree_util.tree_map(lambda _: Prep, coarse)
    fm = free.astype(dtype)
    md = jnp.zeros(free.shape[:1], dtype) if md is None else md.astype(dtype)

    def views(hl, loc):
        hl = dataclasses.replace(_local_view(hl), local=True)
        return hl, _local_view(loc)

    def ops(hl, loc, A):
        def matvec(x):
            return hl.scatter_add(ell_matvec(A, loc["cols"], hl.gather(x)))

        def dot(a, b):
            return hl.psum(jnp.sum(a * b))

        return matvec, dot

    def setup(hl, loc, coarse, Ke, md, fm):
        hl, loc = views(hl, loc)
        c = Ke.shape[0]
        k = sh.k
        blocks = Ke.reshape(c, k, d, k, d).transpose(0, 1, 3, 2, 4).reshape(c * k * k, d, d)
        A = jax.ops.segment_sum(
            blocks[loc["el_perm"]],
            loc["el_sorted"],
            num_segments=n_loc * w,
            indices_are_sorted=True,
        ).reshape(n_loc, w, d, d)
        fl = hl.gather(fm)  # (n_loc, d)
        A = A * fl[:, None, :, None] * fl[loc["cols"]][:, :, None, :]
        eye = jnp.eye(d, dtype=dtype)[None]
        dblock = eye * (1.0 - fm)[:, :, None] + md[:, None, None] * eye * fm[:, :, None]
        A = A.at[jnp.arange(n_own), loc["diag"][:n_own]].add(dblock)  # once: owned rows
        if not coarse:  # one level: the whole matrix, summed over the shards, densely
            N = sh.n_shards * n_own
            g = loc["glob"]
            D4 = jnp.zeros((N, N, d, d), dtype).at[g[:, None], g[loc["cols"]]].add(A, mode="drop")
            L = jnp.linalg.cholesky(hl.psum(D4.transpose(0, 2, 1, 3).reshape(N * d, N * d)))
            return A[None], A[None, :0, 0], jnp.zeros((), dtype), dict(L=L)
        D = A[jnp.arange(n_loc), loc["diag"]]
        D = hl.scatter_add(D.reshape(n_loc, d * d)).reshape(n_own, d, d)
        Dinv = block_inverse(D, lapack=False)
        matvec, dot = ops(hl, loc, A)
        lam = lambda_max(matvec, D, Dinv, power_start(loc["start"], dtype), power_iters, dot)
        lv = Level(
            **{f: loc[f] for f in ("cols", "y_slot", "c_slot", "ycols")},
            diag=loc["diag"],
            dead=jnp.zeros((0,), jnp.int32),
            T=loc["T"],
            pcols=jnp.zeros((0,), jnp.int32),
            tslot=jnp.zeros((0,), jnp.int32),
            at_perm=jnp.zeros((0,), jnp.int32),
            at_sorted=jnp.zeros((0,), jnp.int32),
            r_perm=jnp.zeros((0,), jnp.int32),
            r_sorted=jnp.zeros((0,), jnp.int32),
            n=n_loc,
            b=d,
            w=w,
            wp=1,
            wy=wy,
        )
        lv = dataclasses.replace(lv, y_slot=loc["y_slot"][None], c_slot=loc["c_slot"][None])
        assert lv1 is not None
        A1 = hl.psum(galerkin(lv, lv1, A, loc["T"].astype(dtype)[:, None], dead=False))
        data = level_chain(coarse, add_dead(lv1, A1), power_iters, lapack=False)
        return A[None], Dinv[None], lam, data

    data_spec = dict(mats=Prep, Dinvs=Prep, lams=Prep, Ps=Prep, L=Prep) if coarse else dict(L=Prep)
    A0, Dinv0, lam0, data = jax.shard_map(
        setup,
        mesh=mesh,
        in_specs=(halo_spec, local_spec, coarse_spec, Psh, Psh, Psh),
        out_specs=(Psh, Psh, Prep, data_spec),
    )(halo, local, coarse, Ke, md, fm)
    scale = jnp.asarray(coarse_scale, dtype)

    def body(hl, loc, coarse, A, Dinv, lam, data, r):
        hl, loc = views(hl, loc)
        A, Dinv = A[0], Dinv[0]
        r = r.astype(dtype)
        if not coarse:  # one level: an exact solve with the replicated factor
            N, at = sh.n_shards * n_own, jax.lax.axis_index(axis) * n_own
            full = jnp.zeros((N, d), dtype).at[at + jnp.arange(n_own, dtype=at.dtype)].set(r)
            y = jax.scipy.linalg.cho_solve((data["L"], True), hl.psum(full).reshape(-1))
            return jax.lax.dynamic_slice_in_dim(y.reshape(N, d), at, n_own)
        assert lv1 is not None
        matvec, _ = ops(hl, loc, A)
        smooth = chebyshev_smoother(matvec, Dinv, lam, degree, lower)
        solve = make_cycle(coarse, data, degree=degree, lower=lower, cycle=cycle, scale=scale)
        T = loc["T"].astype(dtype)
        x = smooth(jnp.zeros_like(r), r, True)
        res = r - matvec(x)
        rt = jnp.einsum("nbm,nb->nm", T[:n_own], res)
        rc = jax.ops.segment_sum(
            rt[loc["r_perm"]], loc["r_sorted"], num_segments=lv1.n + 1, indices_are_sorted=True
        )[:-1]
        rc = hl.psum(rc)
        ec = solve(0, rc)
        if cycle == "W" and len(coarse) > 1:
            ec = ec + solve(0, rc - ell_matvec(data["mats"][0], lv1.cols, ec))
        ec = jnp.concatenate([ec, jnp.zeros((1,) + ec.shape[1:], dtype)])
        x = x + scale * jnp.einsum("nbm,nm->nb", T[:n_own], ec[loc["agg"]])
        return smooth(x, r, False)

    apply_sharded = jax.shard_map(
        body,
        mesh=mesh,
        in_specs=(halo_spec, local_spec, coarse_spec, Psh, Psh, Prep, data_spec, Psh),
        out_specs=Psh,
    )

    def apply(r):
        return apply_sharded(halo, local, coarse, A0, Dinv0, lam0, data, r)

    return apply
