"""Memory estimate of a scene before anything is allocated: refuse what will not fit.

:func:`mesh_size` reads the mesh size off the scene (a generator's cell counts, the
order and the formulation; for a mesh file the counts of the file read), :func:`estimate`
adds up the arrays a build and a Newton solve hold at their peak, and :func:`check`
refuses a scene whose estimate exceeds the memory available (``psutil``), or
``[solver].max_memory_gb`` when that is set (the override: a larger value runs anyway).

The model, with ``c`` cells of ``k`` nodes and ``q`` quadrature points, ``n`` nodes in
``d`` dimensions, ``m = k·d``, ``E = c·m²`` element-Hessian entries and ``U = c·m(m+1)/2``
of them in the element upper triangles (:func:`estimate_parts`):

* mesh arrays: points, cells, ``dN`` ``(c, q, k, d)``, weights, incidence (host and device);
* element Hessians (``hessian = "element"``/``"projected"``): the device result (``E``
  floats) and its symmetrised upper triangles (``U``), the input of the on-device CSR
  assembly (no host copy: only the ``(nnz_upper,)`` data vector crosses), plus the XLA
  temporaries of computing them (``c·q·k·d³`` and ``c·q·d⁴``);
* host linear solvers (``direct``, ``amg``; ``auto`` picks direct up to 10k dofs in 3D, 80k
  on P2 node sets): the int32 element → upper-CSR map (``U`` entries, 46 MB at 146k tets)
  and the CSR matrices with ``nnz ≈ E / r`` (``r`` measured on structured meshes: tri3
  2.5, tri6 1.5, tet4 5.6, tet10 2.4), a Cholesky factor of the upper triangle with a fill
  growing like ``n^(1/3)`` in 3D and ``log n`` in 2D, or an AMG hierarchy of about twice
  the matrix;
* Newton and line-search vectors, the dynamic state, output cell fields, and a fixed
  0.5 GB for the process with JAX, SciPy and PyAMG loaded and a small compiled program.

The total is the peak resident memory of the process; it is compared with the memory the
process can still grow to (its resident size now plus the memory available). Calibrated
against the peak RSS of twist solves (``tests/test_sparse.py`` checks one within 1.5×):
n = 10 (4k dofs, direct) 533 MiB measured / 530 MiB estimated; n = 19 (24k dofs, direct)
805 / 916 MiB; n = 29 (81k dofs, AMG) 1460–1571 MiB measured / 1517 MiB estimated. It is
meant to refuse a mesh that cannot fit before a NumPy allocation fails after minutes, not
to predict the peak exactly.
"""

from __future__ import annotations

import math
from typing import NamedTuple

from ..solvers.linear.auto import choose
from .load import Scene
from .schema import GENERATOR_DIM

__all__ = [
    "MeshSize",
    "mesh_size",
    "file_mesh_size",
    "estimate",
    "estimate_parts",
    "available_bytes",
    "check",
]

GB = 1e9
"""Bytes per GB (decimal, as ``max_memory_gb``)."""
RUNTIME_BYTES = 0.5 * GB
"""The process with JAX, SciPy, PyAMG and the compiled code of a small scene loaded
(twist n = 10, 4k dofs, PARDISO: 533 MiB peak with about 50 MB of arrays)."""

# (dim, order, composite) -> (element, nodes per cell, quadrature points)
_ELEMENTS = {
    (2, 1, False): ("tri3", 3, 1),
    (3, 1, False): ("tet4", 4, 1),
    (2, 2, False): ("tri6", 6, 6),
    (3, 2, False): ("tet10", 10, 14),
    (2, 1, True): ("tri3x4", 6, 4),
    (3, 1, True): ("tet4x8", 10, 8),
}
_NNZ_RATIO = {"tri3": 2.5, "tri6": 1.5, "tri3x4": 1.5, "tet4": 5.6, "tet10": 2.4, "tet4x8": 2.4}
"""``E / nnz`` of the assembled Hessian (measured on rectangle/box meshes)."""


class MeshSize(NamedTuple):
    """The size of a mesh, known before it is built.

    Attributes:
        n_nodes, n_cells: counts (Python ints, any size); dim: 2 or 3; element: its name;
        nodes_per_cell, n_quad: per cell; what: how messages name the mesh
        (``"[mesh].n = [400, 400, 400]"``).
    """

    n_nodes: int
    n_cells: int
    dim: int
    element: str
    nodes_per_cell: int
    n_quad: int
    what: str


def _element(dim: int, order: int, formulation: str) -> tuple[str, int, int]:
    return _ELEMENTS[(dim, order, order == 1 and formulation != "standard")]


def mesh_size(scene: Scene) -> MeshSize | None:
    """The size of a generator mesh from the scene alone (None for a mesh file)."""
    m = scene.spec.mesh
    if m.generator is None:
        return None
    dim = GENERATOR_DIM[m.generator]
    n = (m.n, m.n) if isinstance(m.n, int) else tuple(m.n or ())
    order = m.order or 1
    el, k, q = _element(dim, order, m.formulation)
    # structured meshes: the mid-edge nodes of P2 / composite cells are the points of the
    # twice finer grid (each square / cube face has one diagonal, each cube one)
    per = 2 if k > dim + 1 else 1
    n_nodes = math.prod(per * a + 1 for a in n)
    n_cells = (2 if dim == 2 else 6) * math.prod(n)
    shown = m.n if isinstance(m.n, int) else list(n)
    return MeshSize(n_nodes, n_cells, dim, el, k, q, f"[mesh].n = {shown}")


def file_mesh_size(
    n_nodes: int, n_cells: int, dim: int, file_nodes_per_cell: int, order, formulation: str
) -> MeshSize:
    """The size of a mesh file's mesh after ``[mesh] order/formulation`` are applied.

    A P1 file lifted to P2 / composite cells gains one node per edge (about
    ``n_nodes + n_cells`` edges in 2D and 3D).
    """
    p1 = file_nodes_per_cell == dim + 1
    lifted = p1 and (order == 2 or formulation != "standard")
    el, k, q = _element(dim, 2 if not p1 or order == 2 else 1, formulation if p1 else "standard")
    nodes = n_nodes + n_cells + n_nodes if lifted else n_nodes
    what = "[mesh].file" + (" (lifted to P2 nodes)" if lifted else "")
    return MeshSize(nodes, n_cells, dim, el, k, q, what)


def _linear_kind(scene: Scene, size: MeshSize) -> str:
    """The linear solver the scene will use: its own choice, or what the ``auto`` table
    (:func:`~jaxelastic.solvers.linear.auto.choose`) picks for this size."""
    s = scene.spec.solver
    if s.linear != "auto":
        return s.linear
    return choose(
        dim=size.dim,
        n_dofs=size.n_nodes * size.dim,
        element=size.element,
        sharded=int(getattr(s, "devices", 1)) > 1,
        check_installed=False,
    )


def estimate(scene: Scene, size: MeshSize) -> dict[str, float]:
    """Bytes per part of a build + solve of ``scene`` on a mesh of ``size`` (see the
    module docstring), largest first."""
    return estimate_parts(
        size,
        linear=_linear_kind(scene, size),
        hessian=scene.spec.solver.hessian,
        static=scene.static,
    )


def estimate_parts(
    size: MeshSize, *, linear: str, hessian: str = "element", static: bool = True
) -> dict[str, float]:
    """The model of :func:`estimate` for a resolved linear solver kind (``"direct"``,
    ``"amg"``, ``"cg"``, ``"multilevel"``), bytes per part, largest first.

    Args:
        size: the mesh size; linear: the linear solver kind (not ``"auto"``);
        hessian: ``"element"``/``"projected"`` (element Hessians are formed) or ``"hvp"``;
        static: False adds the dynamic state.
    """
    n, c, d, k, q = size.n_nodes, size.n_cells, size.dim, size.nodes_per_cell, size.n_quad
    m = k * d
    E = c * m * m
    upper = c * m * (m + 1) // 2  # element-Hessian entries of the local upper triangles
    parts: dict[str, float] = {
        "mesh arrays": 2.0 * 8 * (n * d + c * q * (k * d + 1)) + 4.0 * 5 * c * k,
        "Newton vectors": 8.0 * 40 * n * d,
        "output fields": 8.0 * 4 * c * q * d * d,
        "JAX runtime": RUNTIME_BYTES,
    }
    if hessian == "hvp":
        parts["Hessian-vector products"] = 8.0 * 10 * c * q * d**4
    else:
        # the device result and its symmetrised upper triangle (segment-sum input); no
        # host copies since the CSR data is assembled on the device
        parts["element Hessians"] = 8.0 * (E + upper)
        parts["XLA temporaries"] = 2 * 8.0 * (c * q * k * d**3 + c * q * d**4)
    if linear in ("direct", "amg"):
        nnz = E / _NNZ_RATIO[size.element]
        parts["Hessian scatter map"] = 4.0 * upper  # int32, upper triangles only
        # full CSR (data, int32 indices, upper→full and BSR maps) + upper CSR, host copies
        parts["sparse matrix"] = (8 + 4 + 4 + 4) * nnz + (8 + 4) * 0.55 * nnz + 8.0 * nnz
        dofs = n * d
        if linear == "direct":
            fill = max(4.0, 0.9 * dofs ** (1 / 3)) if d == 3 else max(3.0, math.log2(dofs))
            parts["Cholesky factor"] = 12.0 * fill * 0.55 * nnz
        else:
            parts["AMG hierarchy"] = 2.0 * 12 * nnz + 8.0 * 6 * 3 * dofs
    if not static:
        parts["dynamic state"] = 8.0 * 10 * n * d
    return dict(sorted(parts.items(), key=lambda kv: -kv[1]))


def available_bytes() -> float:
    """Memory this process can grow to [bytes]: its resident size plus the memory
    available now (``psutil``)."""
    import psutil

    rss = psutil.Process().memory_info().rss
    return float(psutil.virtual_memory().available + rss)


def _gb(b: float) -> str:
    x = b / GB
    return f"{x:.3g} GB" if x < 1e3 else f"{x:,.0f} GB"


def check(scene: Scene, size: MeshSize | None = None) -> dict[str, float] | None:
    """Refuse the scene if its estimate exceeds the memory budget.

    Args:
        scene: the scene; size: the mesh size (default: :func:`mesh_size`; None for a mesh
            file whose counts are not known yet: nothing is checked).
    Returns:
        The estimate (bytes per part), or None when nothing was checked.
    Raises:
        SceneError: the estimate exceeds ``[solver].max_memory_gb`` or, when that is not
            set, the available memory; the message gives the estimate, its largest parts,
            the budget and how to override.
    """
    size = size if size is not None else mesh_size(scene)
    if size is None:
        return None
    parts = estimate(scene, size)
    total = sum(parts.values())
    limit = scene.spec.solver.max_memory_gb
    budget = available_bytes() if limit is None else limit * GB
    if total <= budget:
        return parts
    top = ", ".join(f"{name} {_gb(b)}" for name, b in list(parts.items())[:3])
    against = (
        f"the {_gb(budget)} of memory available"
        if limit is None
        else f"[solver].max_memory_gb = {limit:g}"
    )
    suggest = max(1, math.ceil(1.2 * total / GB))
    raise scene.error(
        f"{size.what} needs about {_gb(total)} of memory to build and solve "
        f"({size.n_cells:,} {size.element} cells, {size.n_nodes:,} nodes; {top}), more than "
        f"{against}; use a coarser mesh, or raise the limit with [solver] max_memory_gb = "
        f"{suggest} (--set solver.max_memory_gb={suggest}) to run anyway"
    )
