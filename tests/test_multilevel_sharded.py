"""The device multigrid (je.Multilevel) on a mesh sharded over 4 host CPU devices
(tests/conftest.py sets ``--xla_force_host_platform_device_count=4``): the same hierarchy
as on one device, the same preconditioner to round-off, interface-only fine-level
communication, the same CG iterations and Newton solve."""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic as je
from jaxelastic.mechanics import potential as pm
from jaxelastic.solvers import cg
from jaxelastic.solvers.multilevel import ShardedHierarchy, preconditioner, sharded_preconditioner
from jaxelastic.verification.torsion import twist

S = 4
ML = je.Multilevel(max_coarse=20)  # twist n = 4: 375 -> 36 -> 6 dofs

pytestmark = [
    pytest.mark.extended,  # multi-device comparisons: the second tier
    pytest.mark.skipif(
        len(jax.devices()) < S,
        reason="needs 4 devices: XLA_FLAGS=--xla_force_host_platform_device_count=4 before jax",
    ),
]


def _rel(a, b) -> float:
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


@pytest.fixture(scope="module")
def tw():
    """Twist n = 4 sharded by METIS, element Hessians at a perturbed state (both layouts),
    and both bound solvers."""
    b = twist(4)
    pot_s, bc_s, part = je.shard(b.pot, b.bc, devices=S, method="metis")
    X = jnp.asarray(b.mesh.points)
    x = X + 0.05 * jnp.sin(3.0 * X)
    Ke = pm.elastic_element_hessians(b.pot, x, True)
    Ke_s = jax.device_put(
        part.to_padded(np.asarray(Ke), kind="cells", fill=0.0), pot_s.mesh.halo.sharding()
    )
    one = je.solvers.init_linear(ML, b.mesh, b.bc)[1]
    many = je.solvers.init_linear(ML, pot_s.mesh, bc_s)[1]
    return b, pot_s, bc_s, part, Ke, Ke_s, one, many


def test_same_hierarchy_as_one_device(tw):
    """Aggregation follows the rest geometry, not the numbering: the coarse levels of the
    padded, partitioned mesh are those of the natural one, bit for bit, and the level-0
    prolongator rows of every owned node are the natural node's."""
    b, pot_s, bc_s, part, _, _, one, many = tw
    h, sh = one.hierarchy, many.hierarchy
    assert isinstance(sh, ShardedHierarchy) and len(sh.coarse) == len(h.levels) - 1 == 2
    assert sh.sizes[1:] == h.sizes[1:]
    for a, c in zip(h.levels[1:], sh.coarse, strict=True):
        for f in ("cols", "diag", "dead", "T", "pcols", "tslot", "c_slot", "r_perm"):
            assert np.array_equal(np.asarray(getattr(a, f)), np.asarray(getattr(c, f))), f
    T_own = np.asarray(sh.T)[:, : sh.n_own].reshape(-1, 3, 6)
    assert np.array_equal(part.to_natural(T_own), np.asarray(h.levels[0].T))
    assert je.solvers.init_linear(ML, pot_s.mesh, bc_s)[1].hierarchy is sh  # cached setup
    assert "sharded" in repr(sh)


def _collectives(text: str) -> dict:
    """``{op: [per-device bytes of each]}`` of the collectives in compiled HLO text."""
    itemsize = dict(f64=8, f32=4, s32=4, pred=1)
    out: dict = {}
    pat = (
        r"= \(?((?:[a-z0-9]+\[[0-9,]*\]\S*(?:, )?)+)\)? (all-reduce|collective-permute|all-gather)"
    )
    for m in re.finditer(pat + r"(?:-start)?\(", text):
        size = 0
        for t, dims in re.findall(r"([a-z0-9]+)\[([0-9,]*)\]", m.group(1)):
            size += int(np.prod([int(x) for x in dims.split(",") if x])) * itemsize.get(t, 8)
        out.setdefault(m.group(2), []).append(size)
    return out


@pytest.mark.parametrize("cycle", ["V", pytest.param("W", marks=pytest.mark.slow)])
def test_preconditioner_matches_one_device(tw, cycle):
    """M⁻¹r on 4 shards equals one device's to round-off (V: with a mass diagonal, as in
    dynamics); one application exchanges only interface rows on the fine level: 2 halo
    exchanges per level-0 product, one psum of the level-1 vector, nothing node-sized."""
    b, pot_s, bc_s, part, Ke, Ke_s, one, many = tw
    rng = np.random.default_rng(3)
    free = ~np.asarray(b.bc.mask)
    r = rng.standard_normal(free.shape) * free
    md = None if cycle == "W" else 1.0 + rng.random(free.shape[0])
    halo = pot_s.mesh.halo

    def M1(Ke, md, r):
        return preconditioner(one.hierarchy, Ke, md, jnp.asarray(free), cycle=cycle)(r)

    def Ms(sh, Ke, md, free, r):
        M = sharded_preconditioner(sh, halo, Ke, md, free, cycle=cycle)
        return M(r), M(2.0 * r)  # twice: the second application's collectives are its own

    ref = jax.jit(M1)(Ke, None if md is None else jnp.asarray(md), jnp.asarray(r))
    put = halo.sharding()
    args = (
        many.hierarchy,
        Ke_s,
        None if md is None else jax.device_put(part.to_padded(md, fill=0.0), put),
        ~bc_s.mask,
        jax.device_put(part.to_padded(r, fill=0.0), put),
    )
    compiled = jax.jit(Ms).lower(*args).compile()
    z, z2 = compiled(*args)
    assert _rel(part.to_natural(np.asarray(z)), ref) <= 1e-12
    assert _rel(part.to_natural(np.asarray(z2)), 2.0 * ref) <= 1e-12
    assert np.all(np.asarray(z)[~part.node_real] == 0.0)
    if cycle == "V":
        coll = _collectives(compiled.as_text())
        assert "all-gather" not in coll
        # fine level: ppermutes of interface rows only (at most d×d numbers per node of
        # the widest neighbour list), at least 2·degree products per application, each a
        # gather and a scatter_add over every shift
        widest = max(int(s.shape[-1]) for s in halo.send) * 3 * 3 * 8
        permutes = coll["collective-permute"]
        assert len(permutes) >= 2 * (2 * 4 * 2 * len(halo.shifts)) and max(permutes) <= widest
        # all-reduces: scalars, the level-1 matrix (per Newton step) and the level-1
        # vector (per application); never a fine-level (node-sized) one
        lv1 = many.hierarchy.coarse[0]
        coarse_matrix = lv1.n * lv1.w * 6 * 6 * 8
        assert max(coll["all-reduce"]) <= coarse_matrix + 64  # (+ scalars XLA combined)
        assert any(b in coll["all-reduce"] for b in (lv1.n * 6 * 8, 2 * lv1.n * 6 * 8))


@pytest.mark.slow  # 11-15 s
def test_cg_iterations_match_one_device(tw):
    """PCG on the linearised twist: the same iteration count on 4 shards as on one
    device, and the same solution to 1e-12."""
    b, pot_s, bc_s, part, Ke, Ke_s, one, many = tw
    free = ~np.asarray(b.bc.mask)
    rhs = np.random.default_rng(5).standard_normal(free.shape) * free

    def run(pot, h, Ke, free, rhs, halo=None):
        fm = free.astype(Ke.dtype)
        if halo is None:
            M = preconditioner(h, Ke, None, free)
        else:
            M = sharded_preconditioner(h, halo, Ke, None, free)

        def A(v):
            return fm * pm.element_hessian_vp(pot, Ke, fm * v) + (1 - fm) * v

        tol = 1e-10 * jnp.linalg.norm(rhs)
        return cg(A, rhs, lambda r: fm * M(r), tol=tol, max_iter=200)

    r1 = jax.jit(run)(b.pot, one.hierarchy, Ke, jnp.asarray(free), jnp.asarray(rhs))
    halo = pot_s.mesh.halo
    rhs_s = jax.device_put(part.to_padded(rhs, fill=0.0), halo.sharding())
    rs = jax.jit(lambda *a: run(*a, halo=halo))(pot_s, many.hierarchy, Ke_s, ~bc_s.mask, rhs_s)
    assert int(r1.status) == int(rs.status) == 0
    assert int(rs.stats["iterations"]) == int(r1.stats["iterations"]) > 3
    assert _rel(part.to_natural(np.asarray(rs.x)), r1.x) <= 1e-12


@pytest.mark.slow
def test_one_level_is_a_dense_solve():
    """A mesh of at most max_coarse dofs has one level: summed over the shards and
    factorised densely, M⁻¹ is the exact inverse, as on one device."""
    b = twist(3)
    pot_s, bc_s, part = je.shard(b.pot, b.bc, devices=S, method="sfc")
    sh = je.solvers.init_linear(je.Multilevel(), pot_s.mesh, bc_s)[1].hierarchy
    assert isinstance(sh, ShardedHierarchy) and sh.coarse == ()
    X = jnp.asarray(b.mesh.points)
    Ke = pm.elastic_element_hessians(b.pot, X + 0.03 * jnp.cos(2.0 * X), True)
    free = ~np.asarray(b.bc.mask)
    fm = free.astype(np.float64)
    r = np.random.default_rng(1).standard_normal(free.shape) * fm
    halo = pot_s.mesh.halo
    Ke_s = jax.device_put(part.to_padded(np.asarray(Ke), kind="cells", fill=0.0), halo.sharding())
    r_s = jax.device_put(part.to_padded(r, fill=0.0), halo.sharding())
    z = jax.jit(lambda Ke, f, r: sharded_preconditioner(sh, halo, Ke, None, f)(r))(
        Ke_s, ~bc_s.mask, r_s
    )
    z = part.to_natural(np.asarray(z)) * fm
    Az = fm * np.asarray(pm.element_hessian_vp(b.pot, Ke, jnp.asarray(z)))
    assert _rel(Az, r) <= 1e-10


def test_refusals(tw):
    b, pot_s, bc_s, _, _, _, one, _ = tw
    with pytest.raises(ValueError, match="smooth=True"):
        je.solvers.init_linear(je.Multilevel(smooth=True), pot_s.mesh, bc_s)
    with pytest.raises(ValueError, match="bound to a one-device mesh"):
        je.solve(pot_s, bc_s, solver=je.Newton(linear=ML), linear_state=one)


@pytest.mark.slow
def test_twist_solve_matches_one_device(tw):
    """je.solve of the twist on 4 shards with linear=Multilevel: the same Newton steps and
    CG iterations as on one device, the answer to 1e-12."""
    b, pot_s, bc_s, part, _, _, _, _ = tw
    newton = je.Newton(rtol=1e-10, linear=ML)
    ref = je.solve(b.pot, b.bc, solver=newton)
    res = je.solve(pot_s, bc_s, solver=newton)
    assert int(res.stats["steps"]) == int(ref.stats["steps"])
    assert int(res.stats["linear_iterations"]) == int(ref.stats["linear_iterations"])
    u = np.asarray(ref.x) - np.asarray(b.mesh.points)
    x = part.to_natural(np.asarray(res.x))
    assert np.max(np.abs(x - np.asarray(ref.x))) <= 1e-12 * np.max(np.abs(u))
