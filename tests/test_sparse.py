"""Host sparse assembly and the factorise / apply back ends of the device CG.

Covers :mod:`jaxelastic.solvers.host.pattern` (assembly, elimination, rigid-body modes),
:mod:`jaxelastic.solvers.host` (DirectSolver, AMGSolver) and
:class:`jaxelastic.solvers.host.HostLinearSolver` (factor / apply). The Krylov loop of the
library runs on the device (``solvers.linear.krylov``); here a tiny NumPy CG (:func:`_pcg`, a
test utility) checks that the AMG V-cycle is a good preconditioner.
"""

import functools
import threading
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp

import jaxelastic
from jaxelastic.materials import Lame, neo_hookean
from jaxelastic.solvers.host import (
    BACKEND_KINDS,
    NONFINITE,
    NOT_POSITIVE_DEFINITE,
    SUCCESS,
    AMGSolver,
    DirectSolver,
    HostLinearSolver,
    SparsityPattern,
    available_direct_backends,
    make_backend,
    rigid_body_modes,
)
from jaxelastic.solvers.host.amg import CHEBYSHEV_INTERVAL, RATE_MIN_RATIOS

PARAMS = Lame(mu=jnp.asarray(3.0), lam=jnp.asarray(5.0))
TOKEN = np.int32(0)


def _mesh(dim):
    return jaxelastic.rectangle(3, 2) if dim == 2 else jaxelastic.box(2, 1, 2)


# one compilation per mesh shape (the mesh is a jit argument, never closed over)
_element_hessians = jax.jit(jaxelastic.mechanics.element_hessians, static_argnums=0)
_hvp = jax.jit(jaxelastic.mechanics.hvp, static_argnums=0)


def _deformed(mesh, seed=0, amp=0.03):
    rng = np.random.default_rng(seed)
    X = np.asarray(mesh.points)
    return jnp.asarray(X + amp * rng.standard_normal(X.shape))


def _dense_hessian(mesh, x):
    """Dense Hessian column by column from the matrix-free HVP, ``(n_dofs, n_dofs)``."""
    n, d = mesh.points.shape
    cols = [_hvp(neo_hookean, x, e.reshape(n, d), mesh, PARAMS) for e in jnp.eye(n * d)]
    return np.stack([np.asarray(c).reshape(-1) for c in cols], axis=1)


def _ke(mesh, x):
    return np.asarray(_element_hessians(neo_hookean, x, mesh, PARAMS))


def _pattern_and_ke(mesh, x, fixed=None):
    n, d = mesh.points.shape
    return SparsityPattern.build(np.asarray(mesh.cells), n, d, fixed), _ke(mesh, x)


def _clamped(mesh, side=0.0):
    """Dirichlet mask ``(n_dofs,)`` fixing every dof of the nodes on the face x = side."""
    X = np.asarray(mesh.points)
    return np.repeat(X[:, 0] == side, mesh.dim)


def _pcg(A, b, M, rtol=1e-8, maxiter=300):
    """Test utility: preconditioned CG on ``A x = b`` (``(n,)``); ``(x, iterations)``."""
    x = np.zeros_like(b)
    r = b.copy()
    z = M(r)
    p = z.copy()
    rz = r @ z
    tol = rtol * np.linalg.norm(b)
    for it in range(1, maxiter + 1):
        Ap = A @ p
        alpha = rz / (p @ Ap)
        x += alpha * p
        r -= alpha * Ap
        if np.linalg.norm(r) <= tol:
            return x, it
        z = M(r)
        rz, rz_old = r @ z, rz
        p = z + (rz / rz_old) * p
    return x, maxiter


def _host(mesh, fixed, kind="direct", **opts):
    """HostLinearSolver for ``mesh`` with a ``(n_dofs,)`` mask."""
    return HostLinearSolver(mesh.cells, mesh.points, fixed.reshape(mesh.points.shape), kind, **opts)


# ----------------------------------------------------------------------------------------
# pattern and assembly
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("dim", [2, 3])
def test_assembled_equals_dense_hvp_hessian(dim):
    mesh = _mesh(dim)
    x = _deformed(mesh)
    P, Ke = _pattern_and_ke(mesh, x)
    H = _dense_hessian(mesh, x)
    K = P.assemble_full(Ke)
    assert isinstance(K, sp.csr_matrix) and K.has_sorted_indices
    np.testing.assert_allclose(K.toarray(), H, rtol=1e-10, atol=1e-10 * np.abs(H).max())
    # the upper-triangle data is the upper triangle, and the pattern covers every coupling
    U = P.upper_matrix(P.upper_data(Ke))
    assert U.has_sorted_indices and U.nnz == P.nnz_upper
    np.testing.assert_allclose(U.toarray(), np.triu(H), rtol=1e-10, atol=1e-10 * np.abs(H).max())
    in_pattern = P.matrix(np.ones(P.nnz)).toarray() != 0
    assert np.all(in_pattern[np.abs(H) > 0])
    assert K.nnz == P.nnz


def test_pattern_structure_and_bsr():
    mesh = _mesh(3)
    n, d = mesh.points.shape
    P, Ke = _pattern_and_ke(mesh, _deformed(mesh, 1))
    # every index map is int32 (the element map has one entry per upper element entry)
    for name in ("indptr", "indices", "upper_indptr", "upper_indices", "element_map"):
        assert getattr(P, name).dtype == np.int32, name
    for name in ("full_from_upper", "zeroed", "fixed_diag", "diag_slots", "bsr_perm"):
        assert getattr(P, name).dtype == np.int32, name
    m = Ke.shape[-1]
    assert P.element_map.size == Ke.shape[0] * m * (m + 1) // 2
    assert P.element_map.max() < P.nnz_upper and P.full_from_upper.max() < P.nnz_upper
    assert 2 * P.nnz_upper - n * d == P.nnz
    K = P.assemble(Ke)
    np.testing.assert_array_equal(P.to_bsr(K).toarray(), K.toarray())
    assert P.has_pattern(K) and not P.has_pattern(K[:-1, :-1])
    np.testing.assert_array_equal(K.toarray(), K.toarray().T)
    with pytest.raises(ValueError, match="shape"):
        P.assemble(Ke[:-1])
    # diagonal slots (upper numbering), and adding a diagonal keeps the pattern
    up = P.upper_data(Ke)
    np.testing.assert_allclose(up[P.diag_slots], P.assemble_full(Ke).diagonal())
    m = np.arange(1.0, n * d + 1)
    m = np.arange(1.0, n * d + 1)
    Km = P.assemble_full(Ke, diag=m)
    np.testing.assert_allclose(Km.toarray(), P.assemble_full(Ke).toarray() + np.diag(m))
    assert P.has_pattern(Km)


@pytest.mark.parametrize("dim", [2, 3])
def test_dirichlet_elimination(dim):
    mesh = _mesh(dim)
    x = _deformed(mesh, 2)
    n, d = mesh.points.shape
    rng = np.random.default_rng(3)
    fixed = _clamped(mesh)
    fixed[rng.choice(n * d, 3, replace=False)] = True  # some single components too
    P, Ke = _pattern_and_ke(mesh, x, fixed)
    full = P.assemble_full(Ke).toarray()
    A = P.assemble(Ke).toarray()
    free = ~fixed
    np.testing.assert_array_equal(A[np.ix_(free, free)], full[np.ix_(free, free)])
    np.testing.assert_array_equal(A[np.ix_(fixed, fixed)], np.eye(fixed.sum()))
    assert not A[np.ix_(fixed, free)].any() and not A[np.ix_(free, fixed)].any()
    np.testing.assert_array_equal(A, A.T)
    # solving the eliminated system = solving the free block with zero fixed increments
    b = rng.standard_normal(n * d)
    b[fixed] = 0.0
    x_el = np.linalg.solve(A, b)
    x_ff = np.linalg.solve(full[np.ix_(free, free)], b[free])
    np.testing.assert_allclose(x_el[free], x_ff, rtol=1e-10)
    assert not x_el[fixed].any()


def test_rigid_body_modes_null_space():
    for mesh in (_mesh(2), _mesh(3)):
        X = mesh.points
        P, Ke = _pattern_and_ke(mesh, X)
        K = P.assemble_full(Ke)
        B = rigid_body_modes(X)
        d = mesh.dim
        assert B.shape == (mesh.n_dofs, 3 if d == 2 else 6)
        assert np.linalg.matrix_rank(B) == B.shape[1]
        assert np.abs(K @ B).max() < 1e-10 * abs(K).max()
        # and the stiffness is positive on everything orthogonal to them
        Q, _ = np.linalg.qr(B)
        A = K.toarray()
        Aperp = A - Q @ (Q.T @ A) - (A @ Q) @ Q.T + Q @ (Q.T @ A @ Q) @ Q.T
        ev = np.linalg.eigvalsh(Aperp)
        assert np.sum(ev < 1e-9 * ev.max()) == B.shape[1]
    fixed = np.zeros(X.size, bool)
    fixed[:6] = True
    assert not rigid_body_modes(X, fixed)[:6].any()


def _dense_reference(mesh, Ke, mass_diag, fixed):
    """Element-by-element dense assembly with symmetrisation, mass and elimination."""
    n, d = mesh.points.shape
    K = np.zeros((n * d, n * d))
    dofs = (np.asarray(mesh.cells)[:, :, None] * d + np.arange(d)).reshape(len(Ke), -1)
    for c, ke in zip(dofs, Ke, strict=True):
        K[np.ix_(c, c)] += 0.5 * (ke + ke.T)
    K += np.diag(np.repeat(mass_diag, d))
    K[fixed, :] = 0.0
    K[:, fixed] = 0.0
    K[fixed, fixed] = 1.0
    return K


@pytest.mark.parametrize("dim", [2, 3])
def test_host_assemble_equals_dense_reference(dim):
    mesh = _mesh(dim)
    n = mesh.n_nodes
    fixed = _clamped(mesh)
    fixed[1] = True
    Ke = _ke(mesh, _deformed(mesh, 5))
    Ke = Ke + 1e-3 * np.random.default_rng(6).standard_normal(Ke.shape)  # unsymmetric
    mass = np.linspace(0.5, 2.0, n)
    host = _host(mesh, fixed)
    for md in (mass, np.zeros(n), None):
        K = host.assemble(Ke, md)
        assert isinstance(K, sp.csr_matrix) and K.dtype == np.float64
        ref = _dense_reference(mesh, Ke, np.zeros(n) if md is None else md, fixed)
        np.testing.assert_allclose(K.toarray(), ref, rtol=1e-13, atol=1e-13 * np.abs(ref).max())
        assert host.pattern.has_pattern(K)


# ----------------------------------------------------------------------------------------
# problems: a twisted cube and a bending cantilever (small versions of bench_linear.py)
# ----------------------------------------------------------------------------------------


@functools.cache
def _problem(name):
    """``(mesh, fixed (n_dofs,), Ke, mass_diag (n_nodes,), rhs (n_nodes, 3))``."""
    if name == "twist":  # both faces clamped, the cube twisted a little about its axis
        mesh = jaxelastic.box(6, 6, 6)
        X = np.asarray(mesh.points)
        fixed = np.repeat((X[:, 0] == 0.0) | (X[:, 0] == 1.0), 3)
        th = 0.2 * X[:, 0]
        y, z = X[:, 1] - 0.5, X[:, 2] - 0.5
        x = X.copy()
        x[:, 1] = 0.5 + np.cos(th) * y - np.sin(th) * z
        x[:, 2] = 0.5 + np.sin(th) * y + np.cos(th) * z
    else:  # cantilever clamped at x = 0, at rest
        mesh = jaxelastic.box(12, 3, 3, size=(4.0, 1.0, 1.0))
        X = np.asarray(mesh.points)
        fixed = _clamped(mesh)
        x = X
    Ke = _ke(mesh, jnp.asarray(x))
    rhs = np.random.default_rng(7).standard_normal(X.shape)
    rhs[:, 2] -= 1.0
    rhs.reshape(-1)[fixed] = 0.0
    return mesh, fixed, Ke, np.zeros(mesh.n_nodes), rhs


# ----------------------------------------------------------------------------------------
# direct: factor / apply
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("backend", ["auto", *available_direct_backends()])
@pytest.mark.parametrize("name", ["twist", "cantilever"])
def test_direct_apply_solves(name, backend):
    mesh, fixed, Ke, md, rhs = _problem(name)
    host = _host(mesh, fixed, "direct", backend=backend)
    assert host.exact
    status = host.factor(Ke, md, TOKEN)
    assert status.shape == () and status.dtype == np.int32 and status == SUCCESS
    assert host.last_info["positive_definite"] and host.last_info["status"] == SUCCESS
    x = host.apply(rhs, TOKEN)
    assert x.shape == rhs.shape and x.dtype == rhs.dtype
    assert not x.reshape(-1)[fixed].any()
    K = host.assemble(Ke, md)
    b = rhs.reshape(-1)
    # relative residual ~1e-12 (the cantilever's condition number is ~1e5); backward
    # error ‖Kx − b‖ / (‖K‖‖x‖ + ‖b‖) at round-off
    res = np.linalg.norm(K @ x.reshape(-1) - b)
    assert res <= 1e-11 * np.linalg.norm(b)
    kn = sp.linalg.norm(K, "fro")
    assert res <= 1e-14 * (kn * np.linalg.norm(x) + np.linalg.norm(b))
    # a batch of right-hand sides, and float32 in -> float32 out
    xb = host.apply(np.stack([rhs, 2.0 * rhs]), TOKEN)
    np.testing.assert_allclose(xb[1], 2.0 * x, rtol=1e-10, atol=1e-14)
    x32 = host.apply(rhs.astype(np.float32), TOKEN)
    assert x32.dtype == np.float32
    np.testing.assert_allclose(x32, x, rtol=1e-4, atol=1e-6 * np.abs(x).max())
    assert (host.calls, host.factorizations, host.applications) == (4, 1, 3)


def test_direct_mass_diagonal_and_float32_hessians():
    mesh, fixed, Ke, _, rhs = _problem("cantilever")
    host = _host(mesh, fixed)
    md = np.full(mesh.n_nodes, 10.0)
    assert host.factor(Ke.astype(np.float32), md.astype(np.float32), TOKEN) == SUCCESS
    x = host.apply(rhs, TOKEN).reshape(-1)
    K = host.assemble(Ke.astype(np.float32), md)
    assert np.linalg.norm(K @ x - rhs.reshape(-1)) <= 1e-12 * np.linalg.norm(rhs)


@pytest.mark.parametrize("backend", available_direct_backends())
def test_factor_reports_not_positive_definite(backend, capfd):
    mesh, fixed, Ke, _, rhs = _problem("cantilever")
    host = _host(mesh, fixed, "direct", backend=backend)
    K = host.assemble(Ke)
    top = sp.linalg.eigsh(K, k=1, which="LA", return_eigenvectors=False)[0]
    md = np.full(mesh.n_nodes, -0.5 * top)  # K - top/2 on the free dofs: indefinite
    assert host.factor(Ke, md, TOKEN) == NOT_POSITIVE_DEFINITE
    assert host.last_info["positive_definite"] is False
    assert "CHOLMOD" not in capfd.readouterr().out  # CHOLMOD's own message is silenced
    # the LU factorisation still solves the indefinite system
    x = host.apply(rhs, TOKEN).reshape(-1)
    Kind = host.assemble(Ke, md)
    assert np.linalg.norm(Kind @ x - rhs.reshape(-1)) <= 1e-10 * np.linalg.norm(rhs)
    # negative definite as well; back to SPD afterwards
    assert host.factor(-Ke, None, TOKEN) == NOT_POSITIVE_DEFINITE
    assert host.factor(Ke, None, TOKEN) == SUCCESS
    # without the LU fallback apply gives NaN on the free dofs
    strict = _host(mesh, fixed, "direct", backend=backend, on_indefinite="fail")
    assert strict.factor(Ke, md, TOKEN) == NOT_POSITIVE_DEFINITE
    y = strict.apply(rhs, TOKEN).reshape(-1)
    assert np.isnan(y[~fixed]).all() and not y[fixed].any()


def test_factor_nonfinite():
    mesh, fixed, Ke, md, rhs = _problem("cantilever")
    host = _host(mesh, fixed)
    assert host.factor(Ke, md, TOKEN) == SUCCESS
    bad = Ke.copy()
    bad[3, 0, 0] = np.nan
    assert host.factor(bad, md, TOKEN) == NONFINITE
    assert host.factorizations == 1 and host.last_info["status"] == NONFINITE
    y = host.apply(rhs, TOKEN).reshape(-1)  # the old factorisation is not used
    assert np.isnan(y[~fixed]).all() and not y[fixed].any()
    assert host.factor(Ke, np.full(mesh.n_nodes, np.inf), TOKEN) == NONFINITE
    assert host.factor(Ke, md, TOKEN) == SUCCESS
    assert np.isfinite(host.apply(rhs, TOKEN)).all()


def test_direct_solver_backend():
    mesh, fixed, Ke, md, rhs = _problem("cantilever")
    K = _host(mesh, fixed).assemble(Ke, md)
    B = np.random.default_rng(8).standard_normal((K.shape[0], 3))
    ref = np.linalg.solve(K.toarray(), B)
    for backend in ("auto", *available_direct_backends()):
        s = DirectSolver(backend=backend)
        with pytest.raises(RuntimeError, match="update"):
            s.solve(B)
        s.update(K)
        assert s.ready and s.positive_definite and s.setup_time > 0
        np.testing.assert_allclose(s.solve(B), ref, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(s.solve(B[:, 0]), ref[:, 0], rtol=1e-9, atol=1e-12)
        singular = sp.diags(np.r_[np.ones(K.shape[0] - 1), 0.0]).tocsr()
        s.update(singular)
        assert s.positive_definite is False and not s.ready
        assert np.isnan(s.solve(B)).all()
    with pytest.raises(ValueError, match="on_indefinite"):
        DirectSolver(on_indefinite="project")


# ----------------------------------------------------------------------------------------
# AMG: factor builds the hierarchy, apply is one V-cycle
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("name,max_its", [("twist", 15), ("cantilever", 25)])
def test_amg_preconditions_cg(name, max_its):
    mesh, fixed, Ke, md, rhs = _problem(name)
    host = _host(mesh, fixed, "amg", sa_options=dict(max_coarse=10))
    assert not host.exact
    assert host.factor(Ke, md, TOKEN) == SUCCESS
    info = host.last_info
    assert info["levels"] >= 2 and info["rebuilt"] and info["operator_complexity"] > 1.0
    shape = rhs.shape

    def M(v):
        return host.apply(v.reshape(shape), TOKEN).reshape(-1)

    rng = np.random.default_rng(9)
    for _ in range(3):  # symmetric positive definite on the free dofs
        r, s = rng.standard_normal((2, mesh.n_dofs))
        r[fixed] = s[fixed] = 0.0
        Mr = M(r)
        assert r @ Mr > 0 and not Mr[fixed].any()
        assert abs(s @ Mr - r @ M(s)) <= 1e-10 * np.linalg.norm(s) * np.linalg.norm(Mr)
    K = host.assemble(Ke, md)
    b = rhs.reshape(-1)
    x, its = _pcg(K, b, M, rtol=1e-8)
    assert its <= max_its, its
    assert np.linalg.norm(K @ x - b) <= 1e-8 * np.linalg.norm(b)
    # far fewer iterations than Jacobi-CG
    _, its_jacobi = _pcg(K, b, lambda r: r / K.diagonal(), rtol=1e-8, maxiter=2000)
    assert its_jacobi > 3 * its


def test_amg_2d():
    mesh = jaxelastic.rectangle(24, 6, size=(4.0, 1.0))
    fixed = _clamped(mesh)
    Ke = _ke(mesh, mesh.points)
    host = _host(mesh, fixed, "amg", sa_options=dict(max_coarse=5))
    assert host.factor(Ke, np.zeros(mesh.n_nodes), TOKEN) == SUCCESS
    assert host.last_info["levels"] >= 2
    b = np.zeros((mesh.n_nodes, 2))
    b[:, 1] = -1.0
    b = b.reshape(-1)
    b[fixed] = 0.0
    K = host.assemble(Ke)
    x, its = _pcg(K, b, lambda v: host.apply(v.reshape(-1, 2), TOKEN).reshape(-1), 1e-9)
    assert its < 40
    np.testing.assert_allclose(x, np.linalg.solve(K.toarray(), b), rtol=1e-6, atol=1e-12)


def test_amg_reuse_and_refresh():
    mesh, fixed, Ke, md, rhs = _problem("twist")
    host = _host(mesh, fixed, "amg", reuse=3, sa_options=dict(max_coarse=10))
    rebuilt = []
    for scale in (1.0, 1.5, 2.0, 1.2):
        assert host.factor(scale * Ke, md, TOKEN) == SUCCESS
        rebuilt.append(host.last_info["rebuilt"])
    assert rebuilt == [True, False, False, True]  # every 3rd factor rebuilds
    K = host.assemble(1.2 * Ke, md)
    for refresh in ("galerkin", "none"):
        s = AMGSolver(mesh.points, fixed, reuse=3, refresh=refresh, pattern=host.pattern)
        with pytest.raises(RuntimeError, match="update"):
            s.precondition(rhs.reshape(-1))
        s.update(host.assemble(Ke, md))
        s.update(K)
        assert s.ready and not s.rebuilt
        _, its = _pcg(K, rhs.reshape(-1), s.precondition)
        assert its < 30, (refresh, its)
        z = s.precondition(np.stack([rhs.reshape(-1)] * 2, axis=1))  # (n, m) columns
        np.testing.assert_allclose(z[:, 1], s.precondition(rhs.reshape(-1)), rtol=1e-12)


def test_amg_v_cycle_is_pyamgs():
    """With PyAMG's smoother the V-cycle traversed in AMGSolver is PyAMG's one-cycle
    solve, bit for bit, for one and for several right-hand sides."""
    mesh, fixed, Ke, md, rhs = _problem("twist")
    host = _host(mesh, fixed, "amg", smoother="gauss_seidel", sa_options=dict(max_coarse=10))
    assert host.factor(Ke, md, TOKEN) == SUCCESS
    ml = host.backend.ml
    assert ml is not None and len(ml.levels) >= 3  # the recursion is exercised
    b = rhs.reshape(-1).copy()
    b[fixed] = 0.0
    reference = ml.aspreconditioner(cycle="V").matvec
    assert np.array_equal(host.backend.precondition(b), reference(b))
    B = np.stack([b, 2.0 * b + 1.0], axis=1)
    z = host.backend.precondition(B)
    assert np.array_equal(z[:, 1], reference(np.ascontiguousarray(B[:, 1])))


def test_amg_chebyshev_smoother():
    """The Chebyshev smoother's Lanczos estimate of λ_max(D⁻¹A) lies within 5 % below the
    dense eigenvalue on every smoothed level, the polynomial damps the error on the
    interval it was built for (|1 − t q(t)| < 1), and the V-cycle is a symmetric positive
    definite preconditioner; a second update warm-starts the estimate."""
    from jaxelastic.solvers.host.amg import CHEBYSHEV_DEGREE, chebyshev_coefficients

    mesh, fixed, Ke, md, rhs = _problem("twist")
    host = _host(mesh, fixed, "amg", sa_options=dict(max_coarse=10))
    s = host.backend
    assert s.smoother == "chebyshev"
    assert host.factor(Ke, md, TOKEN) == SUCCESS
    assert s.ml is not None and len(s.ml.levels) >= 3
    for level, (dinv, coeffs) in zip(s.ml.levels[:-1], s._cheb, strict=True):
        A = level.A.toarray()
        lam_true = np.max(np.linalg.eigvals(dinv[:, None] * A).real)
        t = np.linspace(1e-6, 1.0, 200)
        hi = CHEBYSHEV_INTERVAL[1]
        # the interval's top is 1.1 λ_est: recover λ_est from the coefficients' interval
        lo_hi = [lam for lam in np.linspace(0.5, 1.5, 2001) * lam_true]
        err = [
            np.max(np.abs(c - chebyshev_coefficients(lam / 30, hi * lam, CHEBYSHEV_DEGREE)))
            for lam, c in ((lam, coeffs) for lam in lo_hi)
        ]
        lam_est = lo_hi[int(np.argmin(err))]
        assert 0.95 * lam_true <= lam_est <= 1.0001 * lam_true, (lam_est, lam_true)
        damp = 1.0 - t * hi * lam_est * np.polyval(coeffs, t * hi * lam_est)
        assert np.all(np.abs(damp[t * hi >= 1 / 30]) < 1.0)
    rng = np.random.default_rng(3)
    for _ in range(3):
        r, q = rng.standard_normal((2, mesh.n_dofs))
        r[fixed] = q[fixed] = 0.0
        Mr, Mq = s.precondition(r), s.precondition(q)
        assert r @ Mr > 0
        assert abs(q @ Mr - r @ Mq) <= 1e-10 * np.linalg.norm(q) * np.linalg.norm(Mr)
    ritz = [v.copy() for v in s._ritz]
    assert host.factor(1.1 * Ke, md, TOKEN) == SUCCESS and not s.rebuilt
    # refresh="fine": a new estimate on the finest level only (the coarse ones unchanged)
    assert not np.array_equal(ritz[0], s._ritz[0])
    assert all(np.array_equal(a, b) for a, b in zip(ritz[1:], s._ritz[1:], strict=True))
    with pytest.raises(ValueError, match="smoother"):
        AMGSolver(mesh.points, fixed, smoother="sor")


def test_amg_warm_lanczos_estimate_and_rebuilt_sizes():
    """A refresh re-estimates λ_max(D⁻¹A) by LANCZOS_WARM_STEPS steps from the previous
    Ritz vector, within 2 % below the dense eigenvalue; a rebuild starts the coarse levels
    cold (their stored Ritz vectors, here of other sizes, belong to the old bases)."""
    from jaxelastic.solvers.host.amg import LANCZOS_WARM_STEPS, lanczos_max

    mesh, fixed, Ke, md, rhs = _problem("twist")
    host = _host(mesh, fixed, "amg", sa_options=dict(max_coarse=10))
    s = host.backend
    assert host.factor(Ke, md, TOKEN) == SUCCESS
    K2 = host.assemble(1.3 * Ke, md)
    A = s._amg_matrix(K2)
    d = A.diagonal()
    lam_true = np.max(np.linalg.eigvalsh((A.toarray() / np.sqrt(d)[:, None]) / np.sqrt(d)))
    lam, _ = lanczos_max(A, 1.0 / np.sqrt(d), s._ritz[0], LANCZOS_WARM_STEPS)
    assert 0.98 * lam_true <= lam <= (1.0 + 1e-12) * lam_true, (lam, lam_true)
    s._ritz = [s._ritz[0]] + [v[:-3] for v in s._ritz[1:]]  # as if the sizes had changed
    s.reuse = 1  # the next update rebuilds
    assert host.factor(1.3 * Ke, md, TOKEN) == SUCCESS and s.rebuilt
    assert [v.size for v in s._ritz] == [lv.A.shape[0] for lv in s.ml.levels[:-1]]
    b = rhs.reshape(-1).copy()
    b[fixed] = 0.0
    x, its, status = s.solve(b, 1e-8 * np.linalg.norm(b), 200)
    assert status == 0 and its < 60


def test_host_cg_matches_device_cg():
    """The host PCG of the AMG back end (one callback per Newton step) takes the device
    CG's iterations on the same matrix and preconditioner: same iterate to round-off, same
    iteration count; non-positive curvature and the iteration cap give the device's
    statuses."""
    from jaxelastic.solvers.host import host_cg
    from jaxelastic.solvers.linear import cg
    from jaxelastic.solvers.results import Status

    mesh, fixed, Ke, md, rhs = _problem("twist")
    host = _host(mesh, fixed, "amg", sa_options=dict(max_coarse=10))
    assert host.factor(Ke, md, TOKEN) == SUCCESS
    K = host.assemble(Ke, md)
    b = rhs.reshape(-1).copy()
    b[fixed] = 0.0
    tol = 1e-9 * np.linalg.norm(b)
    M = host.backend.precondition
    x_h, its_h, st_h = host_cg(lambda v: K @ v, b, M, tol, 200)
    Kd = jnp.asarray(K.toarray())
    dev = cg(
        lambda v: Kd @ v,
        jnp.asarray(b),
        lambda r: jax.pure_callback(M, jax.ShapeDtypeStruct(r.shape, r.dtype), r),
        tol=tol,
        max_iter=200,
    )
    assert st_h == Status.SUCCESS == int(dev.status)
    assert its_h == int(dev.stats["iterations"])
    np.testing.assert_allclose(x_h, np.asarray(dev.x), rtol=1e-9, atol=1e-12)
    assert np.linalg.norm(K @ x_h - b) <= 1.01 * tol
    # the one-callback Newton path: a refresh (its smoother's estimate warm-started, so
    # a slightly different preconditioner), then the same solve; zero on fixed dofs
    data = host.pattern.upper_data(np.asarray(Ke))
    x2, its2, st2 = host.factor_cg_upper(data, md, rhs, tol, np.int32(200), TOKEN)
    assert int(st2) == Status.SUCCESS and abs(int(its2) - its_h) <= 1
    assert not x2.reshape(-1)[fixed].any()
    assert np.linalg.norm(K @ x2.reshape(-1) - b) <= 1.01 * tol
    # an indefinite operator: negative curvature, the preconditioned residual at k = 0
    x_n, its_n, st_n = host_cg(lambda v: -(K @ v), b, M, tol, 200)
    assert (its_n, st_n) == (1, Status.NEGATIVE_CURVATURE)
    np.testing.assert_array_equal(x_n, M(b))
    _, its_c, st_c = host_cg(lambda v: K @ v, b, M, 1e-30, 3)
    assert (its_c, st_c) == (3, Status.MAX_STEPS)
    # non-finite data: NONFINITE, NaN on the free dofs, nothing factorised
    bad = data.copy()
    bad[0] = np.nan
    x3, _, st3 = host.factor_cg_upper(bad, md, rhs, tol, np.int32(200), TOKEN)
    assert int(st3) == NONFINITE and np.isnan(x3.reshape(-1)[~fixed]).all()
    direct = _host(mesh, fixed, "direct")
    with pytest.raises(ValueError, match="amg"):
        direct.factor_cg_upper(data, md, rhs, tol, np.int32(200), TOKEN)


def test_amg_rebuilds_on_slower_convergence():
    """Between the ``reuse`` cap, the hierarchy is rebuilt only when the residual norms
    handed to the preconditioner show a markedly slower CG than the first one measured
    after the last rebuild (REBUILD_DIGITS_RATIO of its digits per iteration)."""
    mesh, fixed, Ke, md, rhs = _problem("twist")
    host = _host(mesh, fixed, "amg", sa_options=dict(max_coarse=10))
    s = AMGSolver(mesh.points, fixed, sa_options=dict(max_coarse=10), pattern=host.pattern)
    K = host.assemble(Ke, md)
    r = rhs.reshape(-1)

    def solve_with_rate(rho, its=RATE_MIN_RATIOS + 1):  # the residuals of a CG at rate ρ
        for i in range(its):
            s.precondition(r * rho**i)

    s.update(K)
    assert s.rebuilt and s.rate is None
    solve_with_rate(0.1)
    s.update(K)  # the reference rate, measured
    assert not s.rebuilt and s.rate == pytest.approx(0.1)
    solve_with_rate(0.15)  # 0.82 of the digits per iteration: keep
    s.update(K)
    assert not s.rebuilt
    solve_with_rate(0.5, its=RATE_MIN_RATIOS)  # a short CG (inexact Newton): not measured
    s.update(K)
    assert not s.rebuilt and s.rate is None
    solve_with_rate(0.3)  # 0.52 of the digits per iteration: rebuild
    s.update(K)
    assert s.rebuilt and s.rate == pytest.approx(0.3)
    # a rise (the start of another solve) is not a ratio; too few ratios measure nothing
    s.precondition(r)
    s.precondition(0.5 * r)
    s.precondition(10.0 * r)
    s.update(K)
    assert s.rate is None and not s.rebuilt


def test_amg_fine_refresh():
    """``refresh="fine"`` sets the new matrix on the finest level only, and refreshes the
    coarse operators (Galerkin) once the CG's convergence per iteration degrades."""
    mesh, fixed, Ke, md, rhs = _problem("twist")
    host = _host(mesh, fixed, "amg", sa_options=dict(max_coarse=10))
    opts = dict(sa_options=dict(max_coarse=10), pattern=host.pattern, refresh="fine")
    s = AMGSolver(mesh.points, fixed, **opts)
    K1, K2 = host.assemble(Ke, md), host.assemble(1.3 * Ke, md)
    r = rhs.reshape(-1)
    s.update(K1)
    assert s.ml is not None
    coarse = s.ml.levels[1].A
    for i in range(RATE_MIN_RATIOS + 1):
        s.precondition(r * 0.1**i)
    s.update(K2)  # converged fast: fine level only
    assert not s.rebuilt and s.ml.levels[1].A is coarse
    np.testing.assert_array_equal(s.ml.levels[0].A.toarray(), s._amg_matrix(K2).toarray())
    for i in range(RATE_MIN_RATIOS + 1):
        s.precondition(r * 0.2**i)  # 0.70 of the digits per iteration: Galerkin refresh
    s.update(K2)
    assert not s.rebuilt and s.ml.levels[1].A is not coarse
    Rc = s.ml.levels[0].R @ s._amg_matrix(K2) @ s.ml.levels[0].P
    np.testing.assert_allclose(s.ml.levels[1].A.toarray(), Rc.toarray(), rtol=1e-12, atol=1e-12)
    _, its = _pcg(K2, r, s.precondition)
    assert its < 30
    with pytest.raises(ValueError, match="refresh"):
        AMGSolver(mesh.points, fixed, refresh="coarse")


def test_amg_flags_nonpositive_diagonal():
    mesh, fixed, Ke, md, rhs = _problem("cantilever")
    host = _host(mesh, fixed, "amg")
    assert host.factor(-Ke, md, TOKEN) == NOT_POSITIVE_DEFINITE


# ----------------------------------------------------------------------------------------
# identity, construction errors, thread safety
# ----------------------------------------------------------------------------------------


def test_hash_and_eq_by_content():
    mesh, fixed, *_ = _problem("cantilever")
    a = _host(mesh, fixed)
    b = HostLinearSolver(
        np.array(mesh.cells), np.array(mesh.points), fixed.reshape(-1, 3).copy(), "direct"
    )
    assert a == b and hash(a) == hash(b) and len({a, b}) == 1
    other_mask = fixed.copy()
    other_mask[-1] = True
    for c in (
        _host(mesh, fixed, "amg"),
        _host(mesh, fixed, "direct", backend="splu"),
        _host(mesh, other_mask),
        HostLinearSolver(mesh.cells, np.asarray(mesh.points) * 2.0, fixed.reshape(-1, 3)),
    ):
        assert c != a and hash(c) != hash(a)
    assert a != "direct"
    assert repr(a) == f"HostLinearSolver(kind='direct', n_dofs={mesh.n_dofs})"
    assert _host(mesh, fixed, "amg", reuse=2) == _host(mesh, fixed, "amg", reuse=2)


def test_construction_errors():
    mesh, fixed, Ke, md, rhs = _problem("cantilever")
    with pytest.raises(ValueError, match="direct, amg"):
        _host(mesh, fixed, "cholmod")
    with pytest.raises(ValueError, match="fixed mask"):
        HostLinearSolver(mesh.cells, mesh.points, fixed)
    with pytest.raises(ValueError, match="reuse"):
        _host(mesh, fixed, "amg", reuse=0)
    assert BACKEND_KINDS == ("direct", "amg")
    assert isinstance(make_backend("amg", mesh.points, fixed, reuse=2), AMGSolver)
    with pytest.raises(ValueError, match="points"):
        make_backend("amg")
    host = _host(mesh, fixed)
    with pytest.raises(ValueError, match="shape"):
        host.apply(rhs[:-1], TOKEN)
    # apply before any factor: NaN on the free dofs, zero on the fixed ones
    y = host.apply(rhs, TOKEN).reshape(-1)
    assert np.isnan(y[~fixed]).all() and not y[fixed].any()
    bc = jaxelastic.Dirichlet(mask=jnp.asarray(fixed.reshape(-1, 3)), values=mesh.points)
    assert HostLinearSolver.for_problem(mesh, bc) == host


def test_calls_are_serialised():
    mesh, fixed, Ke, md, rhs = _problem("cantilever")
    host = _host(mesh, fixed)
    active, peak = [0], [0]
    inner_update, inner_solve = host.backend.update, host.backend.solve

    def guarded(fn):
        def wrapper(*a):
            active[0] += 1
            peak[0] = max(peak[0], active[0])
            time.sleep(0.005)
            try:
                return fn(*a)
            finally:
                active[0] -= 1

        return wrapper

    inner_upper = host.backend.update_upper
    host.backend.update = guarded(inner_update)
    host.backend.update_upper = guarded(inner_upper)
    host.backend.solve = guarded(inner_solve)
    host.factor(Ke, md, TOKEN)
    errors = []

    def worker(i):
        try:
            if i % 2:
                assert host.factor(Ke, md, TOKEN) == SUCCESS
            else:
                assert np.isfinite(host.apply(rhs, TOKEN)).all()
        except Exception as e:  # noqa: BLE001 - reported below
            errors.append(e)

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and peak[0] == 1
    assert (host.calls, host.factorizations, host.applications) == (9, 5, 4)


_RSS_SCRIPT = """
import json, resource, sys
import jax
jax.config.update("jax_enable_x64", True)
import jaxelastic as je
from jaxelastic import verification as benchmarks
b = benchmarks.twist(int(sys.argv[1]))
newton = je.solvers.prepare_solver(je.Newton(rtol=1e-8, linear="direct"), b.mesh, b.bc)
for _ in range(2):  # cold and warm, as a scene's static solve then a time step
    r = je.solve(b.pot, b.bc, solver=newton, throw=False)
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
print(json.dumps(dict(status=int(r.status), peak=peak)))
"""


@pytest.mark.slow
def test_memory_estimate_matches_measured_peak():
    """:func:`jaxelastic.scene.memory.estimate_parts` is within 1.5× of the measured peak
    RSS of a twist solve (n = 14: 16k tets, 10k dofs, direct) in a fresh process."""
    import json
    import subprocess
    import sys

    from jaxelastic.scene import memory

    n = 14
    out = subprocess.run(
        [sys.executable, "-c", _RSS_SCRIPT, str(n)], capture_output=True, text=True, check=True
    )
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["status"] == 0
    size = memory.MeshSize((n + 1) ** 3, 6 * n**3, 3, "tet4", 4, 1, "twist")
    est = sum(memory.estimate_parts(size, linear="direct").values())
    assert r["peak"] / 1.5 <= est <= 1.5 * r["peak"], (est / 2**20, r["peak"] / 2**20)


def test_split_matvec_equals_the_product(monkeypatch):
    """The row-split, threaded product (AMG's large level matrices) gives the product bit
    for bit: each row is summed in the same order; empty and uneven parts included."""
    from jaxelastic.solvers.host import products

    monkeypatch.setattr(products, "SPLIT_MIN_ENTRIES", 0)
    monkeypatch.setattr(products, "_cores", lambda: 3)
    rng = np.random.default_rng(3)
    A = sp.random(90, 60, density=0.2, random_state=4, format="csr")
    B = sp.kron(sp.random(30, 20, density=0.3, random_state=5), np.ones((3, 3))).tobsr((3, 3))
    # all entries in the first rows: the later parts are empty
    C = sp.csr_matrix((np.arange(1.0, 6.0), ([0, 0, 1, 1, 2], [0, 5, 1, 7, 3])), shape=(40, 8))
    for M in (A, B, C):
        v = rng.standard_normal(M.shape[1])
        mv = products.split_matvec(M)
        assert mv != M.__matmul__  # (the split path, not the fallback)
        np.testing.assert_array_equal(mv(v), M @ v)
    monkeypatch.setattr(products, "SPLIT_MIN_ENTRIES", 1 << 20)
    assert products.split_matvec(A) == A.__matmul__  # small: the plain product


def test_galerkin_product_equals_the_product(monkeypatch):
    """The row-split, threaded ``R A P`` (AMG's Galerkin refresh from the host Newton loop)
    gives ``R @ A @ P`` bit for bit, in the same format and block size; CSR and BSR,
    uneven and empty row parts included; the stacking keeps the structure."""
    from jaxelastic.solvers.host import products

    monkeypatch.setattr(products, "SPLIT_MIN_ENTRIES", 0)
    monkeypatch.setattr(products, "_cores", lambda: 3)
    A = sp.random(60, 60, density=0.1, random_state=1, format="csr")
    A = (A + A.T + 60 * sp.eye(60)).tocsr()
    P = sp.random(60, 12, density=0.2, random_state=2, format="csr")
    Pz = P.tolil()
    Pz[:, :4] = 0.0  # R's first rows empty
    Pz = Pz.tocsr()
    Ab = sp.kron(A, np.ones((3, 3))).tobsr((3, 3))
    Pb = sp.kron(P, np.ones((3, 6))).tobsr((3, 6))
    for R_, A_, P_ in ((P.T.tocsr(), A, P), (Pz.T.tocsr(), A, Pz), (Pb.T.tobsr(), Ab, Pb)):
        ref = R_ @ A_ @ P_
        out = products.galerkin_product(R_, A_, P_)
        assert out.format == ref.format and out.shape == ref.shape
        if ref.format == "bsr":
            assert out.blocksize == ref.blocksize
        np.testing.assert_array_equal(out.toarray(), ref.toarray())
        out.check_format(full_check=True)
    monkeypatch.setattr(products, "SPLIT_MIN_ENTRIES", 1 << 20)
    R = P.T.tocsr()
    small = products.galerkin_product(R, A, P)  # small: the plain product
    np.testing.assert_array_equal(small.toarray(), (R @ A @ P).toarray())


def test_amg_threaded_solve_equals_serial(monkeypatch):
    """``AMGSolver.solve(threads=True)`` (the host Newton loop's call from Python) runs the
    same CG with the same V-cycles as without threads: the same iterate bit for bit."""
    from jaxelastic.solvers.host import products

    monkeypatch.setattr(products, "SPLIT_MIN_ENTRIES", 0)
    mesh, fixed, Ke, md, rhs = _problem("twist")
    host = _host(mesh, fixed, "amg", sa_options=dict(max_coarse=10))
    s = AMGSolver(mesh.points, fixed, sa_options=dict(max_coarse=10), pattern=host.pattern)
    K = host.assemble(Ke, md)
    b = np.asarray(rhs, np.float64).reshape(-1)
    b[fixed] = 0.0
    s.update(K)
    x1, its1, st1 = s.solve(b, 1e-8 * np.linalg.norm(b), 200)
    x2, its2, st2 = s.solve(b, 1e-8 * np.linalg.norm(b), 200, threads=True)
    assert st1 == st2 == SUCCESS and its1 == its2 > 2
    np.testing.assert_array_equal(x2, x1)


def test_a_batch_of_right_hand_sides_is_one_host_solve():
    """Under jax.vmap (the tangents of jax.jacfwd) the host preconditioner's application is
    one call with every right-hand side, equal to applying them one by one."""
    from jaxelastic.solvers.linear.host import _host_preconditioner

    mesh, fixed, Ke, md, rhs = _problem("cantilever")
    host = _host(mesh, fixed)
    assert host.factor(Ke, md, TOKEN) == SUCCESS
    free = jnp.asarray(~fixed.reshape(rhs.shape))
    M = _host_preconditioner(host, free, jnp.asarray(TOKEN))
    R = np.stack([rhs, -3.0 * rhs + 1.0])
    before = host.applications
    X = np.asarray(jax.jit(jax.vmap(M))(jnp.asarray(R)))
    assert host.applications == before + 1
    for r, x in zip(R, X, strict=True):
        np.testing.assert_allclose(x, np.where(free, host.apply(r, TOKEN), 0.0), rtol=1e-12)
