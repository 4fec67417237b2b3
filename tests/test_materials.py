"""Built-in materials: derivatives vs finite differences and hand formulas, rest state,
linearisation, objectivity, behaviour at inversion and repeated singular values, Lamé."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _common import IDS, MODEL_DIMS
from scipy.optimize import brentq

from jaxelastic import materials as M
from jaxelastic.materials import reference
from jaxelastic.mechanics.kinematics import cofactor

MU, LAM = 1.3, 2.9  # distinct values, so that a swapped μ/λ shows
PARAMS = M.Lame(jnp.asarray(MU), jnp.asarray(LAM))
# nearly incompressible (ν ≈ 0.49): λ/μ ≈ 49
PARAMS_STIFF = M.Lame(jnp.asarray(MU), jnp.asarray(49.0 * MU))


INVARIANT = [(n, d) for n, d in MODEL_DIMS if n != "linear"]
INVERTIBLE = [
    "stable_neo_hookean",
    "stable_neo_hookean_log",
    "fixed_corotated",
    "corotated",
    "arap",
]


# --------------------------------------------------------------------------- evaluation kit
# Compiled once per model and dimension, evaluated on many F: compile time is the cost, and
# XLA's backend optimisation level 0 cuts it (same float64 arithmetic).
_O0 = {"xla_backend_optimization_level": 0}


@functools.partial(jax.jit, static_argnames="psi", compiler_options=_O0)
def _eval(Fs, p, *, psi):
    def one(F):
        return psi(F, p), jax.grad(psi)(F, p), jax.hessian(psi)(F, p)

    return jax.vmap(one)(Fs)


@functools.partial(jax.jit, static_argnames="hand", compiler_options=_O0)
def _eval_hand(Fs, p, *, hand):
    return jax.vmap(hand, in_axes=(0, None))(Fs, p)


CHUNK = 64  # every call uses this batch size: one compile per (model, dim)


def _chunked(fn, Fs):
    Fs = np.asarray(Fs, dtype=np.float64)
    n, d = Fs.shape[0], Fs.shape[-1]
    pad = (-n) % CHUNK
    Fp = np.concatenate([Fs, np.broadcast_to(np.eye(d), (pad, d, d))])
    outs = [fn(jnp.asarray(Fp[i : i + CHUNK])) for i in range(0, len(Fp), CHUNK)]
    if isinstance(outs[0], tuple):
        return tuple(np.concatenate([o[k] for o in outs])[:n] for k in range(len(outs[0])))
    return np.concatenate(outs)[:n]


def evaluate(name, Fs, p=PARAMS):
    """ψ ``(n,)``, P ``(n, d, d)`` and ∂²ψ/∂F² ``(n, d, d, d, d)`` at a batch of F."""
    return _chunked(lambda F: _eval(F, p, psi=M.BUILTIN[name]), Fs)


def hand_P(name, Fs, p=PARAMS):
    return _chunked(lambda F: _eval_hand(F, p, hand=reference.HAND_P[name]), Fs)


def rel(a, b, floor=0.0):
    a, b = np.asarray(a), np.asarray(b)
    return np.max(np.abs(a - b)) / max(np.max(np.abs(b)), floor, 1e-300)


# --------------------------------------------------------------------------- F generators
def random_rotation(rng, d):
    Q, R = np.linalg.qr(rng.standard_normal((d, d)))
    Q = Q * np.sign(np.diag(R))[None, :]
    if np.linalg.det(Q) < 0:
        Q[:, 0] = -Q[:, 0]
    return Q


def random_Fs(n, d, seed=0, smin=0.2, smax=5.0, inverted=False):
    """``(n, d, d)`` F = Q₁ diag(s) Q₂ᵀ, log-uniform σ; ``det < 0`` when ``inverted``."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        s = np.exp(rng.uniform(np.log(smin), np.log(smax), size=d))
        if inverted:
            s[-1] = -s[-1]
        out.append(random_rotation(rng, d) @ np.diag(s) @ random_rotation(rng, d).T)
    return np.stack(out)


def rotation(d, angle=0.7):
    c, s = np.cos(angle), np.sin(angle)
    if d == 2:
        return np.array([[c, -s], [s, c]])
    k = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * Kx + (1 - c) * Kx @ Kx


def special_Fs(d):
    """Identity, scaled rotations and repeated singular values: where plain SVDs fail."""
    Q = rotation(d)
    Fs = [np.eye(d), Q, 2.0 * Q, 0.5 * Q, 1.5 * np.eye(d)]
    if d == 3:
        Fs += [np.diag([2.0, 2.0, 0.5]), Q @ np.diag([2.0, 2.0, 0.5]) @ Q.T, np.diag([1.5] * 3)]
    else:
        Fs += [Q @ np.diag([2.0, 2.0])]
    return np.stack(Fs)


def fd_stencil(Fs, h):
    """``(n, d, d, 2, d, d)`` matrices ``F ± h e_k e_lᵀ`` for every entry (k, l)."""
    n, d, _ = Fs.shape
    E = np.eye(d * d).reshape(d, d, d, d)  # E[k, l] = e_k e_lᵀ
    plus = Fs[:, None, None] + h * E[None]
    minus = Fs[:, None, None] - h * E[None]
    return np.stack([plus, minus], axis=3)


# --------------------------------------------------------------------------- derivatives
@pytest.mark.parametrize("name,d", MODEL_DIMS, ids=IDS)
def test_P_and_hessian_match_finite_differences(name, d):
    """P vs central FD of ψ, and ∂²ψ/∂F² vs central FD of P, at random F (J > 0) and at the
    identity / rotations / repeated singular values."""
    Fs = np.concatenate([random_Fs(12, d, seed=d, smin=0.5, smax=2.0), special_Fs(d)])
    n = len(Fs)
    h = 1e-5
    _, P, H = evaluate(name, Fs)
    st = fd_stencil(Fs, h).reshape(-1, d, d)
    psi_st, P_st, _ = evaluate(name, st)
    psi_st = psi_st.reshape(n, d, d, 2)
    P_st = P_st.reshape(n, d, d, 2, d, d)
    P_fd = (psi_st[..., 0] - psi_st[..., 1]) / (2 * h)  # (n, k, l)
    H_fd = np.moveaxis((P_st[:, :, :, 0] - P_st[:, :, :, 1]) / (2 * h), (1, 2), (3, 4))
    for i in range(n):
        assert rel(P[i], P_fd[i], floor=MU) < 1e-7, (i, Fs[i])
        assert rel(H[i], H_fd[i], floor=MU) < 1e-6, (i, Fs[i])
    # Hessians have major symmetry ∂²ψ/∂F_ij∂F_kl = ∂²ψ/∂F_kl∂F_ij
    np.testing.assert_allclose(H, np.transpose(H, (0, 3, 4, 1, 2)), atol=1e-10 * np.abs(H).max())


@pytest.mark.parametrize("name", INVERTIBLE + ["stvk", "linear"])
@pytest.mark.parametrize("d", [2, 3])
def test_P_and_hessian_match_finite_differences_inverted(name, d):
    if name == "stable_neo_hookean_log" and d == 2:
        pytest.skip("3D only")
    Fs = random_Fs(8, d, seed=10 + d, smin=0.5, smax=2.0, inverted=True)
    n, h = len(Fs), 1e-6
    _, P, H = evaluate(name, Fs)
    psi_st, P_st, _ = evaluate(name, fd_stencil(Fs, h).reshape(-1, d, d))
    P_fd = (psi_st.reshape(n, d, d, 2)[..., 0] - psi_st.reshape(n, d, d, 2)[..., 1]) / (2 * h)
    P_st = P_st.reshape(n, d, d, 2, d, d)
    H_fd = np.moveaxis((P_st[:, :, :, 0] - P_st[:, :, :, 1]) / (2 * h), (1, 2), (3, 4))
    for i in range(n):
        assert rel(P[i], P_fd[i], floor=MU) < 1e-6, (i, Fs[i])
        assert rel(H[i], H_fd[i], floor=MU) < 1e-5, (i, Fs[i])


@pytest.mark.parametrize("name,d", MODEL_DIMS, ids=IDS)
@pytest.mark.parametrize("params", [PARAMS, PARAMS_STIFF], ids=["nu~0.35", "nu~0.49"])
def test_autodiff_P_equals_hand_P(name, d, params):
    """``first_piola(psi)`` vs the closed forms of :mod:`jaxelastic.materials.reference`,
    ≤ 1e-12."""
    parts = [random_Fs(200, d, seed=100 + d), special_Fs(d)]
    if name != "neo_hookean":
        parts.append(random_Fs(60, d, seed=200 + d, smin=0.3, smax=3.0, inverted=True))
    Fs = np.concatenate(parts)
    _, P, _ = evaluate(name, Fs, params)
    Ph = hand_P(name, Fs, params)
    errs = [rel(P[i], Ph[i], floor=float(params.mu)) for i in range(len(Fs))]
    worst = int(np.argmax(errs))
    assert errs[worst] <= 1e-12, (errs[worst], Fs[worst])


# --------------------------------------------------------------------------- rest state
def linear_tensor(d, mu, lam):
    """Hessian of ``materials.linear`` at F = I: μ(δ_ik δ_jl + δ_il δ_jk) + λ δ_ij δ_kl."""
    _, _, H = evaluate("linear", np.eye(d)[None], M.Lame(jnp.asarray(mu), jnp.asarray(lam)))
    I = np.eye(d)
    analytic = mu * (np.einsum("ik,jl->ijkl", I, I) + np.einsum("il,jk->ijkl", I, I))
    analytic += lam * np.einsum("ij,kl->ijkl", I, I)
    np.testing.assert_allclose(H[0], analytic, atol=1e-13)
    return H[0]


@pytest.mark.parametrize("name,d", MODEL_DIMS, ids=IDS)
@pytest.mark.parametrize("params", [PARAMS, PARAMS_STIFF], ids=["nu~0.35", "nu~0.49"])
def test_rest_state_and_linearisation(name, d, params):
    """ψ(I) = 0, P(I) = 0, and ∂²ψ/∂F²(I) is linear elasticity with the same μ, λ
    (ARAP: λ = 0)."""
    mu, lam = float(params.mu), float(params.lam)
    psi, P, H = evaluate(name, np.eye(d)[None], params)
    assert abs(psi[0]) <= 1e-13 * mu
    assert np.abs(P[0]).max() <= 1e-13 * mu
    C = linear_tensor(d, mu, 0.0 if name == "arap" else lam)
    assert rel(H[0], C) <= 1e-9


# --------------------------------------------------------------------------- objectivity
@pytest.mark.parametrize("name,d", INVARIANT, ids=[f"{n}-{d}D" for n, d in INVARIANT])
def test_rotation_invariance(name, d):
    """ψ(QF) = ψ(F) and P(QF) = Q·P(F) for every rotation-invariant model."""
    rng = np.random.default_rng(3)
    parts = [random_Fs(20, d, seed=d), special_Fs(d)]
    if name != "neo_hookean":
        parts.append(random_Fs(10, d, seed=50 + d, smin=0.3, smax=3.0, inverted=True))
    Fs = np.concatenate(parts)
    Qs = np.stack([random_rotation(rng, d) for _ in range(len(Fs))])
    psi, P, _ = evaluate(name, Fs)
    psiQ, PQ, _ = evaluate(name, Qs @ Fs)
    scale = np.maximum(np.abs(psi), MU)
    assert np.max(np.abs(psiQ - psi) / scale) < 1e-12
    QP = Qs @ P
    for i in range(len(Fs)):
        assert rel(PQ[i], QP[i], floor=MU) < 1e-12, (i, Fs[i])


@pytest.mark.parametrize("d", [2, 3])
def test_linear_is_not_rotation_invariant(d):
    """Linear elasticity stores energy under a pure rotation (its well-known flaw)."""
    Q = rotation(d, 0.5)
    psi, P, _ = evaluate("linear", np.stack([np.eye(d), Q]))
    assert psi[0] == 0.0
    assert psi[1] > 1e-2 * MU
    assert np.abs(P[1]).max() > 1e-2 * MU


# --------------------------------------------------------------------------- robustness
@pytest.mark.parametrize("name,d", MODEL_DIMS, ids=IDS)
def test_hessian_finite_at_identity_rotations_repeated_sigma(name, d):
    Fs = special_Fs(d)
    psi, P, H = evaluate(name, Fs)
    assert np.all(np.isfinite(psi)) and np.all(np.isfinite(P))
    for i in range(len(Fs)):
        assert np.all(np.isfinite(H[i])), (name, Fs[i])


@pytest.mark.parametrize("d", [2, 3])
def test_neo_hookean_is_infinite_when_inverted(d):
    Fs = np.stack(
        [
            np.diag([1.0] * (d - 1) + [0.0]),  # J = 0
            np.diag([1.0] * (d - 1) + [-0.5]),  # J < 0
            -np.eye(d) if d == 3 else np.diag([-1.0, 1.0]),  # reflection
            np.diag([1.0] * (d - 1) + [1e-3]),  # J > 0 tiny: finite
        ]
    )
    psi, _, _ = evaluate("neo_hookean", Fs)
    assert np.all(np.isposinf(psi[:3]))
    assert np.isfinite(psi[3])


def _inverted_F(d):
    return np.diag([1.0] * (d - 1) + [-0.5])


@pytest.mark.parametrize("name", INVERTIBLE)
@pytest.mark.parametrize("d", [2, 3])
def test_stable_models_push_inverted_elements_back(name, d):
    """Finite ψ, P, Hessian at an inverted F, and a small gradient-descent step on ψ
    increases J (the element is pushed toward J > 0)."""
    if name == "stable_neo_hookean_log" and d == 2:
        pytest.skip("3D only")
    F = _inverted_F(d)
    rot = rotation(d)
    for F0 in (F, rot @ F, F @ rot.T):  # also rotated versions
        psi, P, H = evaluate(name, F0[None])
        assert np.isfinite(psi[0]) and psi[0] > 0
        assert np.all(np.isfinite(P)) and np.all(np.isfinite(H))
        step = 1e-3 * P[0] / np.linalg.norm(P[0])
        J0, J1 = np.linalg.det(F0), np.linalg.det(F0 - step)
        assert J1 > J0, (name, J0, J1)
        # first order: dJ = cof F : dF > 0
        assert np.sum(np.asarray(cofactor(jnp.asarray(F0))) * -step) > 0


@pytest.mark.parametrize("d", [2, 3])
def test_stvk_cannot_uninvert(d):
    """The documented StVK trap: zero energy at a reflection, and at an inverted F a gradient
    step drives J further negative."""
    refl = np.diag([1.0] * (d - 1) + [-1.0])
    psi, P, _ = evaluate("stvk", np.stack([refl, _inverted_F(d)]))
    assert abs(psi[0]) < 1e-14 and np.abs(P[0]).max() < 1e-14
    F0 = _inverted_F(d)
    step = 1e-3 * P[1] / np.linalg.norm(P[1])
    assert np.linalg.det(F0 - step) < np.linalg.det(F0)


def test_stable_neo_hookean_log_refuses_2d():
    with pytest.raises(ValueError, match="3D only"):
        M.stable_neo_hookean_log(jnp.eye(2), PARAMS)


# --------------------------------------------------------------------------- known answers
@pytest.mark.parametrize("d", [2, 3])
def test_neo_hookean_uniaxial_and_shear_known_answers(d):
    """REFERENCES: free lateral faces μ(b² − 1) + λ ln(a b^{d−1}) = 0, P₁₁ = μ(a − b²/a);
    simple shear P₁₂ = μγ."""
    a = 1.7
    b = brentq(lambda b: MU * (b * b - 1) + LAM * np.log(a * b ** (d - 1)), 0.1, 1.0, xtol=1e-15)
    gamma = 0.8
    S = np.eye(d)
    S[0, 1] = gamma
    _, P, _ = evaluate("neo_hookean", np.stack([np.diag([a] + [b] * (d - 1)), S]))
    np.testing.assert_allclose(P[0][0, 0], MU * (a - b * b / a), rtol=1e-12)
    np.testing.assert_allclose(np.diag(P[0])[1:], 0.0, atol=1e-12)
    np.testing.assert_allclose(P[1][0, 1], MU * gamma, rtol=1e-12)


# --------------------------------------------------------------------------- Lamé
def test_lame_formulas():
    E, nu = 210.0, 0.3
    mu, lam = M.lame(E, nu)
    assert mu == pytest.approx(E / (2 * (1 + nu)), rel=1e-15)
    assert lam == pytest.approx(E * nu / ((1 + nu) * (1 - 2 * nu)), rel=1e-15)
    assert M.lame(E, nu, dim=2) == pytest.approx((mu, lam), rel=1e-15)  # plane strain
    assert M.lame(E, nu, dim=2, plane="strain") == pytest.approx((mu, lam), rel=1e-15)
    mu_s, lam_s = M.lame(E, nu, dim=2, plane="stress")
    assert mu_s == pytest.approx(mu, rel=1e-15)
    assert lam_s == pytest.approx(E * nu / ((1 + nu) * (1 - nu)), rel=1e-15)
    assert lam_s == pytest.approx(2 * mu * lam / (lam + 2 * mu), rel=1e-14)  # λ* identity
    # plane is ignored in 3D; a textbook pair: E = 1, ν = 0.25 -> μ = λ = 0.4
    assert M.lame(1.0, 0.25, dim=3, plane="stress") == pytest.approx((0.4, 0.4), rel=1e-15)
    # per-cell arrays
    mus, lams = M.lame(np.array([1.0, 2.0]), np.array([0.25, 0.25]))
    np.testing.assert_allclose(mus, [0.4, 0.8])
    np.testing.assert_allclose(lams, [0.4, 0.8])


@pytest.mark.parametrize(
    "E,nu,match",
    [
        (0.0, 0.3, "E must be > 0"),
        (-1.0, 0.3, "E must be > 0"),
        (float("nan"), 0.3, "finite"),
        (float("inf"), 0.3, "finite"),
        (1.0, -1.0, r"\(-1, 0.5\)"),
        (1.0, 0.5, r"\(-1, 0.5\)"),
        (1.0, 0.7, r"\(-1, 0.5\)"),
        (1.0, float("nan"), "finite"),
        (np.array([1.0, -2.0]), 0.3, "E must be > 0"),
    ],
)
def test_lame_refuses_invalid(E, nu, match):
    with pytest.raises(ValueError, match=match):
        M.lame(E, nu)


def test_lame_refuses_bad_options():
    with pytest.raises(ValueError, match="dim"):
        M.lame(1.0, 0.3, dim=4)
    with pytest.raises(ValueError, match="plane"):
        M.lame(1.0, 0.3, dim=2, plane="membrane")


@pytest.mark.parametrize("dim,plane", [(3, "strain"), (2, "strain"), (2, "stress")])
def test_lame_is_differentiable(dim, plane):
    def f(E, nu):
        mu, lam = M.lame(E, nu, dim=dim, plane=plane)
        return mu + 2.0 * lam

    E, nu, h = 3.0, 0.3, 1e-6
    gE, gnu = jax.grad(f, argnums=(0, 1))(E, nu)
    np.testing.assert_allclose(gE, (f(E + h, nu) - f(E - h, nu)) / (2 * h), rtol=1e-8)
    np.testing.assert_allclose(gnu, (f(E, nu + h) - f(E, nu - h)) / (2 * h), rtol=1e-8)
    # analytic: ∂μ/∂E = 1/(2(1+ν))
    g_mu = jax.grad(lambda E: M.lame(E, nu, dim=dim, plane=plane)[0])(E)
    np.testing.assert_allclose(g_mu, 1.0 / (2 * (1 + nu)), rtol=1e-14)
    # under jit (traced values are not validated, but the formula is the same)
    np.testing.assert_allclose(jax.jit(f)(E, nu), f(E, nu), rtol=1e-15)
