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

import functools
import math
import weakref
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer

from .fusion import always, computed
from .kinematics import b_bar, cofactor, deformation_gradients, det, displacements, f_bar
from .mesh.elements import get_element

__all__ = [
    "first_piola",
    "energy",
    "energy_densities",
    "forces",
    "hvp",
    "element_forces",
    "element_hessians",
    "element_hessians_reference",
    "element_gradient_kernel",
    "project_psd",
    "project_element_psd",
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
    except (AttributeError, KeyError) as e:  # ψ read a field its parameters do not have
        if not own_errors:
            return
        raise TypeError(
            f"{where}: ψ {psi_name(psi)!r} could not read its parameters "
            f"({type(e).__name__}: {e}); they were a {type(params).__name__}. The built-in "
            "models take je.Lame(mu, lam) (e.g. je.Lame(*je.lame(E, nu))); a user ψ gets "
            "exactly the pytree given as params"
        ) from e
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
    if mesh.halo is not None:
        return _sharded_energy(psi, x, mesh, params)
    return jnp.sum(mesh.weights * _energy_densities(psi, x, mesh, params))


def _cell_grad(ue, dN):
    """``∇u_q = Σ_k u_k ⊗ ∇N_k(q)`` for one cell: ue ``(k, d)``, dN ``(q, k, d)`` → ``(q, d, d)``.

    ``ue`` is any nodal field of the cell: displacements (F = I + ∇u, :func:`_cell_F`) or an
    HVP direction (dF). P1 keeps the einsum; for more nodes the sum over k is unrolled into
    broadcasts, which XLA fuses into one loop: the vmapped einsum becomes a batched
    dot_general of tiny matrices, measured 15× slower on CPU for tet10 (50 ms vs 3 ms on
    10k cells).
    """
    k, d = ue.shape
    if k == d + 1:
        return jnp.einsum("ka,qkb->qab", ue, dN)
    out = ue[0][None, :, None] * dN[:, 0, None, :]
    for a in range(1, k):
        out = out + ue[a][None, :, None] * dN[:, a, None, :]
    return out


def _cell_F(ue, dN):
    """``F_q = I + Σ_k u_k ⊗ ∇N_k(q)`` from the cell's nodal displacements ``ue`` ``(k, d)``:
    the round-off does not grow with the coordinates (see
    :func:`~jaxelastic.kinematics.deformation_gradients`)."""
    d = ue.shape[1]
    return _cell_grad(ue, dN) + jnp.eye(d, dtype=ue.dtype)[None]


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
    """The F̄ element energy ``(ue, dN, w, params) ↦ Σ_q w_q ψ(F̄_q)`` of one cell."""
    fmap = b_bar if form == "bbar" else f_bar

    def ee(ue, dN, w, p):
        F = fmap(_cell_F(ue, dN), w)
        return jnp.sum(w * jax.vmap(psi, in_axes=(0, None))(F, p))

    return ee


def _element_energy(psi, form: str | None = None):
    """The element energy ``(ue, dN, w, params) ↦ Σ_q w_q ψ(F_q)`` (F̄ under a formulation)."""
    if form:
        return _fbar_element_energy(psi, form)

    def ee(ue, dN, w, p):
        return jnp.sum(w * jax.vmap(psi, in_axes=(0, None))(_cell_F(ue, dN), p))

    return ee


def _is_fbar(mesh) -> str | None:
    """The mesh's F̄ map name (``"fbar"``/``"bbar"``), or None for the standard path."""
    form = getattr(mesh, "formulation", "standard")
    return None if form == "standard" else form


def element_gradient_kernel(psi, fbar: str | None = None):
    """The per-element energy gradient ``(ue (k, d), dN (q, k, d), w (q,), params) ↦
    ∂E_e/∂x_e (k, d)`` of ψ, with ``ue`` the element's nodal *displacements* ``x_e − X_e``
    (autodiff P at ``F = I + Σ u_k ⊗ ∇N_k``, contracted with the shape-function gradients;
    with ``fbar="fbar"``/``"bbar"`` the gradient of the F̄ element energy). Unbatched: vmap
    it over cells (as :func:`element_forces` does)."""
    if fbar:
        return jax.grad(_fbar_element_energy(psi, fbar))
    P = first_piola(psi)

    def fe(ue, dN, w, p):
        # ue (k, d), dN (q, k, d), w (q,) -> ∂E_e/∂xe (k, d)
        F = _cell_F(ue, dN)
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
    ue = displacements(x, mesh)[mesh.cells]
    fe = element_gradient_kernel(psi, _is_fbar(mesh))
    return _per_cell(fe, params, mesh.n_cells)(ue, mesh.dN, mesh.weights, params)


_MAX_UNROLLED_VALENCE = 256  # above this, gather (n_nodes, valence, d) then sum


def assemble(mesh, per_element: jax.Array) -> jax.Array:
    """Sum per-element nodal vectors ``(n_cells, k, d)`` into ``(n_nodes, d)``.

    Uses the precomputed node→slot incidence table: one gather per valence column, summed
    in column order (XLA fuses them into a single loop with no ``(n_nodes, valence, d)``
    intermediate). Measured by ``scripts/bench_kernels.py``: 3–6× faster at 10⁵–10⁶ cells
    than a gather-then-sum, and faster than an unsorted scatter-add on XLA:CPU.
    """
    if not hasattr(mesh, "incidence") or not hasattr(mesh, "cells"):
        raise TypeError(
            f"assemble(mesh, per_element): mesh must be a je.Mesh, got {type(mesh).__name__}"
        )
    if getattr(mesh, "halo", None) is not None:
        return _sharded_assemble(mesh, per_element)
    shape = tuple(jnp.shape(per_element))
    want = (int(mesh.cells.shape[0]), int(mesh.cells.shape[1]), int(mesh.points.shape[1]))
    if shape != want:
        raise ValueError(
            f"per_element must have shape {want} (n_cells, nodes per cell, dim), got {shape}"
        )
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
    if mesh.halo is not None:
        return _sharded_nodal(forces, psi, x, mesh, params)
    return -assemble(mesh, _element_forces(psi, x, mesh, params))


def _element_hvp(psi, fbar: str | None = None):
    if fbar:
        g = jax.grad(_fbar_element_energy(psi, fbar))

        def he_fbar(ue, ve, dN, w, p):
            return jax.jvp(lambda y: g(y, dN, w, p), (ue,), (ve,))[1]

        return he_fbar
    P = first_piola(psi)

    def he(ue, ve, dN, w, p):
        F = _cell_F(ue, dN)
        dF = _cell_grad(ve, dN)
        Pp = lambda f: jax.vmap(P, in_axes=(0, None))(f, p)
        _, dP = jax.jvp(Pp, (F,), (dF,))
        return _cell_contract(w, dP, dN)

    return he


def hvp(psi: Psi, x: jax.Array, v: jax.Array, mesh, params) -> jax.Array:
    """Hessian-vector product ``(∂²E/∂x²)·v`` by forward-over-reverse, ``(n_nodes, d)``.

    Never forms a Hessian: per element, ``dP = jvp(∂ψ/∂F)(F; dF)`` with ``dF = Σ v_a ⊗ ∇N_a``.
    ``v``: ``(n_nodes, d)`` direction [length], cast to the mesh's dtype; other args as
    :func:`energy_densities`.
    """
    _check_call("je.hvp", psi, x, mesh, params, v=v)
    if mesh.halo is not None:
        return _sharded_nodal(hvp, psi, x, mesh, params, v)
    dtype = mesh.points.dtype
    ue, ve = displacements(x, mesh)[mesh.cells], v.astype(dtype)[mesh.cells]
    fn = jax.vmap(
        _element_hvp(psi, _is_fbar(mesh)),
        in_axes=(0, 0, 0, 0, cell_params_axes(params, mesh.n_cells)),
    )
    return assemble(mesh, fn(ue, ve, mesh.dN, mesh.weights, params))


def project_psd(K: jax.Array, floor: float = 0.0) -> jax.Array:
    """Clamp the eigenvalues of symmetric matrices ``(..., m, m)`` to ``≥ floor``.

    The standard fix that makes Newton's linear systems positive (semi)definite
    (Teran et al. 2005, *Robust quasistatic finite elements and flesh simulation*, §5).
    """
    K = 0.5 * (K + jnp.swapaxes(K, -1, -2))
    lam, Q = jnp.linalg.eigh(K)
    lam = jnp.maximum(lam, floor)
    return jnp.einsum("...ij,...j,...kj->...ik", Q, lam, Q)


def _translation_free_basis(k: int, d: int) -> np.ndarray:
    """``(k·d, (k−1)·d)`` orthonormal columns spanning the node-major displacements of
    ``k`` nodes in ``d`` dimensions with no net translation (``Σ_nodes u = 0``)."""
    Q, _ = np.linalg.qr(np.eye(k)[:, 1:] - 1.0 / k)  # (k, k−1), orthogonal to (1, …, 1)
    return np.kron(Q, np.eye(d))


def project_element_psd(K: jax.Array, dim: int) -> jax.Array:
    """:func:`project_psd` (floor 0) of element Hessians of a translation-invariant energy,
    through the ``(k−1)·d`` square matrices that remain once the d rigid translations are
    taken out: 9×9 eigenproblems for 4-node tets instead of 12×12.

    The energy of a cell depends on its nodes through F only, so ``K (1 ⊗ e_x) = 0``: with
    ``W`` the orthonormal complement of the translations (a constant), ``K = W H Wᵀ``,
    ``H = Wᵀ K W``, and ``W H⁺ Wᵀ`` is the projection of K (its translation eigenvalues are
    0 and stay 0). Not for matrices with other terms added (contact's per-node blocks).
    Measured on 64k tet4 Hessians: 0.31 s against :func:`project_psd`'s 0.48 s (the
    ``eigh`` 0.27 against 0.38 s), equal to 4e-15 of the largest entry.

    Args:
        K: ``(c, k·d, k·d)`` element Hessians (node-major dofs); dim: d.

    Returns:
        ``(c, k·d, k·d)`` symmetric positive semidefinite.
    """
    c, m, _ = K.shape
    W = jnp.asarray(_translation_free_basis(m // dim, dim), K.dtype)  # (m, r)
    hp = jax.lax.Precision.HIGHEST

    def sandwich(A, B):  # Bᵀ A B for (c, p, p) A and a constant (p, s) B, as two GEMMs
        p, s = B.shape
        T = jnp.dot(A.reshape(c * p, p), B, precision=hp).reshape(c, p, s)
        T = jnp.swapaxes(T, 1, 2).reshape(c * s, p)  # (Aᵀ B)ᵀ = Bᵀ A (A symmetric)
        return jnp.dot(T, B, precision=hp).reshape(c, s, s)

    H = sandwich(0.5 * (K + jnp.swapaxes(K, 1, 2)), W)  # (c, r, r)
    H = 0.5 * (H + jnp.swapaxes(H, 1, 2))
    lam, V = jnp.linalg.eigh(H)
    Vs = V * jnp.sqrt(jnp.maximum(lam, 0.0))[:, None, :]  # H⁺ = Vs Vsᵀ
    WV = jnp.einsum("mr,crs->cms", W, Vs, precision=hp)  # W H⁺ Wᵀ = (W Vs)(W Vs)ᵀ
    return jnp.einsum("cms,cns->cmn", WV, WV, precision=hp)


def project_psd_serial(K: jax.Array, floor: float = 0.0) -> jax.Array:
    """:func:`project_psd` one matrix at a time (``lax.map``), for programs that run on
    several XLA:CPU devices of one process.

    jaxlib 0.10's batched LAPACK kernels (``eigh``, ``cholesky``, ``inv``) split a batch
    over XLA:CPU's intra-op thread pool and block on it; when the other devices' programs
    hold the pool's threads (waiting in a collective), that wait never ends (measured:
    twist n = 29 on 4 host devices hung in ``dsyevd``'s ``ParallelBatchMap``). A batch of
    one runs inline, so this cannot deadlock; it is slower than the batched call.
    """
    return jax.lax.map(lambda k: project_psd(k, floor), K)


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
        pred: :func:`~jaxelastic.fusion.always` of the mesh (for
            :func:`~jaxelastic.fusion.computed`).

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
            reference gradients at its quadrature points; pred: :func:`~jaxelastic.fusion.always`.

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
    :func:`~jaxelastic.kinematics.f_bar`). B-bar (F̄ linear in F: no geometric term) is the
    same algebra with ``θ = 1``, F⁻ᵀ and cof F replaced by I, ``y = w C̄ : I``, ``A = 0``.

    Long because: the derivation is stated next to the terms it produces, and the B-bar
    branch shares them.

    Args:
        psi: ψ(F, params).
        F: ``(q, d, d)`` compatible deformation gradients; w: ``(q,)`` weights; p: params.
        form: ``"fbar"`` or ``"bbar"``.
        pred: :func:`~jaxelastic.fusion.always` (stores C and y once, see
            :func:`~jaxelastic.fusion.computed`).

    Returns:
        ``(Ĉ, Gq, Zq, κ)``: Ĉ ``(q, d, d, d, d)``; Gq, Zq ``(q, d, d)`` with
        ``g = Σ_q B_qᵀ vec Gq`` and ``z = Σ_q B_qᵀ vec Zq`` (:func:`_bt_sum`); κ a scalar.
    """
    d = F.shape[-1]
    H = jax.vmap(jax.hessian(psi, argnums=0), in_axes=(0, None))
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
    dpsi = jax.vmap(jax.grad(psi, argnums=0), in_axes=(0, None))
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
    return _cell_contract(jnp.ones(Mq.shape[0], Mq.dtype), Mq, dN)


def _element_hessian_terms(psi, fbar: str | None, pred):
    """Per cell ``(ue, dN, w, params) ↦ (Ĉ (q, d, d, d, d), g (k, d), z (k, d), κ)``: the
    element Hessian is ``Σ_q B_qᵀ Ĉ_q B_q + g zᵀ + z gᵀ + κ g gᵀ`` (g = z = 0, κ = 0 for
    the standard formulation, where ``Ĉ_q = w_q ∂²ψ/∂F²(F_q)``)."""
    H = jax.vmap(jax.hessian(psi, argnums=0), in_axes=(0, None))

    def terms(ue, dN, w, p):
        F = _cell_F(ue, dN)
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
            :func:`project_psd`), for Newton on indefinite configurations.

    Other args as :func:`energy_densities`.
    """
    _check_call("je.element_hessians", psi, x, mesh, params)
    if mesh.halo is not None:
        return _sharded_element_hessians(psi, x, mesh, params, project)
    ue = displacements(x, mesh)[mesh.cells]
    c, k, d = ue.shape
    form = _is_fbar(mesh)
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
        terms = _per_cell(_element_hessian_terms(psi, form, pred), p, n)
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
    to check a new ψ. Args as :func:`energy_densities`.
    """
    _check_call("je.element_hessians_reference", psi, x, mesh, params)
    ue = displacements(x, mesh)[mesh.cells]
    ee = _element_energy(psi, _is_fbar(mesh))

    def ke(ue, dN, w, p):
        k, d = ue.shape
        return jax.hessian(ee)(ue, dN, w, p).reshape(k * d, k * d)

    return _per_cell(ke, params, mesh.n_cells)(ue, mesh.dN, mesh.weights, params)


# --------------------------------------------------------------------- sharded meshes
#
# A mesh with a halo (jaxelastic.shard) runs the functions above per shard under
# shard_map on its local tables (Halo.map_mesh): positions enter as owned blocks, the
# ghosts' displacements are gathered from their owners, nodal results are scatter-added
# back to the owners and scalars psum-ed. Only interface nodes cross between devices.
# Jitted (ψ static): an eager shard_map would run op by op, and a fresh closure per call
# would recompile every time.


@functools.partial(jax.jit, static_argnums=0)
def _sharded_energy(psi, x, mesh, params):
    """:func:`energy` of a sharded mesh: the per-shard energies, psum-ed."""
    h = mesh.halo

    def body(hl, loc, pts, x_b, p):
        return hl.psum(energy(psi, hl.displacements(x_b, pts), loc, p))

    return h.map_mesh(body, mesh, x, params, out_specs=jax.sharding.PartitionSpec())


@functools.partial(jax.jit, static_argnums=(0, 1))
def _sharded_nodal(fn, psi, x, mesh, params, *vs):
    """``fn(psi, x, mesh, params, *vs)`` (:func:`forces`, :func:`hvp`) of a sharded mesh:
    local nodal results scatter-added to their owners, ``(n_nodes, d)`` sharded."""
    h = mesh.halo
    dtype = mesh.points.dtype

    def body(hl, loc, pts, x_b, p, *v_b):
        v_loc = [hl.gather(v.astype(dtype)) for v in v_b]
        return hl.scatter_add(fn(psi, hl.displacements(x_b, pts), *v_loc, loc, p))

    spec = jax.sharding.PartitionSpec(h.axis)
    return h.map_mesh(body, mesh, x, params, *vs, out_specs=spec)


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


@jax.jit
def _sharded_assemble(mesh, per_element):
    """:func:`assemble` of a sharded mesh: local incidence, then ghost rows to owners."""
    h = mesh.halo

    def body(hl, loc, pts, pe):
        return hl.scatter_add(assemble(loc, pe))

    spec = jax.sharding.PartitionSpec(h.axis)
    return h.map_mesh(body, mesh, per_element, out_specs=spec)
