"""Newton solver: patch tests, closed-form nonlinear solutions, convergence rate, statuses.

Every distinct (ψ, settings, mesh shape, potential structure, linear solver) compiles the
Newton loop — and ``solve``'s default ``linear="auto"`` solver is keyed on the Dirichlet
mask too — so the tests share a few meshes (``rectangle(4, 4)``, ``box(3, 2, 2)``), a few
boundary-condition sets, one material parameter set (Python floats: weak-typed, so new
values never recompile) and two Newton objects. Tests about the matrix-free path pass
``linear="cg"`` (or call :func:`jaxelastic.solve` under jit on a traced mesh, where
``"auto"`` is CG).
"""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

import jaxelastic as je
from jaxelastic import CG, Newton, SolveError, Status, postprocess, solve
from jaxelastic import loads as L
from jaxelastic import materials as M
from jaxelastic.mechanics.kinematics import deformation_gradients

E_MOD, NU = 1.0e4, 0.3
MU, LAM = (float(v) for v in M.lame(E_MOD, NU))
PARAMS = M.Lame(MU, LAM)
DEFAULT = Newton()
# exact element Hessians, no preconditioner, tight tolerance: used wherever the answer is
# compared with an exact one (and for the quadratic-convergence test)
TIGHT = Newton(rtol=1e-12)
TIGHT_CG = Newton(rtol=1e-12, linear=CG(preconditioner="none"))

NONLINEAR = ["stvk", "neo_hookean", "stable_neo_hookean", "fixed_corotated", "corotated", "arap"]


@pytest.fixture(scope="module")
def rect():
    return je.rectangle(4, 4)


@pytest.fixture(scope="module")
def blk():
    """A 3 × 1 × 1 bar, element spacing (1, ½, ½)."""
    return je.box(3, 2, 2, size=(3.0, 1.0, 1.0))


def _mesh(rect, blk, dim):
    return rect if dim == 2 else blk


def _min_J(x, mesh):
    return float(jnp.min(jnp.linalg.det(deformation_gradients(x, mesh)[:, 0])))


# --------------------------------------------------------------------------------------
# MacNeal & Harder (1985) membrane patch test, linear elasticity, plane stress
# --------------------------------------------------------------------------------------


def _macneal_harder_mesh():
    pts = np.array(
        [
            [0.0, 0.0],
            [0.24, 0.0],
            [0.24, 0.12],
            [0.0, 0.12],
            [0.04, 0.02],
            [0.18, 0.03],
            [0.16, 0.08],
            [0.08, 0.08],
        ]
    )
    quads = [(0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7), (4, 5, 6, 7)]
    tris = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    return je.from_arrays(pts, np.array(tris), orient="refuse")


def test_macneal_harder_membrane_patch():
    mesh = _macneal_harder_mesh()
    mu, lam = (float(v) for v in M.lame(1.0e6, 0.25, dim=2, plane="stress"))
    p = M.Lame(mu, lam)

    def u_exact(X):
        return 1e-3 * np.stack([X[:, 0] + X[:, 1] / 2, X[:, 1] + X[:, 0] / 2], axis=1)

    bc = L.fix(mesh, [0, 1, 2, 3], displacement=u_exact)
    pot = je.Potential(mesh=mesh, params=p, psi=M.linear)
    res = solve(pot, bc, solver=DEFAULT)
    X = np.asarray(mesh.points)
    np.testing.assert_allclose(np.asarray(res.x) - X, u_exact(X), rtol=0, atol=1e-14)
    # the stress is exact in every element (linear model: P = σ)
    F = deformation_gradients(res.x, mesh)[:, 0]
    P = np.asarray(jax.vmap(je.first_piola(M.linear), in_axes=(0, None))(F, p))
    np.testing.assert_allclose(P[:, 0, 0], 4000.0 / 3.0, rtol=1e-9)
    np.testing.assert_allclose(P[:, 1, 1], 4000.0 / 3.0, rtol=1e-9)
    np.testing.assert_allclose(P[:, 0, 1], 400.0, rtol=1e-9)
    np.testing.assert_allclose(P[:, 1, 0], 400.0, rtol=1e-9)


# --------------------------------------------------------------------------------------
# Nonlinear patch test: an affine boundary map is reproduced exactly inside
# --------------------------------------------------------------------------------------


def _affine(dim):
    """A finite, rotated, sheared, stretched affine map F0 (det > 0) and a translation."""
    if dim == 2:
        U = np.array([[1.25, 0.1], [0.1, 0.85]])
        t = 0.4
        R = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
        c = np.array([0.3, -0.2])
    else:
        U = np.array([[1.2, 0.1, -0.05], [0.1, 0.9, 0.08], [-0.05, 0.08, 1.1]])
        R = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
        c = np.array([0.3, -0.2, 0.1])
    return R @ U, c


def _patch_problem(mesh):
    F0, c = _affine(mesh.dim)
    X = np.asarray(mesh.points)
    x_aff = X @ F0.T + c
    bnd = je.mesh.boundary_nodes(mesh)
    interior = np.setdiff1d(np.arange(mesh.n_nodes), bnd)
    bc = L.fix(mesh, bnd, displacement=lambda Xb: Xb @ F0.T + c - Xb)
    return x_aff, interior, bc


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("name", NONLINEAR)
def test_affine_map_is_equilibrium(rect, blk, dim, name):
    """Cheap half of the nonlinear patch test (no Newton compile): at x = F0·X + c the
    interior nodal forces vanish for every material."""
    mesh = _mesh(rect, blk, dim)
    x_aff, interior, _ = _patch_problem(mesh)
    f = np.asarray(je.forces(M.BUILTIN[name], jnp.asarray(x_aff), mesh, PARAMS))
    scale = np.abs(
        np.asarray(
            je.mechanics.element_gradients(M.BUILTIN[name], jnp.asarray(x_aff), mesh, PARAMS)
        )
    ).max()
    assert scale > 1.0  # the elements are really stressed
    np.testing.assert_allclose(f[interior], 0.0, atol=1e-11 * scale)


def _check_patch_solve(mesh, name):
    x_aff, interior, bc = _patch_problem(mesh)
    # start from the rest shape with the interior perturbed (the boundary is moved by
    # Newton's Dirichlet step): the solver must find the affine interior
    rng = np.random.default_rng(0)
    x0 = np.asarray(mesh.points).copy()
    x0[interior] += 0.03 * rng.standard_normal((interior.size, mesh.dim))
    pot = je.Potential(mesh=mesh, params=PARAMS, psi=M.BUILTIN[name])
    res = solve(pot, bc, x0=x0, solver=TIGHT)
    np.testing.assert_allclose(np.asarray(res.x)[interior], x_aff[interior], rtol=0, atol=1e-11)


@pytest.mark.parametrize("dim", [2, 3])
def test_nonlinear_patch_neo_hookean(rect, blk, dim):
    _check_patch_solve(_mesh(rect, blk, dim), "neo_hookean")


@pytest.mark.slow
@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("name", [n for n in NONLINEAR if n != "neo_hookean"])
def test_nonlinear_patch_all_materials(rect, blk, dim, name):
    _check_patch_solve(_mesh(rect, blk, dim), name)


# --------------------------------------------------------------------------------------
# Uniaxial tension of a neo-Hookean block against the closed form
# --------------------------------------------------------------------------------------


def _uniaxial_bc(mesh, a):
    d = mesh.dim
    Lx = float(np.ptp(np.asarray(mesh.points)[:, 0]))
    sets = [L.fix(mesh, L.nodes_on_plane(mesh, k, 0.0), components=(k,)) for k in range(d)]
    right = L.nodes_on_plane(mesh, 0, Lx)
    du = np.zeros(d)
    du[0] = (a - 1.0) * Lx
    pull = L.fix(mesh, right, components=(0,), displacement=du)
    return L.combine(*sets, pull), pull


@pytest.mark.parametrize("dim", [2, 3])
def test_uniaxial_neo_hookean_closed_form(rect, blk, dim):
    mesh = _mesh(rect, blk, dim)
    a = 1.4
    bc, pull = _uniaxial_bc(mesh, a)
    pot = je.Potential(mesh=mesh, params=PARAMS, psi=M.neo_hookean)
    res = solve(pot, bc, solver=TIGHT)

    def lateral(b):
        return MU * (b * b - 1.0) + LAM * np.log(a * b ** (dim - 1))

    b = brentq(lateral, 0.3, 1.0, xtol=1e-15)
    assert b < 0.95  # a real Poisson contraction
    X = np.asarray(mesh.points)
    expect = X * np.array([a] + [b] * (dim - 1))
    np.testing.assert_allclose(np.asarray(res.x), expect, rtol=0, atol=1e-11)
    # the nominal stress P11 = μ(a − b²/a) times the reference face area is the pull force
    area = float(np.prod(np.ptp(X, axis=0)[1:]))
    R = postprocess.reaction_force(M.neo_hookean, res.x, mesh, PARAMS, pull)
    np.testing.assert_allclose(float(R[0]), MU * (a - b * b / a) * area, rtol=1e-8)


# --------------------------------------------------------------------------------------
# Convergence rate, linear solvers, Hessian options
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("linear", ["auto", pytest.param("cg", marks=pytest.mark.extended)])
def test_quadratic_convergence(blk, linear):
    """Sparse direct solves (the default) and inexact CG with the forcing term ~‖g‖ both
    keep Newton quadratic: r_{k+1}/r_k² stays bounded."""
    bc, _ = _uniaxial_bc(blk, 2.2)
    pot = je.Potential(mesh=blk, params=PARAMS, psi=M.neo_hookean)
    res = solve(pot, bc, solver=TIGHT.replace(linear=linear))
    r = np.asarray(res.stats["residual_history"])[: int(res.stats["steps"]) + 1]
    r = r / r.max()
    assert int(res.stats["steps"]) <= 8
    # asymptotic regime: r_k < 0.1, and r_{k+1} above the round-off floor (~1e-13)
    pairs = [(r[k], r[k + 1]) for k in range(len(r) - 1) if 0 < r[k] < 0.1 and r[k + 1] > 1e-11]
    assert len(pairs) >= 2, r
    ratios = [rk1 / rk**2 for rk, rk1 in pairs]
    # linear convergence with rate 0.1 would give r_{k+1}/r_k² = 0.1/r_k > 1000 here
    assert max(ratios) < 10.0, (r, ratios)


@pytest.mark.parametrize(
    "pc",
    [pytest.param(p, marks=pytest.mark.extended) for p in ("none", "jacobi")] + ["block_jacobi"],
)
def test_cg_preconditioners_agree(blk, pc):
    """Matrix-free CG with each preconditioner finds the sparse-direct solution."""
    bc, _ = _uniaxial_bc(blk, 1.4)
    pot = je.Potential(mesh=blk, params=PARAMS, psi=M.neo_hookean)
    settings = Newton(rtol=1e-12, linear=CG(preconditioner=pc))
    ref = solve(pot, bc, solver=TIGHT)  # linear="auto": sparse Cholesky at this size
    res = solve(pot, bc, solver=settings)
    assert res.ok and int(res.stats["linear_iterations"]) > int(res.stats["steps"])  # CG really ran
    np.testing.assert_allclose(np.asarray(res.x), np.asarray(ref.x), rtol=0, atol=1e-11)


def test_hvp_matches_element_hessians(blk):
    """The matrix-free forward-over-reverse HVP and assembled element Hessians give the
    same Newton iterates (CG, no preconditioner, so nothing else differs)."""
    bc, _ = _uniaxial_bc(blk, 1.4)
    pot = je.Potential(mesh=blk, params=PARAMS, psi=M.neo_hookean)
    ref = solve(pot, bc, solver=Newton(rtol=1e-12, linear="cg"))  # element Hessians
    res = solve(pot, bc, solver=TIGHT_CG.replace(hessian="hvp"))
    assert int(res.stats["steps"]) == int(ref.stats["steps"])
    np.testing.assert_allclose(np.asarray(res.x), np.asarray(ref.x), rtol=0, atol=1e-11)


def test_projected_hessian_converges(blk):
    """PSD-projected element Hessians: always a descent direction, possibly more steps."""
    bc = L.combine(
        L.fix(blk, L.nodes_on_plane(blk, 0, 0.0)),
        L.fix(blk, L.nodes_on_plane(blk, 0, 3.0), displacement=[-1.2, 0.0, 0.4]),
    )
    pot = je.Potential(mesh=blk, params=PARAMS, psi=M.neo_hookean)
    ref = solve(pot, bc, solver=TIGHT)
    res = solve(pot, bc, solver=Newton(hessian="projected"))
    assert res.ok and int(res.stats["steps"]) >= int(ref.stats["steps"]) - 1
    np.testing.assert_allclose(np.asarray(res.x), np.asarray(ref.x), rtol=0, atol=1e-6)


# --------------------------------------------------------------------------------------
# Status codes and failure reporting
# --------------------------------------------------------------------------------------


def test_max_steps_status_under_jit(rect):
    """Under jit a failed solve returns its status instead of raising."""
    bc, _ = _uniaxial_bc(rect, 1.4)
    pot = je.Potential(mesh=rect, params=PARAMS, psi=M.neo_hookean)
    jitted = jax.jit(lambda p, b: solve(p, b, solver=Newton(max_steps=1, linear="cg")))
    res = jitted(pot, bc)
    assert int(res.status) == Status.MAX_STEPS
    assert int(res.stats["steps"]) == 1
    assert np.isfinite(np.asarray(res.x)).all()
    assert not res.ok and "iteration limit" in res.reason


def _inverted_start(mesh):
    """Rest shape with one interior corner node pushed through its neighbours."""
    x0 = np.asarray(mesh.points).copy()
    bnd = je.mesh.boundary_nodes(mesh)
    i = np.setdiff1d(np.arange(mesh.n_nodes), bnd)[0]
    x0[i, 0] += 1.5 * np.ptp(x0[:, 0]) / {2: 4, 3: 3}[mesh.dim]  # 1.5 element spacings
    assert _min_J(jnp.asarray(x0), mesh) < 0
    return x0


def test_inverted_start_neo_hookean(blk):
    bc = L.fix(blk, L.nodes_on_plane(blk, 0, 0.0))
    pot = je.Potential(mesh=blk, params=PARAMS, psi=M.neo_hookean)
    x0 = _inverted_start(blk)
    res = solve(pot, bc, x0=x0, solver=TIGHT, throw=False)
    assert int(res.status) == Status.INVERTED
    assert int(res.stats["steps"]) == 0
    np.testing.assert_array_equal(np.asarray(res.x), x0)
    with pytest.raises(SolveError, match="INVERTED"):
        solve(pot, bc, x0=x0, solver=TIGHT, throw=True)


def _psi_nan(F, p):
    return jnp.nan * jnp.sum(F * F) * p.mu


def test_nonfinite_status_and_error_message(rect):
    bc = L.fix(rect, L.nodes_on_plane(rect, 0, 0.0))
    pot = je.Potential(mesh=rect, params=PARAMS, psi=_psi_nan)
    res = solve(pot, bc, throw=False)
    assert int(res.status) == Status.NONFINITE
    with pytest.raises(SolveError, match="NONFINITE") as info:
        solve(pot, bc)
    assert info.value.status == Status.NONFINITE
    assert int(info.value.solution.status) == Status.NONFINITE


def _neo_hookean_abs(F, p):
    """A careless user model: neo-Hookean with ln|J| — finite garbage for J < 0."""
    d = F.shape[0]
    lnJ = jnp.log(jnp.abs(jnp.linalg.det(F)))
    return 0.5 * p.mu * (jnp.sum(F * F) - d) - p.mu * lnJ + 0.5 * p.lam * lnJ**2


POSJ = Newton(require_positive_J=True)


def test_require_positive_J(rect):
    bc = L.fix(rect, L.nodes_on_plane(rect, 0, 0.0))
    pot = je.Potential(mesh=rect, params=PARAMS, psi=_neo_hookean_abs)
    x0 = _inverted_start(rect)
    assert np.isfinite(float(je.energy(_neo_hookean_abs, jnp.asarray(x0), rect, PARAMS)))
    res = solve(pot, bc, x0=x0, solver=POSJ, throw=False)
    assert int(res.status) == Status.INVERTED
    # a strong compression from the rest shape: the flag keeps every iterate uninverted
    bc2 = L.combine(bc, L.fix(rect, L.nodes_on_plane(rect, 0, 1.0), displacement=[-0.6, 0.2]))
    res2 = solve(pot, bc2, solver=POSJ)
    assert _min_J(res2.x, rect) > 0


# --------------------------------------------------------------------------------------
# Loads and reactions; Dirichlet-only loading
# --------------------------------------------------------------------------------------


def test_reaction_balances_gravity_and_traction(blk):
    beam = blk
    clamp = L.fix(beam, L.nodes_on_plane(beam, 0, 0.0))
    f = L.gravity_load(beam, 50.0, [0.0, 0.0, -9.81])
    tip = L.facets_where(beam, lambda X: np.isclose(X[:, 0], 3.0))
    f = f + L.traction_load(beam, tip, [0.0, 300.0, -500.0])
    pot = je.Potential(mesh=beam, params=PARAMS, f_ext=jnp.asarray(f), psi=M.neo_hookean)
    res = solve(pot, clamp)
    x = np.asarray(res.x)
    assert x[:, 2].min() < -0.05  # it really bends
    R = np.asarray(
        postprocess.reaction_force(M.neo_hookean, res.x, beam, PARAMS, clamp, f_ext=pot.f_ext)
    )
    total = f.sum(axis=0)
    np.testing.assert_allclose(R, -total, rtol=0, atol=1e-7 * np.abs(total).max())


def test_twist_dirichlet_only(blk):
    """Twist one end face of a bar by 90° (no loads, only prescribed positions)."""
    beam = blk
    theta = np.pi / 2

    def twist(X):
        y, z = X[:, 1] - 0.5, X[:, 2] - 0.5
        c, s = np.cos(theta), np.sin(theta)
        return np.stack([0 * y, c * y - s * z - y, s * y + c * z - z], axis=1)

    bc = L.combine(
        L.fix(beam, L.nodes_on_plane(beam, 0, 0.0)),
        L.fix(beam, L.nodes_on_plane(beam, 0, 3.0), displacement=twist),
    )
    kappa = PARAMS.lam + 2.0 * PARAMS.mu / 3  # the bulk modulus, in the lam slot
    pot = je.Potential(mesh=beam, params=M.Lame(PARAMS.mu, kappa), psi=M.isochoric_neo_hookean)
    res = solve(pot, bc)
    assert _min_J(res.x, beam) > 0
    mid = L.nodes_on_plane(beam, 0, 2.0)
    # the section at x = 2 has turned in the same sense (by roughly 2/3 of θ)
    X = np.asarray(beam.points)[mid]
    x = np.asarray(res.x)[mid]
    ang = np.arctan2(x[:, 2] - 0.5, x[:, 1] - 0.5) - np.arctan2(X[:, 2] - 0.5, X[:, 1] - 0.5)
    ang = np.angle(np.exp(1j * ang))
    far = np.hypot(X[:, 1] - 0.5, X[:, 2] - 0.5) > 0.1
    assert np.all((ang[far] > 0.3 * theta) & (ang[far] < 0.9 * theta)), ang[far]


# --------------------------------------------------------------------------------------
# Round-off floor of the residual: no false MAX_STEPS
# --------------------------------------------------------------------------------------


def test_stiff_linear_problem_stops_at_the_roundoff_floor():
    """A steel block (E = 210 GPa, linear material) under a small end load: one Newton
    step solves it exactly; the residual left is round-off (~eps·|K||x|), which rtol·‖f‖
    lies below. Newton must stop there with SUCCESS after one step (it took 2–3 before)
    and report the floor it used."""
    mesh = je.box(6, 2, 2, size=(3.0, 0.5, 0.5))
    params = je.Lame.from_E_nu(210e9, 0.3)
    clamp = L.fix(mesh, L.nodes_on_plane(mesh, 0, 0.0))
    end = L.facets_where(mesh, lambda X: np.isclose(X[:, 0], 3.0))
    f = jnp.asarray(L.traction_load(mesh, end, [0.0, 0.0, -1e4]))
    pot = je.Potential(mesh=mesh, params=params, f_ext=f, psi=M.linear)
    res = solve(pot, clamp, solver=Newton(linear="direct"))
    assert int(res.stats["steps"]) == 1
    floor = float(res.stats["residual_floor"])
    assert 0 < float(res.stats["residual"]) <= floor
    # the floor is round-off, far below the load: the answer is the linear one
    assert floor < 1e-6 * float(jnp.linalg.norm(f))  # ~1e-7 relative here
    ref = solve(pot, clamp, solver=Newton(linear="cg", rtol=1e-6))
    np.testing.assert_allclose(np.asarray(res.x), np.asarray(ref.x), rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "name, free",
    [
        ("none", "6 rigid-body motion(s) free (translation along x"),
        ("one node", "3 rigid-body motion(s) free (rotation about x, rotation about y"),
        ("x on a plane", "3 rigid-body motion(s) free (translation along y"),
    ],
)
def test_unconstrained_static_solve_is_refused_before_solving(blk, name, free):
    """A static solve whose Dirichlet data leave rigid motions free has no unique answer
    (it used to end in MAX_STEPS with a residual of 1e9): refused before any compilation,
    naming the free motions. Dynamics (a mass term) accepts a free body."""
    bc = {
        "none": L.no_dirichlet(blk),
        "one node": L.fix(blk, np.array([0])),
        "x on a plane": L.fix(blk, L.nodes_on_plane(blk, 0, 0.0), components=[0]),
    }[name]
    g = jnp.asarray(L.gravity_load(blk, 1.0, [0.0, 0.0, -9.81]))
    pot = je.Potential(mesh=blk, params=PARAMS, f_ext=g, psi=M.neo_hookean)
    with pytest.raises(ValueError, match=re.escape(free)):
        solve(pot, bc)
    mass = jnp.asarray(L.lumped_mass(blk, 1.0))
    state = je.dynamics.init_state(blk.points)
    _, res = je.dynamics.step(pot.replace(mass=mass), state, bc, je.Integrator(0.01))
    assert bool(res.ok)


def test_float32_converges_at_its_roundoff_floor():
    """With x64 off in a subprocess the README-sized problem converges (at the float32
    round-off floor of the residual) instead of ending in MAX_STEPS."""
    import subprocess
    import sys

    code = """
import jax, jax.numpy as jnp, numpy as np
import jaxelastic as je
from jaxelastic import loads
assert not jax.config.jax_enable_x64
mesh = je.rectangle(16, 2, size=(4.0, 0.5))
params = je.Lame.from_E_nu(1e4, 0.3, dim=2)
clamp = loads.fix(mesh, loads.nodes_on_plane(mesh, 0, 0.0))
tip = loads.facets_where(mesh, lambda X: np.isclose(X[:, 0], 4.0))
f = jnp.asarray(loads.traction_load(mesh, tip, [0.0, -20.0]))
pot = je.Potential(mesh=mesh, params=params, f_ext=f, psi=je.materials.neo_hookean)
for lin in ("cg", "direct"):
    r = je.solve(pot, clamp, solver=je.Newton(linear=lin))
    assert r.x.dtype == jnp.float32
    print(lin, int(r.stats["steps"]), float(r.stats["residual"]), float(r.x[:, 1].min()))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    rows = [line.split() for line in out.stdout.splitlines()]
    assert len(rows) == 2
    beam = je.rectangle(16, 2, size=(4.0, 0.5))
    tip = L.facets_where(beam, lambda X: np.isclose(X[:, 0], 4.0))
    f = jnp.asarray(L.traction_load(beam, tip, [0.0, -20.0]))
    params = je.Lame.from_E_nu(1e4, 0.3, dim=2)
    pot = je.Potential(mesh=beam, params=params, f_ext=f, psi=M.neo_hookean)
    clamp = L.fix(beam, L.nodes_on_plane(beam, 0, 0.0))
    tip64 = float(solve(pot, clamp).x[:, 1].min())
    for _, steps, _, tip32 in rows:
        assert int(steps) < 20
        # float32 at its floor (F from absolute positions): 2e-4 relative measured
        assert abs(float(tip32) - tip64) < 1e-3 * abs(tip64)


# --------------------------------------------------------------------------------------
# The two Newton drivers: jitted lax.while_loop and the host loop
# --------------------------------------------------------------------------------------


def _turned_square(rect):
    """``(pot, bc, prepared solver)``: a neo-Hookean square whose right edge is turned by
    1 rad about its midpoint (too large a Dirichlet motion for one step: cutbacks)."""

    def turn(X, theta=1.0):
        y = X[:, 1] - 0.5
        return np.stack([-np.sin(theta) * y, (np.cos(theta) - 1.0) * y], axis=1)

    left = L.fix(rect, L.nodes_on_plane(rect, 0, 0.0))
    bc = L.combine(left, L.fix(rect, L.nodes_on_plane(rect, 0, 1.0), displacement=turn))
    pot = je.Potential(mesh=rect, params=PARAMS, psi=M.neo_hookean)
    return pot, bc, je.solvers.prepare_solver(Newton(rtol=1e-10, linear="direct"), rect, bc)


@pytest.mark.extended  # about 1 min: one traced and one host solve per iterate
def test_traced_and_python_newton_loops_take_the_same_iterates(rect):
    """The one Newton loop runs under ``lax.while_loop`` when traced (here: ``jit`` of
    ``minimize``, the host solve a callback) and in Python over compiled pieces for
    concrete inputs with a host linear solver. On a solve with line-search cutbacks (a
    neo-Hookean square whose right edge is turned by 1 rad about its midpoint: too large a
    Dirichlet motion for one step), both reach every iterate with the same energy,
    residual, step length and linear iterations, and the same answer and statistics."""
    from jaxelastic.solvers import newton as N
    from jaxelastic.solvers.results import RUNNING

    pot, bc, prep = _turned_square(rect)
    s, ls = prep.newton, prep.linear_state
    x0 = rect.points
    assert N.runs_on_host(s, pot)

    # iterate by iterate: the traced step (jitted) vs the Python loop stopped after k steps
    step = jax.jit(N.step, static_argnums=0)
    st = jax.jit(N.init, static_argnums=0)(s, pot, bc, x0)
    length = jnp.sqrt(jnp.sum((x0.max(0) - x0.min(0)) ** 2))
    energies = [float(st.energy)]
    while int(st.status) == RUNNING:
        st = step(s, ls, pot, bc, st, length)
        k = int(st.k)
        host = N.minimize(s.replace(max_steps=k), ls, pot, bc, x0)
        assert int(host.stats["steps"]) == k
        if int(st.status) != RUNNING:
            assert int(host.status) == int(st.status), k
        assert int(host.stats["line_search_cutbacks"]) == int(st.cuts), k
        np.testing.assert_allclose(host.stats["energy"], st.energy, rtol=1e-12, err_msg=k)
        np.testing.assert_allclose(host.x, st.x, rtol=0, atol=1e-12, err_msg=k)
        assert float(host.stats["step_history"][k - 1]) == float(st.alpha_hist[k - 1]), k
        energies.append(float(st.energy))
    assert int(st.status) == Status.SUCCESS and int(st.cuts) >= 1
    # Π rises while the Dirichlet motion is applied (step 1), then decreases
    assert len(energies) >= 5 and np.all(np.diff(energies[1:-2]) < 0), energies

    # the whole loops: their Solutions agree field by field
    a = jax.jit(N.minimize, static_argnums=0)(s, ls, pot, bc, x0)
    b = N.minimize(s, ls, pot, bc, x0)
    assert int(a.status) == int(b.status) == Status.SUCCESS
    np.testing.assert_allclose(b.x, a.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(b.x, st.x, rtol=0, atol=1e-12)
    for key in ("steps", "linear_iterations", "line_search_cutbacks", "negative_curvature"):
        assert int(a.stats[key]) == int(b.stats[key]), key
    np.testing.assert_array_equal(a.stats["linear_history"], b.stats["linear_history"])
    np.testing.assert_array_equal(a.stats["step_history"], b.stats["step_history"])
    np.testing.assert_allclose(b.stats["energy"], a.stats["energy"], rtol=1e-12)
    n = int(a.stats["steps"]) + 1
    # the last residual is round-off (≈ 3e-12 of the largest): compared against that scale
    ra, rb = (
        np.asarray(a.stats["residual_history"][:n]),
        np.asarray(b.stats["residual_history"][:n]),
    )
    np.testing.assert_allclose(rb, ra, rtol=1e-7, atol=1e-10 * float(ra.max()))
    assert n == len(energies)


@pytest.mark.parametrize("linear", ["direct", "cg"])
def test_differentiated_solve_takes_the_plain_solves_path(rect, linear, monkeypatch):
    """An eager ``jax.grad`` through ``je.solve`` runs the same Newton loop, on the same
    concrete values, as the plain solve: the whole loop compiled as one program for a
    device solver (CG), the Python loop for a host one (Direct), never the traced loop
    with callbacks; the same iterates either way."""
    from jaxelastic.solvers.newton import driver

    pot, bc, _ = _turned_square(rect)
    solver = Newton(rtol=1e-10, linear=linear)
    calls = []
    for name in ("solve_jit", "_python_loop"):
        orig = getattr(driver, name)
        monkeypatch.setattr(driver, name, lambda *a, _o=orig, _n=name: calls.append(_n) or _o(*a))
    plain = je.solve(pot, bc, solver=solver)
    first = list(calls)

    def loss(mu):
        p = pot.replace(params=PARAMS._replace(mu=mu))
        return jnp.sum(je.solve(p, bc, solver=solver).x ** 2)

    g = jax.grad(loss)(PARAMS.mu)
    assert np.isfinite(float(g))
    assert first == [("solve_jit" if linear == "cg" else "_python_loop")]
    assert calls == first + first  # the differentiated solve took the same path
    again = je.solve(pot, bc, solver=solver)
    np.testing.assert_array_equal(again.x, plain.x)


@pytest.mark.extended
def test_first_line_search_trial_outside_the_loop_changes_nothing(rect, monkeypatch):
    """Large meshes (``STRAIGHT_TRIAL_MIN_CELLS``) try α = 1 before the line search's
    while loop, small ones inside it: the same iterates, cutbacks and answer either way
    (a solve with cutbacks: the square's right edge turned by 1 rad)."""
    from jaxelastic.solvers import newton as N
    from jaxelastic.solvers.newton import iteration

    pot, bc, prep = _turned_square(rect)
    out = []
    for threshold in (0, 1 << 62):  # outside the loop, then inside
        monkeypatch.setattr(iteration, "STRAIGHT_TRIAL_MIN_CELLS", threshold)
        jax.clear_caches()  # (the constant is read when tracing)
        out.append(N.minimize(prep.newton, prep.linear_state, pot, bc, rect.points))
    jax.clear_caches()
    sol, ref = out
    assert int(ref.status) == Status.SUCCESS and int(ref.stats["line_search_cutbacks"]) >= 1
    assert int(sol.status) == Status.SUCCESS
    for key in ("steps", "line_search_cutbacks", "linear_iterations"):
        assert int(sol.stats[key]) == int(ref.stats[key]), key
    np.testing.assert_array_equal(sol.stats["step_history"], ref.stats["step_history"])
    np.testing.assert_allclose(sol.x, ref.x, rtol=0, atol=1e-12)


@pytest.mark.extended
def test_a_warm_start_converges_relative_to_the_reaction_it_carries(rect):
    """A displacement-driven solve warm-started from a nearby solution meets rtol relative
    to the reaction on its prescribed dofs (the load it carries), as a solve from rest
    does, not relative to its own small starting residual; a start that does not meet it
    is never reported converged."""
    bc, pull = _uniaxial_bc(rect, 1.2)
    pot = je.Potential(mesh=rect, params=PARAMS, psi=M.neo_hookean)
    cold = solve(pot, bc, solver=TIGHT)
    R = -je.forces(M.neo_hookean, cold.x, rect, PARAMS)
    reaction = float(jnp.linalg.norm(jnp.where(bc.mask, R, 0.0)))
    assert reaction > 100.0
    again = solve(pot, bc, x0=cold.x, solver=DEFAULT)  # converged to rtol: no step
    assert again.status == Status.SUCCESS and int(again.stats["steps"]) == 0
    near = pot.replace(params=M.Lame(1.01 * MU, LAM))
    warm = solve(near, bc, x0=cold.x, solver=DEFAULT)
    assert warm.status == Status.SUCCESS
    assert float(warm.stats["residual_reference"]) >= 0.99 * reaction
    assert float(warm.stats["residual"]) <= DEFAULT.rtol * float(warm.stats["residual_reference"])
    exact = solve(near, bc, solver=TIGHT)
    np.testing.assert_allclose(np.asarray(warm.x), np.asarray(exact.x), rtol=0, atol=1e-7)
    far = pot.replace(params=M.Lame(3.0 * MU, LAM))
    one = solve(far, bc, x0=cold.x, solver=DEFAULT.replace(max_steps=1), throw=False)
    assert one.status == Status.MAX_STEPS
    assert float(one.stats["residual"]) > DEFAULT.rtol * float(one.stats["residual_reference"])
