"""Direct back ends (PARDISO, CHOLMOD, cholespy, SuperLU), their fallback chain, the int32
device assembly, and linear problems in one Newton step.

Every back end importable here is checked against a dense solve and for detecting
matrices that are not positive definite (the status that makes the Newton step's projected retry
project and retry); CHOLMOD (scikit-sparse) is tested only where it imports.
"""

import subprocess
import sys
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp

import jaxelastic as je
from jaxelastic import loads, materials
from jaxelastic.solvers.host import (
    NOT_POSITIVE_DEFINITE,
    SUCCESS,
    DirectSolver,
    HostLinearSolver,
    SparsityPattern,
    available_direct_backends,
    direct,
    pardiso,
)

BACKENDS = available_direct_backends()


def _spd(n=40, seed=0, shift=0.0):
    """Sparse symmetric ``(n, n)`` CSR: an SPD matrix minus ``shift``·I."""
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((n, n))
    S = A @ A.T / n + np.eye(n)
    S[np.abs(S) < 0.15] = 0.0  # sparse, still symmetric
    S += (np.abs(S).sum(1).max()) * np.eye(n) * 0.5  # keep it SPD after the thinning
    return sp.csr_matrix(S - shift * np.eye(n))


def test_splu_always_available_and_order():
    assert BACKENDS[-1] == "splu"
    order = ["pardiso", "cholmod", "cholespy", "splu"]
    assert list(BACKENDS) == [b for b in order if b in BACKENDS]


@pytest.mark.parametrize("backend", BACKENDS)
def test_backend_matches_dense_solve(backend):
    K = _spd()
    B = np.random.default_rng(1).standard_normal((K.shape[0], 3))
    ref = np.linalg.solve(K.toarray(), B)
    s = DirectSolver(backend=backend)
    for scale in (1.0, 2.5):  # a second factorisation of the same pattern
        s.update(scale * K)
        assert s.positive_definite and s.ready and s.method == "cholesky" or backend == "splu"
        np.testing.assert_allclose(s.solve(B), ref / scale, rtol=1e-10, atol=1e-13)
        np.testing.assert_allclose(s.solve(B[:, 1]), ref[:, 1] / scale, rtol=1e-10, atol=1e-13)
    s.release()
    assert not s.ready


@pytest.mark.parametrize("backend", BACKENDS)
def test_backend_detects_indefinite(backend):
    K = _spd()
    lam = np.linalg.eigvalsh(K.toarray())
    b = np.random.default_rng(2).standard_normal(K.shape[0])
    for M in (K - 0.5 * (lam[2] + lam[3]) * sp.eye(K.shape[0]), -K):
        s = DirectSolver(backend=backend)  # on_indefinite="lu": still solves
        s.update(sp.csr_matrix(M))
        assert s.positive_definite is False
        x = s.solve(b)
        assert np.linalg.norm(M @ x - b) <= 1e-9 * np.linalg.norm(b)
        strict = DirectSolver(backend=backend, on_indefinite="fail")
        strict.update(sp.csr_matrix(M))
        assert strict.positive_definite is False and np.isnan(strict.solve(b)).all()
    # a singular matrix: not positive definite, and no (garbage) solve
    s = DirectSolver(backend=backend)
    s.update(sp.diags(np.r_[np.ones(9), 0.0]).tocsr())
    assert s.positive_definite is False and np.isnan(s.solve(np.ones(10))).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_host_indefinite_status_per_backend(backend):
    """The status the projected retry acts on, for a FEM matrix, with every back end."""
    mesh = je.box(3, 2, 2)
    X = np.asarray(mesh.points)
    fixed = np.repeat(X[:, 0] == 0.0, 3)
    host = HostLinearSolver(mesh.cells, mesh.points, fixed.reshape(-1, 3), backend=backend)
    Ke = np.asarray(
        je.mechanics.element_hessians(materials.neo_hookean, mesh.points, mesh, _PARAMS)
    )
    assert host.factor(Ke, None) == SUCCESS
    assert host.last_info["backend"] == backend
    K = host.assemble(Ke)
    top = np.linalg.eigvalsh(K.toarray()).max()
    assert host.factor(Ke, np.full(mesh.n_nodes, -0.5 * top)) == NOT_POSITIVE_DEFINITE
    assert host.factor(-Ke, None) == NOT_POSITIVE_DEFINITE
    assert host.factor(Ke, None) == SUCCESS


_PARAMS = je.Lame.from_E_nu(10.0, 0.3)


@pytest.mark.skipif("pardiso" not in BACKENDS, reason="pypardiso / MKL not importable")
def test_pardiso_analyses_once_per_pattern():
    K = _spd()
    s = DirectSolver(backend="pardiso")
    assert s.wants_upper
    for scale in (1.0, 2.0, 3.0):
        s.update(scale * K)
    h = s._pardiso
    assert h is not None and h.analyses == 1 and s.factor_nnz and s.factor_nnz > 0
    s.update(_spd(seed=5))  # another pattern: analysed again
    assert h.analyses == 2
    # the upper-triangle entry point with every diagonal stored, even a zero one
    U = sp.triu(K, format="csr")
    s.update_upper(U)
    b = np.ones(K.shape[0])
    np.testing.assert_allclose(K @ s.solve(b), b, rtol=1e-10)


@pytest.mark.skipif("cholmod" not in BACKENDS, reason="scikit-sparse not importable")
def test_cholmod_reuses_analysis():
    K = _spd()
    s = DirectSolver(backend="cholmod")
    s.update(K)
    first = s._cholmod
    s.update(2.0 * K)
    assert s._cholmod is first
    b = np.ones(K.shape[0])
    np.testing.assert_allclose(2.0 * K @ s.solve(b), b, rtol=1e-10)


def test_fallback_chain_warns_once(monkeypatch):
    """Without pypardiso (and scikit-sparse) ``auto`` falls back, saying so once."""
    monkeypatch.setitem(sys.modules, "pypardiso", None)  # `import pypardiso` fails
    monkeypatch.setitem(sys.modules, "pypardiso.pardiso_wrapper", None)
    monkeypatch.setitem(sys.modules, "sksparse", None)
    monkeypatch.setitem(sys.modules, "sksparse.cholmod", None)
    monkeypatch.setattr(pardiso, "_MKL", [])
    monkeypatch.setattr(direct, "_WARNED", set())
    assert pardiso.pardiso_function() is None
    assert available_direct_backends()[0] in ("cholespy", "splu")
    with pytest.warns(RuntimeWarning, match="falls back"):
        s = DirectSolver()
    assert s.backend == available_direct_backends()[0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        DirectSolver()  # no second warning
    with pytest.raises(ImportError, match="pypardiso"):
        DirectSolver(backend="pardiso")
    K = _spd()
    s.update(K)
    assert s.positive_definite
    np.testing.assert_allclose(K @ s.solve(np.ones(40)), np.ones(40), rtol=1e-10)


def test_import_does_not_load_host_packages():
    code = (
        "import sys, jaxelastic; bad = [m for m in ('pypardiso', 'mkl', 'sksparse', "
        "'cholespy', 'pyamg') if m in sys.modules]; print(bad); sys.exit(bool(bad))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr


# ----------------------------------------------------------------------------------------
# int32 maps and the device assembly
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("order", [1, 2])
def test_device_assembly_equals_host(order):
    from jaxelastic.solvers.linear import assemble_upper  # the device assembly

    mesh = je.box(2, 2, 1, order=order)
    X = np.asarray(mesh.points)
    fixed = np.repeat(X[:, 0] == 0.0, 3)
    host = HostLinearSolver(mesh.cells, mesh.points, fixed.reshape(-1, 3))
    P: SparsityPattern = host.pattern
    assert host.element_map.dtype == np.int32
    rng = np.random.default_rng(3)
    Ke = rng.standard_normal((mesh.n_cells,) + (mesh.cells.shape[1] * 3,) * 2)
    emap = jnp.asarray(host.element_map)
    dev = np.asarray(jax.jit(lambda K: assemble_upper(K, emap, host.nnz_upper))(jnp.asarray(Ke)))
    np.testing.assert_allclose(dev, P.upper_data(Ke), rtol=1e-13, atol=1e-13)
    # symmetrisation folded in: the full matrix is (ΣKe + ΣKeᵀ)/2
    full = P.matrix(P.full_data(dev)).toarray()
    n = mesh.n_dofs
    dense = np.zeros((n, n))
    dofs = (np.asarray(mesh.cells)[:, :, None] * 3 + np.arange(3)).reshape(mesh.n_cells, -1)
    for c in range(mesh.n_cells):
        dense[np.ix_(dofs[c], dofs[c])] += Ke[c]
    np.testing.assert_allclose(full, 0.5 * (dense + dense.T), rtol=1e-12, atol=1e-12)


def test_pattern_memory_is_int32():
    mesh = je.box(6, 6, 6)
    P = SparsityPattern.build(np.asarray(mesh.cells), mesh.n_nodes, 3)
    # 4 bytes per upper element entry (27% of the old int64 map of all 144 entries), and
    # all index arrays together less than that old map alone
    assert P.element_map.nbytes == 4 * mesh.n_cells * 78
    assert P.nbytes < 8 * mesh.n_cells * 144


# ----------------------------------------------------------------------------------------
# linear problems: one Newton step
# ----------------------------------------------------------------------------------------


def _linear_problem():
    mesh = je.box(8, 2, 2, size=(4.0, 1.0, 1.0))
    bc = loads.fix(mesh, loads.nodes_on_plane(mesh, 0, 0.0))
    f = jnp.asarray(loads.gravity_load(mesh, 1.0, [0.0, 0.0, -1e-2]))
    pot = je.Potential(mesh=mesh, params=_PARAMS, psi=materials.linear, f_ext=f)
    return pot, bc


@pytest.mark.parametrize("linear", ["direct", "amg", pytest.param("cg", marks=pytest.mark.slow)])
def test_linear_problem_one_newton_step(linear):
    pot, bc = _linear_problem()
    from jaxelastic.solvers.newton import is_quadratic

    assert is_quadratic(pot)
    r = je.solve(pot, bc, solver=je.Newton(linear=linear))
    assert int(r.status) == 0 and int(r.stats["steps"]) == 1, r.stats["residual_history"]


def test_nonlinear_material_is_not_quadratic():
    from jaxelastic.solvers.newton import is_quadratic

    pot, _ = _linear_problem()
    assert not is_quadratic(pot.replace(psi=materials.neo_hookean))
    fbar = je.box(2, 1, 1, order=2, formulation="fbar")
    assert not is_quadratic(je.Potential(mesh=fbar, params=_PARAMS, psi=materials.linear))


def test_auto_keeps_direct_for_quadratic_problems(monkeypatch):
    """``auto`` picks the direct solver for a quadratic potential above the nonlinear
    limit (one factorisation beats an AMG-CG solve there), AMG for a nonlinear one; the
    limits are lowered here so that a small mesh sits between them."""
    from jaxelastic.solvers import linear as L
    from jaxelastic.solvers.linear import auto

    pot, bc = _linear_problem()
    n = pot.mesh.n_dofs
    monkeypatch.setattr(auto, "AUTO_DIRECT_MAX_DOFS", {2: n - 1, 3: n - 1})
    monkeypatch.setattr(auto, "AUTO_DIRECT_MAX_DOFS_QUADRATIC", {2: n, 3: n})
    assert isinstance(L.resolve("auto", pot.mesh, bc), L.AMG)
    assert isinstance(L.resolve("auto", pot.mesh, bc, quadratic=True), L.Direct)
    # je.solve passes is_quadratic(pot): the linear material solves directly, in one step
    r = je.solve(pot, bc, solver=je.Newton(linear="auto"))
    assert int(r.status) == 0 and int(r.stats["steps"]) == 1
    assert r.stats["linear_iterations"] == 1  # a direct solve (AMG-CG would iterate)
    monkeypatch.setattr(auto, "AUTO_DIRECT_MAX_DOFS_QUADRATIC", {2: n - 1, 3: n - 1})
    assert isinstance(L.resolve("auto", pot.mesh, bc, quadratic=True), L.AMG)
