"""From a user's choice of linear solver to settings and state: :func:`resolve` and
:func:`init_linear`."""

from __future__ import annotations

import warnings

import jax
from jax.core import Tracer

from ...parallel.sharding import is_sharded
from .auto import LINEAR_SOLVERS, choose
from .host import AMG, Direct, HostSolver
from .krylov import CG
from .multilevel import Multilevel
from .protocol import LinearSolver, LinearState

__all__ = ["resolve", "init_linear", "bind_linear", "BY_NAME"]

BY_NAME: dict[str, type[LinearSolver]] = {
    "cg": CG,
    "direct": Direct,
    "amg": AMG,
    "multilevel": Multilevel,
}


def _traced(*trees) -> bool:
    return any(isinstance(a, Tracer) for t in trees for a in jax.tree_util.tree_leaves(t))


def resolve(linear, mesh, bc, *, quadratic: bool = False) -> LinearSolver:
    """The linear-solver settings a choice stands for, for one mesh and Dirichlet mask.

    Args:
        linear: ``"auto"`` (:func:`~jaxelastic.solvers.linear.auto.choose`), ``"cg"``,
            ``"direct"``, ``"amg"``, ``"multilevel"``, None (= ``"auto"``) or a solver
            object (returned as it is, after the checks below).
        mesh: the :class:`~jaxelastic.mesh.Mesh`; bc: the
            :class:`~jaxelastic.loads.Dirichlet` data.
        quadratic: the potential is quadratic (one Newton step).

    Raises:
        ValueError: unknown name; a host solver on a mesh sharded over devices
            (:func:`jaxelastic.shard`).
        TypeError: neither a name nor a solver object.
    """
    if linear is None:
        linear = "auto"
    if isinstance(linear, str):
        if linear not in LINEAR_SOLVERS:
            raise ValueError(f"linear solver must be one of {LINEAR_SOLVERS}, got {linear!r}")
        if linear == "auto":
            linear = choose(
                dim=int(mesh.dim),
                n_dofs=int(mesh.n_dofs),
                element=mesh.element,
                quadratic=quadratic,
                traced=_traced((mesh.cells, mesh.points, bc.mask)),
                sharded=is_sharded(mesh),
            )
        linear = BY_NAME[linear]()
    if not isinstance(linear, LinearSolver):
        raise TypeError(
            f"linear solver must be a name {LINEAR_SOLVERS} or je.CG/je.Direct/je.AMG/"
            f"je.Multilevel, got {type(linear).__name__}"
        )
    if isinstance(linear, HostSolver) and is_sharded(mesh):
        raise ValueError(
            f"linear solver {type(linear).__name__}() runs on the host and cannot take a "
            "mesh sharded over several devices (je.shard); use linear='multilevel' (the "
            "device multigrid) or linear='cg' (matrix-free, block-Jacobi preconditioned)"
        )
    return linear


def init_linear(linear, mesh, bc, *, quadratic: bool = False) -> tuple[LinearSolver, LinearState]:
    """``(settings, state)`` of a linear-solver choice for ``mesh`` and ``bc.mask``
    (outside jit; the state is cached by content, so calling it again is cheap).

    Make it once and pass the state to :func:`jaxelastic.solve` (``linear_state=``) where
    the mesh or the mask is traced (passed as ``jit`` arguments); :func:`jaxelastic.solve`
    makes it itself otherwise.

    Raises:
        ValueError: as :func:`resolve`; a solver that builds host structures (Direct, AMG,
            Multilevel) on a traced mesh or mask.
    """
    settings = resolve(linear, mesh, bc, quadratic=quadratic)
    if settings.kind != "cg" and _traced((mesh.cells, mesh.points, bc.mask)):
        raise ValueError(
            f"{type(settings).__name__}() builds its state from the mesh and the Dirichlet "
            "mask on the host, but they are traced here (passed as jit arguments): make it "
            "first, outside jit, with settings, state = je.solvers.init_linear(linear, mesh, "
            "bc) and pass je.solve(..., linear_state=state), or use linear='cg'"
        )
    return settings, settings.init(mesh, bc)


def bind_linear(linear, mesh, bc, *, quadratic: bool = False) -> LinearSolver:
    """Deprecated: :func:`init_linear` (settings and their state, kept apart). Returns the
    resolved settings and makes their state (cached, so a later solve finds it)."""
    warnings.warn(
        "je.solvers.bind_linear is deprecated: settings, state = "
        "je.solvers.init_linear(linear, mesh, bc), then je.solve(..., linear_state=state)",
        DeprecationWarning,
        stacklevel=2,
    )
    return init_linear(linear, mesh, bc, quadratic=quadratic)[0]
