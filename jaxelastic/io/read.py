"""Reading meshes with meshio: the validated mesh and its named point, cell and facet sets.

:func:`read_mesh` reads any meshio-readable file (Gmsh ``.msh`` v2/v4 ascii/binary, VTU,
XDMF, Abaqus ``.inp``, …) holding linear or quadratic triangles (2D: ``triangle``,
``triangle6``) or tetrahedra (3D: ``tetra``, ``tetra10``) and returns a :class:`MeshData`:
the validated :class:`~jaxelastic.mesh.Mesh` plus named point, cell and boundary-facet sets
taken from Gmsh physical groups and meshio point/cell sets.

meshio is imported lazily; importing this module has no side effects.
"""

from __future__ import annotations

import dataclasses
import os
import re

import numpy as np

from ..mesh import Mesh, MeshError, boundary_facets, from_arrays

__all__ = ["MeshIOError", "MeshData", "read_mesh"]

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
