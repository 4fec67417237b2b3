"""Files in and out: meshio reading with named sets, VTU output, ParaView time series, and
the one atomic writer and JSON sanitiser of the package.

* :func:`read_mesh` reads any meshio-readable file (Gmsh ``.msh`` v2/v4 ascii/binary, VTU,
  XDMF, Abaqus ``.inp``, …) holding linear or quadratic triangles (2D: ``triangle``,
  ``triangle6``) or tetrahedra (3D: ``tetra``, ``tetra10``) and returns a
  :class:`MeshData`: the validated :class:`~jaxelastic.mesh.Mesh` plus named point, cell and
  boundary-facet sets taken from Gmsh physical groups and meshio point/cell sets.
* :func:`write_vtu` writes one state (rest geometry + ``displacement``, optionally J,
  Green strain, first Piola and Cauchy stress, von Mises stress and ψ per cell, and the
  recovered nodal Cauchy and von Mises stress per node, :func:`nodal_stress`);
  :class:`TimeSeriesWriter` writes ``basename_0000.vtu``… and a ParaView ``.pvd``
  collection.
* :func:`write_atomic` is the atomic writer every output goes through;
  :func:`to_jsonable` turns numpy/JAX values, NamedTuples, enums and paths into plain JSON
  values (NaN/inf → ``null``) and :func:`write_json` writes them atomically.

Every file is written atomically (temporary file in the target directory, then
``os.replace``): a reader never sees a half-written file and a crash leaves no partial
output. Outputs are overwritten by default (a time series rewrites its own files); pass
``overwrite=False`` to refuse, and ``protect=[...]`` (paths or :class:`MeshData`) to refuse
ever writing over an input mesh.

meshio is imported lazily; importing this module has no side effects.
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import functools
import json
import math
import os
import re
import secrets
import warnings
import xml.etree.ElementTree as ET
from typing import Any, cast

import jax
import jax.numpy as jnp
import numpy as np

from .mechanics.checks import cell_params_axes, check_positions, check_psi, psi_name
from .mechanics.kernels import first_piola
from .mechanics.kinematics import deformation_gradients, det, green_strain
from .mesh import Mesh, MeshError, boundary_facets, from_arrays
from .mesh.elements import ref_nodes

__all__ = [
    "MeshIOError",
    "MeshData",
    "read_mesh",
    "write_vtu",
    "cell_fields",
    "nodal_stress",
    "stress_fields",
    "contact_point_data",
    "TimeSeriesWriter",
    "write_atomic",
    "write_json",
    "to_jsonable",
]

# volume cell types per dimension, with the matching boundary facet type
_VOLUME = {2: ("triangle", "triangle6"), 3: ("tetra", "tetra10")}
_FACET = {"triangle": "line", "triangle6": "line3", "tetra": "triangle", "tetra10": "triangle6"}


class MeshIOError(MeshError):
    """A mesh file cannot be read or written; the message names the file and the reason."""


@dataclasses.dataclass(frozen=True)
class MeshData:
    """A mesh read from a file, with its named sets (all indices refer to ``mesh``).

    Attributes:
        mesh: the validated rest mesh.
        point_sets: name → ``(m,)`` sorted node indices (tagged vertices; in 3D also the
            nodes of tagged lines; meshio point sets).
        cell_sets: name → ``(m,)`` sorted indices into ``mesh.cells``.
        facet_sets: name → ``(m, dim)`` node indices of tagged facets (lines in 2D,
            triangles in 3D); facets on the boundary are oriented with outward normals
            exactly as :func:`~jaxelastic.mesh.boundary_facets` returns them.
        node_map: ``(n_nodes,)`` index in the file of each kept node (unused nodes, e.g.
            Gmsh geometry points, are pruned).
        source: absolute path of the file read.
    """

    mesh: Mesh
    point_sets: dict
    cell_sets: dict
    facet_sets: dict
    node_map: np.ndarray
    source: str


def _read_raw(path: str, file_format: str | None):
    """Call meshio's reader directly: ``meshio.read`` calls ``sys.exit`` on a parse error."""
    import meshio

    if not os.path.exists(path):
        raise MeshIOError(f"cannot read mesh {path!r}: no such file")
    if os.path.isdir(path):
        raise MeshIOError(f"cannot read mesh {path!r}: it is a directory")
    if file_format is None:
        name, formats = os.path.basename(path).lower(), []
        for ext, fmts in meshio.extension_to_filetypes.items():
            if name.endswith(ext) and len(name) > len(ext):
                formats += [f for f in fmts if f not in formats]
        if not formats:
            raise MeshIOError(
                f"cannot read mesh {path!r}: unknown file extension; meshio reads "
                f"{', '.join(sorted(meshio.extension_to_filetypes))} (or pass file_format=)"
            )
    else:
        formats = [file_format]
    if os.path.getsize(path) == 0:
        raise MeshIOError(f"cannot read mesh {path!r}: the file is empty (0 bytes)")
    readers = getattr(getattr(meshio, "_helpers", None), "reader_map", {})
    errors = []
    for fmt in formats:
        try:
            return readers[fmt](path) if fmt in readers else meshio.read(path, file_format=fmt)
        except ImportError as e:
            errors.append(f"{fmt} needs the optional package {e.name!r} (pip install {e.name})")
        except SystemExit:
            errors.append(f"meshio could not parse it as {fmt}")
        except Exception as e:  # noqa: BLE001 — any parser failure is reported with the path
            why = f"{type(e).__name__}: {e}" if str(e) else type(e).__name__
            errors.append(f"meshio could not parse it as {fmt} ({why})")
    if _declares_no_points(path):  # meshio fails on some empty files (VTU, legacy VTK)
        raise MeshIOError(f"{path}: the mesh is empty (0 points, 0 cells)")
    raise MeshIOError(f"cannot read mesh {path!r}: " + "; ".join(errors))


def _declares_no_points(path: str) -> bool:
    """Whether the header of a VTK file (XML or legacy) declares 0 points."""
    with open(path, "rb") as f:
        head = f.read(1 << 16).decode("latin-1")
    xml = re.findall(r"<Piece\b[^>]*\bNumberOfPoints\s*=\s*[\"'](\d+)", head)
    legacy = re.findall(r"^\s*POINTS\s+(\d+)", head, flags=re.MULTILINE)
    counts = xml or legacy
    return bool(counts) and all(int(c) == 0 for c in counts)


def _tagged_groups(raw):
    """Yield ``(name, block index, local cell indices)`` for every physical group / cell set."""
    blocks = raw.cells
    phys = raw.cell_data.get("gmsh:physical")
    if phys is not None and len(phys) == len(blocks):
        names = {}
        for k, v in raw.field_data.items():
            v = np.asarray(v).ravel()
            if v.size == 2:  # gmsh: name -> [tag, dim]
                names[(int(v[0]), int(v[1]))] = k
        for i, b in enumerate(blocks):
            tags = np.asarray(phys[i]).astype(np.int64).ravel()
            for t in np.unique(tags[tags > 0]):  # tag 0 = "in no physical group"
                yield names.get((int(t), b.dim), str(int(t))), i, np.flatnonzero(tags == t)
    for name, per_block in raw.cell_sets.items():
        if name.startswith("gmsh:") or len(per_block) != len(blocks):
            continue
        for i, idx in enumerate(per_block):
            if idx is not None and np.size(idx) > 0:
                yield name, i, np.asarray(idx, dtype=np.int64).ravel()


def _named_sets(raw, mesh: Mesh, new: np.ndarray, offset: dict, vol_dim: int, vol_type: str):
    """Point, cell and facet sets of ``raw`` in the numbering of ``mesh``.

    Args:
        raw: the meshio mesh as read.
        mesh: the validated rest mesh built from its volume cells.
        new: ``(n_file_nodes,)`` index in ``mesh`` of each file node (−1: pruned).
        offset: block index → index in ``mesh.cells`` of the block's first cell.
        vol_dim, vol_type: dimension and meshio type of the volume cells.

    Returns:
        ``(point_sets, cell_sets, facet_sets)`` as in :class:`MeshData`.
    """
    blocks = raw.cells
    acc: dict[str, dict[str, list]] = {"point": {}, "cell": {}, "facet": {}}
    for name, i, local in _tagged_groups(raw):
        b = blocks[i]
        if b.dim == vol_dim:
            acc["cell"].setdefault(name, []).append(offset[i] + local)
            continue
        conn = new[np.asarray(b.data, dtype=np.int64)[local]]
        if b.type == _FACET[vol_type]:
            acc["facet"].setdefault(name, []).append(conn[(conn >= 0).all(axis=1)])
        elif b.dim == 0 or (vol_dim == 3 and b.dim == 1):
            acc["point"].setdefault(name, []).append(conn.ravel()[conn.ravel() >= 0])
    for name, idx in raw.point_sets.items():
        idx = new[np.asarray(idx, dtype=np.int64).ravel()]
        acc["point"].setdefault(name, []).append(idx[idx >= 0])

    point_sets = {k: np.unique(np.concatenate(v)) for k, v in acc["point"].items()}
    cell_sets = {k: np.unique(np.concatenate(v)) for k, v in acc["cell"].items()}
    facet_sets = {}
    if acc["facet"]:
        bf = boundary_facets(mesh)
        facet_sets = {k: _orient_facets(np.concatenate(v), bf) for k, v in acc["facet"].items()}
    return point_sets, cell_sets, facet_sets


def read_mesh(path, *, orient: str = "fix", file_format: str | None = None) -> MeshData:
    """Read a triangle (2D) or tetrahedron (3D) mesh file, linear or quadratic, with its
    named sets.

    Args:
        path: the mesh file; the format is deduced from the extension unless
            ``file_format`` (a meshio format name, e.g. ``"gmsh"``) is given.
        orient: passed to :func:`~jaxelastic.mesh.from_arrays` (``"fix"`` reorients
            clockwise/left-handed cells with a warning, ``"refuse"`` raises).

    Returns:
        A :class:`MeshData`. Volume cells of all blocks are concatenated in file order.
        Lower-dimensional cells carrying a physical group or cell set become facet sets
        (lines in 2D, triangles in 3D, of the matching order: ``line3``/``triangle6`` for
        quadratic meshes) or point sets (vertices; lines in 3D); untagged ones
        are ignored. Unnamed Gmsh physical groups are named by their tag (``"7"``). Points
        stored with 3 coordinates and constant z make a 2D mesh.

    Raises:
        MeshIOError: missing/unreadable file, unknown extension, an empty mesh (the
            message says "empty"), no or unsupported volume
            cells (quad, hex, mixed types), a triangle mesh that is not planar,
            or invalid geometry (the :class:`~jaxelastic.mesh.MeshError` message, prefixed
            with the path).
    """
    path = os.path.abspath(os.fspath(path))
    raw = _read_raw(path, file_format)
    blocks = raw.cells
    n_cells = sum(len(b.data) for b in blocks)
    if len(raw.points) == 0 or n_cells == 0:
        raise MeshIOError(
            f"{path}: the mesh is empty ({len(raw.points)} points, {n_cells} cells); a mesh "
            "needs triangle (2D) or tetrahedron (3D) cells"
        )
    dims = {b.type: b.dim for b in blocks if len(b.data)}
    vol_dim = max(dims.values(), default=-1)
    vol_types = sorted(t for t, d in dims.items() if d == vol_dim)
    if vol_dim < 2:
        raise MeshIOError(f"{path}: no triangle or tetra cells (cell types found: {sorted(dims)})")
    if len(vol_types) != 1 or vol_types[0] not in _VOLUME.get(vol_dim, ()):
        raise MeshIOError(
            f"{path}: unsupported volume cell types {vol_types}; jaxelastic reads meshes of "
            "triangles (2D: triangle, triangle6) or tetrahedra (3D: tetra, tetra10), one "
            "type per mesh"
        )
    vol_type = vol_types[0]
    vol = [i for i, b in enumerate(blocks) if b.type == vol_type and len(b.data)]
    offset = dict(zip(vol, np.cumsum([0] + [len(blocks[i].data) for i in vol]), strict=False))
    cells = np.concatenate([np.asarray(blocks[i].data, dtype=np.int64) for i in vol])
    n_file = len(raw.points)
    if cells.size and (cells.min() < 0 or cells.max() >= n_file):
        raise MeshIOError(f"{path}: cells reference nodes outside [0, {n_file})")
    node_map = np.unique(cells)
    new = np.full(n_file, -1, dtype=np.int64)
    new[node_map] = np.arange(node_map.size)
    points = np.asarray(raw.points, dtype=np.float64)[node_map]
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():  # named by the file's node numbers, not the pruned ones
        idx = node_map[bad]
        raise MeshIOError(
            f"{path}: {idx.size} node(s) used by cells have NaN/inf coordinates, e.g. file "
            f"nodes {idx[:5].tolist()} (0-based)"
        )
    if vol_dim == 2 and points.shape[1] == 3:
        extent = np.ptp(points[:, :2], axis=0).max()
        if np.ptp(points[:, 2]) > 1e-10 * extent:
            raise MeshIOError(
                f"{path}: triangle cells with varying z coordinates: a surface mesh in 3D "
                "is not a solid (use tetrahedra for 3D bodies)"
            )
        points = points[:, :2]
    try:
        mesh = from_arrays(points, new[cells], vol_type, orient=orient)
    except MeshError as e:
        raise MeshIOError(f"{path}: {e}") from None

    point_sets, cell_sets, facet_sets = _named_sets(raw, mesh, new, offset, vol_dim, vol_type)
    return MeshData(mesh, point_sets, cell_sets, facet_sets, node_map, path)


def _orient_facets(facets: np.ndarray, boundary: np.ndarray) -> np.ndarray:
    """Deduplicate ``facets`` and replace each boundary one by its outward-oriented copy."""
    _, first = np.unique(np.sort(facets, axis=1), axis=0, return_index=True)
    facets = facets[np.sort(first)]
    keys = np.sort(np.concatenate([boundary, facets]), axis=1)
    _, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.ravel()
    lookup = np.full(inv.max() + 1, -1)
    lookup[inv[: len(boundary)]] = np.arange(len(boundary))
    match = lookup[inv[len(boundary) :]]
    out = facets.copy()
    out[match >= 0] = boundary[match[match >= 0]]
    return out


def _von_mises(s3, xp=jnp):
    """Von Mises stress of ``(..., 3, 3)`` Cauchy stresses (``xp``: ``jnp`` under jit, or
    ``np`` for host arrays)."""
    eye = xp.eye(3, dtype=s3.dtype).reshape((1,) * (s3.ndim - 2) + (3, 3))
    dev = s3 - xp.trace(s3, axis1=-2, axis2=-1)[..., None, None] / 3.0 * eye
    return xp.sqrt(1.5 * xp.sum(dev * dev, axis=(-2, -1)))


def _embed3(F):
    """The 3D embedding ``diag(F, 1)`` of in-plane ``(..., 2, 2)`` deformation gradients."""
    F3 = jnp.zeros(F.shape[:-2] + (3, 3), F.dtype).at[..., :2, :2].set(F)
    return F3.at[..., 2, 2].set(1.0)


# the in-plane probe of the plane-strain consistency test ψ₂(F) = ψ₃(diag(F, 1)) + const
_PROBE = np.array([[1.1, 0.07], [-0.04, 0.93]])


def _plane_strain_parts(psi, F, J, params, ax):
    """σ_zz ``(c, q)`` of the 3D embedding and, per cell, the relative mismatch of the
    in-plane P of ψ on 3×3 F against ψ on 2×2 F at a fixed probe F (0 when ψ on 2×2 F
    is the plane-strain restriction of ψ on 3×3 F)."""
    P3 = jax.vmap(jax.vmap(first_piola(psi), in_axes=(0, None)), in_axes=(0, ax))(
        _embed3(F), params
    )
    szz = P3[..., 2, 2] / J  # σ = P Fᵀ / J and row z of diag(F, 1) is e_z
    Fp = jnp.asarray(_PROBE, F.dtype)
    c = J.shape[0]
    P2p = jax.vmap(lambda p: first_piola(psi)(Fp, p), in_axes=(ax,), axis_size=c)(params)
    P3p = jax.vmap(lambda p: first_piola(psi)(_embed3(Fp), p), in_axes=(ax,), axis_size=c)(params)
    diff = jnp.max(jnp.abs(P3p[:, :2, :2] - P2p), axis=(-2, -1))
    scale = jnp.max(jnp.abs(P2p), axis=(-2, -1))
    mismatch = jnp.where(scale > 0, diff / jnp.where(scale > 0, scale, 1.0), diff)
    return szz, mismatch


def _linear_basis(xi) -> np.ndarray:
    """``(n, d+1)`` values of the linear monomials ``1, ξ₁, …, ξ_d`` at reference points."""
    xi = np.asarray(xi, dtype=np.float64)
    return np.concatenate([np.ones((xi.shape[0], 1)), xi], axis=1)


def _recovery_incidence(element) -> np.ndarray:
    """``(n_q, k)`` 0/1: which element nodes each quadrature point's (constant) stress is
    attributed to in the nodal average: all nodes for P1 (one point), the sub-simplex's
    nodes for the composite elements (one point per sub-simplex)."""
    if element.is_composite:
        B = np.zeros((element.n_quad, element.n_nodes))
        for s, sub in enumerate(element.sub_cells):
            B[s, list(sub)] = 1.0
        return B
    return np.ones((element.n_quad, element.n_nodes))


def _nodal_average(s3, mesh):
    """Recovered nodal Cauchy stress ``(n_nodes, 9)`` from quadrature values ``(c, q, 3, 3)``.

    P2 (``order == 2``): per element, the weighted least-squares (local L2) fit of a linear
    field in the reference coordinates to the quadrature values, evaluated at the element's
    nodes (exact when the stress is linear in the element, as for linear elasticity on a
    straight-sided P2 element); P1 and the composite elements: the piecewise-constant value
    of the (sub-)simplex. Each node then takes the average of its elements' values weighted
    by the element (sub-simplex) measure.
    """
    el = mesh.element_type
    c, q = s3.shape[:2]
    sq = s3.reshape(c, q, 9)
    w = mesh.weights  # (c, q) [length^d]
    if el.order == 2 and not el.is_composite:
        Pq = jnp.asarray(_linear_basis(el.quad_points), s3.dtype)  # (q, d+1)
        Pn = jnp.asarray(_linear_basis(ref_nodes(el.dim)), s3.dtype)  # (k, d+1)
        G = jnp.einsum("qi,cq,qj->cij", Pq, w, Pq)
        coef = jnp.linalg.solve(G, jnp.einsum("qi,cq,cqx->cix", Pq, w, sq))  # (c, d+1, 9)
        wts = jnp.broadcast_to(w.sum(axis=1)[:, None], (c, el.n_nodes))
        num = jnp.einsum("ki,cix->ckx", Pn, coef) * wts[..., None]
    else:
        B = jnp.asarray(_recovery_incidence(el), s3.dtype)  # (q, k)
        num = jnp.einsum("qk,cq,cqx->ckx", B, w, sq)
        wts = jnp.einsum("qk,cq->ck", B, w)
    idx = mesh.cells.reshape(-1)
    n = mesh.points.shape[0]
    total = jax.ops.segment_sum(num.reshape(-1, 9), idx, num_segments=n)
    weight = jax.ops.segment_sum(wts.reshape(-1), idx, num_segments=n)
    return total / jnp.where(weight > 0, weight, jnp.nan)[:, None]


@functools.partial(jax.jit, static_argnums=(0, 4))
def _cell_fields(psi, x, mesh, params, embed: bool):
    F = deformation_gradients(x, mesh)  # (c, q, d, d); F̄ under the F-bar formulation
    c, q, d = F.shape[:3]
    ax = cell_params_axes(params, mesh.n_cells)
    P = jax.vmap(jax.vmap(first_piola(psi), in_axes=(0, None)), in_axes=(0, ax))(F, params)
    W = jax.vmap(jax.vmap(psi, in_axes=(0, None)), in_axes=(0, ax))(F, params)  # (c, q)
    J = jax.vmap(jax.vmap(det))(F)
    sigma = P @ jnp.swapaxes(F, -1, -2) / J[..., None, None]  # Cauchy σ = P Fᵀ / J
    s3 = jnp.zeros((c, q, 3, 3), F.dtype).at[..., :d, :d].set(sigma)  # σ_zz = 0 for now
    wn = mesh.weights / jnp.sum(mesh.weights, axis=1, keepdims=True)  # (c, q)

    def avg(a):  # weighted average over the quadrature points
        return jnp.einsum("cq,cq...->c...", wn, a)

    out = {
        "J": avg(J),
        "green_strain": avg(jax.vmap(jax.vmap(green_strain))(F)).reshape(c, d * d),
        "stress_P": avg(P).reshape(c, d * d),
        "cauchy_stress": avg(s3).reshape(c, 9),
        "von_mises": avg(_von_mises(s3)),
        "energy_density": avg(W),
        "cauchy_stress_nodal": _nodal_average(s3, mesh),
    }
    if embed:
        szz, mismatch = _plane_strain_parts(psi, F, J, params, ax)
        s3z = s3.at[..., 2, 2].set(szz)
        out["von_mises_plane_strain"] = avg(_von_mises(s3z))
        out["cauchy_stress_plane_strain"] = avg(s3z).reshape(c, 9)
        out["cauchy_stress_nodal_plane_strain"] = _nodal_average(s3z, mesh)
        out["stress_zz"] = avg(szz)
        out["mismatch"] = mismatch
    return out


def _accepts_3d(psi, mesh: Mesh, params) -> str | None:
    """None if ψ returns a scalar for a 3×3 F, else why not (for the warning)."""
    try:
        check_psi(psi, 3, mesh.points.dtype, params, mesh.n_cells, where="cell_fields")
    except Exception as e:  # noqa: BLE001 — any failure means: no 3D embedding
        return f"{type(e).__name__}: {e}"
    return None


def cell_fields(psi, x, mesh: Mesh, params, *, plane: str = "strain") -> dict[str, np.ndarray]:
    """Per-cell output fields, averaged over the cell's quadrature points with their weights
    (the one value for P1; of F̄ under F-bar), jitted, mesh passed as an argument.

    In 2D the von Mises stress needs the out-of-plane Cauchy stress σ_zz. Plane strain
    (``plane="strain"``, the default, as in :func:`~jaxelastic.materials.lame`): σ_zz is the
    zz Cauchy stress of the 3D embedding ``F₃ = diag(F, 1)`` of the same ψ, ``P₃_zz / J``
    (for linear elasticity ``σ_zz = ν(σ_xx + σ_yy)``). That is the plane-strain σ_zz
    whenever ψ on 2×2 F is the restriction of ψ on 3×3 F (true for every built-in
    material); if ψ does not accept a 3×3 F, or its in-plane stress on ``diag(F, 1)``
    differs from the 2D one (a genuinely 2D model), a :class:`UserWarning` says so and
    von Mises is written with σ_zz = 0 and without ``stress_zz``. Plane stress
    (``plane="stress"``): σ_zz = 0 exactly.

    Args:
        psi: strain-energy density ``psi(F, params)`` [energy / rest measure].
        x: ``(n_nodes, dim)`` current positions [length].
        mesh: the rest mesh.
        params: material parameters (shared scalars or per-cell leaves).
        plane: 2D only: ``"strain"`` or ``"stress"`` (ignored in 3D).

    Returns:
        ``J`` ``(n_cells,)``: det F; ``green_strain`` ``(n_cells, d²)``: E = ½(FᵀF − I)
        row-major; ``stress_P`` ``(n_cells, d²)``: first Piola P [Pa]; ``cauchy_stress``
        ``(n_cells, 9)``: the Cauchy stress σ = P Fᵀ/J as a row-major 3×3 tensor [Pa]
        (in 2D with σ_zz as above, zero shear out of plane); ``von_mises`` ``(n_cells,)``:
        of σ [Pa]; ``energy_density`` ``(n_cells,)``: ψ [Pa]; in 2D ``stress_zz``
        ``(n_cells,)``: the σ_zz used [Pa] (0 in plane stress). Recovered nodal
        stresses: :func:`nodal_stress`.
    """
    return stress_fields(psi, x, mesh, params, plane=plane)[0]


def nodal_stress(psi, x, mesh: Mesh, params, *, plane: str = "strain") -> dict[str, np.ndarray]:
    """Recovered, continuous nodal (point) stresses, e.g. to read a peak stress at a notch.

    The Cauchy stress σ = P Fᵀ/J at the quadrature points is turned into one value per
    element node and averaged over the elements that share the node, weighted by the
    element measure:

    * P2 (``tri6``, ``tet10``): per element the local L2 projection (weighted least
      squares over the quadrature points) of σ onto linear fields, evaluated at the 6 / 10
      nodes. For linear elasticity on straight-sided P2 elements σ is linear in the
      element, so this is the element's own nodal stress, exactly.
    * P1 (``tri3``, ``tet4``): the constant stress of each cell; composite F-bar elements
      (``tri3x4``, ``tet4x8``): the constant stress of each linear sub-simplex.

    A stress field the elements represent exactly (uniform for P1, linear for P2) is
    recovered exactly at every node; elsewhere the averaging recovers the peak far better
    than the largest cell average (the concentration at a hole of a plate, within the
    discretisation error of the P2 field). σ_zz in 2D is that of :func:`cell_fields`.

    Args:
        psi, x, mesh, params, plane: as for :func:`cell_fields`.

    Returns:
        ``cauchy_stress_nodal`` ``(n_nodes, 9)``: row-major 3×3 Cauchy stress [Pa];
        ``von_mises_nodal`` ``(n_nodes,)``: the von Mises stress of that tensor [Pa].
    """
    return stress_fields(psi, x, mesh, params, plane=plane)[1]


def stress_fields(psi, x, mesh: Mesh, params, *, plane: str = "strain") -> tuple[dict, dict]:
    """``(cell fields, point fields)``: :func:`cell_fields` and :func:`nodal_stress` of
    positions ``x`` ``(n_nodes, dim)`` [length] from one jitted evaluation (the plane-strain
    σ_zz decision and its warning here). Pass the pair to :func:`write_vtu` (``fields=``)
    to write a state whose stresses are also needed elsewhere (e.g. a picture coloured by
    ``von_mises_nodal``) without evaluating them twice.

    Args:
        psi, x, mesh, params, plane: as for :func:`cell_fields`.

    Returns:
        ``(cells, points)``: dicts of host (numpy) arrays, ``cells`` as
        :func:`cell_fields` returns (leading axis ``n_cells``), ``points`` as
        :func:`nodal_stress` returns (leading axis ``n_nodes``).
    """
    if plane not in ("strain", "stress"):
        raise ValueError(f"plane must be 'strain' or 'stress', got {plane!r}")
    check_positions(x, mesh, where="cell_fields")
    check_psi(psi, mesh.dim, mesh.points.dtype, params, mesh.n_cells, where="cell_fields")
    strain2d = mesh.dim == 2 and plane == "strain"
    why = _accepts_3d(psi, mesh, params) if strain2d else None
    embed = strain2d and why is None
    out = _cell_fields(psi, jnp.asarray(x, dtype=mesh.points.dtype), mesh, params, embed)
    out = {k: np.asarray(v) for k, v in out.items()}
    nodal = out.pop("cauchy_stress_nodal")
    if embed:
        mismatch = float(np.nanmax(out.pop("mismatch")))
        vm, szz = out.pop("von_mises_plane_strain"), out.pop("stress_zz")
        sig, sig_n = (
            out.pop("cauchy_stress_plane_strain"),
            out.pop("cauchy_stress_nodal_plane_strain"),
        )
        tol = float(np.sqrt(np.finfo(out["J"].dtype).eps))
        if mismatch <= tol:
            out["von_mises"], out["stress_zz"], out["cauchy_stress"] = vm, szz, sig
            nodal = sig_n
        else:
            why = (
                f"its in-plane stress on diag(F, 1) differs from that on F by {mismatch:.2g} "
                "(relative): it is not the plane-strain restriction of a 3D model"
            )
    elif mesh.dim == 2 and plane == "stress":
        out["stress_zz"] = np.zeros_like(out["J"])
    if why is not None:
        warnings.warn(
            f"plane strain: von_mises is written with σ_zz = 0 (the in-plane stress state) "
            f"and without stress_zz, since σ_zz cannot be taken from the 3D embedding of ψ "
            f"{psi_name(psi)!r}: {why}",
            UserWarning,
            stacklevel=3,
        )
    # in numpy: eager jnp ops took 0.09 s (dispatch + compile or persistent-cache loads)
    # in a fresh CLI process, numpy takes 2 ms at 27k nodes
    vm = _von_mises(np.asarray(nodal).reshape(-1, 3, 3), np)
    points = {"cauchy_stress_nodal": nodal, "von_mises_nodal": vm}
    return out, points


def _pad3(a: np.ndarray) -> np.ndarray:
    """Pad ``(n, 2)`` vectors with a zero z component (ParaView wants 3-vectors)."""
    return np.pad(a, ((0, 0), (0, 1))) if a.ndim == 2 and a.shape[1] == 2 else a


def _same_file(a: str, b: str) -> bool:
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    return os.path.exists(a) and os.path.exists(b) and os.path.samefile(a, b)


def write_atomic(path, write_fn) -> None:
    """Write a file atomically: ``write_fn(tmp)`` fills a temporary file, which replaces
    ``path`` only once it is complete.

    The temporary file lies in the directory of ``path`` (so ``os.replace`` is atomic on
    POSIX and Windows), is flushed to disk with ``fsync`` before the rename and is removed
    if anything fails, ``KeyboardInterrupt`` included: ``path`` then keeps its old content
    (or stays absent) and no temporary file is left behind. The new file gets mode 0644.

    Args:
        path: the destination file (``str`` or path-like); its directory must exist.
        write_fn: called once as ``write_fn(tmp)`` with the temporary path (a ``str``
            ending in ``.tmp``); it must write the whole content to that path (pass an
            explicit format to writers that guess it from the extension).
    """
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    if os.path.isdir(path):
        raise IsADirectoryError(f"cannot write {path!r}: it is a directory; give a file name")
    if not os.path.isdir(directory):
        raise FileNotFoundError(
            f"cannot write {path!r}: the directory {directory!r} does not exist (create it "
            "first, e.g. os.makedirs(..., exist_ok=True))"
        )
    tmp = None
    try:
        for _ in range(100):
            # the name is bound before the file exists (unlike tempfile.mkstemp), so an
            # interrupt landing at any instant leaves nothing the cleanup below cannot see
            tmp = os.path.join(directory, f".{os.path.basename(path)}.{secrets.token_hex(8)}.tmp")
            try:
                os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
                break
            except FileExistsError:  # someone else's file: never remove it
                tmp = None
        else:
            raise FileExistsError(f"cannot create a temporary file for {path!r}")
        write_fn(tmp)
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)  # created 0600; outputs are meant to be read
        os.replace(tmp, path)
    except BaseException:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.remove(tmp)
        raise


def to_jsonable(obj, *, nonfinite: str = "null"):
    """Convert ``obj`` recursively into plain JSON values (dict, list, str, int, float,
    bool, None).

    Handles dicts (keys become ``str``; enum keys their name), lists, tuples and sets,
    NamedTuples (a dict of their fields), dataclass instances (a dict of their fields),
    enums (their ``name``, also for ``IntEnum`` such as ``Status``), paths (``os.fspath``),
    numpy and JAX scalars and arrays (nested lists), Python and numpy numbers.

    Args:
        obj: the object to convert (not a traced JAX value).
        nonfinite: how NaN and ±inf floats are written: ``"null"`` (default, ``None``) or
            ``"string"`` (``"nan"``, ``"inf"``, ``"-inf"``).

    Returns:
        A value that ``json.dumps(..., allow_nan=False)`` accepts.

    Raises:
        TypeError: an object of another type (the message names its position).
        ValueError: an unknown ``nonfinite``.
    """
    if nonfinite not in ("null", "string"):
        raise ValueError(f"nonfinite must be 'null' or 'string', got {nonfinite!r}")
    return _jsonable(obj, nonfinite, "obj")


def _json_float(x: float, nonfinite: str):
    if math.isfinite(x):
        return x
    if nonfinite == "null":
        return None
    return "nan" if math.isnan(x) else ("inf" if x > 0 else "-inf")


def _json_key(k) -> str:
    return k.name if isinstance(k, enum.Enum) else str(k)


def _jsonable(x, nonfinite: str, where: str):
    """:func:`to_jsonable` of ``x`` found at ``where`` (for the error message)."""
    if x is None or isinstance(x, bool):
        return x
    if isinstance(x, str):
        return str(x)  # np.str_ too
    if isinstance(x, enum.Enum):
        return x.name
    if isinstance(x, int):
        return int(x)
    if isinstance(x, float):
        return _json_float(float(x), nonfinite)
    if isinstance(x, (np.ndarray, np.generic, jax.Array)):
        a = np.asarray(x)
        if a.dtype.kind in "biu":
            return a.tolist()
        if a.dtype.kind == "f":
            if a.ndim == 0:
                return _json_float(float(a), nonfinite)
            return [_jsonable(v, nonfinite, f"{where}[{i}]") for i, v in enumerate(a)]
        if a.dtype.kind in "OUS":
            return _jsonable(a.tolist(), nonfinite, where)
        raise TypeError(f"to_jsonable: {where} is an array of dtype {a.dtype}")
    if isinstance(x, dict):
        return {_json_key(k): _jsonable(v, nonfinite, f"{where}[{k!r}]") for k, v in x.items()}
    if isinstance(x, tuple) and hasattr(x, "_asdict"):  # NamedTuple
        fields: dict = cast(Any, x)._asdict()
        return {k: _jsonable(v, nonfinite, f"{where}.{k}") for k, v in fields.items()}
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return {
            f.name: _jsonable(getattr(x, f.name), nonfinite, f"{where}.{f.name}")
            for f in dataclasses.fields(x)
        }
    if isinstance(x, (list, tuple)):
        return [_jsonable(v, nonfinite, f"{where}[{i}]") for i, v in enumerate(x)]
    if isinstance(x, (set, frozenset)):
        items = [_jsonable(v, nonfinite, f"{where}{{...}}") for v in x]
        return sorted(items, key=repr)
    if isinstance(x, os.PathLike):
        return os.fspath(x)
    raise TypeError(f"to_jsonable: {where} has type {type(x).__name__}, not JSON-serialisable")


def write_json(path, obj, *, indent: int | None = 1, nonfinite: str = "null") -> None:
    """Write ``to_jsonable(obj)`` as JSON (UTF-8, trailing newline) atomically to ``path``.

    Args:
        path: the destination file; see :func:`write_atomic`.
        obj: anything :func:`to_jsonable` accepts.
        indent: ``json.dumps`` indentation (``None``: one line).
        nonfinite: how NaN/inf are written, see :func:`to_jsonable`.
    """
    text = json.dumps(to_jsonable(obj, nonfinite=nonfinite), indent=indent, allow_nan=False)

    def write(tmp: str) -> None:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text + "\n")

    write_atomic(path, write)


@jax.jit
def _contact_fields(contact, x):
    def gap(p):
        if not contact.obstacles:  # self-contact only: no obstacle gap
            return jnp.asarray(jnp.inf, p.dtype)
        return jnp.min(jnp.stack([ob.distance(p, contact.t) for ob in contact.obstacles]))

    return contact.forces(x), jax.vmap(gap)(x)


def contact_point_data(contact, x) -> dict[str, np.ndarray]:
    """The VTU point fields of a contact term (:class:`~jaxelastic.contact.Contact`) at
    positions ``x`` ``(n_nodes, dim)`` [m], with the obstacles at ``contact.t``:

    * ``contact_force`` ``(n_nodes, dim)`` [N]: the contact force on each node
      (``−∂Π_c/∂x``: barrier + friction; zero off the contact nodes and out of reach);
    * ``gap`` ``(n_nodes,)`` [m]: every node's signed distance to the nearest obstacle
      (> 0 outside; the barrier acts where ``gap < d̂``).
    """
    f, d = _contact_fields(contact, jnp.asarray(x, contact.dhat.dtype))
    return {"contact_force": np.asarray(f), "gap": np.asarray(d)}


def write_vtu(
    path,
    mesh: Mesh,
    x=None,
    *,
    point_data=None,
    cell_data=None,
    psi=None,
    params=None,
    plane: str = "strain",
    protect=(),
    overwrite: bool = True,
    contact=None,
    fields: tuple[dict, dict] | None = None,
    compression: str | None = "zlib",
) -> None:
    """Write one state of ``mesh`` as a VTU file (rest geometry + ``displacement``).

    Long because: the checks of every input (protected paths, shapes, NaN positions, name
    clashes) come before anything is written, each with its own message.

    Args:
        path: output ``.vtu`` file.
        x: ``(n_nodes, dim)`` current positions [length]; ``None`` means the rest shape.
            Stored as point data ``displacement = x − rest`` (3 components, also in 2D):
            use ParaView's *Warp By Vector* to see the deformed body.
        point_data, cell_data: extra arrays, leading axis ``n_nodes`` resp. ``n_cells``;
            ``(n_nodes, 2)`` point vectors are padded to 3 components.
        psi, params: when both are given, add the :func:`cell_fields` (J, green_strain,
            stress_P, cauchy_stress, von_mises, energy_density; in 2D stress_zz) as cell
            data and the recovered :func:`nodal_stress` (cauchy_stress_nodal,
            von_mises_nodal) as point data.
        plane: 2D only, ``"strain"`` (default) or ``"stress"``: the out-of-plane stress
            assumed by ``von_mises`` (see :func:`cell_fields`).
        protect: paths (or :class:`MeshData`) that must never be overwritten, e.g. the
            mesh file the data came from.
        overwrite: replace an existing ``path`` (default, what a time series needs).
        contact: a :class:`~jaxelastic.contact.Contact` (e.g. ``pot.contact``): add its
            :func:`contact_point_data` (``contact_force``, ``gap``) as point data.
        fields: ``(cells, points)`` as :func:`stress_fields` returns them for this ``x``,
            ``psi``, ``params`` and ``plane``: written instead of evaluating them again
            (only with ``psi`` and ``params``).
        compression: ``"zlib"`` (default, VTK's ``vtkZLibDataCompressor``), ``"lzma"``
            or None (raw base64 binary; measured at 146k tet4 cells with all stress
            fields: 0.13 s and 61 MB uncompressed vs 0.81 s and 39 MB with zlib).

    Raises:
        MeshIOError: ``path`` is protected, or exists and ``overwrite=False``.
        ValueError: wrong array shapes, NaN/inf positions ``x`` (nothing is written), a
            name clash with a built-in field, only one of ``psi``/``params``, ``fields``
            without them, or an unknown ``compression``.
    """
    import meshio

    path = os.fspath(path)
    for p in protect:
        p = p.source if isinstance(p, MeshData) else os.fspath(p)
        if _same_file(path, p):
            raise MeshIOError(f"refusing to write {path!r}: it is the protected input {p!r}")
    if not overwrite and os.path.exists(path):
        raise MeshIOError(f"refusing to write {path!r}: file exists (pass overwrite=True)")
    if (psi is None) != (params is None):
        raise ValueError("pass both psi and params to write stress and strain fields")
    if fields is not None and psi is None:
        raise ValueError("fields= are the stress fields of psi and params: pass them too")
    if compression not in ("zlib", "lzma", None):
        raise ValueError(f"compression must be 'zlib', 'lzma' or None, got {compression!r}")
    rest = np.asarray(mesh.points, dtype=np.float64)
    x = rest if x is None else np.asarray(x, dtype=np.float64)
    if x.shape != rest.shape:
        raise ValueError(f"x must have shape {rest.shape} like mesh.points, got {x.shape}")
    bad = ~np.isfinite(x).all(axis=1)
    if bad.any():
        idx = np.flatnonzero(bad)
        raise ValueError(
            f"write_vtu: x (positions) has NaN/inf coordinates at {idx.size} of {x.shape[0]} "
            f"node(s), e.g. nodes {idx[:5].tolist()}; refusing to write {path!r} (was the "
            "solve successful? check solution.status)"
        )
    pdata: dict[str, Any] = {"displacement": _pad3(x - rest)}
    cdata: dict[str, Any] = {}
    if fields is not None:
        cdata, nodal = dict(fields[0]), fields[1]
        pdata.update(nodal)
    elif psi is not None:
        cdata, nodal = stress_fields(psi, x, mesh, params, plane=plane)
        pdata.update(nodal)
    if contact is not None:
        cfields = contact_point_data(contact, x)
        pdata.update(contact_force=_pad3(cfields["contact_force"]), gap=cfields["gap"])
    for extra, out, n, what in (
        (point_data, pdata, mesh.n_nodes, "n_nodes"),
        (cell_data, cdata, mesh.n_cells, "n_cells"),
    ):
        for k, v in (extra or {}).items():
            v = np.asarray(v)
            if k in out:
                raise ValueError(f"data name {k!r} clashes with a built-in output field")
            if v.ndim == 0 or v.shape[0] != n:
                raise ValueError(f"{k!r} must have leading axis {what}={n}, got {v.shape}")
            out[k] = _pad3(v) if out is pdata else v
    m = meshio.Mesh(
        _pad3(rest),
        [(mesh.element_type.meshio_type, np.asarray(mesh.cells))],
        point_data=pdata,
        cell_data={k: [v] for k, v in cdata.items()},
    )
    # zlib dominates the write (0.68 of 0.81 s at 146k tet4 cells, 43 MB of float64
    # fields); its level does not help (level 1: 0.53 s, ratio 0.67; level 6: 0.68 s,
    # ratio 0.67), hence the choice is between zlib and no compression only
    write_atomic(path, lambda tmp: meshio.write(tmp, m, file_format="vtu", compression=compression))


def _time_labels(times: list[float]) -> list[str]:
    """``.pvd`` time stamps: 12 significant digits (``0.7``, not ``0.7000000000000001``),
    the exact ``repr`` for any times that 12 digits would not tell apart."""
    short = [f"{t:.12g}" for t in times]
    seen: dict[str, set[float]] = {}
    for t, s in zip(times, short, strict=True):
        seen.setdefault(s, set()).add(t)
    return [s if len(seen[s]) == 1 else repr(t) for t, s in zip(times, short, strict=True)]


class TimeSeriesWriter:
    """Write ``directory/basename_0000.vtu``, … and the ParaView collection ``basename.pvd``.

    The ``.pvd`` is rewritten (atomically) after every step, so a series interrupted by a
    crash is still readable; :meth:`close` (or leaving the ``with`` block) writes it once
    more and forbids further writes. The directory is created if needed; files of an
    earlier series with the same basename are overwritten.

    Args:
        directory: output directory.
        basename: file stem (no path separators).
        mesh: the rest mesh.
        psi, params: optional material, to add :func:`cell_fields` to every step.
        plane: 2D only, ``"strain"`` or ``"stress"`` (see :func:`cell_fields`).
        contact: optional :class:`~jaxelastic.contact.Contact`: every step gets its
            :func:`contact_point_data` with the obstacles at the step's time ``t``.
        compression: the VTU compression of every step (see :func:`write_vtu`).
    """

    def __init__(
        self,
        directory,
        basename: str,
        mesh: Mesh,
        psi=None,
        params=None,
        *,
        plane="strain",
        contact=None,
        compression: str | None = "zlib",
    ):
        if not basename or os.sep in basename or (os.altsep and os.altsep in basename):
            raise ValueError(f"basename must be a plain file stem, got {basename!r}")
        if (psi is None) != (params is None):
            raise ValueError("pass both psi and params to write stress and strain fields")
        self.directory = os.fspath(directory)
        if plane not in ("strain", "stress"):
            raise ValueError(f"plane must be 'strain' or 'stress', got {plane!r}")
        self.basename, self.mesh, self.psi, self.params = basename, mesh, psi, params
        self.plane = plane
        self.contact = contact
        self.compression = compression
        self.steps: list[tuple[float, str]] = []  # (time, file name relative to directory)
        self._closed = False
        os.makedirs(self.directory, exist_ok=True)

    @property
    def pvd_path(self) -> str:
        return os.path.join(self.directory, f"{self.basename}.pvd")

    def write(
        self, t, x, *, params=None, point_data=None, cell_data=None, fields=None, **extra
    ) -> str:
        """Write the state at time ``t`` [time] with positions ``x`` ``(n_nodes, dim)``.

        ``params`` overrides the writer's parameters for this step; ``fields``: the
        :func:`stress_fields` of this state, already evaluated (see :func:`write_vtu`);
        ``extra`` arrays are point data if their leading axis is ``n_nodes``, cell data if
        it is ``n_cells`` (use ``point_data=``/``cell_data=`` when both counts are equal).
        Returns the path.
        """
        if self._closed:
            raise ValueError("TimeSeriesWriter is closed")
        t = float(t)
        if not np.isfinite(t):
            raise ValueError(f"time must be finite, got {t}")
        point_data, cell_data = dict(point_data or {}), dict(cell_data or {})
        nn, nc = self.mesh.n_nodes, self.mesh.n_cells
        for k, v in extra.items():
            n = np.shape(v)[0] if np.ndim(v) else None
            if (n == nn) == (n == nc):
                raise ValueError(
                    f"cannot tell whether {k!r} of shape {np.shape(v)} is point or cell data "
                    f"(n_nodes={nn}, n_cells={nc}); pass it in point_data= or cell_data="
                )
            (point_data if n == nn else cell_data)[k] = v
        name = f"{self.basename}_{len(self.steps):04d}.vtu"
        path = os.path.join(self.directory, name)
        p = self.params if params is None else params
        write_vtu(
            path,
            self.mesh,
            x,
            point_data=point_data,
            cell_data=cell_data,
            psi=self.psi,
            params=p,
            plane=self.plane,
            contact=None if self.contact is None else self.contact.at_time(t),
            fields=fields,
            compression=self.compression,
        )
        self.steps.append((t, name))
        self._write_pvd()
        return path

    def _write_pvd(self) -> None:
        root = ET.Element("VTKFile", type="Collection", version="0.1", byte_order="LittleEndian")
        coll = ET.SubElement(root, "Collection")
        labels = _time_labels([t for t, _ in self.steps])
        for label, (_, name) in zip(labels, self.steps, strict=True):
            ET.SubElement(coll, "DataSet", timestep=label, group="", part="0", file=name)
        ET.indent(root)
        tree = ET.ElementTree(root)
        write_atomic(self.pvd_path, lambda tmp: tree.write(tmp, "utf-8", xml_declaration=True))

    def close(self) -> None:
        """Write the final ``.pvd`` collection; further writes raise."""
        if not self._closed:
            self._write_pvd()
            self._closed = True

    def __enter__(self) -> TimeSeriesWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
