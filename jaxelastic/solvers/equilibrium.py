"""The one entry point for "find x*": :func:`solve`.

In the spirit of optimistix's ``root_find(fn, solver, y0, args, *, adjoint, throw)``:
``solve(pot, bc, *, x0, solver, adjoint, throw) -> Solution``, the same defaults
everywhere (statics, load stepping, dynamics steps, fitting), differentiable by the
implicit function theorem whenever it is differentiated (:mod:`.adjoint`).
"""

from __future__ import annotations

import dataclasses
import functools
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer

from ..cache import ensure_persistent_cache
from ..loads import Dirichlet
from ..materials import ActiveTension, Guccione, Lame, check_guccione, check_lame
from ..mechanics.checks import check_psi
from ..mechanics.potential import Potential, is_array
from ..mechanics.pressure import check_closed
from ..mesh import Mesh
from ..parallel.distributed import host_array
from .adjoint import ImplicitAdjoint, differentiable_minimize
from .host import rigid_body_modes
from .linear import LinearState, init_linear, resolve
from .newton import Newton, is_quadratic
from .newton import terms as newton_terms
from .results import Solution, SolveError, Status

__all__ = ["solve", "PreparedSolver", "prepare_solver", "bind_solver", "is_traced"]


def is_traced(*trees) -> bool:
    """Whether any leaf of ``trees`` is a JAX tracer (we are inside jit/vmap/grad)."""
    return any(isinstance(a, Tracer) for t in trees for a in jax.tree_util.tree_leaves(t))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PreparedSolver:
    """Newton settings with their linear solver resolved, and that solver's state for one
    mesh and Dirichlet mask (:func:`prepare_solver`). A pytree: the settings are static,
    the state's arrays (a device hierarchy) are leaves, so it can be a ``jit`` argument.
    Pass it as ``je.solve(..., solver=prepared)`` to reuse the state across solves.

    Attributes:
        newton: :class:`~jaxelastic.solvers.newton.Newton` with a resolved ``linear``.
        linear_state: :class:`~jaxelastic.solvers.linear.LinearState`.
    """

    newton: Newton = dataclasses.field(metadata=dict(static=True))
    linear_state: LinearState = dataclasses.field(default_factory=LinearState)

    @property
    def linear(self):
        """The resolved linear-solver settings."""
        return self.newton.linear


def prepare_solver(
    solver: Newton | PreparedSolver,
    mesh,
    bc: Dirichlet,
    *,
    quadratic: bool = False,
    linear_state=None,
) -> PreparedSolver:
    """``solver`` with its linear solver resolved (``"auto"`` → the table's choice,
    :func:`~jaxelastic.solvers.linear.resolve`) and that solver's state for ``mesh`` and
    ``bc.mask`` (:func:`~jaxelastic.solvers.linear.init_linear`; host work, cached by
    content). ``linear_state``: a state made before (kept as is). Call it once outside jit
    where the mesh or the mask will be traced (e.g. a fit, whose cases are jit arguments).

    Raises:
        TypeError: ``solver`` is not Newton settings; ValueError: a ``linear_state`` of
            another solver, or as :func:`~jaxelastic.solvers.linear.init_linear`.
    """
    # the host structures depend on the topology (and the primal points), never on a
    # derivative: an eager jax.grad with respect to the rest points keeps the host solvers
    if is_traced(mesh, bc):
        mesh, bc = jax.lax.stop_gradient(mesh), jax.lax.stop_gradient(bc)
    if isinstance(solver, PreparedSolver):
        if linear_state is not None and linear_state is not solver.linear_state:
            raise ValueError("pass the linear state once: in the PreparedSolver or as linear_state")
        return solver
    if not isinstance(solver, Newton):
        raise TypeError(f"solver must be a je.Newton(...), got {type(solver).__name__}")
    if linear_state is not None:
        if not isinstance(linear_state, LinearState):
            raise TypeError(
                "linear_state must be the state of je.solvers.init_linear(linear, mesh, bc), "
                f"got {type(linear_state).__name__}"
            )
        linear = resolve(solver.linear, mesh, bc, quadratic=quadratic)
        if linear.kind != linear_state.kind:
            raise ValueError(
                f"linear_state belongs to a {linear_state.kind!r} solver but the Newton "
                f"settings use {linear.kind!r}: make the state from the same linear solver"
            )
        state = linear_state
    else:
        linear, state = init_linear(solver.linear, mesh, bc, quadratic=quadratic)
    settings = solver if linear is solver.linear else dataclasses.replace(solver, linear=linear)
    return PreparedSolver(settings, state)


def bind_solver(
    solver: Newton | PreparedSolver, mesh, bc: Dirichlet, *, quadratic: bool = False
) -> PreparedSolver:
    """Deprecated name of :func:`prepare_solver`."""
    warnings.warn(
        "je.solvers.bind_solver is deprecated: use je.solvers.prepare_solver (same arguments)",
        DeprecationWarning,
        stacklevel=2,
    )
    return prepare_solver(solver, mesh, bc, quadratic=quadratic)


@functools.partial(jax.jit, static_argnames=("solver", "adjoint"))
def _solve_jit(pot, bc, x0, solver, adjoint, lstate):
    return differentiable_minimize(solver, lstate, adjoint, pot, bc, x0)


def _check_inputs(pot: Potential, bc: Dirichlet, x0):
    if not isinstance(pot, Potential):
        raise TypeError(f"pot must be a je.Potential, got {type(pot).__name__}")
    if not isinstance(bc, Dirichlet):
        raise TypeError(
            f"bc must be je.Dirichlet data (e.g. je.loads.fix(mesh, nodes)), got "
            f"{type(bc).__name__}"
        )
    if not isinstance(pot.mesh, Mesh):
        raise TypeError(
            f"pot.mesh must be a je.Mesh (e.g. je.box(...), je.read_mesh(path), "
            f"je.from_arrays(points, cells)), got {type(pot.mesh).__name__}"
        )
    shape = tuple(pot.mesh.points.shape)
    for name, a in (("bc.mask", bc.mask), ("bc.values", bc.values)):
        if not is_array(a):
            raise TypeError(
                f"{name} must be an array of shape {shape} (n_nodes, dim), got "
                f"{type(a).__name__}: build the Dirichlet data with je.loads.fix(mesh, nodes) "
                "or pass jnp.asarray(...)"
            )
        if tuple(jnp.shape(a)) != shape:
            raise ValueError(f"{name} must have shape {shape} (n_nodes, dim), got {jnp.shape(a)}")
    if jnp.result_type(bc.mask) != jnp.bool_:
        raise TypeError(
            f"bc.mask must be a boolean array (True where a dof is prescribed), got dtype "
            f"{jnp.result_type(bc.mask)}: use mask.astype(bool), or build the Dirichlet data "
            "with je.loads.fix(mesh, nodes)"
        )
    if not jnp.issubdtype(jnp.result_type(bc.values), jnp.floating):
        raise TypeError(f"bc.values must be floating point, got {jnp.result_type(bc.values)}")
    if not isinstance(bc.mask, Tracer) and not isinstance(bc.values, Tracer):
        m, v = host_array(bc.mask), host_array(bc.values)
        bad = ~np.isfinite(v) & m
        if bad.any():
            node, comp = (int(i) for i in np.argwhere(bad)[0])
            raise ValueError(
                f"bc.values is not finite at {int(bad.sum())} prescribed dof(s) (first: node "
                f"{node}, component {comp}): every prescribed position must be a finite number"
            )
    for name in ("f_ext", "mass", "x_tilde", "x_prev"):
        a = getattr(pot, name)
        if a is not None and not is_array(a):
            raise TypeError(
                f"pot.{name} must be an array (or None), got {type(a).__name__}: pass "
                f"jnp.asarray(...) of the right shape"
            )
    dt, vt = jnp.result_type(pot.mesh.points), jnp.result_type(bc.values)
    if jnp.finfo(vt).bits > jnp.finfo(dt).bits:  # (bc.values is floating: checked above)
        raise ValueError(
            f"bc.values has dtype {vt} but the mesh is {dt}: build the Dirichlet data from "
            f"the mesh (je.loads.fix) or cast the values to {dt}"
        )
    if not is_traced(pot.params):
        if isinstance(pot.params, Lame):
            check_lame(pot.params, int(shape[1]))
        passive = pot.params.passive if isinstance(pot.params, ActiveTension) else pot.params
        if isinstance(passive, Guccione):
            check_guccione(passive)
        mesh = pot.mesh
        check_psi(
            pot.psi, int(shape[1]), mesh.points.dtype, pot.params, mesh.n_cells, where="je.solve"
        )
    if x0 is None:
        return pot.mesh.points
    if tuple(jnp.shape(x0)) != shape:
        raise ValueError(f"x0 must have shape {shape} (n_nodes, dim), got {jnp.shape(x0)}")
    return jnp.asarray(x0, pot.mesh.points.dtype)


def _free_rigid_motions(pot: Potential, bc: Dirichlet) -> list[str]:
    """The infinitesimal rigid-body motions of the rest shape that ``bc`` leaves free.

    A static potential (no mass term) is invariant under them, so its Hessian is singular
    and the solve has no unique answer; under a load it does not converge at all.
    """
    X = host_array(pot.mesh.points).astype(np.float64)  # host_array: across processes too
    d = X.shape[1]
    mask = host_array(bc.mask).astype(bool)
    inc = host_array(pot.mesh.incidence)
    in_cells = inc[:, 0] < pot.mesh.cells.size  # not the padding of a sharded mesh (je.shard)
    X, mask = X[in_cells], mask[in_cells].reshape(-1)
    R = rigid_body_modes(X)  # (n·d, m): translations then rotations
    m = R.shape[1]
    RD = R[mask]
    if RD.shape[0] == 0:
        null = np.eye(m)
    else:
        if RD.shape[0] < m:  # zero rows change neither the singular values nor V
            RD = np.concatenate([RD, np.zeros((m - RD.shape[0], m))])
        # only V is needed: full_matrices=True also formed the (n_D, n_D) U, 0.84 s of
        # every static solve at 5400 fixed dofs (twist n = 29)
        _, sv, Vt = np.linalg.svd(RD, full_matrices=False)
        rank = int(np.sum(sv > 1e-9 * max(float(sv.max(initial=0.0)), 1.0)))
        null = Vt[rank:].T  # (m, m - rank)
    if null.shape[1] == 0:
        return []
    axes = "xyz"[:d]
    rot_axes = "z" if d == 2 else "xyz"
    Nt, Nr = null[:d], null[d:]  # translation and rotation parts of the free motions
    U, sr, Vt2 = np.linalg.svd(Nr, full_matrices=True)
    r = int(np.sum(sr > 1e-6))
    used: list[int] = []
    for i in range(r):  # a distinct dominant axis per free rotation
        w = np.abs(U[:, i]).copy()
        w[used] = -1.0
        used.append(int(np.argmax(w)))
    names = [f"rotation about {rot_axes[j]}" for j in sorted(used)]
    pure = Nt @ Vt2[r:].T  # free motions without a rotational part: translations
    names += [f"translation along {axes[int(np.argmax(np.abs(t)))]}" for t in pure.T]
    return sorted(names, key=lambda n: (not n.startswith("translation"), n))


def _check_constrained(pot: Potential, bc: Dirichlet) -> None:
    static_form = pot.inertia_weight is not None and not np.any(np.asarray(pot.inertia_weight))
    if pot.mass is not None and not static_form:  # (zero weight: dynamics.static_potential)
        return  # dynamics: a free body is valid (the mass term removes the null space)
    if pot.contact is not None:
        return  # obstacles may hold the body (a singular Hessian then fails the solve)
    free = _free_rigid_motions(pot, bc)
    if free:
        raise ValueError(
            f"the Dirichlet conditions leave {len(free)} rigid-body motion(s) free "
            f"({', '.join(free)}): a static solve has no unique solution (the Hessian is "
            "singular) and does not converge under a load. Fix enough dofs to remove them "
            "(e.g. je.loads.fix(mesh, nodes)), or solve dynamics (a Potential with mass), "
            "where a free body is valid"
        )


def solve(
    pot: Potential,
    bc: Dirichlet,
    *,
    x0: jax.Array | None = None,
    solver: Newton | PreparedSolver = Newton(),
    adjoint: ImplicitAdjoint = ImplicitAdjoint(),
    throw: bool = True,
    linear_state: LinearState | None = None,
) -> Solution:
    """Minimise Π(x) subject to ``x[bc.mask] = bc.values[bc.mask]``.

    Jit-able, vmap-able (with the matrix-free :class:`~jaxelastic.solvers.linear.CG`) and
    differentiable: under ``jax.grad``/``jax.vjp`` (default ``ImplicitAdjoint()``) or
    ``jax.jvp``/``jax.jacfwd`` (``ImplicitAdjoint(mode="forward")``) the derivatives of
    ``x`` with respect to every floating leaf of ``pot`` (material parameters, ``f_ext``,
    masses, the rest points of a mesh moved by :meth:`~jaxelastic.mesh.Mesh.with_points`,
    …) and to ``bc.values`` come from the implicit function theorem (one linear
    solve with the Hessian at x*), never from the Newton iterations; if the solve failed
    they are NaN. Derivatives with respect to ``x0`` are zero.

    Long because: the checks, the choice between a traced and a concrete solve and the
    failure message read best in one place.

    The Newton loop (:func:`~jaxelastic.solvers.newton.minimize`) runs on
    ``lax.stop_gradient`` of the inputs: under ``jit``/``vmap`` as one ``lax.while_loop``;
    outside, on concrete values — also under an eager ``jax.grad``/``jax.jvp`` — as one
    compiled program, or as a Python loop over compiled pieces where the linear solver
    runs on the host (Direct, AMG) or a term wants a host refresh (self-contact).

    Args:
        pot: the :class:`~jaxelastic.potential.Potential` (elastic energy, loads, inertia).
        bc: :class:`~jaxelastic.loads.Dirichlet` data.
        x0: ``(n_nodes, dim)`` initial positions (default: the rest shape; Dirichlet dofs
            need not be in place).
        solver: :class:`~jaxelastic.solvers.newton.Newton` settings and linear solver
            (default ``linear="auto"``: sparse Cholesky up to 10k dofs in 3D, AMG-CG above,
            matrix-free CG on traced meshes).
        adjoint: :class:`~jaxelastic.solvers.adjoint.ImplicitAdjoint` settings of the
            derivative solves.
        throw: outside jit, raise :class:`~jaxelastic.solvers.results.SolveError` unless
            the status is SUCCESS. Inside jit nothing is raised: read ``status``.
        linear_state: the linear solver's state for this mesh and mask
            (:func:`~jaxelastic.solvers.linear.init_linear`); made here when None, which
            needs a concrete mesh and mask for Direct, AMG and Multilevel.

    Raises:
        ValueError: (outside jit, before anything is compiled) inputs of the wrong shape, a
            static potential whose Dirichlet conditions leave rigid-body motions free, or a
            pressure surface whose rim moves freely (not conservative:
            :func:`~jaxelastic.mechanics.pressure.check_closed`).

    Returns:
        :class:`~jaxelastic.solvers.results.Solution` (``x``, ``status``, ``stats``; outside
        jit ``stats["wall_time"]`` is the wall-clock time of the solve in seconds).
    """
    ensure_persistent_cache()  # the library's default cache (once; jaxelastic.cache)
    x0 = _check_inputs(pot, bc, x0)
    prepared = prepare_solver(
        solver, pot.mesh, bc, quadratic=is_quadratic(pot), linear_state=linear_state
    )
    solver, lstate = prepared.newton, prepared.linear_state
    if not isinstance(adjoint, ImplicitAdjoint):
        raise TypeError(f"adjoint must be je.ImplicitAdjoint(...), got {type(adjoint).__name__}")
    stop = jax.lax.stop_gradient
    if is_traced(stop(pot), stop(bc), stop(x0)):
        # inside jit/vmap: one compiled solve under an eager vmap too (op by op it took
        # ~5x the compile of the whole); inside a jit: inlined
        return _solve_jit(pot, bc, x0, solver, adjoint, lstate)
    if not is_traced(pot, bc, x0):
        _check_constrained(pot, bc)
        if pot.pressure is not None:  # conservative only with a closed or held rim
            check_closed(
                pot.pressure,
                host_array(pot.mesh.points),
                host_array(bc.mask),
                host_array(bc.values),
            )
        pot = newton_terms.refreshed(pot, x0)  # self-contact: the broad phase at x0
    t0 = time.perf_counter()
    res = jax.block_until_ready(differentiable_minimize(solver, lstate, adjoint, pot, bc, x0))
    stats = dict(res.stats, wall_time=time.perf_counter() - t0)
    res = res._replace(stats=stats)
    if throw and int(res.status) != Status.SUCCESS:
        what = "Newton solve"
        if x0.dtype == jnp.float32:
            x64 = jax.config.jax_enable_x64  # pyright: ignore[reportAttributeAccessIssue]
            how = (
                "build the mesh in float64 (e.g. je.box(..., dtype=jnp.float64), or "
                '[solver] precision = "float64" in a scene)'
                if x64
                else "enable float64 with jax.config.update('jax_enable_x64', True)"
            )
            what += (
                " in float32 (Newton stops with SUCCESS at the residual's round-off floor, "
                f"{float(res.stats['residual_floor']):.2e} here, once a full step no longer "
                f"reduces it; to solve in float64, {how})"
            )
        raise SolveError(res, what)
    return res
