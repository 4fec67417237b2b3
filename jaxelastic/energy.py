"""Mechanics derived from ψ by autodiff: energy, stress, forces, HVP, element Hessians.

Everything here is a pure function of ``(psi, x, mesh, params)``:

* ``psi(F, params) -> scalar`` for one unbatched ``(d, d)`` F (a static Python callable);
* ``x``: ``(n_nodes, d)`` current positions;
* ``mesh``: a :class:`~jaxelastic.mesh.Mesh` (pass it as a jit *argument*);
* ``params``: any pytree. A leaf of shape ``()`` is shared by all cells; a leaf with a
  leading axis of length ``n_cells`` is a per-cell field (e.g. ``Lame(mu=mu_cells,
  lam=1e4)``). Gradients w.r.t. params (shared or per-cell) just work.

The total energy is ``E(x) = Σ_c Σ_q w_cq ψ(F_cq)``. Forces, HVP and element Hessians are
computed per element with ``jax.grad``/``jax.jvp``/``jax.hessian`` of ψ, contracted with the
shape-function gradients, and assembled with a scatter-free node→slot gather
(``mesh.incidence``): unsorted scatter-add is slow on XLA:CPU. ``jax.grad(energy)`` gives
the same forces through JAX's own (scatter) path and is kept for users and tests.

Under the ``"fbar"`` formulation (``mesh.formulation``, static) F_cq is replaced by
F̄_cq = (J̄_c/J_cq)^{1/d} F_cq (:func:`~jaxelastic.kinematics.f_bar`). F̄ couples the
quadrature points of a cell, so the F-bar kernels differentiate the element energy with
respect to the element's node positions (``jax.grad``/``jax.jvp``/``jax.hessian``) instead
of contracting P with ∇N; they are still cell-local, so element Hessians are exact and every
solver works unchanged. ``"bbar"`` is the small-strain analogue (B-bar,
:func:`~jaxelastic.kinematics.b_bar`) for small-strain materials. Nothing of either is traced
for ``"standard"`` meshes.

Input checks: the public functions check, before anything is traced and at no cost to a
jitted computation (static shapes only, under jit/vmap/grad too): ``x`` (and ``v``) must
have the mesh's shape ``(n_nodes, dim)``, and ψ must return a scalar float for one
unbatched ``(d, d)`` F (:func:`check_psi`, evaluated abstractly once per ψ, dimension,
dtype and parameter structure, then cached). Outside any transformation (no argument is a
JAX tracer) they also refuse NaN/inf in ``x`` and the float leaves of ``params``
(:func:`check_finite`); inside ``jax.jit`` (or under ``vmap``/``grad``) nothing is checked
by value and non-finite input gives NaN results (the solvers report it in their status).
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer

from .kinematics import b_bar, deformation_gradients, f_bar

__all__ = [
    "first_piola",
    "energy",
    "energy_densities",
    "forces",
    "hvp",
    "element_forces",
    "element_hessians",
    "element_gradient_kernel",
    "project_psd",
    "assemble",
    "cell_params_axes",
    "check_positions",
    "check_psi",
    "check_finite",
    "psi_name",
]

Psi = Callable[..., jax.Array]


def first_piola(psi: Psi) -> Callable:
    """First Piola–Kirchhoff stress ``P(F, params) = ∂ψ/∂F`` by autodiff."""
    return jax.grad(psi, argnums=0)


def cell_params_axes(params, n_cells: int):
    """vmap ``in_axes`` for ``params``: 0 for per-cell leaves, None for shared scalars.

    Raises:
        ValueError: a non-scalar leaf whose leading axis is not ``n_cells``.
    """

    def axis(leaf):
        shape = jnp.shape(leaf)
        if len(shape) == 0:
            return None
        if shape[0] != n_cells:
            raise ValueError(
                f"material parameter leaf of shape {shape} is neither a scalar nor a "
                f"per-cell field with leading axis n_cells={n_cells}"
            )
        return 0

    return jax.tree_util.tree_map(axis, params)


# ----------------------------------------------------------------------------- input checks


def psi_name(psi) -> str:
    """A readable name of ψ for error messages: its ``__qualname__`` (that of the wrapped
    function for ``functools.partial``), else its ``repr``."""
    func = getattr(psi, "func", None)  # functools.partial
    if func is not None and callable(func) and hasattr(psi, "args"):
        return f"functools.partial({psi_name(func)}, ...)"
    name = getattr(psi, "__qualname__", None) or getattr(psi, "__name__", None)
    return str(name) if name else repr(psi)


def check_positions(x, mesh, *, name: str = "x", where: str = "je.energy") -> None:
    """Raise unless ``x`` has the shape ``(n_nodes, dim)`` of ``mesh.points``.

    Static shapes only: free under jit, and under vmap it checks the per-example shape.

    Args:
        x: the array to check (positions, or a direction such as ``v`` of :func:`hvp`).
        mesh: the :class:`~jaxelastic.mesh.Mesh` it belongs to.
        name, where: the argument's and the calling function's names, for the message.

    Raises:
        TypeError: ``mesh`` is not a mesh (e.g. arguments swapped).
        ValueError: the message names the argument, the expected and the given shape.
    """
    pts = getattr(mesh, "points", None)
    if pts is None or not hasattr(pts, "shape") or not hasattr(mesh, "cells"):
        raise TypeError(
            f"{where}: mesh must be a je.Mesh (e.g. je.rectangle(...), je.read_mesh(path).mesh),"
            f" got {type(mesh).__name__}; the signature is {where}(psi, x, mesh, params)"
        )
    shape, want = tuple(jnp.shape(x)), tuple(pts.shape)
    if shape != want:
        dim = want[1] if len(want) == 2 else "?"
        raise ValueError(
            f"{where}: {name} must have shape (n_nodes, dim) = {want} like mesh.points "
            f"(a {dim}D mesh of {want[0]} nodes), got {shape}"
        )


# ψ -> set of (dim, dtype, params structure) keys already checked
_PSI_CHECKED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


_NUMBERS = (bool, int, float, complex)


def _param_key(params, n_cells: int):
    """``(treedef, leaves, per_cell, key)`` of ``params``: ``per_cell[i]`` says leaf i has a
    leading ``n_cells`` axis; ``key`` is a hashable summary of the structure ψ sees (None if a
    leaf is neither an array nor a Python number: nothing can be checked)."""
    leaves, treedef = jax.tree_util.tree_flatten(params)
    per_cell, key = [], []
    for leaf in leaves:
        if isinstance(leaf, _NUMBERS):
            per_cell.append(False)
            key.append(type(leaf))
            continue
        shape, dtype = getattr(leaf, "shape", None), getattr(leaf, "dtype", None)
        if shape is None or dtype is None:
            return treedef, leaves, per_cell, None
        shape = tuple(shape)
        if shape and shape[0] != n_cells:
            cell_params_axes(params, n_cells)  # raises the message naming the shape
        per_cell.append(bool(shape))
        key.append((shape, dtype, bool(getattr(leaf, "weak_type", False))))
    return treedef, leaves, per_cell, (treedef, tuple(key))


def _param_spec(treedef, leaves, per_cell):
    """Parameters as ψ sees them for one cell, as ShapeDtypeStructs (numbers kept)."""
    spec = [
        leaf
        if isinstance(leaf, _NUMBERS)
        else jax.ShapeDtypeStruct(
            tuple(leaf.shape)[1:] if pc else tuple(leaf.shape),
            leaf.dtype,
            weak_type=bool(getattr(leaf, "weak_type", False)),
        )
        for leaf, pc in zip(leaves, per_cell, strict=True)
    ]
    return jax.tree_util.tree_unflatten(treedef, spec)


def _describe_return(out, raw) -> str | None:
    """What ψ returned, when it is not a scalar float (else None)."""
    if isinstance(raw, bool) or isinstance(raw, int):
        return f"the Python {type(raw).__name__} {raw!r}"
    if not isinstance(out, jax.ShapeDtypeStruct):
        return f"a {type(raw).__name__}" + (f" {raw!r}" if raw is None else "")
    if out.shape != () or not jnp.issubdtype(out.dtype, jnp.floating):
        return f"an array of shape {out.shape} and dtype {out.dtype}"
    return None


def check_psi(
    psi, dim: int, dtype, params, n_cells: int, *, where: str = "je.energy", own_errors=True
) -> None:
    """Raise unless ``psi(F, params)`` returns a scalar float for one ``(dim, dim)`` F.

    Evaluated abstractly (``jax.eval_shape`` at F = I with one cell's parameters), so it
    works under jit/vmap/grad too; the result is cached per ψ object, ``dim``, ``dtype`` and
    parameter structure, so repeated calls cost a dictionary lookup. Errors raised by ψ
    itself propagate unchanged (``own_errors=True``) or are ignored (``own_errors=False``,
    e.g. for a potential built with placeholder parameters: they surface when it is used).

    Args:
        psi: the strain-energy density ``psi(F, params)``.
        dim: 2 or 3.
        dtype: the float dtype of F (the mesh's).
        params: the parameter pytree as passed to the energy (shared or per-cell leaves).
        n_cells: number of cells (to recognise per-cell leaves).
        where: the calling function's name, for the message.

    Raises:
        TypeError: ψ is not callable, or returns anything but a scalar float (the message
            names ψ by its ``__qualname__``, what it returned and what is required).
        ValueError: a parameter leaf is neither a scalar nor a per-cell field.
    """
    if not callable(psi):
        raise TypeError(f"{where}: psi must be a function psi(F, params), got {psi!r}")
    treedef, leaves, per_cell, key = _param_key(params, n_cells)
    if key is None:
        return
    key = (int(dim), jnp.dtype(dtype), key)
    try:
        done = _PSI_CHECKED.get(psi)
    except TypeError:  # unhashable callable: check every time
        done = None
    if done is not None and key in done:
        return
    spec = _param_spec(treedef, leaves, per_cell)
    raw = []

    def at_identity(p):
        out = psi(jnp.eye(dim, dtype=dtype), p)
        raw.append(out)
        return out

    try:
        out = jax.eval_shape(at_identity, spec)
    except Exception:
        if own_errors:
            raise
        return
    what = _describe_return(out, raw[0] if raw else None)
    if what is not None:
        raise TypeError(
            f"{where}: ψ {psi_name(psi)!r} returned {what} at F = I ({dim}×{dim}); a "
            f"strain-energy density must return a scalar float for one unbatched F of shape "
            f"({dim}, {dim}) (reduce with jnp.sum, return floats: 0.0 not 0)"
        )
    try:
        _PSI_CHECKED.setdefault(psi, set()).add(key)
    except TypeError:
        pass  # not weak-referenceable or unhashable: nothing is cached


def _first_bad(leaf) -> str:
    """Where the first NaN/inf of a concrete array sits (for the message)."""
    a = np.asarray(leaf)
    bad = ~np.isfinite(a)
    n = int(bad.sum())
    if a.ndim == 0:
        return f"is {a.item()!r}"
    idx = np.unravel_index(int(np.flatnonzero(bad.ravel())[0]), a.shape)
    at = f"node {idx[0]}" if a.ndim == 2 else f"index {tuple(int(i) for i in idx)}"
    return f"has {n} NaN/inf value(s) of {a.size}, the first at {at} ({a[idx]!r})"


def _all_finite(a: jax.Array) -> bool:
    """``isfinite(a).all()`` of a concrete array: on the host for CPU arrays (a zero-copy
    view, ~5 µs), one reduction on the device otherwise (no copy of ``a``)."""
    if all(d.platform == "cpu" for d in a.devices()) and a.is_fully_addressable:
        return bool(np.isfinite(np.asarray(a)).all())
    return bool(jnp.isfinite(a).all())


def check_finite(where: str, **trees) -> None:
    """Outside any JAX transformation, raise if a float leaf of ``trees`` holds NaN/inf.

    Skipped entirely (free) when any leaf is a JAX tracer, i.e. under jit/vmap/grad, where
    NaN propagates to the results instead. One reduction per float array otherwise.

    Args:
        where: the calling function's name, for the message.
        trees: name → array or pytree (e.g. ``x=x, params=params``).

    Raises:
        ValueError: the message names the argument (and the leaf path of a pytree).
    """
    named = []
    for name, tree in trees.items():
        for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
            if isinstance(leaf, Tracer):
                return
            named.append((name + jax.tree_util.keystr(path), leaf))
    for name, leaf in named:
        if isinstance(leaf, float):
            ok = math.isfinite(leaf)
        elif isinstance(leaf, (np.ndarray, np.generic)):
            ok = not np.issubdtype(leaf.dtype, np.inexact) or bool(np.isfinite(leaf).all())
        elif isinstance(leaf, jax.Array):
            ok = not jnp.issubdtype(leaf.dtype, jnp.inexact) or _all_finite(leaf)
        else:
            continue
        if not ok:
            raise ValueError(
                f"{where}: {name} {_first_bad(leaf)}; refusing non-finite input (inside "
                "jax.jit nothing is checked and the result is NaN)"
            )


def _check_call(where: str, psi, x, mesh, params, **more) -> None:
    """The checks of every public ``(psi, x, mesh, params)`` function."""
    check_positions(x, mesh, where=where)
    for name, v in more.items():
        check_positions(v, mesh, name=name, where=where)
    check_psi(psi, mesh.points.shape[1], mesh.points.dtype, params, mesh.n_cells, where=where)
    if not isinstance(mesh.points, Tracer):  # a traced mesh: inside a transformation
        check_finite(where, x=x, params=params, **more)


def _per_cell(fn, params, n_cells):
    """vmap ``fn(cell_data..., params)`` over cells, broadcasting shared parameters."""
    return jax.vmap(fn, in_axes=(0, 0, 0, cell_params_axes(params, n_cells)))


def energy_densities(psi: Psi, x: jax.Array, mesh, params) -> jax.Array:
    """ψ at every quadrature point, ``(n_cells, n_q)`` [energy / rest measure] (of F̄
    under the ``"fbar"`` formulation).

    Args:
        psi: ``psi(F, params) -> scalar`` for one unbatched ``(d, d)`` F.
        x: ``(n_nodes, d)`` current positions [length].
        mesh: the rest :class:`~jaxelastic.mesh.Mesh`.
        params: material parameter pytree (shared scalars or per-cell leaves).

    Raises (here and in :func:`energy`, :func:`forces`, :func:`hvp`,
    :func:`element_forces`, :func:`element_hessians`; all checks happen before tracing):
        TypeError: ``mesh`` is not a mesh, or ψ does not return a scalar float.
        ValueError: ``x`` (or ``v``) is not ``(n_nodes, dim)``, a parameter leaf is neither
            a scalar nor per-cell, or, outside any transformation only, ``x``/``params``
            hold NaN/inf. Inside ``jax.jit`` non-finite input is not checked: it gives NaN.
    """
    _check_call("je.energy_densities", psi, x, mesh, params)
    return _energy_densities(psi, x, mesh, params)


def _energy_densities(psi: Psi, x: jax.Array, mesh, params) -> jax.Array:
    F = deformation_gradients(x, mesh)
    ax = cell_params_axes(params, mesh.n_cells)
    per_q = jax.vmap(psi, in_axes=(0, None))
    return jax.vmap(per_q, in_axes=(0, ax))(F, params)


def energy(psi: Psi, x: jax.Array, mesh, params) -> jax.Array:
    """Total elastic energy ``Σ_c Σ_q w_cq ψ(F_cq)`` [energy], a scalar.

    Args: as :func:`energy_densities` (``x``: ``(n_nodes, d)`` positions [length]).
    """
    _check_call("je.energy", psi, x, mesh, params)
    return jnp.sum(mesh.weights * _energy_densities(psi, x, mesh, params))


def _cell_grad(xe, dN):
    """``F_q = Σ_k x_k ⊗ ∇N_k(q)`` for one cell: xe ``(k, d)``, dN ``(q, k, d)`` → ``(q, d, d)``.

    P1 keeps the einsum; for more nodes the sum over k is unrolled into broadcasts, which XLA
    fuses into one loop: the vmapped einsum becomes a batched dot_general of tiny matrices,
    measured 15× slower on CPU for tet10 (50 ms vs 3 ms on 10k cells).
    """
    k, d = xe.shape
    if k == d + 1:
        return jnp.einsum("ka,qkb->qab", xe, dN)
    out = xe[0][None, :, None] * dN[:, 0, None, :]
    for a in range(1, k):
        out = out + xe[a][None, :, None] * dN[:, a, None, :]
    return out


def _cell_contract(w, Pq, dN):
    """``f_k = Σ_q w_q P_q ∇N_k(q)``: w ``(q,)``, Pq ``(q, d, d)``, dN ``(q, k, d)`` →
    ``(k, d)``; unrolled over (q, b) beyond P1 for the same reason as :func:`_cell_grad`
    (tet10 forces: 3× faster than the einsum)."""
    q, k, d = dN.shape
    if k == d + 1:
        return jnp.einsum("q,qab,qkb->ka", w, Pq, dN)
    WP = w[:, None, None] * Pq
    out = WP[0, None, :, 0] * dN[0, :, 0, None]
    for i in range(q):
        for b in range(d):
            if i or b:
                out = out + WP[i, None, :, b] * dN[i, :, b, None]
    return out


def _fbar_element_energy(psi, form: str = "fbar"):
    fmap = b_bar if form == "bbar" else f_bar

    def ee(xe, dN, w, p):
        F = fmap(_cell_grad(xe, dN), w)
        return jnp.sum(w * jax.vmap(psi, in_axes=(0, None))(F, p))

    return ee


def _is_fbar(mesh) -> str | None:
    """The mesh's F̄ map name (``"fbar"``/``"bbar"``), or None for the standard path."""
    form = getattr(mesh, "formulation", "standard")
    return None if form == "standard" else form


def element_gradient_kernel(psi, fbar: str | None = None):
    """The per-element energy gradient ``(xe (k, d), dN (q, k, d), w (q,), params) ↦
    ∂E_e/∂xe (k, d)`` of ψ (autodiff P contracted with the shape-function gradients; with
    ``fbar="fbar"``/``"bbar"`` the gradient of the F̄ element energy). Unbatched: vmap it
    over cells (as :func:`element_forces` does)."""
    if fbar:
        return jax.grad(_fbar_element_energy(psi, fbar))
    P = first_piola(psi)

    def fe(xe, dN, w, p):
        # xe (k, d), dN (q, k, d), w (q,) -> ∂E_e/∂xe (k, d)
        F = _cell_grad(xe, dN)
        Pq = jax.vmap(P, in_axes=(0, None))(F, p)  # (q, d, d)
        return _cell_contract(w, Pq, dN)

    return fe


def element_forces(psi: Psi, x: jax.Array, mesh, params) -> jax.Array:
    """Per-element energy gradients ``∂E_c/∂x_a = Σ_q w P·∇N_a``, ``(n_cells, k, d)``.

    (Element *forces* are the negatives; this is the quantity that gets assembled.)
    Args as :func:`energy_densities`.
    """
    _check_call("je.element_forces", psi, x, mesh, params)
    return _element_forces(psi, x, mesh, params)


def _element_forces(psi: Psi, x: jax.Array, mesh, params) -> jax.Array:
    xe = x[mesh.cells]
    fe = element_gradient_kernel(psi, _is_fbar(mesh))
    return _per_cell(fe, params, mesh.n_cells)(xe, mesh.dN, mesh.weights, params)


_MAX_UNROLLED_VALENCE = 256  # above this, gather (n_nodes, valence, d) then sum


def assemble(mesh, per_element: jax.Array) -> jax.Array:
    """Sum per-element nodal vectors ``(n_cells, k, d)`` into ``(n_nodes, d)``.

    Uses the precomputed node→slot incidence table: one gather per valence column, summed
    in column order (XLA fuses them into a single loop with no ``(n_nodes, valence, d)``
    intermediate). Measured by ``scripts/bench_kernels.py``: 3–6× faster at 10⁵–10⁶ cells
    than a gather-then-sum, and faster than an unsorted scatter-add on XLA:CPU.
    """
    c, k, d = per_element.shape
    flat = per_element.reshape(c * k, d)
    inc = mesh.incidence  # (n_nodes, valence); padding entries are c*k (out of range)
    if inc.shape[1] > _MAX_UNROLLED_VALENCE:  # e.g. a fan of many cells around one node
        padded = jnp.concatenate([flat, jnp.zeros((1, d), flat.dtype)])
        return padded[inc].sum(axis=1)
    out = flat.at[inc[:, 0]].get(mode="fill", fill_value=0)
    for j in range(1, inc.shape[1]):
        out = out + flat.at[inc[:, j]].get(mode="fill", fill_value=0)  # padding reads 0
    return out


def forces(psi: Psi, x: jax.Array, mesh, params) -> jax.Array:
    """Nodal elastic forces ``f = −∂E/∂x``, ``(n_nodes, d)`` [force].

    Args: as :func:`energy_densities` (``x``: ``(n_nodes, d)`` positions [length]).
    """
    _check_call("je.forces", psi, x, mesh, params)
    return -assemble(mesh, _element_forces(psi, x, mesh, params))


def _element_hvp(psi, fbar: str | None = None):
    if fbar:
        g = jax.grad(_fbar_element_energy(psi, fbar))

        def he_fbar(xe, ve, dN, w, p):
            return jax.jvp(lambda y: g(y, dN, w, p), (xe,), (ve,))[1]

        return he_fbar
    P = first_piola(psi)

    def he(xe, ve, dN, w, p):
        F = _cell_grad(xe, dN)
        dF = _cell_grad(ve, dN)
        Pp = lambda f: jax.vmap(P, in_axes=(0, None))(f, p)
        _, dP = jax.jvp(Pp, (F,), (dF,))
        return _cell_contract(w, dP, dN)

    return he


def hvp(psi: Psi, x: jax.Array, v: jax.Array, mesh, params) -> jax.Array:
    """Hessian-vector product ``(∂²E/∂x²)·v`` by forward-over-reverse, ``(n_nodes, d)``.

    Never forms a Hessian: per element, ``dP = jvp(∂ψ/∂F)(F; dF)`` with ``dF = Σ v_a ⊗ ∇N_a``.
    ``v``: ``(n_nodes, d)`` direction [length]; other args as :func:`energy_densities`.
    """
    _check_call("je.hvp", psi, x, mesh, params, v=v)
    xe, ve = x[mesh.cells], v[mesh.cells]
    fn = jax.vmap(
        _element_hvp(psi, _is_fbar(mesh)),
        in_axes=(0, 0, 0, 0, cell_params_axes(params, mesh.n_cells)),
    )
    return assemble(mesh, fn(xe, ve, mesh.dN, mesh.weights, params))


def project_psd(K: jax.Array, floor: float = 0.0) -> jax.Array:
    """Clamp the eigenvalues of symmetric matrices ``(..., m, m)`` to ``≥ floor``.

    The standard fix that makes Newton's linear systems positive (semi)definite
    (Teran et al. 2005, *Robust quasistatic finite elements and flesh simulation*, §5).
    """
    K = 0.5 * (K + jnp.swapaxes(K, -1, -2))
    lam, Q = jnp.linalg.eigh(K)
    lam = jnp.maximum(lam, floor)
    return jnp.einsum("...ij,...j,...kj->...ik", Q, lam, Q)


def _element_hessian(psi, fbar: str | None = None):
    if fbar:
        ee = _fbar_element_energy(psi, fbar)

        def ke_fbar(xe, dN, w, p):
            k, d = xe.shape
            return jax.hessian(ee)(xe, dN, w, p).reshape(k * d, k * d)

        return ke_fbar

    def ke(xe, dN, w, p):
        F = _cell_grad(xe, dN)
        C = jax.vmap(jax.hessian(psi, argnums=0), in_axes=(0, None))(F, p)  # (q,d,d,d,d)
        k, d = xe.shape
        K = jnp.einsum("q,qkb,qabcd,qld->kalc", w, dN, C, dN)  # (k, d, k, d)
        return K.reshape(k * d, k * d)

    return ke


def element_hessians(psi: Psi, x: jax.Array, mesh, params, *, project: bool = False):
    """Per-element Hessians ``∂²E_c/∂x_e²``, ``(n_cells, k·d, k·d)`` (node-major dofs).

    Args:
        project: clamp each element Hessian to positive semidefinite (see
            :func:`project_psd`), for Newton on indefinite configurations.

    Other args as :func:`energy_densities`.
    """
    _check_call("je.element_hessians", psi, x, mesh, params)
    xe = x[mesh.cells]
    ke = _element_hessian(psi, _is_fbar(mesh))
    K = _per_cell(ke, params, mesh.n_cells)(xe, mesh.dN, mesh.weights, params)
    return project_psd(K) if project else K
