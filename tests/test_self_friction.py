"""Self-contact friction: IPC's lagged smoothed Coulomb friction
between boundary primitive pairs (:mod:`jaxelastic.contact.pair_friction`).

Derivatives are checked against central differences per pair kind (3D point–triangle,
edge–edge, 2D point–edge); the closest-point weights against the library's distances and
an independent brute-force minimisation; the physics with two blocks of one mesh pressed
together and sheared quasi-statically: with μ large the upper one sticks (slip per load
step ≤ ε), with μ small it slides and the tangential reaction is μ × the normal one.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _common import TINY_SCENE

import jaxelastic as je
from jaxelastic import contact as jc
from jaxelastic.contact import distance as D
from jaxelastic.contact.pair_friction import (
    edge_edge_weights,
    lag_pair_friction,
    point_edge_weights_2d,
    point_triangle_weights,
)

RNG = np.random.default_rng(11)


def _self_contact(x, pt=(), ee=(), dim=3):
    """A :class:`SelfContact` holding the given candidate pairs (no broad phase)."""
    q = 4 if dim == 3 else 3
    i32 = jnp.int32
    pt = np.asarray(pt, np.int32).reshape(-1, q)
    ee = np.asarray(ee, np.int32).reshape(-1, 4)
    X = np.asarray(x)
    eps = [float(D.mollifier_eps(*jnp.asarray(X[e]))) for e in ee]
    n = X.shape[0]
    return jc.SelfContact(
        faces=jnp.zeros((0, 3), i32),
        edges=jnp.zeros((0, 2), i32),
        nodes=jnp.arange(n, dtype=i32),
        rest=jnp.asarray(X),
        pt=jnp.asarray(pt),
        pt_valid=jnp.ones(len(pt), bool),
        ee=jnp.asarray(ee),
        ee_valid=jnp.ones(len(ee), bool),
        ee_eps=jnp.asarray(eps, jnp.float64).reshape(-1),
        x_ref=jnp.asarray(X),
        margin=jnp.asarray(1.0),
        base_margin=jnp.asarray(1.0),
        dim=dim,
    )


def _rot3(seed):
    Q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return Q * np.sign(np.linalg.det(Q))


# two pairs of each kind, 0.02–0.04 m apart (d̂ = 0.05 m), plus an out-of-reach slot
def _pt_pairs():
    tri = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    pts = np.array([[0.2, 0.3, 0.03], [1.02, -0.01, 0.01], [0.3, 0.3, 0.5]])  # in, corner, far
    X = np.vstack([tri, pts]) @ _rot3(1).T
    return X, [[3, 0, 1, 2], [4, 0, 1, 2], [5, 0, 1, 2]], [], 3


def _ee_pairs():
    X = np.array(
        [[0.0, 0, 0], [1, 0, 0], [0.4, -0.5, 0.03], [0.5, 0.5, 0.03], [1.02, -0.05, -0.5],
         [1.02, 0.05, 0.5], [0.0, 0.0, 0.4], [1.0, 0.1, 0.4]]
    ) @ _rot3(2).T  # fmt: skip
    return X, [], [[0, 1, 2, 3], [0, 1, 4, 5], [0, 1, 6, 7]], 3


def _pe_pairs():
    X = np.array([[0.0, 0], [1, 0], [0.3, 0.03], [-0.02, 0.02], [0.5, 0.4]])
    return X, [[2, 0, 1], [3, 0, 1], [4, 0, 1]], [], 2


KINDS = {"point-triangle": _pt_pairs, "edge-edge": _ee_pairs, "point-edge-2d": _pe_pairs}
DHAT, KAPPA, MU = 0.05, 10.0, 0.4


def _lagged(kind):
    X, pt, ee, dim = KINDS[kind]()
    sc = _self_contact(X, pt, ee, dim)
    eps = 1e-3
    lag = lag_pair_friction(sc, jnp.asarray(X), DHAT, KAPPA, MU, eps)
    return jnp.asarray(X), sc, lag, eps


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_pair_friction_derivatives(kind):
    """Gradient and Hessian = central differences, with slips below and beyond ε; the
    node-diagonal blocks + the coupling operator = the whole Hessian; PSD."""
    X, sc, lag, eps = _lagged(kind)
    lam = np.asarray(lag.normal_force)
    assert np.all(lam[:2] > 0) and lam[2] == 0  # in reach / out of reach
    n, shape = X.size, X.shape
    E = jax.jit(jax.vmap(lambda lag, z: lag.energy(z.reshape(shape)), (None, 0)))
    G = jax.jit(jax.vmap(lambda lag, z: lag.gradient(z.reshape(shape)).ravel(), (None, 0)))
    HV = jax.jit(
        jax.vmap(lambda lag, x, v: lag.hvp(x, v.reshape(shape), project=False).ravel(),
                 (None, None, 0))
    )  # fmt: skip
    split = jax.jit(
        lambda lag, x, v: jnp.einsum("nij,nj->ni", lag.node_blocks(x), v) + lag.coupling(x)(v)
    )
    hvp = jax.jit(lambda lag, x, v: lag.hvp(x, v))
    e, h = np.eye(n), 1e-7
    for scale in (0.3 * eps, 5 * eps):  # mollified (stick) and sliding regimes
        x = X + scale * jnp.asarray(RNG.normal(size=shape))
        y = np.asarray(lag.slips(x))[:2]
        assert np.all(np.abs(y - eps) > 0.05 * eps), y  # clear of f₁'s kink at ε
        xr = x.ravel()[None]
        g = np.asarray(G(lag, xr))[0]
        g_fd = (np.asarray(E(lag, xr + h * e)) - np.asarray(E(lag, xr - h * e))) / (2 * h)
        assert np.allclose(g, g_fd, rtol=1e-6, atol=1e-6 * np.abs(g).max()), (g, g_fd)
        H = np.asarray(HV(lag, x, jnp.asarray(e))).T
        H_fd = (np.asarray(G(lag, xr + h * e)) - np.asarray(G(lag, xr - h * e))).T / (2 * h)
        assert np.allclose(H, H_fd, rtol=1e-5, atol=1e-5 * np.abs(H).max()), np.abs(H - H_fd).max()
        assert np.min(np.linalg.eigvalsh(0.5 * (H + H.T))) >= -1e-9 * np.abs(H).max()
        v = jnp.asarray(RNG.normal(size=shape))
        sv = split(lag, x, v)
        assert np.allclose(sv, hvp(lag, x, v), rtol=1e-12, atol=1e-12 * np.abs(H).max())


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_no_friction_force_without_tangential_motion(kind):
    """Zero force at the lag, after a rigid translation of a pair, and after normal motion;
    sliding far beyond ε gives the Coulomb force w·μλ on the pair's first node (weight w)."""
    X, sc, lag, eps = _lagged(kind)
    lam = np.asarray(lag.normal_force)
    scale = MU * lam.max()
    assert np.abs(np.asarray(lag.gradient(X))).max() <= 1e-14 * scale
    dim = X.shape[1]
    shift = jnp.asarray(RNG.normal(size=dim))
    assert np.abs(np.asarray(lag.gradient(X + shift[None]))).max() <= 1e-12 * scale
    # move the first pair's first node along its normal only
    k, a = 0, int(lag.pairs[0, 0])
    nrm = np.asarray(lag.z_lag[k]) / np.linalg.norm(np.asarray(lag.z_lag[k]))
    x = X.at[a].add(0.3 * DHAT * jnp.asarray(nrm))
    assert np.abs(np.asarray(lag.gradient(x))[a]).max() <= 1e-12 * scale
    t = np.asarray(lag.basis[k])[:, 0]
    x = X.at[a].add(100 * eps * jnp.asarray(t))
    f = np.asarray(lag.gradient(x))[a]
    w = abs(float(lag.weights[k, 0]))  # 1 but for edge–edge (1 − s); other pairs: 0 here
    assert np.linalg.norm(f) == pytest.approx(w * MU * lam[k], rel=1e-10)
    assert np.dot(f, t) > 0  # opposes the motion (f is the energy gradient)


def _brute_closest(A, B, n=41):
    """Closest points of two convex point sets' hulls, by sampling barycentric grids."""

    def bary(k):
        if k == 1:
            return np.ones((1, 1))
        g = np.linspace(0, 1, n)
        if k == 2:
            return np.stack([1 - g, g], 1)
        a, b = np.meshgrid(g, g)
        m = a + b <= 1
        return np.stack([1 - a[m] - b[m], a[m], b[m]], 1)

    pa, pb = bary(len(A)) @ A, bary(len(B)) @ B
    d = np.sqrt(((pa[:, None] - pb[None]) ** 2).sum(-1))
    return d.min()


def test_closest_point_weights_match_distances():
    """‖Σ w_i x_i‖ = the library's pair distance (every case of each kind), Σ w_i = 0,
    and ≈ an independent brute-force distance (barycentric sampling)."""
    for _ in range(60):
        P = RNG.normal(size=(4, 3))
        w = np.asarray(point_triangle_weights(*jnp.asarray(P)))
        z = w @ P
        assert abs(w.sum()) < 1e-12 and np.all(-w[1:] >= -1e-12)
        d2 = float(D.point_triangle_d2(*jnp.asarray(P)))
        assert np.dot(z, z) == pytest.approx(d2, rel=1e-9, abs=1e-14)
        assert np.sqrt(d2) <= _brute_closest(P[:1], P[1:]) + 1e-12
        assert np.sqrt(d2) >= _brute_closest(P[:1], P[1:]) - 0.05
        w = np.asarray(edge_edge_weights(*jnp.asarray(P)))
        z = w @ P
        assert abs(w.sum()) < 1e-12
        d2 = float(D.edge_edge_d2(*jnp.asarray(P)))
        assert np.dot(z, z) == pytest.approx(d2, rel=1e-9, abs=1e-14)
        assert np.sqrt(d2) <= _brute_closest(P[:2], P[2:]) + 1e-12
        Q = P[:3, :2]
        w = np.asarray(point_edge_weights_2d(*jnp.asarray(Q)))
        z = w @ Q
        assert np.dot(z, z) == pytest.approx(float(D.point_edge_d2_2d(*jnp.asarray(Q))), rel=1e-9)


# ------------------------------------------------------- two blocks pressed, then sheared


def _stacked(dim, gap):
    """One mesh: a lower block (clamped entirely) and a smaller upper block ``gap`` above
    it, offset so that their boundary nodes do not line up. Returns the mesh, the upper
    block's node mask, its top and bottom nodes."""
    if dim == 2:
        a = je.rectangle(4, 2, size=(1.0, 0.5))
        b = je.rectangle(3, 2, size=(0.5, 0.25), origin=(0.27, 0.5 + gap))
    else:
        a = je.box(2, 2, 1, size=(1.0, 1.0, 0.5))
        b = je.box(2, 2, 1, size=(0.5, 0.5, 0.25), origin=(0.27, 0.23, 0.5 + gap))
    na = a.points.shape[0]
    P = np.concatenate([np.asarray(a.points), np.asarray(b.points)])
    C = np.concatenate([np.asarray(a.cells), np.asarray(b.cells) + na])
    mesh = je.from_arrays(P, C)
    upper = np.arange(P.shape[0]) >= na
    z = P[:, -1]
    top = np.where(upper & (z > z.max() - 1e-9))[0]
    bottom = np.where(upper & (z < 0.5 + gap + 1e-9))[0]
    return mesh, upper, top, bottom


def _press_and_shear(dim, mu, press=0.03, shear=0.02, gap=0.01, steps=4):
    """Quasi-static: the upper block's top moved down by ``press`` (load factor s ≤ ½),
    then sideways by ``shear`` (s > ½), friction lagged at every load step. Returns the
    tangential and normal reactions on the top, the upper block's bottom slip during the
    shear phase (x-displacement; the lower block does not move) and the contact."""
    mesh, upper, top, bottom = _stacked(dim, gap)
    X = np.asarray(mesh.points)
    mask = np.zeros_like(X, bool)
    mask[~upper] = True
    mask[top] = True
    mask = jnp.asarray(mask)

    def path(s):
        v = X.copy()
        v[top, -1] -= press * min(2 * s, 1.0)
        v[top, 0] += shear * max(2 * s - 1, 0.0)
        return je.Dirichlet(mask=mask, values=jnp.asarray(v))

    E, nu = 1e4, 0.3
    lmu, lam = je.materials.lame(E, nu, dim=dim)
    pot = je.Potential(mesh, je.Lame(lmu, lam), psi=je.materials.neo_hookean)
    pot = jc.with_contact(pot, self_contact=True, self_friction=mu)
    xs = {}

    def cb(s, sol):
        xs[s] = np.asarray(sol.x)

    res = je.solve_incremental(pot, path(1.0), steps=steps, path=path, callback=cb)
    x = np.asarray(res.x)
    s_half = max(s for s in xs if s <= 0.5 + 1e-12)
    slip = x[bottom, 0] - xs[s_half][bottom, 0]
    top_mask = np.zeros_like(X, bool)
    top_mask[top] = True
    bc_top = je.Dirichlet(mask=jnp.asarray(top_mask), values=jnp.asarray(x))
    R = np.asarray(je.postprocess.reaction_force(pot.psi, res.x, mesh, pot.params, bc_top))
    increments = [r["s"] for r in res.stats["increments"] if r["accepted"]]
    return dict(Ft=abs(R[0]), Fn=abs(R[-1]), slip=slip, contact=pot.contact, res=res,
                increments=increments, x=x)  # fmt: skip


@pytest.mark.slow  # 2D 30–55 s, 3D 57–150 s on a loaded 2-core machine (compiles)
@pytest.mark.parametrize("dim, rel", [(2, 0.02), (3, 0.03)])
def test_blocks_stick_or_slide(dim, rel):
    """Two blocks of one mesh pressed together (top moved down 0.03 m, 0.02 m past the
    gap) then sheared by 0.02 m in 2 load steps: needs |F_t|/|F_n| ≈ 0.27 to stick (2D:
    point–edge pairs; 3D: point–triangle and edge–edge). μ = 1: sticks, slip ≤ ε per load
    step; μ = 0.1: slides, |F_t| = μ|F_n| within ``rel`` (measured −0.1 % in 2D, +1.0 %
    in 3D)."""
    out = {}
    for mu in (0.1, 1.0):
        r = _press_and_shear(dim, mu)
        eps = float(r["contact"].self_friction.eps)
        ratio = r["Ft"] / r["Fn"]
        out[mu] = ratio
        slip = np.max(np.abs(r["slip"]))
        print(f"{dim}D μ = {mu}: F_t/F_n = {ratio:.4f}, max slip in the shear phase "
              f"{slip:.2e} m (ε = {eps:.2e} m)")  # fmt: skip
        if dim == 2:
            assert r["increments"] == [0.25, 0.5, 0.75, 1.0]
        x = jnp.asarray(r["x"])
        assert float(r["contact"].refreshed(x, force=True).min_distance(x)) > 0
        if mu == 1.0:
            assert slip <= 2 * eps, (slip, eps)  # 2 shear steps
            assert ratio < 0.5
        else:
            assert np.min(r["slip"]) > 100 * eps  # every bottom node slides forward
            assert ratio == pytest.approx(mu, rel=rel)
    assert out[1.0] > 2 * out[0.1]


@pytest.mark.extended
def test_contact_hook_and_refresh():
    """``Contact`` carries the pair friction: energy, gradient, forces and the Hessian
    split (node blocks in Ke + coupling) include it; a broad phase re-run keeps the lagged
    pairs; ``make_contact`` checks that self-contact is on."""
    mesh, upper, _, _ = _stacked(2, 0.01)
    lmu, lam = je.materials.lame(1e4, 0.3, dim=2)
    pot = je.Potential(mesh, je.Lame(lmu, lam), psi=je.materials.neo_hookean)
    ground = jc.HalfSpace(jnp.array([0.0, -1.0]), jnp.array([0.0, 1.0]))
    with pytest.raises(ValueError, match="needs self_contact=True"):
        jc.make_contact(pot, [ground], kappa=1.0, self_friction=0.3)
    pot = jc.with_contact(pot, self_contact=True, self_friction=0.5)
    c = pot.contact
    X = mesh.points
    x = X.at[:, 1].add(jnp.where(jnp.asarray(upper), -0.01 + 0.4 * c.dhat, 0.0))
    c = c.refreshed(x, force=True)
    lagged = jax.jit(lambda c, x: c.lag(x))(c, x)
    sf = lagged.self_friction
    assert float(jnp.sum(sf.normal_force > 0)) >= 3 and float(sf.mu) == 0.5
    assert lagged.friction is None  # no obstacle friction switched on
    # pairs survive a new broad phase
    again = lagged.refreshed(x + 1e-3, force=True)
    assert again.self_friction is sf
    y = x.at[:, 0].add(jnp.where(jnp.asarray(upper), 0.5 * float(sf.eps), 0.0))  # stuck
    v = jnp.asarray(RNG.normal(size=x.shape))
    k = mesh.cells.shape[1] * 2
    Ke0 = jnp.zeros((mesh.cells.shape[0], k, k))

    @jax.jit
    def with_minus_without(c, y, v):
        """(Contact with the pair friction) − (without it), and the friction's own."""
        fr = c.self_friction
        c0 = c.replace(self_friction=None)
        both = [
            (c.energy(y), c0.energy(y), fr.energy(y)),
            (c.forces(y), c0.forces(y), -fr.gradient(y)),
            (c.hvp(y, v), c0.hvp(y, v), fr.hvp(y, v)),
            (c.coupling(y)(v), c0.coupling(y)(v), fr.coupling(y)(v)),
            (
                c.add_hessian_blocks(Ke0, mesh, y),
                c0.add_hessian_blocks(Ke0, mesh, y),
                jnp.sum(fr.node_blocks(y)),
            ),
        ]
        return [(a - b, f, jnp.max(jnp.abs(a))) for a, b, f in both]

    out = with_minus_without(lagged, y, v)
    (dE, E_f, _), (df, f_f, sf_), (dHv, Hv_f, sH), (dC, C_f, sC), (dK, K_f, _) = out
    assert float(dE) == pytest.approx(float(E_f), rel=1e-10) and float(dE) > 0
    f = np.asarray(df)
    assert np.allclose(f, f_f, atol=1e-12 * float(sf_))
    assert abs(f[:, 0].sum()) <= 1e-9 * np.abs(f).max()  # action = reaction
    assert np.all(f[upper, 0] <= 1e-12 * np.abs(f).max())  # opposes the upper block's slide
    assert np.min(f[upper, 0]) < 0
    assert float(jnp.abs(Hv_f).max()) > 1e-6 * float(sH)  # the friction Hessian counts
    assert np.allclose(dHv, Hv_f, atol=1e-12 * float(sH))
    assert np.allclose(dC, C_f, atol=1e-12 * float(sC))
    assert float(jnp.sum(dK)) == pytest.approx(float(K_f), rel=1e-10)  # node blocks in Ke


def test_scene_self_friction():
    """``[contact] self_friction`` builds the pair friction (and needs ``self = true``)."""
    from jaxelastic.scene import SceneError, build, load_scene

    tiny = dict(TINY_SCENE, contact={"self": True, "self_friction": 0.3})
    assert float(build(load_scene(tiny)).potential.contact.self_friction.mu) == 0.3
    tiny["obstacle"] = [{"plane": {"point": [0.0, -1.0], "normal": [0.0, 1.0]}}]
    tiny["contact"] = {"self_friction": 0.3}
    with pytest.raises(SceneError, match="self_friction needs self"):
        build(load_scene(tiny))


def _slide_2d(mu, v0=0.5, n_steps=12, h=0.01):
    """Backward Euler: a small block of the mesh launched at ``v0`` [m/s] along the top of
    a clamped block of the same mesh, under gravity. Returns the times, the small block's
    mean x-position and the expected deceleration μg."""
    dhat = 1e-3
    a = je.rectangle(4, 1, size=(1.0, 0.2))
    b = je.rectangle(2, 1, size=(0.2, 0.1), origin=(0.13, 0.2 + 0.88 * dhat))  # ≈ the resting gap
    na = a.points.shape[0]
    P = np.concatenate([np.asarray(a.points), np.asarray(b.points)])
    C = np.concatenate([np.asarray(a.cells), np.asarray(b.cells) + na])
    mesh = je.from_arrays(P, C)
    upper = np.arange(P.shape[0]) >= na
    rho, g = 1000.0, 9.81
    lmu, lam = je.materials.lame(1e6, 0.3, dim=2)
    mass = jnp.asarray(je.loads.lumped_mass(mesh, rho))
    f = jnp.asarray(je.loads.gravity_load(mesh, rho, [0.0, -g]))
    pot = je.Potential(mesh, je.Lame(lmu, lam), f_ext=f, mass=mass, psi=je.materials.neo_hookean)
    pot = jc.with_contact(pot, self_contact=True, self_friction=mu, dhat=dhat)
    mask = np.zeros_like(P, bool)
    mask[~upper] = True
    bc = je.Dirichlet(mask=jnp.asarray(mask), values=jnp.asarray(P))
    v = np.zeros_like(P)
    v[upper, 0] = v0
    ts, s = [], []

    def cb(state, sol, rec):
        ts.append(rec["t"])
        s.append(float(np.mean(np.asarray(state.x)[upper, 0])))

    je.dynamics.simulate(
        pot, je.dynamics.init_state(mesh.points, jnp.asarray(v)), bc, je.Integrator(h=h),
        n_steps, callback=cb, progress=False,
    )  # fmt: skip
    return np.array(ts), np.array(s) - float(np.mean(P[upper, 0])), mu * g


@pytest.mark.slow  # 22 s on a loaded 2-core machine
def test_dynamics_2d_slide_decelerates_at_mu_g():
    """Backward Euler with self-contact friction (lagged at every time step): the launched
    block decelerates at μg (fit of x(t) after the landing transient) within 3 %."""
    t, s, a_exact = _slide_2d(0.3)
    late = t > 0.03
    a_fit = -2 * np.polyfit(t[late], s[late], 2)[0]
    print(f"2D slide, μ = 0.3: deceleration {a_fit:.4f} m/s² (μg = {a_exact:.4f})")
    assert a_fit == pytest.approx(a_exact, rel=0.03)
