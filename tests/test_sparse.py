"""Host sparse assembly and linear solvers (jaxelastic.solvers.sparse)."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp

import jaxelastic
from jaxelastic.materials import Lame, neo_hookean
from jaxelastic.solvers.sparse import (
    SOLVER_KINDS,
    AMGSolver,
    DirectSolver,
    ScipyCGSolver,
    SparsityPattern,
    make_solver,
    rigid_body_modes,
)

PARAMS = Lame(mu=jnp.asarray(3.0), lam=jnp.asarray(5.0))


def _mesh(dim):
    return jaxelastic.rectangle(3, 2) if dim == 2 else jaxelastic.box(2, 1, 2)


# one compilation per mesh shape (the mesh is a jit argument, never closed over)
_element_hessians = jax.jit(jaxelastic.element_hessians, static_argnums=0)
_hvp = jax.jit(jaxelastic.hvp, static_argnums=0)


def _deformed(mesh, seed=0, amp=0.03):
    rng = np.random.default_rng(seed)
    X = np.asarray(mesh.points)
    return jnp.asarray(X + amp * rng.standard_normal(X.shape))


def _dense_hessian(mesh, x):
    """Dense Hessian column by column from the matrix-free HVP, ``(n_dofs, n_dofs)``."""
    n, d = mesh.points.shape
    cols = [_hvp(neo_hookean, x, e.reshape(n, d), mesh, PARAMS) for e in jnp.eye(n * d)]
    return np.stack([np.asarray(c).reshape(-1) for c in cols], axis=1)


def _pattern_and_ke(mesh, x, fixed=None):
    n, d = mesh.points.shape
    P = SparsityPattern.build(np.asarray(mesh.cells), n, d, fixed)
    Ke = np.asarray(_element_hessians(neo_hookean, x, mesh, PARAMS))
    return P, Ke


def _clamped(mesh, side=0):
    """Dirichlet mask fixing every dof of the nodes on the face/edge x = side."""
    X = np.asarray(mesh.points)
    return np.repeat(X[:, 0] == side, mesh.dim)


@pytest.mark.parametrize("dim", [2, 3])
def test_assembled_equals_dense_hvp_hessian(dim):
    mesh = _mesh(dim)
    x = _deformed(mesh)
    P, Ke = _pattern_and_ke(mesh, x)
    H = _dense_hessian(mesh, x)
    K = P.assemble_full(Ke)
    assert isinstance(K, sp.csr_matrix) and K.has_sorted_indices
    np.testing.assert_allclose(K.toarray(), H, rtol=1e-10, atol=1e-10 * np.abs(H).max())
    # unsymmetrised assembly is the plain sum too, and the pattern covers every coupling
    np.testing.assert_allclose(P.assemble_full(Ke, symmetrize=False).toarray(), H, atol=1e-9)
    in_pattern = P.matrix(np.ones(P.nnz)).toarray() != 0
    assert np.all(in_pattern[np.abs(H) > 0])
    assert K.nnz == P.nnz


def test_pattern_structure_and_bsr():
    mesh = _mesh(3)
    n, d = mesh.points.shape
    P, Ke = _pattern_and_ke(mesh, _deformed(mesh, 1))
    assert P.indptr.dtype == np.int32 and P.indices.dtype == np.int32
    assert P.scatter.size == Ke.size and P.scatter.max() < P.nnz
    K = P.assemble(Ke)
    np.testing.assert_array_equal(P.to_bsr(K).toarray(), K.toarray())
    assert P.has_pattern(K) and not P.has_pattern(K[:-1, :-1])
    # data[transpose] is the transpose
    np.testing.assert_array_equal(P.matrix(K.data[P.transpose]).toarray(), K.toarray().T)
    with pytest.raises(ValueError, match="entries"):
        P.assemble(Ke[:-1])
    # diagonal slots, and adding a diagonal keeps the pattern
    np.testing.assert_array_equal(K.data[P.diag_slots], K.diagonal())
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
    K = P.assemble(Ke)
    A = K.toarray()
    free = ~fixed
    np.testing.assert_array_equal(A[np.ix_(free, free)], full[np.ix_(free, free)])
    np.testing.assert_array_equal(A[np.ix_(fixed, fixed)], np.eye(fixed.sum()))
    assert not A[np.ix_(fixed, free)].any() and not A[np.ix_(free, fixed)].any()
    np.testing.assert_array_equal(A, A.T)
    # the pattern is kept: same structure with and without elimination
    np.testing.assert_array_equal(K.indices, P.indices)
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


@functools.cache
def _spd_system():
    """A small clamped 3D elasticity system K u = b at a mildly deformed state."""
    mesh = jaxelastic.box(6, 2, 2, size=(3.0, 1.0, 1.0))
    fixed = _clamped(mesh)
    x = _deformed(mesh, 4, amp=0.01)
    P, Ke = _pattern_and_ke(mesh, x, fixed)
    K = P.assemble(Ke)
    b = np.zeros((mesh.n_nodes, 3))
    b[:, 2] = -1.0
    b = b.reshape(-1)
    b[fixed] = 0.0
    return mesh, fixed, P, K, b


@pytest.mark.parametrize("backend", ["auto", "splu"])
def test_direct_solver(backend):
    _, _, _, K, b = _spd_system()
    s = DirectSolver(backend=backend)
    s.update(K)
    x, info = s.solve(b, rtol=1e-10)
    assert info["converged"] and info["positive_definite"], info
    assert info["residual"] <= 1e-10
    np.testing.assert_allclose(x, np.linalg.solve(K.toarray(), b), rtol=1e-8, atol=1e-12)


@pytest.mark.parametrize("rtol", [1e-6, 1e-10])
def test_amg_solver_reaches_tolerance(rtol):
    mesh, fixed, P, K, b = _spd_system()
    ref = np.linalg.solve(K.toarray(), b)
    s = AMGSolver(mesh.points, fixed, pattern=P, sa_options=dict(max_coarse=10))
    s.update(K)
    x, info = s.solve(b, rtol=rtol)
    assert info["converged"], info
    assert np.linalg.norm(b - K @ x) <= rtol * np.linalg.norm(b) * 1.01
    assert info["iterations"] < 60
    assert np.linalg.norm(x - ref) <= 1e3 * rtol * np.linalg.norm(ref)


def test_amg_reuse_and_refresh():
    mesh, fixed, P, K, b = _spd_system()
    K2 = P.matrix(K.data * 1.5)  # a "new Newton matrix" with the same pattern
    K2.data[P.fixed_diag] = 1.0
    for refresh in ("galerkin", "none"):
        s = AMGSolver(mesh.points, fixed, reuse=3, refresh=refresh, pattern=P)
        s.update(K)
        assert s.rebuilt
        s.update(K2)
        assert not s.rebuilt
        x, info = s.solve(b, rtol=1e-8)
        assert info["converged"] and not info["rebuilt"], info
        np.testing.assert_allclose(K2 @ x, b, atol=1e-7 * np.linalg.norm(b))
        s.update(K2)
        s.update(K2)
        assert s.rebuilt  # every 3rd update rebuilds


def test_cg_jacobi_and_zero_rhs():
    _, _, _, K, b = _spd_system()
    s = ScipyCGSolver()
    s.update(K)
    x, info = s.solve(b, rtol=1e-8)
    assert info["converged"] and info["iterations"] > 10
    x0, info0 = s.solve(np.zeros_like(b), rtol=1e-8)
    assert info0["converged"] and info0["iterations"] == 0 and not x0.any()


def test_cg_reports_max_iterations():
    _, _, _, K, b = _spd_system()
    s = ScipyCGSolver(maxiter=3)
    s.update(K)
    _, info = s.solve(b, rtol=1e-10)
    assert not info["converged"] and info["reason"] == "max iterations"


@pytest.mark.parametrize("backend", ["auto", "splu"])
def test_direct_detects_indefinite(backend, capfd):
    _, _, _, K, b = _spd_system()
    n = K.shape[0]
    shift = 0.5 * sp.linalg.eigsh(K, k=1, which="LA", return_eigenvectors=False)[0]
    Kind = (K - shift * sp.identity(n, format="csr")).tocsr()  # indefinite, nonsingular
    s = DirectSolver(backend=backend)
    s.update(Kind)
    x, info = s.solve(b, rtol=1e-10)
    assert not info["converged"] and info["reason"] == "not positive definite"
    assert info["positive_definite"] is False and np.isnan(x).all()
    assert "CHOLMOD" not in capfd.readouterr().out  # CHOLMOD's own message is silenced
    # on_indefinite="lu" solves it anyway and says so
    s = DirectSolver(backend=backend, on_indefinite="lu")
    s.update(Kind)
    x, info = s.solve(b, rtol=1e-10)
    assert info["converged"] and info["positive_definite"] is False
    assert "not positive definite" in info["reason"]
    np.testing.assert_allclose(Kind @ x, b, atol=1e-9 * np.linalg.norm(b))
    # negative definite and singular matrices are refused too
    for bad in (-K, sp.diags(np.r_[np.ones(n - 1), 0.0]).tocsr()):
        s = DirectSolver(backend=backend)
        s.update(bad)
        _, info = s.solve(b, rtol=1e-10)
        assert not info["converged"] and info["reason"] == "not positive definite"


def test_make_solver():
    mesh, fixed, P, K, b = _spd_system()
    for kind in SOLVER_KINDS:
        s = make_solver(kind, mesh.points, fixed)
        s.update(K)
        x, info = s.solve(b, rtol=1e-8)
        assert info["converged"], (kind, info)
        assert {"iterations", "converged", "residual"} <= set(info)
    assert isinstance(make_solver("amg", mesh.points, fixed, reuse=2), AMGSolver)
    with pytest.raises(ValueError, match="direct, amg, cg-jacobi"):
        make_solver("cholmod", mesh.points, fixed)
    with pytest.raises(RuntimeError, match="update"):
        DirectSolver().solve(b)


def test_amg_2d():
    mesh = jaxelastic.rectangle(12, 3, size=(4.0, 1.0))
    fixed = _clamped(mesh)
    P, Ke = _pattern_and_ke(mesh, mesh.points, fixed)
    K = P.assemble(Ke)
    b = np.zeros((mesh.n_nodes, 2))
    b[:, 1] = -1.0
    b = b.reshape(-1)
    b[fixed] = 0.0
    s = make_solver("amg", mesh.points, fixed, pattern=P, sa_options=dict(max_coarse=5))
    s.update(K)
    x, info = s.solve(b, rtol=1e-9)
    assert info["converged"] and info["levels"] >= 2, info
    np.testing.assert_allclose(x, np.linalg.solve(K.toarray(), b), rtol=1e-6, atol=1e-12)


def test_cg_stops_on_negative_curvature():
    K = sp.csr_matrix(np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]]))
    s = ScipyCGSolver()
    s.update(K)
    _, info = s.solve(np.array([1.0, -1.0, 0.5]), rtol=1e-10)
    assert not info["converged"] and "negative curvature" in info["reason"]
    assert info["iterations"] == 1
