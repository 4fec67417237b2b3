"""Kinematics: deformation gradients, strains, and a rotation-variant polar decomposition.

Functions of a single deformation gradient take an unbatched ``(d, d)`` array (d = 2 or 3)
and are meant to be used inside ψ; :func:`deformation_gradients` maps positions on a mesh
to ``(n_cells, n_q, d, d)``.

The rotation-variant SVD/polar decomposition (Irving, Teran & Fedkiw 2004; Stomakhin et al.
2012) keeps ``U, V ∈ SO(d)`` and puts a reflection into the smallest singular value, which
becomes negative when ``det F < 0``. A plain ``jnp.linalg.svd`` has NaN *second* derivatives
at ``F = I``, at scaled rotations and at repeated singular values; :func:`polar` and
:func:`trace_S` have custom JVPs whose derivatives of every order are finite there:

* ``dR = R·[ω]×`` with ``(tr S·I − S) ω = axial(RᵀdF − dFᵀR)`` in 3D (the polar-rotation
  derivative; singular only when two signed singular values sum to zero, a measure-zero
  set that includes a reflection ``diag(1, 1, −1)``, where the system is regularised);
* in 2D ``R`` has the closed form ``(a, b)/√(a²+b²)`` with ``a = F₀₀+F₁₁, b = F₁₀−F₀₁``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

__all__ = [
    "deformation_gradients",
    "displacements",
    "f_bar",
    "b_bar",
    "det",
    "cofactor",
    "green_strain",
    "small_strain",
    "corotated_strain",
    "polar",
    "polar_rotation",
    "trace_S",
    "svd_rv",
    "principal_stretch_range",
    "deformation_extremes",
    "DeformationExtremes",
]


def deformation_gradients(x: jax.Array, mesh, *, fbar: bool | None = None) -> jax.Array:
    """F at every quadrature point: ``F = I + Σ_a (x_a − X_a) ⊗ ∇N_a`` (``= Ds·Dm⁻¹`` for P1).

    Computed from the displacements ``u = x − X`` (X = ``mesh.points``), not from the
    absolute positions: ``Σ_a ∇N_a = 0``, so both forms are equal in exact arithmetic, but
    the round-off of ``Σ_a x_a ⊗ ∇N_a`` grows with the coordinates (a mesh far from the
    origin, or float32) while that of ``I + ∇u`` only grows with the displacement; at the
    rest state (x = X) F is exactly I. The working dtype is the mesh's: ``u`` is cast to
    ``mesh.points.dtype`` (a float64 ``x`` on a float32 mesh gives float32 F, exact ``u``
    first).

    Under the ``"fbar"``/``"bbar"`` formulations this is the F the energy uses, F̄ (see
    :func:`f_bar`, :func:`b_bar`).

    Args:
        x: ``(n_nodes, dim)`` current positions [length].
        mesh: a :class:`~jaxelastic.mesh.Mesh`.
        fbar: apply the mesh's F̄ map; default: when ``mesh.formulation`` is not
            ``"standard"``. ``fbar=False`` gives the compatible F of the displacement field.

    Returns:
        ``(n_cells, n_q, dim, dim)`` deformation gradients (dimensionless), in the mesh's dtype.

    Raises:
        ValueError: ``x`` does not have the shape ``(n_nodes, dim)`` of ``mesh.points``
            (a static check: free under jit, per example under vmap).
    """
    if tuple(jnp.shape(x)) != tuple(mesh.points.shape):
        raise ValueError(
            f"deformation_gradients: x must have shape (n_nodes, dim) = "
            f"{tuple(mesh.points.shape)} like mesh.points, got {tuple(jnp.shape(x))}"
        )
    ue = displacements(x, mesh)[mesh.cells]  # (c, k, d)
    c, k, d = ue.shape
    if k == d + 1:
        G = jnp.einsum("cka,cqkb->cqab", ue, mesh.dN)
    else:  # unrolled over nodes: a batched einsum is ~15× slower on CPU for P2 (tet10)
        dN = mesh.dN
        G = ue[:, None, 0, :, None] * dN[:, :, 0, None, :]
        for a in range(1, k):
            G = G + ue[:, None, a, :, None] * dN[:, :, a, None, :]
    F = G + jnp.eye(d, dtype=G.dtype)[None, None]
    form = getattr(mesh, "formulation", "standard")
    if fbar is None:
        fbar = form != "standard"
    if not fbar or form == "standard":
        return F
    return jax.vmap(b_bar if form == "bbar" else f_bar)(F, mesh.weights)


def displacements(x: jax.Array, mesh) -> jax.Array:
    """Nodal displacements ``u = x − X`` [length], ``(n_nodes, dim)``, in the mesh's dtype.

    ``X = mesh.points``; the difference is taken in the wider of the two dtypes and then
    cast to ``mesh.points.dtype`` (the working precision: nothing is promoted beyond it).
    """
    X = mesh.points
    with jax.numpy_dtype_promotion("standard"):  # explicit, so valid under "strict" too
        wide = jnp.promote_types(x.dtype, X.dtype)
    u = x.astype(wide) - X.astype(wide)
    return u if u.dtype == X.dtype else u.astype(X.dtype)


def b_bar(F: jax.Array, w: jax.Array) -> jax.Array:
    """Small-strain B-bar of one cell: ``F̄_q = F_q + (⟨tr F⟩ − tr F_q)/d · I``.

    The volumetric part of the small strain ε = sym(F) − I is replaced by its cell average
    ``⟨tr ε⟩ = Σ_q w_q tr ε_q / Σ_q w_q`` (Hughes 1980, IJNME 15:1413, the B̄ method), so a
    small-strain material (``linear``) gets exactly B-bar. It is the linearisation of
    :func:`f_bar` at F = I but not frame-invariant: use ``"fbar"`` for finite strains.

    Args:
        F: ``(n_q, d, d)`` compatible deformation gradients of one cell.
        w: ``(n_q,)`` positive quadrature weights.

    Returns:
        ``(n_q, d, d)`` F̄.
    """
    d = F.shape[-1]
    tr = jnp.trace(F, axis1=-2, axis2=-1)  # (q,)
    sw = jnp.sum(w)
    shift = (jnp.sum(w * tr) / jnp.where(sw > 0, sw, 1.0) - tr) / d
    shift = jnp.where(sw > 0, shift, 0.0)  # Σw = 0 (a padded cell): F̄ = F
    return F + shift[:, None, None] * jnp.eye(d, dtype=F.dtype)[None]


def f_bar(F: jax.Array, w: jax.Array) -> jax.Array:
    """F-bar of one cell: ``F̄_q = (J̄/J_q)^{1/d} F_q`` with ``J̄ = Σ_q w_q J_q / Σ_q w_q``.

    de Souza Neto, Perić, Dutko & Owen 1996, IJSS 33:3277, eq. (8), with the cell average
    of J (a patch average for composite elements, de Souza Neto et al. 2005, IJNME
    62:353): det F̄_q = J̄, so the volumetric part of ψ sees one J per cell (P2/P0-like
    for P2, one volume constraint per patch for composite elements) while the isochoric
    part keeps F_q. Works for any ψ(F).

    Inversion: where ``J_q ≤ 0`` or ``J̄ ≤ 0`` the ratio is undefined (a negative ratio
    would give a finite ψ of a reflected F̄); there F̄_q = F_q is returned, so the
    material's own inversion handling applies (neo-Hookean: +∞, which the Newton line
    search rejects). As ``J_q → 0⁺`` at fixed J̄ > 0, F̄_q → ∞, a barrier for any ψ that
    grows with stretch.

    Args:
        F: ``(n_q, d, d)`` compatible deformation gradients of one cell.
        w: ``(n_q,)`` positive quadrature weights (rest measure included).

    Returns:
        ``(n_q, d, d)`` F̄.
    """
    d = F.shape[-1]
    J = jax.vmap(det)(F)
    sw = jnp.sum(w)
    Jbar = jnp.sum(w * J) / jnp.where(sw > 0, sw, 1.0)  # Σw = 0 (a padded cell): J̄ = 0, F̄ = F
    ok = (J > 0) & (Jbar > 0)
    ratio = jnp.where(ok, Jbar / jnp.where(ok, J, 1.0), 1.0)  # safe: no NaN in gradients
    return (ratio ** (1.0 / d))[:, None, None] * F


def _det_poly(F):
    if F.shape == (2, 2):
        return F[0, 0] * F[1, 1] - F[0, 1] * F[1, 0]
    return (
        F[0, 0] * (F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1])
        - F[0, 1] * (F[1, 0] * F[2, 2] - F[1, 2] * F[2, 0])
        + F[0, 2] * (F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0])
    )


@jax.custom_jvp
def _det(F):
    return _det_poly(F)


@_det.defjvp
def _det_jvp(primals, tangents):
    (F,), (dF,) = primals, tangents
    # dJ = cof F : dF. Written out instead of autodiff'd: reverse mode through the sliced
    # polynomial fused badly on XLA:CPU (3D forces 3x slower, scripts/bench_kernels.py).
    return _det_poly(F), jnp.sum(cofactor(F) * dF)


def det(F: jax.Array) -> jax.Array:
    """Determinant J of a 2×2 or 3×3 matrix, as a polynomial (smooth derivatives of every
    order; ``∂J/∂F = cof F``)."""
    if F.shape not in ((2, 2), (3, 3)):
        raise ValueError(f"det expects a 2x2 or 3x3 matrix, got shape {F.shape}")
    return _det(F)


def cofactor(F: jax.Array) -> jax.Array:
    """Cofactor matrix ``cof F = ∂J/∂F = J·F⁻ᵀ`` (defined for every F, also singular)."""
    if F.shape == (2, 2):
        return jnp.array([[F[1, 1], -F[1, 0]], [-F[0, 1], F[0, 0]]])
    if F.shape == (3, 3):
        c0 = jnp.cross(F[:, 1], F[:, 2])
        c1 = jnp.cross(F[:, 2], F[:, 0])
        c2 = jnp.cross(F[:, 0], F[:, 1])
        return jnp.stack([c0, c1, c2], axis=1)
    raise ValueError(f"cofactor expects a 2x2 or 3x3 matrix, got shape {F.shape}")


def green_strain(F: jax.Array) -> jax.Array:
    """Green–Lagrange strain ``E = ½(FᵀF − I)``."""
    return 0.5 * (F.T @ F - jnp.eye(F.shape[0], dtype=F.dtype))


def small_strain(F: jax.Array) -> jax.Array:
    """Small (infinitesimal) strain ``ε = ½(F + Fᵀ) − I``."""
    return 0.5 * (F + F.T) - jnp.eye(F.shape[0], dtype=F.dtype)


def corotated_strain(F: jax.Array) -> jax.Array:
    """Corotated strain ``S − I`` with ``F = R·S`` the rotation-variant polar decomposition."""
    _, S = polar(F)
    return S - jnp.eye(F.shape[0], dtype=F.dtype)


def _skew3(w):
    z = jnp.zeros((), w.dtype)
    return jnp.array([[z, -w[2], w[1]], [w[2], z, -w[0]], [-w[1], w[0], z]])


def _axial3(A):
    """Axial vector of the skew part's double: for ``A = [a]× ``, returns ``a``."""
    return jnp.array([A[2, 1], A[0, 2], A[1, 0]])


def _svd_rv_primal(F):
    U, s, Vt = jnp.linalg.svd(F)
    V = Vt.T
    d = F.shape[0]
    flip_u = jnp.linalg.det(U) < 0
    flip_v = jnp.linalg.det(V) < 0
    last = jnp.arange(d) == d - 1
    U = jnp.where(flip_u & last[None, :], -U, U)
    V = jnp.where(flip_v & last[None, :], -V, V)
    sign = jnp.where(flip_u ^ flip_v, -1.0, 1.0).astype(F.dtype)
    s = jnp.where(last, sign * s, s)
    return U, s, V


def _rotation_2d(F):
    a = F[0, 0] + F[1, 1]
    b = F[1, 0] - F[0, 1]
    r2 = a * a + b * b
    ok = r2 > jnp.finfo(F.dtype).tiny
    r = jnp.sqrt(jnp.where(ok, r2, 1.0))
    c = jnp.where(ok, a / r, 1.0)
    s = jnp.where(ok, b / r, 0.0)
    return jnp.array([[c, -s], [s, c]]), jnp.where(ok, r, 0.0)


@jax.custom_jvp
def _rotation_3d(F):
    U, _, V = _svd_rv_primal(F)
    return U @ V.T


@_rotation_3d.defjvp
def _rotation_3d_jvp(primals, tangents):
    (F,), (dF,) = primals, tangents
    R = _rotation_3d(F)
    S = R.T @ F
    S = 0.5 * (S + S.T)
    trS = jnp.trace(S)
    M = trS * jnp.eye(3, dtype=F.dtype) - S  # eigenvalues σi+σj ≥ 0
    # regularise the measure-zero set σi + σj = 0 (e.g. an exact reflection)
    delta = 1e-12 * jnp.maximum(jnp.abs(trS), 1.0)
    G = R.T @ dF
    w = jnp.linalg.solve(M + delta * jnp.eye(3, dtype=F.dtype), _axial3(G - G.T))
    return R, R @ _skew3(w)


def polar_rotation(F: jax.Array) -> jax.Array:
    """Rotation ``R ∈ SO(d)`` of the rotation-variant polar decomposition ``F = R·S``.

    ``R = U·Vᵀ`` of the rotation-variant SVD: it maximises ``tr(RᵀF)`` over SO(d), so for
    ``det F < 0`` it stays a rotation and S carries the reflection. Derivatives of all orders
    are finite at F = I, scaled rotations and repeated singular values.
    """
    if F.shape == (2, 2):
        return _rotation_2d(F)[0]
    if F.shape == (3, 3):
        return _rotation_3d(F)
    raise ValueError(f"polar expects a 2x2 or 3x3 matrix, got shape {F.shape}")


def polar(F: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Rotation-variant polar decomposition ``F = R·S``.

    Returns:
        ``(R, S)``: R ∈ SO(d); S = RᵀF symmetric, with eigenvalues the signed singular
        values (the smallest negative when ``det F < 0``).
    """
    R = polar_rotation(F)
    S = R.T @ F
    return R, 0.5 * (S + S.T)


@jax.custom_jvp
def _trace_S_3d(F):
    return jnp.trace(_rotation_3d(F).T @ F)


@_trace_S_3d.defjvp
def _trace_S_3d_jvp(primals, tangents):
    (F,), (dF,) = primals, tangents
    R = _rotation_3d(F)
    return jnp.trace(R.T @ F), jnp.sum(R * dF)


def trace_S(F: jax.Array) -> jax.Array:
    """``tr S = Σ σ̂ᵢ``, the sum of the signed singular values; ``∂ tr S/∂F = R``.

    Energies that depend on F through ``I_C = ‖F‖²``, ``J`` and ``tr S`` only (fixed
    corotated, corotated, ARAP) get exact, finite derivatives of every order this way.
    """
    if F.shape == (2, 2):
        return _rotation_2d(F)[1]
    if F.shape == (3, 3):
        return _trace_S_3d(F)
    raise ValueError(f"trace_S expects a 2x2 or 3x3 matrix, got shape {F.shape}")


@jax.custom_jvp
def svd_rv(F: jax.Array):
    """Rotation-variant SVD ``F = U·diag(σ̂)·Vᵀ`` with ``U, V ∈ SO(d)``.

    Returns:
        ``(U, sigma, V)``; sigma sorted descending in magnitude, the last one negative
        when ``det F < 0``.

    First derivatives are finite everywhere (the ``1/(σⱼ² − σᵢ²)`` terms of dU, dV are set
    to zero where singular values coincide). Second derivatives of a ψ written through
    ``sigma`` are *not* exact at repeated singular values: write such energies with
    :func:`trace_S`, :func:`polar` or invariants instead (the built-in models do).
    """
    return _svd_rv_primal(F)


@svd_rv.defjvp
def _svd_rv_jvp(primals, tangents):
    (F,), (dF,) = primals, tangents
    U, s, V = _svd_rv_primal(F)
    P = U.T @ dF @ V
    ds = jnp.diagonal(P)
    si, sj = s[:, None], s[None, :]
    den = sj**2 - si**2
    scale = jnp.maximum(jnp.max(jnp.abs(s)) ** 2, jnp.finfo(F.dtype).tiny)
    ok = jnp.abs(den) > 1e-12 * scale
    den_safe = jnp.where(ok, den, 1.0)
    wu = jnp.where(ok, (sj * P + si * P.T) / den_safe, 0.0)
    wv = jnp.where(ok, (si * P + sj * P.T) / den_safe, 0.0)
    return (U, s, V), (U @ wu, ds, V @ wv)


def principal_stretch_range(F: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The smallest and largest principal stretch ``(λ_min, λ_max)`` of one ``(d, d)`` F.

    The square roots of the extreme eigenvalues of ``C = FᵀF`` in closed form (2D: the
    quadratic formula; 3D: the trigonometric solution of the characteristic cubic, Smith,
    *Eigenvalues of a symmetric 3 × 3 matrix*, Commun. ACM 4(4):168, 1961) — no LAPACK
    call, so it runs inside sharded programs too. Not meant to be differentiated.
    """
    C = F.T @ F
    d = F.shape[0]
    if d == 2:
        m = 0.5 * (C[0, 0] + C[1, 1])
        r = jnp.sqrt(0.25 * (C[0, 0] - C[1, 1]) ** 2 + C[0, 1] ** 2)
        lo, hi = m - r, m + r
    else:
        q = jnp.trace(C) / 3.0
        off = C[0, 1] ** 2 + C[0, 2] ** 2 + C[1, 2] ** 2
        p2 = (C[0, 0] - q) ** 2 + (C[1, 1] - q) ** 2 + (C[2, 2] - q) ** 2 + 2.0 * off
        p = jnp.sqrt(p2 / 6.0)
        tiny = p <= jnp.finfo(F.dtype).eps * jnp.maximum(jnp.abs(q), jnp.finfo(F.dtype).tiny)
        B = (C - q * jnp.eye(3, dtype=F.dtype)) / jnp.where(tiny, 1.0, p)
        r = jnp.clip(0.5 * _det_poly(B), -1.0, 1.0)
        phi = jnp.arccos(r) / 3.0
        hi = jnp.where(tiny, q, q + 2.0 * p * jnp.cos(phi))
        lo = jnp.where(tiny, q, q + 2.0 * p * jnp.cos(phi + 2.0 * jnp.pi / 3.0))
    return jnp.sqrt(jnp.maximum(lo, 0.0)), jnp.sqrt(jnp.maximum(hi, 0.0))


class DeformationExtremes(NamedTuple):
    """The most deformed cells of a configuration (:func:`deformation_extremes`).

    Attributes:
        min_J: the smallest det F over every quadrature point (≤ 0: an inverted cell).
        min_J_cell: the cell where it occurs (int32).
        max_strain: the largest principal (Biot) strain ``max |λᵢ − 1|`` over every
            quadrature point, λᵢ the principal stretches (dimensionless: 1.0 = 100 %).
        max_strain_cell: the cell where it occurs (int32).
    """

    min_J: jax.Array
    min_J_cell: jax.Array
    max_strain: jax.Array
    max_strain_cell: jax.Array


def deformation_extremes(x: jax.Array, mesh) -> DeformationExtremes:
    """The smallest J and the largest principal strain of positions ``x`` ``(n_nodes, dim)``
    on ``mesh``, and the cells where they occur (from the compatible F, not F̄; traceable,
    not differentiated)."""
    F = jax.lax.stop_gradient(deformation_gradients(x, mesh, fbar=False))  # (c, q, d, d)
    J = jnp.min(jax.vmap(jax.vmap(det))(F), axis=1)  # (c,)
    lo, hi = jax.vmap(jax.vmap(principal_stretch_range))(F)  # (c, q) each
    strain = jnp.max(jnp.maximum(hi - 1.0, 1.0 - lo), axis=1)  # (c,)
    jc, sc = jnp.argmin(J), jnp.argmax(strain)
    return DeformationExtremes(
        min_J=J[jc],
        min_J_cell=jc.astype(jnp.int32),
        max_strain=strain[sc],
        max_strain_cell=sc.astype(jnp.int32),
    )
