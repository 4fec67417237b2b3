"""One mesh sharded over 4 host CPU devices (tests/conftest.py sets
``--xla_force_host_platform_device_count=4``): partition, halo exchange, kernels, solves,
dynamics and gradients against one device."""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.sharding import PartitionSpec as P

import jaxelastic as je
from jaxelastic import dynamics, loads
from jaxelastic.materials import Lame
from jaxelastic.mechanics import potential as pm
from jaxelastic.parallel.partition import partition_mesh
from jaxelastic.verification.torsion import twist

S = 4

pytestmark = pytest.mark.skipif(
    len(jax.devices()) < S,
    reason="needs 4 devices: XLA_FLAGS=--xla_force_host_platform_device_count=4 before jax",
)


def _rel(a, b) -> float:
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


@pytest.fixture(scope="module")
def tw():
    """Twist n = 3 (162 tets: not divisible by 4; 64 nodes) under a body force (so that x*
    depends on E), sharded by METIS."""
    b = twist(3)
    g = loads.gravity_load(b.pot.mesh, 1.0, (0.0, 0.0, -0.5))
    b = dataclasses.replace(b, pot=b.pot.replace(f_ext=jnp.asarray(g)))
    pot_s, bc_s, part = je.shard(b.pot, b.bc, devices=S, method="metis")
    return b, pot_s, bc_s, part


def _state(mesh, seed=0):
    rng = np.random.default_rng(seed)
    X = np.asarray(mesh.points)
    x = X + 0.02 * rng.standard_normal(X.shape)
    v = rng.standard_normal(X.shape)
    return jnp.asarray(x), jnp.asarray(v)


@pytest.mark.parametrize("method", ["metis", "sfc"])
def test_partition_stats(method):
    mesh = je.box(4, 3, 3)
    cells = np.asarray(mesh.cells)
    part = partition_mesh(np.asarray(mesh.points), cells, S, method)
    st = part.stats()
    assert st["method"] == method and st["shards"] == S
    assert sum(st["cells"]) == mesh.n_cells and max(st["cells"]) == part.c_loc
    assert sum(st["owned_nodes"]) == mesh.n_nodes and max(st["owned_nodes"]) == part.n_own
    assert min(st["cells"]) > 0
    # ghosts: Σ over nodes of (parts touching it − 1), whoever owns them
    k = cells.shape[1]
    pairs = np.unique(cells.ravel() * S + np.repeat(part.cell_part, k))
    assert sum(st["ghost_nodes"]) == pairs.size - mesh.n_nodes
    assert 0 < st["halo_bytes_total"] < S * st["replicated_bytes"]
    # every node is owned by a shard one of its cells lives on
    for c in range(mesh.n_cells):
        assert all(part.node_owner[cells[c]] >= 0)
    owner_ok = np.zeros(mesh.n_nodes, bool)
    for c in range(mesh.n_cells):
        owner_ok[cells[c]] |= part.node_owner[cells[c]] == part.cell_part[c]
    assert owner_ok.all()
    a = np.arange(mesh.n_nodes * 3.0).reshape(-1, 3)
    np.testing.assert_array_equal(part.to_natural(part.to_padded(a)), a)
    c = np.arange(float(mesh.n_cells))
    np.testing.assert_array_equal(part.to_natural(part.to_padded(c, kind="cells"), kind="cells"), c)


def test_halo_gather_scatter_against_dense(tw):
    _, pot_s, _, part = tw
    h = pot_s.mesh.halo
    n_loc = h.n_local
    rng = np.random.default_rng(1)
    x = rng.standard_normal((part.n_padded_nodes, 3))
    f_loc = rng.standard_normal((S * n_loc, 3))
    row = h.sharding()

    @jax.jit
    def both(h, x, f):
        fn = lambda hl, xb, fb: (hl.gather(xb), hl.scatter_add(fb))
        return h.map(fn, x, f, out_specs=P(h.axis))

    got, back = both(h, jax.device_put(x, row), jax.device_put(f_loc, row))
    got, back = np.asarray(got).reshape(S, n_loc, 3), np.asarray(back)
    ref_back = np.zeros_like(x)
    for s in range(S):
        g = part.ghosts[s]
        glob = np.concatenate([np.arange(s * part.n_own, (s + 1) * part.n_own), g])
        np.testing.assert_array_equal(got[s, : glob.size], x[glob])
        np.add.at(ref_back, glob, f_loc[s * n_loc : s * n_loc + glob.size])
    np.testing.assert_allclose(back, ref_back, rtol=1e-14, atol=1e-14)
    # the local cells are the global cells in local numbering
    lc = np.asarray(h.local_cells)
    for s in range(S):
        glob = np.concatenate([np.arange(s * part.n_own, (s + 1) * part.n_own), part.ghosts[s]])
        blk = slice(s * part.c_loc, (s + 1) * part.c_loc)
        real = part.cell_real[blk]
        np.testing.assert_array_equal(glob[lc[s][real]], part.padded_cells[blk][real])


@jax.jit
def _kernels(pot, x, v):
    psi, mesh, p = pot.psi, pot.mesh, pot.params
    Ke = je.mechanics.element_hessians(psi, x, mesh, p)
    return dict(
        energy=je.energy(psi, x, mesh, p),
        forces=je.forces(psi, x, mesh, p),
        hvp=je.mechanics.hvp(psi, x, v, mesh, p),
        Ke=Ke,
        blocks=pm.node_hessian_blocks(pot, Ke),
        ehvp=pm.element_hessian_vp(pot, Ke, v),
        grad=jax.grad(lambda y: je.energy(psi, y, mesh, p))(x),
    )


_MESHES = {
    # 2·3·5 = 30 triangles (not divisible by 4), per-cell μ
    "tri3": lambda: je.rectangle(3, 5),
    # composite F-bar: zero-weight padded cells must give exactly nothing
    "tri3x4-fbar": lambda: je.rectangle(3, 3, formulation="fbar"),
    "tet4x8-fbar": lambda: je.box(2, 2, 1, formulation="fbar"),
    "tri6": lambda: je.rectangle(3, 3, order=2),
}
_SLOW = ("tri3", "tet4x8-fbar", "tri6")


@pytest.mark.extended
@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.slow) if n in _SLOW else n for n in _MESHES]
)
def test_kernels_match_one_device(name):
    mesh = _MESHES[name]()
    rng = np.random.default_rng(2)
    mu = jnp.asarray(1.0 + rng.random(mesh.n_cells))
    pot = je.Potential(mesh=mesh, params=Lame(mu, 3.0), psi=je.materials.neo_hookean)
    bc = loads.fix(mesh, loads.nodes_on_plane(mesh, 0, 0.0))
    assert mesh.n_cells % S != 0 or name != "tri3"
    pot_s, _, part = je.shard(pot, bc, devices=S, method="sfc" if name == "tri6" else "auto")
    x, v = _state(mesh)
    ref = _kernels(pot, x, v)
    got = _kernels(pot_s, part.to_padded(x), part.to_padded(v))
    for key, r in ref.items():
        g = got[key]
        if key != "energy":
            g = part.to_natural(g, kind="cells" if key == "Ke" else "nodes")
        assert _rel(g, r) < 1e-13, key
    # padding contributes nothing, exactly
    pad = ~part.node_real
    assert np.all(np.asarray(got["forces"])[pad] == 0)
    assert np.all(np.asarray(got["Ke"])[~part.cell_real] == 0)


def test_kernels_exchange_interface_only(tw):
    """The compiled HVP moves only ghost rows (collective-permutes), no all-reduce or
    all-gather of node vectors."""
    b, pot_s, _, part = tw
    x, v = pot_s.mesh.points, pot_s.mesh.points
    f = jax.jit(lambda x, v: je.mechanics.hvp(b.pot.psi, x, v, pot_s.mesh, pot_s.params))
    hlo = f.lower(x, v).compile().as_text()
    assert "collective-permute" in hlo
    assert "all-gather" not in hlo and "all-reduce" not in hlo


_SOLVER = je.Newton(linear="cg", rtol=1e-10)


@pytest.mark.extended
def test_solve_matches_one_device(tw):
    """Newton-CG (block Jacobi) on 4 shards gives the one-device answer."""
    b, pot_s, bc_s, part = tw
    r1 = je.solve(b.pot, b.bc, solver=_SOLVER)
    r2 = je.solve(pot_s, bc_s, solver=_SOLVER)
    X = np.asarray(b.pot.mesh.points)
    x1, x2 = np.asarray(r1.x), np.asarray(part.to_natural(r2.x))
    assert int(r1.stats["steps"]) == int(r2.stats["steps"])
    assert np.linalg.norm(x2 - x1) <= 1e-12 * np.linalg.norm(x1 - X)


@pytest.mark.slow
def test_solve_jacobi_matches_one_device(tw):
    b, pot_s, bc_s, part = tw
    solver = je.Newton(linear=je.CG(preconditioner="jacobi"), rtol=1e-10)
    r1 = je.solve(b.pot, b.bc, solver=solver)
    r2 = je.solve(pot_s, bc_s, solver=solver)
    X = np.asarray(b.pot.mesh.points)
    x1, x2 = np.asarray(r1.x), np.asarray(part.to_natural(r2.x))
    assert np.linalg.norm(x2 - x1) <= 1e-12 * np.linalg.norm(x1 - X)


def _loss_and_grad(pot, bc, to_nat, to_pad_cells, w):
    solver = _SOLVER

    def loss(E, field):
        mu, lam = je.materials.lame(E, 0.3)
        p = Lame(mu * to_pad_cells(field), lam)
        x = je.solve(pot.replace(params=p), bc, solver=solver).x
        return jnp.sum(w * to_nat(x)), x

    return jax.jit(jax.value_and_grad(loss, argnums=(0, 1), has_aux=True))


@pytest.mark.extended
def test_gradient_matches_one_device(tw):
    """Newton-CG solve and its implicit gradient w.r.t. E and a per-cell field."""
    b, pot_s, bc_s, part = tw
    n_cells = b.pot.mesh.n_cells
    w = jnp.asarray(np.random.default_rng(3).standard_normal((b.pot.mesh.n_nodes, 3)))
    field = jnp.ones(n_cells) + 0.1 * jnp.sin(jnp.arange(n_cells))
    ident = lambda a: a
    (l1, x1), (gE1, gf1) = _loss_and_grad(b.pot, b.bc, ident, ident, w)(10.0, field)
    fs = _loss_and_grad(pot_s, bc_s, part.to_natural, lambda f: part.to_padded(f, "cells"), w)
    (l2, x2), (gE2, gf2) = fs(10.0, field)
    X = np.asarray(b.pot.mesh.points)
    x2n = np.asarray(part.to_natural(x2))
    assert np.linalg.norm(x2n - x1) <= 1e-12 * np.linalg.norm(x1 - X)
    assert abs(l2 - l1) <= 1e-12 * abs(l1)
    assert abs(gE2 - gE1) <= 1e-12 * abs(gE1)
    assert np.linalg.norm(gf2 - gf1) <= 1e-12 * np.linalg.norm(gf1)


@pytest.mark.slow  # 13-17 s
def test_dynamic_step_matches_one_device():
    mesh = je.box(3, 2, 2)  # 72 tets: 18 per shard
    mass = jnp.asarray(loads.lumped_mass(mesh, 1.0))
    g = jnp.asarray(loads.gravity_load(mesh, 1.0, (0.0, 0.0, -9.81)))
    mu, lam = je.materials.lame(50.0, 0.3)
    pot = je.Potential(
        mesh=mesh, params=Lame(mu, lam), f_ext=g, mass=mass, psi=je.materials.neo_hookean
    )
    bc = loads.fix(mesh, loads.nodes_on_plane(mesh, 0, 0.0))
    integ = je.Integrator(h=0.01)
    solver = je.Newton(linear="cg")
    st1, r1 = dynamics.step(pot, dynamics.init_state(mesh.points), bc, integ, solver=solver)
    pot_s, bc_s, part = je.shard(pot, bc, devices=S)
    st2, r2 = dynamics.step(
        pot_s, dynamics.init_state(pot_s.mesh.points), bc_s, integ, solver=solver
    )
    assert int(r1.status) == int(r2.status) == 0
    X = np.asarray(mesh.points)
    for a, b in ((st2.x, st1.x), (st2.v, st1.v)):
        an = np.asarray(part.to_natural(a))
        assert np.linalg.norm(an - b) <= 1e-12 * np.linalg.norm(np.asarray(st1.x) - X) * (
            1 if a is st2.x else 1 / integ.h
        )


def test_host_solvers_refuse_quickly(tw):
    _, pot_s, bc_s, _ = tw
    for linear in ("direct", "amg", je.Direct(), je.AMG()):
        t = time.perf_counter()
        with pytest.raises(ValueError, match="multilevel.*cg"):
            je.solve(pot_s, bc_s, solver=je.Newton(linear=linear))
        assert time.perf_counter() - t < 1.0
    # the XLA layout without a halo is refused too
    plain = pot_s.replace(mesh=dataclasses.replace(pot_s.mesh, halo=None))
    with pytest.raises(ValueError, match="multilevel"):
        je.solvers.linear.resolve("direct", plain.mesh, bc_s)
    assert not isinstance(je.solvers.linear.resolve("auto", pot_s.mesh, bc_s), je.Direct)


def test_shard_errors(tw):
    b = tw[0]
    with pytest.raises(ValueError, match="xla_force_host_platform_device_count"):
        je.shard(b.pot, b.bc, devices=len(jax.devices()) + 1)
    with pytest.raises(ValueError, match="already sharded"):
        je.shard(tw[1], tw[2], devices=S)
    with pytest.raises(ValueError, match="method"):
        je.shard(b.pot, b.bc, devices=S, method="random")


def test_free_body_still_refused_when_sharded(tw):
    """Padded nodes are Dirichlet-fixed, but they must not hide free rigid motions."""
    b = tw[0]
    pot_s, bc_s, _ = je.shard(b.pot, loads.no_dirichlet(b.pot.mesh), devices=S)
    with pytest.raises(ValueError, match="rigid-body motion"):
        je.solve(pot_s, bc_s, solver=je.Newton(linear="cg"))


def test_sharded_programs_call_no_batched_lapack(tw):
    """jaxlib 0.10's batched LAPACK kernels can deadlock a program on several XLA:CPU
    devices (seen: twist n = 29 hung in dsyevd / dgetrf). The sharded projected element
    Hessians and the sharded block-Jacobi preconditioner must compile to no LAPACK custom
    call with a batch; the unsharded block-Jacobi keeps LAPACK (bit-identical everywhere)."""
    from jaxelastic.solvers.linear import block_jacobi

    _, pot_s, bc_s, _ = tw
    x = pot_s.mesh.points

    def precond(x):
        Ke = pm.elastic_element_hessians(pot_s, x, project=True)
        blocks = pm.node_hessian_blocks(pot_s, Ke)
        return block_jacobi(blocks, ~bc_s.mask, lapack=False)(x)

    hlo = jax.jit(precond).lower(x).compile().as_text()
    calls = [ln for ln in hlo.splitlines() if 'custom_call_target="lapack' in ln]
    # only batch-of-one calls (inside the per-matrix lax.map) may remain
    assert all("[1,12,12]" in ln or "[12,12]" in ln for ln in calls), calls[:3]
    blocks = jnp.eye(3)[None].repeat(5, 0)
    plain = jax.jit(lambda b: block_jacobi(b, jnp.ones((5, 3), bool))(jnp.ones((5, 3))))
    assert "lapack" in plain.lower(blocks).compile().as_text()


def test_spd_block_inverse_matches_lapack_and_flags_indefinite_blocks():
    from jaxelastic.solvers.blocks import spd_block_inverse

    rng = np.random.default_rng(0)
    for b in (2, 3, 6):
        A = rng.normal(size=(40, b, b))
        B = A @ A.transpose(0, 2, 1) + 0.1 * np.eye(b)
        B[3] = -B[3]
        B[7, 0, 0] = np.nan
        inv, ok = spd_block_inverse(jnp.asarray(B))
        ok = np.asarray(ok)
        assert not ok[3] and not ok[7] and ok.sum() == 38
        assert _rel(np.asarray(inv)[ok], np.linalg.inv(B[ok])) < 1e-12
