"""Self-contact: primitive distances, broad phase, additive CCD, the pair
barrier in Newton, and scenes that would self-intersect without contact.

The no-intersection checks of the solved shapes use a triangle–triangle intersection
test written here (segment–triangle crossings by signed volumes, as in Möller 1997, "A
fast triangle-triangle intersection test"), not the library's distance code.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic as je
from jaxelastic import contact as jc
from jaxelastic.contact import distance as D
from jaxelastic.contact.broadphase import candidate_pairs, surface_of
from jaxelastic.contact.ccd import additive_toi

RNG = np.random.default_rng(7)


def _rigid(pts, seed):
    """A fixed random rotation + translation of ``(k, 3)`` points."""
    r = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(r.normal(size=(3, 3)))
    return pts @ Q.T + r.normal(size=3)


# ------------------------------------------------------------------- independent references


def _seg_point(p, a, b):
    e = b - a
    t = np.clip(np.dot(p - a, e) / np.dot(e, e), 0, 1)
    return np.sum((p - a - t * e) ** 2)


def _ref_pt(p, t0, t1, t2):
    """Point–triangle squared distance: plane if the projection is inside, else sides."""
    n = np.cross(t1 - t0, t2 - t0)
    n = n / np.linalg.norm(n)
    q = p - np.dot(p - t0, n) * n
    M = np.stack([t1 - t0, t2 - t0], 1)
    uv = np.linalg.lstsq(M, q - t0, rcond=None)[0]
    if uv.min() >= 0 and uv.sum() <= 1:
        return float(np.dot(p - t0, n) ** 2)
    return min(_seg_point(p, t0, t1), _seg_point(p, t1, t2), _seg_point(p, t2, t0))


def _ref_ee(a0, a1, b0, b1):
    """Segment–segment squared distance: the convex quadratic's box minimum."""
    best = min(
        _seg_point(a0, b0, b1),
        _seg_point(a1, b0, b1),
        _seg_point(b0, a0, a1),
        _seg_point(b1, a0, a1),
    )
    A = np.stack([a1 - a0, -(b1 - b0)], 1)
    st = np.linalg.lstsq(A, b0 - a0, rcond=None)[0]
    if np.all((st > 0) & (st < 1)):
        best = min(best, float(np.sum((a0 + st[0] * (a1 - a0) - b0 - st[1] * (b1 - b0)) ** 2)))
    return best


# -------------------------------------------------------------------------- distances

_T = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
PT_CASES = {
    0: [-0.3, -0.2, 0.4],
    1: [1.3, -0.2, 0.3],
    2: [-0.2, 1.3, 0.3],
    3: [0.4, -0.3, 0.2],
    4: [0.7, 0.7, 0.3],
    5: [-0.3, 0.4, 0.2],
    6: [0.2, 0.3, 0.4],
}
_A = [[0.0, 0, 0], [1, 0, 0]]
EE_CASES = {
    0: _A + [[-0.3, -0.2, 0.3], [-0.3, -1.2, 0.3]],
    1: _A + [[-0.3, -1.2, 0.3], [-0.3, -0.2, 0.3]],
    2: _A + [[1.3, -0.2, 0.3], [1.3, -1.2, 0.3]],
    3: _A + [[1.3, -1.2, 0.3], [1.3, -0.2, 0.3]],
    4: _A + [[-0.3, -0.5, 0.3], [-0.3, 0.5, 0.4]],
    5: _A + [[1.3, -0.5, 0.3], [1.3, 0.5, 0.2]],
    6: _A + [[0.5, 0.2, 0.3], [0.6, 1.2, 0.3]],
    7: _A + [[0.6, 1.2, 0.3], [0.5, 0.2, 0.3]],
    8: _A + [[0.5, -0.5, 0.3], [0.4, 0.5, 0.35]],
}
PE2_CASES = {
    0: [[-0.3, 0.4], [0, 0], [1, 0.1]],
    1: [[1.4, 0.4], [0, 0], [1, 0.1]],
    2: [[0.5, 0.4], [0, 0], [1, 0.1]],
}


def _fd_check(f, x, h=1e-6, rtol_g=1e-6, rtol_h=1e-5):
    """Central differences of f's autodiff gradient and Hessian at x (flat). f, its gradient
    and its Hessian are each compiled once (evaluated op by op, the difference quotients
    took 2.7x the CPU time)."""
    f = jax.jit(f)
    gf = jax.jit(jax.grad(f))
    g = np.asarray(gf(x))
    H = np.asarray(jax.jit(jax.hessian(f))(x))
    e = np.eye(x.size)
    g_fd = np.array([(f(x + h * e[i]) - f(x - h * e[i])) / (2 * h) for i in range(x.size)])
    H_fd = np.stack([(gf(x + h * e[i]) - gf(x - h * e[i])) / (2 * h) for i in range(x.size)])
    assert np.allclose(g, g_fd, rtol=rtol_g, atol=rtol_g * np.abs(g).max()), (g, g_fd)
    assert np.allclose(H, H_fd, rtol=rtol_h, atol=rtol_h * np.abs(H).max()), np.abs(H - H_fd).max()
    return g, H


@pytest.mark.parametrize("case", sorted(PT_CASES))
def test_point_triangle_cases(case):
    pts = _rigid(np.vstack([PT_CASES[case], _T]), case)
    p, t0, t1, t2 = (jnp.asarray(v) for v in pts)
    assert int(D.point_triangle_case(p, t0, t1, t2)) == case
    d2 = float(D.point_triangle_d2(p, t0, t1, t2))
    assert d2 == pytest.approx(_ref_pt(*pts), rel=1e-12)
    _fd_check(lambda z: D.point_triangle_d2(*z.reshape(4, 3)), jnp.asarray(pts.ravel()))


@pytest.mark.parametrize("case", sorted(EE_CASES))
def test_edge_edge_cases(case):
    pts = _rigid(np.asarray(EE_CASES[case]), 10 + case)
    assert int(D.edge_edge_case(*jnp.asarray(pts))) == case
    d2 = float(D.edge_edge_d2(*jnp.asarray(pts)))
    assert d2 == pytest.approx(_ref_ee(*pts), rel=1e-12)
    _fd_check(lambda z: D.edge_edge_d2(*z.reshape(4, 3)), jnp.asarray(pts.ravel()))


@pytest.mark.parametrize("case", sorted(PE2_CASES))
def test_point_edge_2d_cases(case):
    pts = np.asarray(PE2_CASES[case], float)
    assert int(D.point_edge_case_2d(*jnp.asarray(pts))) == case
    d2 = float(D.point_edge_d2_2d(*jnp.asarray(pts)))
    assert d2 == pytest.approx(_seg_point(*pts), rel=1e-12)
    _fd_check(lambda z: D.point_edge_d2_2d(*z.reshape(3, 2)), jnp.asarray(pts.ravel()))


def test_random_pairs_match_references():
    for _ in range(200):
        x = RNG.normal(size=(4, 3))
        assert float(D.point_triangle_d2(*jnp.asarray(x))) == pytest.approx(
            _ref_pt(*x), rel=1e-9, abs=1e-14
        )
        assert float(D.edge_edge_d2(*jnp.asarray(x))) == pytest.approx(
            _ref_ee(*x), rel=1e-9, abs=1e-14
        )


def test_mollified_edge_edge_energy_near_parallel():
    """The mollified edge–edge barrier κ m(c) b(d): FD gradient and Hessian below and
    above ε_×, and m → 0 (energy → 0) for parallel edges; projected pair Hessians PSD."""
    dhat = 0.2
    base = np.array([[0.0, 0, 0], [1, 0, 0], [0.2, 0.0, 0.1], [0.8, 0.0, 0.1]])
    eps = float(D.mollifier_eps(*jnp.asarray(base)))
    for tilt, below in ((0.005, True), (0.3, False)):
        x = base.copy()
        x[3, 1:] += (0.5 * tilt, tilt)  # closest points b0 and a: away from case borders
        x = _rigid(x, 3)
        c = float(D.edge_cross2(*jnp.asarray(x)))
        assert (c < eps) == below

        def e(z):
            a0, a1, b0, b1 = z.reshape(4, 3)
            d = jnp.sqrt(D.edge_edge_d2(a0, a1, b0, b1))
            return D.edge_edge_mollifier(a0, a1, b0, b1, eps) * jc.barrier(d, dhat)

        z = jnp.asarray(x.ravel())
        assert 0 < float(e(z))
        _fd_check(e, z, h=1e-7, rtol_g=1e-6, rtol_h=2e-5)
    par = _rigid(base, 3)
    assert float(D.edge_edge_mollifier(*jnp.asarray(par), eps)) < 1e-20  # round-off of c = 0


# ------------------------------------------------------------------------ broad phase


def _brute_pairs(x, surf, r):
    def box(prims):
        p = x[prims]
        return p.min(1) - r / 2, p.max(1) + r / 2

    lp, hp = box(surf.nodes[:, None])
    lf, hf = box(surf.faces)
    ov = np.all((lp[:, None] <= hf[None]) & (lf[None] <= hp[:, None]), axis=2)
    ip, jf = np.nonzero(ov)
    P, F = surf.nodes[ip], surf.faces[jf]
    k = np.all(F != P[:, None], 1)
    pt = set(map(tuple, np.concatenate([P[k, None], F[k]], 1)))
    le, he = box(surf.edges)
    ov = np.all((le[:, None] <= he[None]) & (le[None] <= he[:, None]), axis=2)
    ia, ib = np.nonzero(np.triu(ov, 1))
    A, B = surf.edges[ia], surf.edges[ib]
    k = np.all(A[:, :, None] != B[:, None, :], axis=(1, 2))
    ee = set(map(tuple, np.concatenate([A[k], B[k]], 1)))
    return pt, ee


def test_broad_phase_matches_brute_force():
    mesh = je.box(5, 4, 3, size=(1.0, 0.8, 0.6))
    surf = surface_of(mesh)
    x = np.asarray(mesh.points) + 0.03 * RNG.normal(size=mesh.points.shape)
    for r in (0.05, 0.3):
        pt, ee = candidate_pairs(x, surf, r)
        ref_pt, ref_ee = _brute_pairs(x, surf, r)
        assert set(map(tuple, pt)) == ref_pt and len(pt) == len(ref_pt)
        assert set(map(tuple, ee)) == ref_ee and len(ee) == len(ref_ee)
    # every pair closer than r is a candidate (distance check on the complement)
    pt, ee = candidate_pairs(x, surf, 0.05)
    got = set(map(tuple, pt))
    for p in surf.nodes[:40]:
        for f in surf.faces:
            if p in f or (p, *f) in got:
                continue
            assert _ref_pt(x[p], *x[f]) >= 0.05**2


def test_broad_phase_2d():
    mesh = je.rectangle(6, 5)
    surf = surface_of(mesh)
    x = np.asarray(mesh.points)
    pt, ee = candidate_pairs(x, surf, 0.4)
    assert ee.shape == (0, 4) and pt.shape[1] == 3
    ref = set()
    for p in surf.nodes:
        for e in surf.edges:
            if p in e:
                continue
            lo = np.minimum(x[e].min(0), x[p]) - 0.2
            if np.all(np.maximum(x[e].max(0), x[p]) + 0.2 - lo >= 0):
                box_ok = np.all(
                    (x[p] - 0.2 <= x[e].max(0) + 0.2) & (x[e].min(0) - 0.2 <= x[p] + 0.2)
                )
                if box_ok:
                    ref.add((p, *e))
    assert set(map(tuple, pt)) == ref


def test_capacity_policy_grows_rarely():
    """Buffer capacities: kept while they fit, never shrunk, one power-of-2 level for both
    kinds with 2× headroom, at most the number of all possible pairs."""
    from jaxelastic.contact.broadphase import MIN_CAPACITY, capacity_for

    assert capacity_for((10, 10)) == MIN_CAPACITY == (1024, 2048)
    assert capacity_for((600, 2000), (1024, 2048)) == (1024, 2048)  # fits: kept
    assert capacity_for((1500, 100), (1024, 2048)) == (4096, 8192)  # 2 × 1500 → level 2
    assert capacity_for((1500, 100), (1024, 2048), bounds=(2000, 500)) == (2000, 500)
    assert capacity_for((10, 10), (4096, 8192)) == (4096, 8192)  # never shrinks
    assert capacity_for((5000, 10), (4096, 8192)) == (16384, 32768)


def test_strip_buffer_sized_once():
    """The ``fold`` strip (one element thick): the default motion bound stays below half
    the thickness, so opposite faces are not candidates at rest, and the buffer has room
    for a long step's candidates (the whole fold then runs on this shape)."""
    mesh = je.box(24, 2, 1, size=(1.0, 0.1, 0.02))
    sc = jc.make_self_contact(mesh, 1e-3)
    assert float(sc.base_margin) == pytest.approx(0.25 * 0.02)
    surf = surface_of(mesh)
    X = np.asarray(mesh.points)
    at_rest = tuple(map(len, candidate_pairs(X, surf, 1e-3 + 2 * float(sc.base_margin))))
    assert sc.counts == at_rest == (296, 828)
    long_step = tuple(map(len, candidate_pairs(X, surf, 1e-3 + 8 * float(sc.base_margin))))
    assert all(n <= c / 2 for n, c in zip(long_step, sc.capacity, strict=True))
    assert sc.capacity == (4096, 8192)
    again = sc.refreshed(mesh.points + 1e-3, 1e-3)  # fits: the same shape
    assert again.capacity == sc.capacity


# ------------------------------------------------------------------------------- CCD


def _crossing_times(x, p, kind):
    """Exact times τ ∈ [0, 1] at which the pair moving along x + τp meets (roots of the
    coplanarity cubic, then an inside test), numpy only."""

    def vol(t):
        y = x + t * p
        return np.linalg.det(np.stack([y[1] - y[0], y[2] - y[0], y[3] - y[0]]))

    ts = np.linspace(0, 1, 4)
    coef = np.polyfit(ts, [vol(t) for t in ts], 3)
    out = []
    for r in np.roots(coef):
        if abs(r.imag) > 1e-9 or not 0 <= r.real <= 1:
            continue
        t = r.real
        y = x + t * p
        if kind == "pt":
            ok = _ref_pt(*y) < 1e-16
        else:
            ok = _ref_ee(*y) < 1e-16
        if ok:
            out.append(t)
    return out


@pytest.mark.parametrize("kind", ["pt", "ee"])
def test_additive_ccd_never_crosses(kind):
    d2 = (lambda z: D.point_triangle_d2(*z)) if kind == "pt" else (lambda z: D.edge_edge_d2(*z))
    ref = _ref_pt if kind == "pt" else _ref_ee
    split = 1 if kind == "pt" else 2
    toi = jax.jit(jax.vmap(lambda x, p: additive_toi(d2, x, p, split)))
    xs = RNG.normal(size=(300, 4, 3))
    ps = 2.0 * RNG.normal(size=(300, 4, 3))
    taus = np.asarray(toi(jnp.asarray(xs), jnp.asarray(ps)))
    hits = 0
    for x, p, tau in zip(xs, ps, taus, strict=True):
        assert 0 <= tau <= 1
        cross = _crossing_times(x, p, kind)
        if cross:
            hits += 1
            assert tau < min(cross), (tau, cross)
        assert ref(*(x + tau * p)) > 0
    assert hits > 10  # the random motions do collide


# ---------------------------------------------------------------- Newton with pairs


def _two_blocks_3d(gap=0.05, n=3):
    a = je.box(n, n, n, size=(1.0, 1.0, 0.5))
    b = je.box(n, n, n, size=(1.0, 1.0, 0.5), origin=(0.3, 0.2, 0.5 + gap))
    P = np.concatenate([np.asarray(a.points), np.asarray(b.points)])
    C = np.concatenate([np.asarray(a.cells), np.asarray(b.cells) + a.points.shape[0]])
    return je.from_arrays(P, C)


def _pot(mesh, E=1e4):
    mu, lam = je.materials.lame(E, 0.3, dim=mesh.dim)
    return je.Potential(mesh, je.Lame(mu, lam), psi=je.materials.neo_hookean)


@pytest.mark.slow  # 32 s idle-ish, 120 s loaded (compiling the pair Hessians)
def test_pair_energy_derivatives_and_operator_split():
    mesh = _two_blocks_3d(gap=0.01)
    pot = jc.with_contact(_pot(mesh), self_contact=True, dhat=0.05, margin=0.02)
    c = pot.contact
    sc = c.self_contact
    assert sc.counts[0] > 0 and sc.counts[1] > 0
    energy = jax.jit(lambda c, x: c.energy(x))
    grad = jax.jit(lambda c, x: c.gradient(x))
    hvp = jax.jit(lambda c, x, v, exact: c.hvp(x, v, exact=exact), static_argnums=3)

    @jax.jit
    def split(c, x, v):
        blocks = c.self_contact.node_blocks(x, c.dhat, c.kappa)
        return jnp.einsum("nij,nj->ni", blocks, v) + c.coupling(x)(v)

    x = mesh.points + 0.002 * jnp.asarray(RNG.normal(size=mesh.points.shape))
    assert 0 < float(c.min_distance(x)) < float(c.dhat)
    assert float(energy(c, x)) > 0
    g = grad(c, x)
    v = jnp.asarray(RNG.normal(size=x.shape))
    h = 1e-7
    fd = (float(energy(c, x + h * v)) - float(energy(c, x - h * v))) / (2 * h)
    assert float(jnp.sum(g * v)) == pytest.approx(fd, rel=1e-6)
    Hv = hvp(c, x, v, True)
    fd = (grad(c, x + h * v) - grad(c, x - h * v)) / (2 * h)
    assert np.allclose(Hv, fd, rtol=1e-5, atol=1e-5 * float(jnp.abs(Hv).max()))
    # node-diagonal blocks + coupling operator = the whole (projected) pair HVP
    Hp = hvp(c, x, v, False)
    sv = split(c, x, v)
    assert np.allclose(sv, Hp, rtol=1e-12, atol=1e-12 * float(jnp.abs(sv).max()))
    assert float(jnp.sum(v * Hp)) >= 0  # projected: PSD
    f = jax.jit(lambda c, x: c.forces(x))(c, x)
    assert np.allclose(jnp.sum(f, axis=0), 0.0, atol=1e-9 * float(jnp.abs(g).max()))


def _press(mesh, depth):
    X = np.asarray(mesh.points)
    z = X[:, 2]
    bot, top = np.where(z < 1e-9)[0], np.where(z > z.max() - 1e-9)[0]
    vals = X.copy()
    vals[top, 2] -= depth
    mask = np.zeros_like(X, bool)
    mask[np.concatenate([bot, top])] = True
    return je.Dirichlet(mask=jnp.asarray(mask), values=jnp.asarray(vals))


@pytest.mark.slow  # 70 s (direct) and 230 s (cg) on a loaded 2-core machine
@pytest.mark.parametrize("linear", ["direct", "cg"])
def test_pressed_blocks_stay_apart(linear):
    """Two blocks of one mesh pressed together (the upper one's top moved down by more
    than the gap): without self-contact they overlap; with it the solve converges, every
    pair stays apart, and the contact force balances the reactions."""
    mesh = _two_blocks_3d(gap=0.05, n=2)
    bc = _press(mesh, 0.12)
    free = je.solve(_pot(mesh), bc, solver=je.Newton(linear=linear))
    assert _intersecting_pairs(mesh, np.asarray(free.x)) > 0
    pot = jc.with_contact(_pot(mesh), self_contact=True)
    res = je.solve_incremental(pot, bc, steps=2, solver=je.Newton(linear=linear))
    x = np.asarray(res.x)
    assert _intersecting_pairs(mesh, x) == 0
    c = pot.contact.refreshed(res.x, force=True)
    dmin = float(c.min_distance(res.x))
    print(f"min distance {dmin:.3e} m (d̂ = {float(c.dhat):.3e})")
    assert 0 < dmin < float(c.dhat)


# ---------------------------------------- independent triangle–triangle intersection test


def _orient(a, b, c, d):
    return np.einsum("...i,...i->...", np.cross(b - a, c - a), d - a)


def _segments_cross_triangles(p, q, a, b, c):
    """Whether segment pq properly crosses triangle abc (vectorised over leading axes)."""
    s1, s2 = _orient(a, b, c, p), _orient(a, b, c, q)
    o1, o2, o3 = _orient(p, q, a, b), _orient(p, q, b, c), _orient(p, q, c, a)
    straddle = s1 * s2 < 0
    inside = ((o1 > 0) & (o2 > 0) & (o3 > 0)) | ((o1 < 0) & (o2 < 0) & (o3 < 0))
    return straddle & inside


def _intersecting_pairs(mesh, x) -> int:
    """Number of boundary-triangle pairs (sharing no node) that intersect at x: a pair
    intersects iff an edge of one crosses the other (Möller 1997; non-degenerate)."""
    from jaxelastic.mesh import boundary_facets

    F = np.asarray(boundary_facets(mesh))[:, :3]
    T = x[F]  # (f, 3, 3)
    lo, hi = T.min(1), T.max(1)
    ov = np.all((lo[:, None] <= hi[None]) & (lo[None] <= hi[:, None]), axis=2)
    i, j = np.nonzero(np.triu(ov, 1))
    share = np.any(F[i][:, :, None] == F[j][:, None, :], axis=(1, 2))
    i, j = i[~share], j[~share]
    hit = np.zeros(len(i), bool)
    for A, B in ((i, j), (j, i)):
        for e0, e1 in ((0, 1), (1, 2), (2, 0)):
            hit |= _segments_cross_triangles(T[A, e0], T[A, e1], T[B, 0], T[B, 1], T[B, 2])
    return int(np.sum(hit))


def test_intersection_checker_sees_overlap():
    mesh = _two_blocks_3d(gap=0.05, n=2)
    X = np.asarray(mesh.points)
    assert _intersecting_pairs(mesh, X) == 0
    Y = X.copy()
    upper = X[:, 2] > 0.52
    Y[upper, 2] -= 0.1
    assert _intersecting_pairs(mesh, Y) > 0


@pytest.mark.slow  # 50–67 s on a shared 2-core machine (most of it compiling the contact)
def test_fold_scene_stays_intersection_free():
    """The shipped ``fold`` scene: the strip's ends are brought together until its legs
    meet. At every converged increment no boundary-triangle pair intersects (independent
    test) and the smallest pair distance is > 0; without self-contact the final shape
    self-intersects."""
    from jaxelastic.scene import build, load_scene
    from jaxelastic.scene.run import static_solve

    built = build(load_scene("fold"))
    mesh, c0 = built.mesh, built.potential.contact
    seen = []

    def check(s, sol):
        x = np.asarray(sol.x)
        c = c0.refreshed(x, force=True)
        seen.append((s, _intersecting_pairs(mesh, x), float(c.min_distance(sol.x))))

    x, _, sol = static_solve(built, callback=check)
    assert bool(sol.ok) and seen[-1][0] == 1.0
    print("fold (s, intersecting pairs, min distance):", seen)
    assert all(n == 0 and d > 0 for _, n, d in seen)
    assert min(d for *_, d in seen) < float(c0.dhat)  # the legs did meet
    free = built.potential.replace(contact=None, mass=None)
    y = je.solve_incremental(free, built.bc_fn(1.0), steps=10, path=built.bc_fn).x
    assert _intersecting_pairs(mesh, np.asarray(y)) > 0


TWIST_TURNS, TWIST_SHORTENING, TWIST_STEPS = 2.0, 0.86, 10


def _twisted_bar(n: int = 16):
    """A neo-Hookean bar (1 m × 6 cm × 6 cm, E = 1e5 Pa, ν = 0.3, 1000 kg/m³ under
    gravity; ``6·4n`` tets) clamped at x = 0, and the load path of its other end: turned
    ``TWIST_TURNS`` full turns about the bar's axis while moved back towards the clamp by
    ``TWIST_SHORTENING`` of the length (``s ↦`` Dirichlet data)."""
    L, a = 1.0, 0.06
    mesh = je.box(n, 2, 2, size=(L, a, a))
    X = np.asarray(mesh.points)
    end = X[:, 0] > L - 1e-9
    mask = np.zeros_like(X, bool)
    mask[(X[:, 0] < 1e-9) | end] = True
    axis = np.array([L, a / 2, a / 2])

    def path(s):
        th = s * TWIST_TURNS * 2 * np.pi
        R = np.array([[1, 0, 0], [0, np.cos(th), -np.sin(th)], [0, np.sin(th), np.cos(th)]])
        V = X.copy()
        V[end] = (X[end] - axis) @ R.T + axis - [s * TWIST_SHORTENING * L, 0.0, 0.0]
        return je.Dirichlet(mask=jnp.asarray(mask), values=jnp.asarray(V))

    g = je.loads.gravity_load(mesh, 1000.0, [0.0, 0.0, -9.81])
    mu, lam = je.materials.lame(1e5, 0.3)
    pot = je.Potential(mesh, je.Lame(mu, lam), psi=je.materials.neo_hookean, f_ext=jnp.asarray(g))
    return mesh, pot, path


@pytest.mark.slow  # 197 s on a loaded 2-core machine (~30 Newton steps per increment in contact)
def test_twisted_bar_stays_intersection_free():
    """The bar's end turns two full turns while it comes back to 0.14 m from the clamp:
    the bar buckles into a loop whose legs, next to the clamp, twist around each other.
    Without self-contact the legs pass through each other (independent
    triangle–triangle test); with it no boundary-triangle pair intersects at any
    converged increment and the smallest pair distance stays > 0 (and below d̂: the legs
    do touch)."""
    mesh, pot, path = _twisted_bar()
    free = je.solve_incremental(pot, path(1.0), steps=TWIST_STEPS, path=path)
    crossing = _intersecting_pairs(mesh, np.asarray(free.x))
    print(f"twisted bar without self-contact: {crossing} intersecting triangle pairs")
    assert crossing > 0
    pot = jc.with_contact(pot, self_contact=True)
    c0 = pot.contact
    seen = []

    def check(s, sol):
        x = np.asarray(sol.x)
        d = float(c0.refreshed(x, force=True).min_distance(sol.x))
        seen.append((s, _intersecting_pairs(mesh, x), d))

    newton = je.Newton(max_steps=200)  # the last increments press the legs together hard
    res = je.solve_incremental(
        pot, path(1.0), steps=TWIST_STEPS, path=path, solver=newton, callback=check
    )
    print("twisted bar (s, intersecting pairs, min distance):", seen)
    assert bool(res.ok) and seen[-1][0] == 1.0
    assert all(n == 0 and d > 0 for _, n, d in seen)
    assert min(d for *_, d in seen) < float(c0.dhat)
