"""The objective the solvers minimise: elastic energy + loads + (for dynamics) inertia.

``Π(x) = E(x) − f_extᵀx + w/2 Σ_a m_a ‖x_a − x̃_a‖² + c_M/2 Σ_a m_a ‖x_a − x_n,a‖²``

* statics: only the first two terms (no mass term is compiled in);
* backward Euler: ``w = 1/h²``, ``x̃ = x_n + h v_n``; BDF2: ``w = 1/(2h/3)²`` with its x̃
  (Kim & Eberle 2022, §"Time integration"; REFERENCES "Integrators");
* optional contact with rigid obstacles ``Π_c`` (IPC barrier + lagged friction,
  :mod:`jaxelastic.contact`; ``contact=None``: nothing of it is traced);
* optional pressure on cavity boundaries ``−Σ_s p_s V_s(x)`` (:mod:`~.pressure`; a follower
  load, conservative for closed cavities; ``pressure=None``: nothing of it is traced);
* optional mass-proportional Rayleigh damping ``c_M = α/h`` and stiffness-proportional
  ``c_K/2 (x − x_n)ᵀ K(x_n) (x − x_n)``, ``c_K = β/h``.

A :class:`Potential` is a frozen pytree whose optional parts are ``None`` when a scene does
not need them; jit specialises on that structure, so a scene without gravity compiles no
load term and statics no inertia.

Construction checks (static shapes and dtypes only, so also free under jit/vmap, where the
per-example shapes are checked): ``f_ext``, ``x_tilde``, ``x_prev`` must be
``(n_nodes, dim)`` like ``mesh.points``, ``mass`` ``(n_nodes,)``, the scalars ``()``; ψ
must return a scalar float (:func:`~jaxelastic.mechanics.checks.check_psi`, cached per ψ). The
mesh's float dtype is the working precision: a float leaf that would widen it (a float64
``f_ext`` or parameter on a float32 mesh with x64 enabled) is refused, because it would
silently promote the solve and break its loops; narrower leaves are promoted exactly.
To vmap over a field, replace it inside the vmapped function
(``jax.vmap(lambda f: je.solve(pot.replace(f_ext=f), bc).x)(fs)``).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from ..mesh import Mesh
from .checks import check_psi
from .hessians import element_hessians
from .kernels import Psi, assemble, energy, forces, hvp
from .pressure import Pressure
from .psd import project_element_psd, project_psd

__all__ = [
    "Potential",
    "value",
    "gradient",
    "hessian_vp",
    "node_hessian_blocks",
    "element_hessian_vp",
    "elastic_element_hessians",
    "projected_element_hessians",
    "projection_dim",
    "mass_diagonal",
    "check_potential",
    "loop_terms",
    "with_loop_terms",
    "has_coupling",
    "coupling_data",
    "coupling",
    "is_array",
]


@dataclasses.dataclass(frozen=True)
class Potential:
    """Everything but the unknown positions that defines Π(x).

    Attributes:
        mesh: the rest mesh.
        params: material parameter pytree (shared scalars or per-cell fields).
        f_ext: ``(n_nodes, dim)`` dead external nodal forces, or None.
        mass: ``(n_nodes,)`` lumped masses, or None (statics).
        x_tilde: ``(n_nodes, dim)`` inertial predictor, or None.
        inertia_weight: scalar w (1/h² for backward Euler), or None.
        x_prev: ``(n_nodes, dim)`` positions at the start of the step (damping), or None.
        mass_damping: scalar c_M, or None.
        stiffness_damping: scalar c_K, or None.
        contact: a :class:`~jaxelastic.contact.Contact` barrier (+ friction) term against
            obstacles, or None (nothing of contact is traced).
        pressure: a :class:`~jaxelastic.mechanics.pressure.Pressure` term (follower
            pressure on cavity boundaries, potential ``−Σ p V``), or None.
        psi: the strain-energy density (static).

    Raises (at construction, see :func:`check_potential`):
        ValueError: a field of the wrong shape, or a float leaf wider than the mesh's dtype.
        TypeError: ψ does not return a scalar float for one ``(dim, dim)`` F.
    """

    mesh: Mesh
    params: Any
    f_ext: jax.Array | None = None
    mass: jax.Array | None = None
    x_tilde: jax.Array | None = None
    inertia_weight: jax.Array | None = None
    x_prev: jax.Array | None = None
    mass_damping: jax.Array | None = None
    stiffness_damping: jax.Array | None = None
    contact: Any = None
    pressure: Pressure | None = None
    psi: Psi = dataclasses.field(kw_only=True, metadata=dict(static=True))

    def __post_init__(self):
        # parameter types with shared vectors (HGO fibre directions) broadcast them per cell
        for_cells = getattr(self.params, "for_cells", None)
        cells: Any = getattr(self.mesh, "cells", None)
        if callable(for_cells) and is_array(cells) and len(cells.shape) == 2:
            leaves = jax.tree_util.tree_leaves(self.params)
            if leaves and all(is_array(a) or isinstance(a, (int, float)) for a in leaves):
                object.__setattr__(self, "params", for_cells(int(cells.shape[0])))
        check_potential(self)

    def replace(self, **kw) -> Potential:
        return dataclasses.replace(self, **kw)


jax.tree_util.register_dataclass(
    Potential,
    data_fields=[
        "mesh",
        "params",
        "f_ext",
        "mass",
        "x_tilde",
        "inertia_weight",
        "x_prev",
        "mass_damping",
        "stiffness_damping",
        "contact",
        "pressure",
    ],
    meta_fields=["psi"],
)


_FIELD_SHAPES = {
    "f_ext": ("(n_nodes, dim)", lambda n, d: (n, d)),
    "mass": ("(n_nodes,)", lambda n, d: (n,)),
    "x_tilde": ("(n_nodes, dim)", lambda n, d: (n, d)),
    "x_prev": ("(n_nodes, dim)", lambda n, d: (n, d)),
    "inertia_weight": ("() (a scalar)", lambda n, d: ()),
    "mass_damping": ("() (a scalar)", lambda n, d: ()),
    "stiffness_damping": ("() (a scalar)", lambda n, d: ()),
}


def is_array(a) -> bool:
    """Whether ``a`` is an array (has a shape and a dtype): a field a user set, not None, a
    Python list or one of JAX's placeholders when it rebuilds the pytree."""
    return hasattr(a, "shape") and hasattr(a, "dtype")


def _wider(dt, mesh_dtype) -> bool:
    """Whether ``dt`` would promote ``mesh_dtype`` (JAX's standard lattice, whatever the
    session's ``jax_numpy_dtype_promotion``)."""
    with jax.numpy_dtype_promotion("standard"):
        return jnp.promote_types(dt, mesh_dtype) != mesh_dtype


def _widening_leaves(pot: Potential, mesh_dtype):
    """``(name, dtype)`` of every strongly typed float leaf wider than the mesh's dtype."""
    named = [(k, getattr(pot, k)) for k in _FIELD_SHAPES] + [("params", pot.params)]
    named.append(("contact", pot.contact))
    named.append(("pressure", pot.pressure))
    for name, tree in named:
        for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
            if not is_array(leaf) or getattr(leaf, "weak_type", False):
                continue
            dt = jax.dtypes.canonicalize_dtype(leaf.dtype)
            if jnp.issubdtype(dt, jnp.floating) and _wider(dt, mesh_dtype):
                yield name + jax.tree_util.keystr(path), dt


def check_potential(pot: Potential) -> None:
    """Check the shapes and float dtypes of ``pot``'s fields against its mesh, and ψ.

    Runs at construction (and on every rebuild of the pytree, e.g. inside jit, where only
    static shapes are used). Fields that are not arrays (None, or JAX's placeholders when it
    rebuilds the tree, e.g. for ``in_axes``) and meshes that are not ``(n_nodes, dim)``
    arrays (stacked potentials) are not checked.

    Raises:
        ValueError: a field of the wrong shape (the message names the field, the expected
            and the given shape), or a float leaf wider than the mesh's dtype (naming both).
        TypeError: ψ does not return a scalar float (see
            :func:`~jaxelastic.mechanics.checks.check_psi`).
    """
    pts: Any = getattr(pot.mesh, "points", None)
    if not is_array(pts) or len(pts.shape) != 2 or not is_array(pot.mesh.cells):
        return
    n, d = (int(k) for k in pts.shape)
    for name, (what, expected) in _FIELD_SHAPES.items():
        a = getattr(pot, name)
        if is_array(a) and tuple(a.shape) != expected(n, d):
            raise ValueError(
                f"Potential: {name} must have shape {what} = {expected(n, d)} for this mesh of "
                f"{n} nodes in {d}D, got {tuple(a.shape)}"
            )
    mesh_dtype = jax.dtypes.canonicalize_dtype(pts.dtype)
    for name, dt in _widening_leaves(pot, mesh_dtype):
        raise ValueError(
            f"Potential: {name} has dtype {dt} but the mesh is {mesh_dtype} (mesh.points); "
            f"mixing them would promote the solve to {dt}. Build the mesh in {dt} (e.g. "
            f"je.from_arrays(points, cells, dtype=jnp.{dt}) or je.rectangle(..., dtype=jnp.{dt}))"
            f" or cast {name.split('.')[0].split('[')[0]} to {mesh_dtype}"
        )
    n_cells = int(pot.mesh.cells.shape[0])
    check_psi(pot.psi, d, mesh_dtype, pot.params, n_cells, where="Potential", own_errors=False)


def _needs(a: jax.Array | None, name: str) -> jax.Array:
    """``a``, or TypeError when a term that is switched on lacks the field it needs."""
    if a is None:
        raise TypeError(f"Potential.{name} is None but a term that needs it is set")
    return a


def value(pot: Potential, x: jax.Array) -> jax.Array:
    """Π(x), a scalar [energy]; +inf/NaN propagate (the line search treats them as +inf)."""
    v = energy(pot.psi, x, pot.mesh, pot.params)
    if pot.f_ext is not None:
        v = v - jnp.sum(pot.f_ext * x)
    if pot.mass is not None:
        dx = x - _needs(pot.x_tilde, "x_tilde")
        v = v + 0.5 * _needs(pot.inertia_weight, "inertia_weight") * jnp.sum(
            pot.mass[:, None] * dx * dx
        )
    if pot.mass_damping is not None:
        dx = x - _needs(pot.x_prev, "x_prev")
        v = v + 0.5 * pot.mass_damping * jnp.sum(_needs(pot.mass, "mass")[:, None] * dx * dx)
    if pot.stiffness_damping is not None:
        x_prev = _needs(pot.x_prev, "x_prev")
        dx = x - x_prev
        Kdx = hvp(pot.psi, x_prev, dx, pot.mesh, pot.params)
        v = v + 0.5 * pot.stiffness_damping * jnp.sum(dx * Kdx)
    if pot.contact is not None:
        v = v + pot.contact.energy(x)
    if pot.pressure is not None:
        v = v + pot.pressure.energy(x)
    return v


def gradient(pot: Potential, x: jax.Array) -> jax.Array:
    """∂Π/∂x, ``(n_nodes, dim)`` [force]."""
    g = -forces(pot.psi, x, pot.mesh, pot.params)
    if pot.f_ext is not None:
        g = g - pot.f_ext
    if pot.mass is not None:
        w = _needs(pot.inertia_weight, "inertia_weight")
        g = g + w * pot.mass[:, None] * (x - _needs(pot.x_tilde, "x_tilde"))
    if pot.mass_damping is not None:
        dx = x - _needs(pot.x_prev, "x_prev")
        g = g + pot.mass_damping * _needs(pot.mass, "mass")[:, None] * dx
    if pot.stiffness_damping is not None:
        x_prev = _needs(pot.x_prev, "x_prev")
        g = g + pot.stiffness_damping * hvp(pot.psi, x_prev, x - x_prev, pot.mesh, pot.params)
    if pot.contact is not None:
        g = g + pot.contact.gradient(x)
    if pot.pressure is not None:
        g = g + pot.pressure.gradient(x)
    return g


def mass_diagonal(pot: Potential) -> jax.Array | None:
    """Diagonal (per-node) inertia + mass-damping part of the Hessian, ``(n_nodes,)`` [mass/time²],
    or None (statics)."""
    w = None
    if pot.mass is not None:
        w = _needs(pot.inertia_weight, "inertia_weight") * pot.mass
    if pot.mass_damping is not None:
        w = _needs(w, "mass") + pot.mass_damping * _needs(pot.mass, "mass")
    return w


def hessian_vp(
    pot: Potential, x: jax.Array, v: jax.Array, exact_contact: bool = False
) -> jax.Array:
    """``(∂²Π/∂x²)·v``, ``(n_nodes, dim)``, matrix-free (the contact blocks PSD-projected
    unless ``exact_contact``, as for the implicit-differentiation solves)."""
    Hv = hvp(pot.psi, x, v, pot.mesh, pot.params)
    w = mass_diagonal(pot)
    if w is not None:
        Hv = Hv + w[:, None] * v
    if pot.stiffness_damping is not None:
        x_prev = _needs(pot.x_prev, "x_prev")
        Hv = Hv + pot.stiffness_damping * hvp(pot.psi, x_prev, v, pot.mesh, pot.params)
    if pot.contact is not None:
        Hv = Hv + pot.contact.hvp(x, v, exact=exact_contact)
    if pot.pressure is not None:
        Hv = Hv + pot.pressure.hvp(x, v)
    return Hv


def element_hessian_vp(pot: Potential, Ke: jax.Array, v: jax.Array) -> jax.Array:
    """``(∂²Π/∂x²)·v`` from precomputed elastic element Hessians ``(n_cells, k·d, k·d)``
    plus the lumped-mass diagonal (the stiffness-damping term is not included)."""
    mesh = pot.mesh
    if mesh.halo is not None:  # per shard: gather v's ghosts, scatter-add to owners
        Hv = _sharded_kv(mesh, Ke, v)
    else:
        ve = v[mesh.cells].reshape(mesh.n_cells, -1)
        out = jnp.einsum("cij,cj->ci", Ke, ve).reshape(mesh.cells.shape + (-1,))
        Hv = assemble(mesh, out)
    md = mass_diagonal(pot)
    if md is not None:
        Hv = Hv + md[:, None] * v
    return Hv


def node_hessian_blocks(pot: Potential, Ke: jax.Array) -> jax.Array:
    """Diagonal ``dim×dim`` blocks of the Hessian per node, ``(n_nodes, dim, dim)``.

    Args:
        Ke: element Hessians ``(n_cells, k·dim, k·dim)`` of the elastic energy (the
            stiffness-damping term, if any, is approximated by the same blocks).
    """
    mesh = pot.mesh
    if mesh.halo is not None:  # per shard; the ghosts' blocks go to their owners
        B = _sharded_blocks(mesh, Ke)
    else:
        B = _node_blocks(mesh, Ke)
    w = mass_diagonal(pot)
    if w is not None:
        B = B + w[:, None, None] * jnp.eye(mesh.dim, dtype=Ke.dtype)[None]
    return B


def _node_blocks(mesh: Mesh, Ke: jax.Array) -> jax.Array:
    """Σ over a node's cells of their diagonal ``d×d`` blocks, ``(n_nodes, d, d)``."""
    c, k, d = Ke.shape[0], mesh.cells.shape[1], mesh.dim
    K4 = Ke.reshape(c, k, d, k, d)
    blocks = K4[:, jnp.arange(k), :, jnp.arange(k), :]  # (k, c, d, d)
    blocks = jnp.swapaxes(blocks, 0, 1).reshape(c * k, d, d)
    flat = jnp.concatenate([blocks, jnp.zeros((1, d, d), Ke.dtype)])
    return flat[mesh.incidence].sum(axis=1)  # (n, d, d)


def _spec(mesh: Mesh):
    return jax.sharding.PartitionSpec(mesh.halo.axis)


@jax.jit
def _sharded_kv(mesh: Mesh, Ke, v):
    return mesh.halo.map_mesh(_local_kv, mesh, Ke, v, out_specs=_spec(mesh))


@jax.jit
def _sharded_blocks(mesh: Mesh, Ke):
    return mesh.halo.map_mesh(_local_blocks, mesh, Ke, out_specs=_spec(mesh))


def _local_kv(hl, loc: Mesh, pts, Ke, v):
    """One shard of :func:`element_hessian_vp`'s ``Σ_c Kₑ vₑ`` (see ``Halo.map_mesh``)."""
    del pts
    ve = hl.gather(v)[loc.cells].reshape(loc.n_cells, -1)
    out = jnp.einsum("cij,cj->ci", Ke, ve).reshape(loc.cells.shape + (-1,))
    return hl.scatter_add(assemble(loc, out))


def _local_blocks(hl, loc: Mesh, pts, Ke):
    """One shard of :func:`node_hessian_blocks` (see ``Halo.map_mesh``)."""
    del pts
    B = _node_blocks(loc, Ke)
    n, d = B.shape[0], B.shape[1]
    return hl.scatter_add(B.reshape(n, d * d)).reshape(-1, d, d)


def projection_dim(pot: Potential) -> int:
    """The ``dim`` for :func:`~jaxelastic.mechanics.psd.project_element_psd` of this potential's
    element Hessians (:func:`elastic_element_hessians`): the mesh's dimension where
    elasticity alone contributes (the rigid translations are in every Hessian's kernel),
    0 with a contact or pressure term (its blocks are not translation-invariant:
    :func:`~jaxelastic.mechanics.psd.project_psd`)."""
    return pot.mesh.dim if pot.contact is None and pot.pressure is None else 0


def projected_element_hessians(pot: Potential, Ke: jax.Array) -> jax.Array:
    """The PSD projection of element Hessians from :func:`elastic_element_hessians`:
    :func:`~jaxelastic.mechanics.psd.project_element_psd` (the translations taken out first,
    exact) or :func:`~jaxelastic.mechanics.psd.project_psd`, as :func:`projection_dim` says.

    Args:
        Ke: ``(n_cells, k·dim, k·dim)``.
    """
    dim = projection_dim(pot)
    return project_element_psd(Ke, dim) if dim else project_psd(Ke)


def elastic_element_hessians(
    pot: Potential, x: jax.Array, project: bool, exact_contact: bool = False, pair_hessians=None
) -> jax.Array:
    """Element Hessians of the elastic energy at x, ``(n_cells, k·dim, k·dim)``; with a
    contact term, its per-node blocks are added to one element per contact node
    (:meth:`~jaxelastic.contact.Contact.add_hessian_blocks`; PSD-projected unless
    ``exact_contact``; ``pair_hessians``: the self-contact pair Hessians at x with that
    projection, :meth:`~jaxelastic.contact.Contact.pair_hessians`, if computed before); with
    a pressure term, each loaded facet's block is added to its cell
    (:meth:`~jaxelastic.mechanics.pressure.Pressure.add_hessian_blocks`, the touched cells
    projected again when ``project``)."""
    Ke = element_hessians(pot.psi, x, pot.mesh, pot.params, project=project)
    if pot.pressure is not None:
        Ke = pot.pressure.add_hessian_blocks(Ke, x, project=project)
    if pot.contact is not None:
        Ke = pot.contact.add_hessian_blocks(
            Ke, pot.mesh, x, project=not exact_contact, pair_hessians=pair_hessians
        )
    return Ke


# -- terms of the potential that take part in the Newton loop -------------------------------


def loop_terms(pot: Potential) -> dict[str, Any]:
    """The terms of ``pot`` that take part in the Newton loop beyond their energy, by
    field name: each may bound a step (``step_bound(x, step)``), be refreshed on the host
    between iterations (``refreshed(x, step)``) and adapt a stiffness inside the solve
    (``adapt_init`` / ``adapt`` / ``adapted``); today the contact term."""
    return {} if pot.contact is None else {"contact": pot.contact}


def with_loop_terms(pot: Potential, terms: dict[str, Any]) -> Potential:
    """``pot`` with the given :func:`loop_terms` replaced."""
    return pot.replace(**terms) if terms else pot


def has_coupling(pot: Potential) -> bool:
    """Whether the Hessian couples nodes of different elements (self-contact pairs, a
    cavity's volume control), so the Newton operator is more than the assembled element
    matrix."""
    sc = pot.contact is not None and getattr(pot.contact, "self_contact", None) is not None
    return sc or (pot.pressure is not None and pot.pressure.kappa is not None)


def coupling_data(pot: Potential, x: jax.Array, exact: bool = False):
    """The per-iterate data of the :func:`coupling` at ``x`` (the self-contact pair
    Hessians, projected unless ``exact``), or None: computed once, it can be handed from
    one compiled piece to another."""
    return None if pot.contact is None else pot.contact.pair_hessians(x, exact=exact)


def coupling(pot: Potential, x: jax.Array, data=None, exact: bool = False):
    """The Hessian's coupling of nodes of different elements as ``v ↦ H_c v``
    (``(n_nodes, dim) -> (n_nodes, dim)``): self-contact pairs and a cavity's volume
    control (:meth:`~jaxelastic.mechanics.pressure.Pressure.coupling`), or None where there
    is none."""
    ops = []
    if pot.contact is not None:
        ops.append(pot.contact.coupling(x, exact=exact, pair_hessians=data))
    if pot.pressure is not None:
        ops.append(pot.pressure.coupling(x))
    ops = [op for op in ops if op is not None]
    if not ops:
        return None
    if len(ops) == 1:
        return ops[0]
    return lambda v: ops[0](v) + ops[1](v)
