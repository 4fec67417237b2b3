"""Mechanics derived from ψ by autodiff: energy, stress, forces, HVP, assembly.

Everything here is a pure function of ``(psi, x, mesh, params)``:

* ``psi(F, params) -> scalar`` for one unbatched ``(d, d)`` F (a static Python callable);
* ``x``: ``(n_nodes, d)`` current positions;
* ``mesh``: a :class:`~jaxelastic.mesh.Mesh` (pass it as a jit *argument*);
* ``params``: any pytree. A leaf of shape ``()`` is shared by all cells; a leaf with a
  leading axis of length ``n_cells`` is a per-cell field (e.g. ``Lame(mu=mu_cells,
  lam=1e4)``). Gradients w.r.t. params (shared or per-cell) just work.

The total energy is ``E(x) = Σ_c Σ_q w_cq ψ(F_cq)``. Forces and HVPs are computed per
element with ``jax.grad``/``jax.jvp`` of ψ, contracted with the shape-function gradients,
and assembled with a scatter-free node→slot gather (``mesh.incidence``): unsorted
scatter-add is slow on XLA:CPU. ``jax.grad(energy)`` gives the same forces through JAX's
own (scatter) path and is kept for users and tests. Element Hessians are in
:mod:`~jaxelastic.mechanics.hessians`, their PSD projection in
:mod:`~jaxelastic.mechanics.psd`.

Under the ``"fbar"`` formulation (``mesh.formulation``, static) F_cq is replaced by
F̄_cq = (J̄_c/J_cq)^{1/d} F_cq (:func:`~jaxelastic.mechanics.kinematics.f_bar`). F̄ couples
the quadrature points of a cell, so the F-bar kernels differentiate the element energy with
respect to the element's node positions (``jax.grad``/``jax.jvp``) instead of contracting P
with ∇N; they are still cell-local, so every solver works unchanged. ``"bbar"`` is the
small-strain analogue (B-bar, :func:`~jaxelastic.mechanics.kinematics.b_bar`) for
small-strain materials. Nothing of either is traced for ``"standard"`` meshes.

Input checks (:mod:`~jaxelastic.mechanics.checks`): the public functions check shapes and ψ
before anything is traced, and NaN/inf input outside any JAX transformation.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax.core import Tracer

from .checks import cell_params_axes, check_call, per_cell
from .kinematics import b_bar, deformation_gradients, displacements, f_bar
from .quadrature_fields import over_quadrature

__all__ = [
    "Psi",
    "first_piola",
    "energy",
    "energy_densities",
    "forces",
    "hvp",
    "element_forces",
    "element_gradients",
    "element_gradient_kernel",
    "assemble",
    "cell_F",
    "cell_contract",
    "element_energy",
    "fbar_form",
]

Psi = Callable[..., jax.Array]


def first_piola(psi: Psi) -> Callable:
    """First Piola–Kirchhoff stress ``P(F, params) = ∂ψ/∂F`` by autodiff."""
    return jax.grad(psi, argnums=0)


def energy_densities(psi: Psi, x: jax.Array, mesh, params) -> jax.Array:
    """ψ at every quadrature point, ``(n_cells, n_q)`` [energy / rest measure] (of F̄
    under the ``"fbar"`` formulation).

    Args:
        psi: ``psi(F, params) -> scalar`` for one unbatched ``(d, d)`` F.
        x: ``(n_nodes, d)`` current positions [length].
        mesh: the rest :class:`~jaxelastic.mesh.Mesh`.
        params: material parameter pytree (shared scalars or per-cell leaves).

    Raises (here and in :func:`energy`, :func:`forces`, :func:`hvp`,
    :func:`element_gradients`, :func:`~jaxelastic.mechanics.hessians.element_hessians`; all
    checks happen before tracing):
        TypeError: ``mesh`` is not a mesh, or ψ does not return a scalar float.
        ValueError: ``x`` (or ``v``) is not ``(n_nodes, dim)``, a parameter leaf is neither
            a scalar nor per-cell, or, outside any transformation only, ``x``/``params``
            hold NaN/inf. Inside ``jax.jit`` non-finite input is not checked: it gives NaN.
    """
    check_call("je.mechanics.energy_densities", psi, x, mesh, params)
    return _energy_densities(psi, x, mesh, params)


def _energy_densities(psi: Psi, x: jax.Array, mesh, params) -> jax.Array:
    F = deformation_gradients(x, mesh)
    ax = cell_params_axes(params, mesh.n_cells)
    per_q = over_quadrature(psi)
    return jax.vmap(per_q, in_axes=(0, ax))(F, params)


def energy(psi: Psi, x: jax.Array, mesh, params) -> jax.Array:
    """Total elastic energy ``Σ_c Σ_q w_cq ψ(F_cq)`` [energy], a scalar.

    Args: as :func:`energy_densities` (``x``: ``(n_nodes, d)`` positions [length]).
    """
    check_call("je.energy", psi, x, mesh, params)
    if mesh.halo is not None:
        return _sharded_energy(psi, x, mesh, params)
    return _eager(_total_energy, psi, x, mesh, params)


def _total_energy(psi, x, mesh, params):
    return jnp.sum(mesh.weights * _energy_densities(psi, x, mesh, params))


def _cell_grad(ue, dN):
    """``∇u_q = Σ_k u_k ⊗ ∇N_k(q)`` for one cell: ue ``(k, d)``, dN ``(q, k, d)`` → ``(q, d, d)``.

    ``ue`` is any nodal field of the cell: displacements (F = I + ∇u, :func:`cell_F`) or an
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


def cell_F(ue, dN):
    """``F_q = I + Σ_k u_k ⊗ ∇N_k(q)`` from the cell's nodal displacements ``ue`` ``(k, d)``:
    the round-off does not grow with the coordinates (see
    :func:`~jaxelastic.mechanics.kinematics.deformation_gradients`)."""
    d = ue.shape[1]
    return _cell_grad(ue, dN) + jnp.eye(d, dtype=ue.dtype)[None]


def cell_contract(w, Pq, dN):
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
        F = fmap(cell_F(ue, dN), w)
        return jnp.sum(w * over_quadrature(psi)(F, p))

    return ee


def element_energy(psi, form: str | None = None):
    """The element energy ``(ue, dN, w, params) ↦ Σ_q w_q ψ(F_q)`` (F̄ under a formulation)."""
    if form:
        return _fbar_element_energy(psi, form)

    def ee(ue, dN, w, p):
        return jnp.sum(w * over_quadrature(psi)(cell_F(ue, dN), p))

    return ee


def fbar_form(mesh) -> str | None:
    """The mesh's F̄ map name (``"fbar"``/``"bbar"``), or None for the standard path."""
    form = getattr(mesh, "formulation", "standard")
    return None if form == "standard" else form


def element_gradient_kernel(psi, fbar: str | None = None):
    """The per-element energy gradient ``(ue (k, d), dN (q, k, d), w (q,), params) ↦
    ∂E_e/∂x_e (k, d)`` of ψ, with ``ue`` the element's nodal *displacements* ``x_e − X_e``
    (autodiff P at ``F = I + Σ u_k ⊗ ∇N_k``, contracted with the shape-function gradients;
    with ``fbar="fbar"``/``"bbar"`` the gradient of the F̄ element energy). Unbatched: vmap
    it over cells (as :func:`element_gradients` does)."""
    if fbar:
        return jax.grad(_fbar_element_energy(psi, fbar))
    P = first_piola(psi)

    def fe(ue, dN, w, p):
        # ue (k, d), dN (q, k, d), w (q,) -> ∂E_e/∂xe (k, d)
        F = cell_F(ue, dN)
        Pq = over_quadrature(P)(F, p)  # (q, d, d)
        return cell_contract(w, Pq, dN)

    return fe


def element_gradients(psi: Psi, x: jax.Array, mesh, params) -> jax.Array:
    """Per-element energy gradients ``∂E_c/∂x_a = Σ_q w P·∇N_a``, ``(n_cells, k, d)`` [force]:
    the quantity that :func:`assemble` sums into ∇E. Args as :func:`energy_densities`.
    """
    check_call("je.mechanics.element_gradients", psi, x, mesh, params)
    return _element_gradients(psi, x, mesh, params)


def element_forces(psi: Psi, x: jax.Array, mesh, params) -> jax.Array:
    """Per-element internal forces ``−∂E_c/∂x_a``, ``(n_cells, k, d)`` [force]: the sign
    of :func:`forces` (``forces = assemble(mesh, element_forces(...))``). Args as
    :func:`energy_densities`."""
    check_call("je.mechanics.element_forces", psi, x, mesh, params)
    return -_element_gradients(psi, x, mesh, params)


def _element_gradients(psi: Psi, x: jax.Array, mesh, params) -> jax.Array:
    ue = displacements(x, mesh)[mesh.cells]
    fe = element_gradient_kernel(psi, fbar_form(mesh))
    return per_cell(fe, params, mesh.n_cells)(ue, mesh.dN, mesh.weights, params)


_MAX_UNROLLED_VALENCE = 256  # above this, gather (n_nodes, valence, d) then sum


def assemble(mesh, per_element: jax.Array) -> jax.Array:
    """Sum per-element nodal vectors ``(n_cells, k, d)`` into ``(n_nodes, d)``.

    Uses the precomputed node→slot incidence table: one gather per valence column, summed
    in column order (XLA fuses them into a single loop with no ``(n_nodes, valence, d)``
    intermediate). Measured by ``scripts/bench_kernels.py``: 3–6× faster at 10⁵–10⁶ cells
    than a gather-then-sum (1.5–1.8× at 2k–30k tets, forces + HVP, interleaved, loaded
    machine, although a gather-then-sum compiles about 30 % faster there), and faster than
    an unsorted scatter-add on XLA:CPU.
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
    check_call("je.forces", psi, x, mesh, params)
    if mesh.halo is not None:
        return _sharded_nodal(forces, psi, x, mesh, params)
    return _eager(_nodal_forces, psi, x, mesh, params)


def _nodal_forces(psi, x, mesh, params):
    return -assemble(mesh, _element_gradients(psi, x, mesh, params))


def _eager(fn, psi, *args):
    """``fn(psi, *args)``; called on concrete arrays (outside any trace), one compiled
    program per ψ and shapes instead of op-by-op dispatch (about 50 small compilations
    for :func:`forces` of a tet mesh). Inside a trace: inlined as it is."""
    if any(isinstance(a, Tracer) for a in jax.tree_util.tree_leaves(args)):
        return fn(psi, *args)
    try:
        hash(psi)
    except TypeError:  # an unhashable callable cannot be a static argument
        return fn(psi, *args)
    return _JITTED[fn](psi, *args)


def _element_hvp(psi, fbar: str | None = None):
    if fbar:
        g = jax.grad(_fbar_element_energy(psi, fbar))

        def he_fbar(ue, ve, dN, w, p):
            return jax.jvp(lambda y: g(y, dN, w, p), (ue,), (ve,))[1]

        return he_fbar
    P = first_piola(psi)

    def he(ue, ve, dN, w, p):
        F = cell_F(ue, dN)
        dF = _cell_grad(ve, dN)
        Pp = lambda f: over_quadrature(P)(f, p)
        _, dP = jax.jvp(Pp, (F,), (dF,))
        return cell_contract(w, dP, dN)

    return he


def hvp(psi: Psi, x: jax.Array, v: jax.Array, mesh, params) -> jax.Array:
    """Hessian-vector product ``(∂²E/∂x²)·v`` by forward-over-reverse, ``(n_nodes, d)``.

    Never forms a Hessian: per element, ``dP = jvp(∂ψ/∂F)(F; dF)`` with ``dF = Σ v_a ⊗ ∇N_a``.
    ``v``: ``(n_nodes, d)`` direction [length], cast to the mesh's dtype; other args as
    :func:`energy_densities`.
    """
    check_call("je.mechanics.hvp", psi, x, mesh, params, v=v)
    if mesh.halo is not None:
        return _sharded_nodal(hvp, psi, x, mesh, params, v)
    return _eager(_nodal_hvp, psi, x, v, mesh, params)


def _nodal_hvp(psi, x, v, mesh, params):
    dtype = mesh.points.dtype
    ue, ve = displacements(x, mesh)[mesh.cells], v.astype(dtype)[mesh.cells]
    fn = jax.vmap(
        _element_hvp(psi, fbar_form(mesh)),
        in_axes=(0, 0, 0, 0, cell_params_axes(params, mesh.n_cells)),
    )
    return assemble(mesh, fn(ue, ve, mesh.dN, mesh.weights, params))


_JITTED = {fn: jax.jit(fn, static_argnums=0) for fn in (_nodal_forces, _nodal_hvp, _total_energy)}


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


@jax.jit
def _sharded_assemble(mesh, per_element):
    """:func:`assemble` of a sharded mesh: local incidence, then ghost rows to owners."""
    h = mesh.halo

    def body(hl, loc, pts, pe):
        return hl.scatter_add(assemble(loc, pe))

    spec = jax.sharding.PartitionSpec(h.axis)
    return h.map_mesh(body, mesh, per_element, out_specs=spec)
