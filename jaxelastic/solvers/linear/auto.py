"""The one table that decides ``linear="auto"``.

Everything that needs to know which linear solver ``"auto"`` picks — :func:`jaxelastic.solve`,
the scene memory estimate, the docs — asks :func:`choose`.
"""

from __future__ import annotations

import warnings

__all__ = [
    "LINEAR_SOLVERS",
    "AUTO_DIRECT_MAX_DOFS",
    "AUTO_DIRECT_MAX_DOFS_P2",
    "AUTO_DIRECT_MAX_DOFS_QUADRATIC",
    "P2_NODE_SETS",
    "choose",
    "missing_host_package",
]

LINEAR_SOLVERS = ("auto", "cg", "direct", "amg", "multilevel")
AUTO_DIRECT_MAX_DOFS = {2: 100_000, 3: 10_000}
"""``"auto"``: sparse Cholesky up to this many dofs (per dimension), AMG-preconditioned CG
above. 3D: whole twist solves (5 Newton steps, warm, ``scripts/bench_solvers.py --sizes
14,19 --solvers direct,amg --skip-extras``) with the whole AMG-CG on the host: direct /
AMG 0.44 / 0.43 s at 10k dofs, 1.53 / 0.83 s at 24k (with a host callback per CG iteration
instead, the crossover was near 27k). 2D: the fill of a nested-dissection
factorisation stays small (Cook P1 at 33k dofs: Cholesky 1.1 s vs AMG-CG 20 s,
``scripts/report_accuracy.py``)."""

AUTO_DIRECT_MAX_DOFS_P2 = {2: 100_000, 3: 80_000}
"""The same for elements on the P2 node set (tri6, tet10 and the composite tri3x4, tet4x8):
their matrices couple more dofs per row and smoothed aggregation needs more CG iterations.
Measured on the neo-Hookean P2 steel bracket (31k dofs, 5 load steps,
``scripts/bench_bracket.py``): warm solve direct 58 s / 20 Newton steps / 1.1 GB against
AMG 311 s / 26 steps / 2.5 GB (loaded machine). 80k is an extrapolation of that 5× lead
with the P1 slope of the direct/AMG ratio (∝ n^0.7), kept conservative."""

AUTO_DIRECT_MAX_DOFS_QUADRATIC = {2: 200_000, 3: 120_000}
"""The same for a quadratic potential (``choose(..., quadratic=True)``, which
:func:`jaxelastic.solve` asks for :func:`~jaxelastic.solvers.newton.is_quadratic`
potentials, e.g. the ``linear`` material): Newton takes one step, so one factorisation
against one tight AMG-CG solve (no reuse of a hierarchy across steps to amortise).
Measured on the linear P1 steel bracket (84k dofs, ``scripts/bench_bracket.py``, loaded
machine): warm direct 4.4 s against AMG 14.8 s. 120k in 3D is a conservative
extrapolation of that 3.4× lead (the direct/AMG ratio grows like n^0.7, see
:data:`AUTO_DIRECT_MAX_DOFS`) that also bounds the factor's memory (1.7 GB peak at 81k dofs
on the twist)."""

P2_NODE_SETS = ("tri6", "tet10", "tri3x4", "tet4x8")


def choose(
    *,
    dim: int,
    n_dofs: int,
    element: str,
    quadratic: bool = False,
    traced: bool = False,
    sharded: bool = False,
    check_installed: bool = True,
) -> str:
    """The solver name ``"auto"`` stands for.

    Args:
        dim: 2 or 3; n_dofs: ``n_nodes·dim``; element: the mesh's element name.
        quadratic: the potential is quadratic (one Newton step).
        traced: the mesh or the mask is traced (a host analysis is impossible): ``"cg"``.
        sharded: the mesh is sharded over devices: ``"multilevel"`` (the device multigrid,
            level 0 per shard).
        check_installed: fall back to ``"multilevel"`` with a warning when the host
            package the choice needs is missing (False: the choice of a full install).

    Returns:
        ``"direct"`` up to :data:`AUTO_DIRECT_MAX_DOFS` dofs (:data:`AUTO_DIRECT_MAX_DOFS_P2`
        on P2 node sets, :data:`AUTO_DIRECT_MAX_DOFS_QUADRATIC` for quadratic potentials),
        ``"amg"`` above; ``"cg"`` / ``"multilevel"`` as above.
    """
    if traced:
        return "cg"
    if sharded:
        return "multilevel"
    limits = AUTO_DIRECT_MAX_DOFS_P2 if element in P2_NODE_SETS else AUTO_DIRECT_MAX_DOFS
    if quadratic:
        limits = AUTO_DIRECT_MAX_DOFS_QUADRATIC
    name = "direct" if n_dofs <= limits.get(dim, 10_000) else "amg"
    missing = missing_host_package(name) if check_installed else None
    if missing:  # a lean install (e.g. a GPU image): the device solver instead
        warnings.warn(
            f"jaxelastic: linear='auto' would use the host {name!r} solver but {missing} is "
            f"not installed; using the device solver linear='multilevel' instead (pip "
            f"install {missing}, or jaxelastic[cpu], for the host one)",
            RuntimeWarning,
            stacklevel=1,  # one location: the default filter shows it once
        )
        name = "multilevel"
    return name


def missing_host_package(kind: str) -> str | None:
    """The package a host back end of ``kind`` (``"direct"``/``"amg"``) needs and cannot
    import here (None when it can): ``pyamg`` for AMG; for direct, a sparse Cholesky
    package (SciPy's SuperLU alone is a slow fallback that ``"auto"`` does not pick)."""
    if kind == "amg":
        try:
            import pyamg  # noqa: F401
        except ImportError:
            return "pyamg"
        return None
    from ..host.direct import available_direct_backends

    return "pypardiso" if available_direct_backends() == ("splu",) else None
