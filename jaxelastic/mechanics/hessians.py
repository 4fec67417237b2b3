"""Element Hessians ``∂²E_c/∂x_e²`` of ψ by contraction, and their autodiff reference.

``Kₑ = Σ_q w_q B_qᵀ C_q B_q`` with ``C = ∂²ψ/∂F²`` (autodiff of ψ per quadrature point) and
the shape-function gradients; under the ``"fbar"``/``"bbar"`` formulations the same
contraction of a modified per-point tensor plus a rank-3 element term
(:func:`element_hessians`; the derivation is in ``docs/guide/performance.md``).
:func:`element_hessians_reference` differentiates the element energy twice instead (the
slow, independent test reference). Sharded meshes run per shard under ``shard_map``.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ..mesh.elements import get_element
from .checks import cell_params_axes, check_call, per_cell
from .fusion import always, computed
from .kernels import Psi, cell_contract, cell_F, element_energy, fbar_form
from .kinematics import b_bar, cofactor, det, displacements
from .psd import project_element_psd, project_psd_serial
from .quadrature_fields import over_quadrature

__all__ = ["element_hessians", "element_hessians_reference"]

# ----------------------------------------------------------------------- element Hessians
#
# Kₑ = Σ_q B_qᵀ Ĉ_q B_q (+ a rank-3 element term under F-bar/B-bar), with B_q the
# (d², k·d) map δu ↦ δF_q = Σ_k δu_k ⊗ ∇N_k(q) and Ĉ_q a (d, d, d, d) tensor per quadrature
# point: w_q ∂²ψ/∂F² for the standard formulation. The Kronecker structure of B_q
# (B[(a,b),(k,x)] = δ_ax ∇N_k,b) is used, never B itself: see _contract_hessian.


def _contract_hessians(Ch, dN, G: np.ndarray, pred):
    """``K[c,k,a,l,x] = Σ_q Σ_{b,e} ∇N_k,b(q) Ĉ_q[a,b,x,e] ∇N_l,e(q)`` for every cell.

    Args:
        Ch: ``(c, q, d, d, d, d)`` per-point tensors Ĉ (quadrature weights included).
        dN: ``(c, q, k, d)`` shape-function gradients.
        G: ``(q, k, d)`` the element's reference gradients at its quadrature points
            (``Element.shape_gradients()``), of which ``dN`` is the push-forward.
        pred: :func:`~jaxelastic.mechanics.fusion.always` of the mesh (for
            :func:`~jaxelastic.mechanics.fusion.computed`).

    Returns:
        ``(c, k, d, k, d)`` element Hessians (node-major dofs).

    Never an ``einsum``: over cells, ``"cqkb,cqabxe,cqle->ckalx"`` is a batched dot_general
    of tiny matrices on XLA:CPU (measured on 100k tet4: 262 ms einsum vs 45 ms unrolled;
    see scripts/bench_kernels.py). P1 (one point): the d² (b, e) terms are unrolled into
    one fused loop over the output. More points: one matrix product per block of cells
    (:func:`_contract_hessians_pulled_back`).
    """
    _, q, k, d = dN.shape
    if q > 1:
        return _contract_hessians_pulled_back(Ch, dN, G, pred)
    N = dN[:, 0]  # (c, k, d)
    out = None
    for b in range(d):
        Nb = N[:, :, None, None, None, b]  # (c, k, 1, 1, 1)
        for e in range(d):
            term = Nb * Ch[:, 0, None, :, b, None, :, e] * N[:, None, None, :, None, e]
            out = term if out is None else out + term
    assert out is not None
    return out


def _pair_gemm_matrix(G: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The constant matrix of the reference-frame contraction, and its node-pair table.

    Args:
        G: ``(q, k, d)`` reference shape-function gradients ``∇̂N_k(ξ_q)``.

    Returns:
        ``M`` ``(q·d·d, P)`` with ``M[(q, β, ε), p] = ∇̂N_k,β(ξ_q) ∇̂N_l,ε(ξ_q)`` for the
        ``P = k(k+1)/2`` node pairs ``p = (k, l)``, ``k ≤ l``, and ``index`` ``(k, k)``, the
        pair of ``(k, l)`` in either order.
    """
    q, k, d = G.shape
    pairs = [(a, b) for a in range(k) for b in range(a, k)]
    M = np.empty((q, d, d, len(pairs)))
    index = np.empty((k, k), dtype=np.int32)
    for p, (a, b) in enumerate(pairs):
        M[..., p] = G[:, a, :, None] * G[:, b, None, :]
        index[a, b] = index[b, a] = p
    return M.reshape(q * d * d, len(pairs)), index


def _contract_hessians_pulled_back(Ch, dN, G: np.ndarray, pred):
    """:func:`_contract_hessians` for cells with several quadrature points, as one matrix
    product over all cells of a block: BLAS-rate (about 50 GFLOP/s on 2 cores), where the
    former two-stage sum of fused broadcasts ran at a few; whole tet10 element Hessians
    measured 2.2× faster (F-bar 1.5×; docs/guide/performance.md).

    Every element of :func:`~jaxelastic.mesh` has ``∇N_k(q) = J_q⁻ᵀ ∇̂N_k(ξ_q)``, so

        K[c,k,a,l,x] = Σ_{q,β,ε} ∇̂N_k,β(ξ_q) C̃[c,q,a,β,x,ε] ∇̂N_l,ε(ξ_q),
        C̃[c,q,a,β,x,ε] = Σ_{b,e} J⁻¹[β,b] Ĉ_q[a,b,x,e] J⁻¹[ε,e]

    (Ĉ pulled back to the reference element; ``J⁻¹ = pinv(∇̂N(ξ_q)) ∇N(q)`` is recovered
    exactly from ``dN``). The first factor is the same for every cell: ``C̃`` reshaped to
    ``(c·d², q·d²)`` times the constant ``(q·d², k(k+1)/2)`` matrix of
    :func:`_pair_gemm_matrix` gives the node pairs ``k ≤ l``; symmetry
    (``K[k,a,l,x] = K[l,x,k,a]``) fills the rest.

    Args:
        Ch: ``(c, q, d, d, d, d)``; dN: ``(c, q, k, d)``; G: ``(q, k, d)`` the element's
            reference gradients at its quadrature points; pred:
            :func:`~jaxelastic.mechanics.fusion.always`.

    Returns:
        ``(c, k, d, k, d)`` element Hessians.
    """
    c, q, k, d = dN.shape
    pinv = jnp.asarray(np.stack([np.linalg.pinv(G[i]) for i in range(q)]), dN.dtype)
    Ji = computed(  # J⁻¹ (c, q, β, b) from dN = G J⁻¹
        lambda dN: _sum_terms(pinv[None, :, :, n, None] * dN[:, :, None, n, :] for n in range(k)),
        pred,
        dN,
    )
    T = _sum_terms(  # (c, q, a, β, x, e)
        Ji[:, :, None, :, None, None, b] * Ch[:, :, :, None, b, :, :] for b in range(d)
    )
    Ct = _sum_terms(  # (c, a, x, q, β, ε)
        jnp.transpose(T[..., e], (0, 2, 4, 1, 3))[..., None]
        * Ji[:, None, None, :, :, e][..., None, :]
        for e in range(d)
    )
    M, index = _pair_gemm_matrix(G)
    out = jnp.dot(
        Ct.reshape(c * d * d, q * d * d),
        jnp.asarray(M, dN.dtype),
        precision=jax.lax.Precision.HIGHEST,
    ).reshape(c, d, d, -1)
    full = out[:, :, :, index]  # (c, a, x, k, l): the pair of (k, l) at (a, x)
    upper = (np.arange(k)[:, None] <= np.arange(k)[None, :])[None, :, None, :, None]
    return jnp.where(
        upper,
        jnp.transpose(full, (0, 3, 1, 4, 2)),  # K[c,k,a,l,x] = pair(k,l)[a,x]   (k ≤ l)
        jnp.transpose(full, (0, 3, 2, 4, 1)),  # K[c,k,a,l,x] = pair(l,k)[x,a]   (k > l)
    )


def _sum_terms(terms):
    """The sum of an iterable of arrays (at least one), as one fused broadcast expression."""
    it = iter(terms)
    out = next(it)
    for t in it:
        out = out + t
    return out


def _outer(X, Y):
    """``(X ⊗ Y)[a,b,x,e] = X[a,b]·Y[x,e]`` of ``(..., d, d)`` matrices."""
    return X[..., :, :, None, None] * Y[..., None, None, :, :]


def _outer_swap(X, Y):
    """``(X ⊠ Y)[a,b,x,e] = X[x,b]·Y[a,e]`` (the index pattern of ``tr(F⁻¹δF F⁻¹δF)``)."""
    return jnp.swapaxes(X, -1, -2)[..., None, :, :, None] * Y[..., :, None, None, :]


def _det_hessian(F):
    """``∂²J/∂F∂F`` of one ``(d, d)`` F, ``(d, d, d, d)``: ``ε_{axi} ε_{bej} F_ij`` in 3D,
    ``ε_ax ε_be`` in 2D (polynomial: exact also at J ≤ 0)."""
    d = F.shape[-1]
    if d == 2:
        eps = jnp.array([[0.0, 1.0], [-1.0, 0.0]], dtype=F.dtype)
        return eps[:, None, :, None] * eps[None, :, None, :]
    eps = np.zeros((3, 3, 3))
    for i, j, k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        eps[i, j, k], eps[j, i, k] = 1.0, -1.0
    E = jnp.asarray(eps, dtype=F.dtype)  # E[a, x, i]
    out = None
    for i in range(3):
        for j in range(3):
            term = E[:, None, :, None, i] * E[None, :, None, :, j] * F[i, j]
            out = term if out is None else out + term
    return out


def _ddot(C, X):
    """``(C : X)[a,b] = Σ_{x,e} C[a,b,x,e] X[x,e]`` for ``(q, d, d, d, d)`` C and ``(q, d, d)``
    X, unrolled (no tiny dot_general)."""
    d = X.shape[-1]
    out = None
    for x in range(d):
        for e in range(d):
            term = C[:, :, :, x, e] * X[:, None, None, x, e]
            out = term if out is None else out + term
    return out


def _fbar_hessian_terms(psi, F, w, p, form: str, pred):
    """Ĉ_q and the element-level term of the F-bar / B-bar element Hessian of one cell.

    F-bar (de Souza Neto et al. 1996): ``F̄_q = θ_q F_q``, ``θ_q = (J̄/J_q)^{1/d}``,
    ``J̄ = Σ_p ω_p J_p`` (``ω = w/Σw``). With ``h_q = (g − g_q)/d`` (``g_q = B_qᵀ vec F_q⁻ᵀ``,
    ``g = Σ_p B_pᵀ vec(ω_p cof F_p)/J̄``), ``dF̄_q = θ_q (B_q + vec F_q h_qᵀ) δu`` and

        Kₑ = Σ_q w_q [θ²(B + f hᵀ)ᵀ C̄ (B + f hᵀ) + θ α (h hᵀ + H_φ) + θ (h sᵀ + s hᵀ)],

    ``C̄, P̄`` at F̄_q, ``α = P̄ : F``, ``s = Bᵀ vec P̄``, ``H_φ`` the Hessian of
    ``φ_q = ln θ_q`` (it has ``d²J̄ = Σ ω_p ∂²J_p`` and ``tr(F⁻¹δF F⁻¹δF)`` terms). Every
    per-point term is ``B_qᵀ (…) B_q`` of a d⁴ tensor and the products of point sums are
    rank-one in the element dofs, so ``Kₑ = Σ_q B_qᵀ Ĉ_q B_q + g zᵀ + z gᵀ + κ g gᵀ`` with

        y = wθ² C̄:F + wθ P̄,   γ = y : F,   A = Σ_q o wθα,   Γ = Σ_q o γ,
        Ĉ = wθ² C̄ − (o/d)(y ⊗ F⁻ᵀ + F⁻ᵀ ⊗ y) + (oγ/d²) F⁻ᵀ ⊗ F⁻ᵀ + (o wθα/d) F⁻ᵀ ⊠ F⁻ᵀ
            + (A ω/(d J̄)) ∂²J,
        z = Σ_q B_qᵀ vec(o (y/d − γ F⁻ᵀ/d²)),   κ = Γ/d² − A/d,

    ``o_q`` = 1 where ``J_q > 0`` and ``J̄ > 0`` (elsewhere F̄_q = F_q, θ_q = 1, as in
    :func:`~jaxelastic.mechanics.kinematics.f_bar`). B-bar (F̄ linear in F: no geometric term) is the
    same algebra with ``θ = 1``, F⁻ᵀ and cof F replaced by I, ``y = w C̄ : I``, ``A = 0``.

    Long because: the derivation is stated next to the terms it produces, and the B-bar
    branch shares them.

    Args:
        psi: ψ(F, params).
        F: ``(q, d, d)`` compatible deformation gradients; w: ``(q,)`` weights; p: params.
        form: ``"fbar"`` or ``"bbar"``.
        pred: :func:`~jaxelastic.mechanics.fusion.always` (stores C and y once, see
            :func:`~jaxelastic.mechanics.fusion.computed`).

    Returns:
        ``(Ĉ, Gq, Zq, κ)``: Ĉ ``(q, d, d, d, d)``; Gq, Zq ``(q, d, d)`` with
        ``g = Σ_q B_qᵀ vec Gq`` and ``z = Σ_q B_qᵀ vec Zq`` (:func:`_bt_sum`); κ a scalar.
    """
    d = F.shape[-1]
    H = over_quadrature(jax.hessian(psi, argnums=0))
    eye = jnp.eye(d, dtype=F.dtype)
    omega = w / jnp.where(jnp.sum(w) > 0, jnp.sum(w), 1.0)  # Σw = 0: a padded cell
    if form == "bbar":
        Fb = b_bar(F, w)
        C = computed(H, pred, Fb, p)  # (q, d, d, d, d)
        I = jnp.broadcast_to(eye, F.shape)
        y = computed(lambda C: w[:, None, None] * _ddot(C, I), pred, C)
        gam = jnp.trace(y, axis1=-2, axis2=-1)
        Ch = (
            w[:, None, None, None, None] * C
            - (_outer(y, I) + _outer(I, y)) / d
            + (gam / d**2)[:, None, None, None, None] * _outer(I, I)
        )
        Gq = omega[:, None, None] * I
        Zq = y / d - (gam / d**2)[:, None, None] * I
        return Ch, Gq, Zq, jnp.sum(gam) / d**2
    J = jax.vmap(det)(F)
    cof = jax.vmap(cofactor)(F)
    Jbar = jnp.sum(omega * J)
    ok = (J > 0) & (Jbar > 0)
    o = ok.astype(F.dtype)
    Jbar_s = jnp.where(Jbar > 0, Jbar, 1.0)
    ratio = jnp.where(ok, Jbar_s / jnp.where(ok, J, 1.0), 1.0)
    theta = ratio ** (1.0 / d)
    Fb = theta[:, None, None] * F
    dpsi = over_quadrature(jax.grad(psi, argnums=0))
    P, C = computed(lambda Fb, p: (dpsi(Fb, p), H(Fb, p)), pred, Fb, p)
    Fi = cof / jnp.where(ok, J, 1.0)[:, None, None]  # F⁻ᵀ where ok (else unused)
    wt = w * theta
    y = computed(
        lambda C, F, P: (wt * theta)[:, None, None] * _ddot(C, F) + wt[:, None, None] * P,
        pred,
        C,
        F,
        P,
    )
    gam = jnp.sum(y * F, axis=(-2, -1))
    alpha = jnp.sum(P * F, axis=(-2, -1))
    A = jnp.sum(o * wt * alpha)
    b4 = (slice(None), None, None, None, None)
    Ch = (
        (wt * theta)[b4] * C
        - (o / d)[b4] * (_outer(y, Fi) + _outer(Fi, y))
        + (o * gam / d**2)[b4] * _outer(Fi, Fi)
        + (o * wt * alpha / d)[b4] * _outer_swap(Fi, Fi)
        + (A * omega / (d * Jbar_s))[b4] * jax.vmap(_det_hessian)(F)
    )
    Gq = (omega / Jbar_s)[:, None, None] * cof
    Zq = o[:, None, None] * (y / d - (gam / d**2)[:, None, None] * Fi)
    kappa = jnp.sum(o * gam) / d**2 - A / d
    return Ch, Gq, Zq, kappa


def _bt_sum(Mq, dN):
    """``Σ_q B_qᵀ vec M_q`` as ``(k, d)``: ``out[k,a] = Σ_q Σ_b M_q[a,b] ∇N_k,b(q)``."""
    return cell_contract(jnp.ones(Mq.shape[0], Mq.dtype), Mq, dN)


def _element_hessian_terms(psi, fbar: str | None, pred):
    """Per cell ``(ue, dN, w, params) ↦ (Ĉ (q, d, d, d, d), g (k, d), z (k, d), κ)``: the
    element Hessian is ``Σ_q B_qᵀ Ĉ_q B_q + g zᵀ + z gᵀ + κ g gᵀ`` (g = z = 0, κ = 0 for
    the standard formulation, where ``Ĉ_q = w_q ∂²ψ/∂F²(F_q)``)."""
    H = over_quadrature(jax.hessian(psi, argnums=0))

    def terms(ue, dN, w, p):
        F = cell_F(ue, dN)
        if not fbar:
            return w[:, None, None, None, None] * H(F, p), None, None, None
        Ch, Gq, Zq, kappa = _fbar_hessian_terms(psi, F, w, p, fbar, pred)
        return Ch, _bt_sum(Gq, dN), _bt_sum(Zq, dN), kappa

    return terms


def element_hessians(psi: Psi, x: jax.Array, mesh, params, *, project: bool = False):
    """Per-element Hessians ``∂²E_c/∂x_e²``, ``(n_cells, k·d, k·d)`` (node-major dofs).

    Formed by contraction, ``Kₑ = Σ_q w_q B_qᵀ C_q B_q`` with ``C = ∂²ψ/∂F²`` (autodiff of
    ψ, ``(d², d²)`` per quadrature point) and the shape-function gradients; under the
    ``"fbar"``/``"bbar"`` formulations the same contraction of a modified per-point tensor
    plus a rank-3 element term (see :func:`_fbar_hessian_terms`; the derivation is in
    ``docs/guide/performance.md``). :func:`element_hessians_reference` differentiates the
    element energy twice instead (the test reference).

    Args:
        project: clamp each element Hessian to positive semidefinite (see
            :func:`~jaxelastic.mechanics.psd.project_psd`), for Newton on indefinite configurations.

    Other args as :func:`~jaxelastic.mechanics.kernels.energy_densities`.
    """
    check_call("je.mechanics.element_hessians", psi, x, mesh, params)
    if mesh.halo is not None:
        return _sharded_element_hessians(psi, x, mesh, params, project)
    ue = displacements(x, mesh)[mesh.cells]
    c, k, d = ue.shape
    form = fbar_form(mesh)
    axes = cell_params_axes(params, c)
    leaves, treedef = jax.tree_util.tree_flatten(params)
    is_cell = jax.tree_util.tree_leaves(axes, is_leaf=lambda a: a is None)
    cell_leaves = [leaf for leaf, ax in zip(leaves, is_cell, strict=True) if ax == 0]

    def block(args):
        ue_b, dN_b, w_b, cells_b, cl = args
        it = iter(cl)
        p = jax.tree_util.tree_unflatten(
            treedef,
            [next(it) if ax == 0 else leaf for leaf, ax in zip(leaves, is_cell, strict=True)],
        )
        n = ue_b.shape[0]
        pred = always(cells_b)  # outside the per-cell vmap: the conditionals stay
        terms = per_cell(_element_hessian_terms(psi, form, pred), p, n)
        # Ĉ (and the F-bar vectors) computed once, stored, then contracted (fusion.computed)
        Ch, g, z, kappa = computed(terms, pred, ue_b, dN_b, w_b, p)
        K = _contract_hessians(Ch, dN_b, G, pred)  # (n, k, d, k, d)
        if g is not None:
            gz = g[:, :, :, None, None] * z[:, None, None, :, :]
            gg = g[:, :, :, None, None] * g[:, None, None, :, :]
            K = K + gz + jnp.transpose(gz, (0, 3, 4, 1, 2)) + kappa[:, None, None, None, None] * gg
        return K.reshape(n, k * d, k * d)

    G = get_element(mesh.element).shape_gradients()
    args = (ue, mesh.dN, mesh.weights, mesh.cells, cell_leaves)
    B = _hessian_block_cells(mesh.dN.shape[1], k, d)
    nb = c // B
    if nb <= 1:
        K = block(args)
    else:  # lax.map over whole blocks (a scan: each block is one unbatched call), then the tail
        head = jax.tree_util.tree_map(lambda a: a[: nb * B].reshape((nb, B) + a.shape[1:]), args)
        K = jax.lax.map(block, head).reshape(nb * B, k * d, k * d)
        if nb * B < c:
            tail = jax.tree_util.tree_map(lambda a: a[nb * B :], args)
            K = jnp.concatenate([K, block(tail)])
    return project_element_psd(K, d) if project else K


def _hessian_block_cells(q: int, k: int, d: int) -> int:
    """Cells per block of :func:`element_hessians` (a ``lax.map`` over blocks).

    One quadrature point (P1): no blocks (they measured 1.25× slower on 100k tet4). More
    points: Ĉ, its pull-back and the element Hessians take about q·d⁴·3 + (k·d)² numbers
    per cell (30 kB for tet10); blocks of about 8 MB bound the memory (a 100k-tet10 call
    would otherwise hold 3 GB of intermediates, and ran 2.4× slower unblocked). The time
    does not depend on the block size between 64 and 8192 tet10 cells (1.50–1.57 s per
    100k cells, measured).
    """
    if q == 1:
        return 1 << 62
    return max(64, (1 << 20) // (3 * q * d**4 + (k * d) ** 2))


def element_hessians_reference(psi: Psi, x: jax.Array, mesh, params) -> jax.Array:
    """Element Hessians by ``jax.hessian`` of the element energy over the element's node
    coordinates, ``(n_cells, k·d, k·d)`` — every formulation, no contraction formula.

    The slow, independent reference for :func:`element_hessians` (the former
    implementation of the F-bar path; 10–50× slower for P2 and F-bar): use it in tests and
    to check a new ψ. Args as :func:`~jaxelastic.mechanics.kernels.energy_densities`.
    """
    check_call("je.element_hessians_reference", psi, x, mesh, params)
    ue = displacements(x, mesh)[mesh.cells]
    ee = element_energy(psi, fbar_form(mesh))

    def ke(ue, dN, w, p):
        k, d = ue.shape
        return jax.hessian(ee)(ue, dN, w, p).reshape(k * d, k * d)

    return per_cell(ke, params, mesh.n_cells)(ue, mesh.dN, mesh.weights, params)


# a mesh with a halo (jaxelastic.shard): per shard under shard_map, as the kernels of
# jaxelastic.mechanics.kernels (jitted, ψ static)


@functools.partial(jax.jit, static_argnums=(0, 4))
def _sharded_element_hessians(psi, x, mesh, params, project):
    """:func:`element_hessians` of a sharded mesh: per shard, no communication but the
    ghosts' displacements; ``(n_cells, k·d, k·d)`` sharded along cells."""
    h = mesh.halo

    def body(hl, loc, pts, x_b, p):
        Ke = element_hessians(psi, hl.displacements(x_b, pts), loc, p)
        return project_psd_serial(Ke) if project else Ke

    spec = jax.sharding.PartitionSpec(h.axis)
    return h.map_mesh(body, mesh, x, params, out_specs=spec)
