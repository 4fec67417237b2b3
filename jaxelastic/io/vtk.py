"""VTU output of one state and ParaView time series.

:func:`write_vtu` writes one state (rest geometry + ``displacement``, optionally J, Green
strain, first Piola and Cauchy stress, von Mises stress and ψ per cell, and the recovered
nodal Cauchy and von Mises stress per node, :func:`~jaxelastic.postprocess.stress_fields`;
a contact term's forces and gaps, :func:`contact_point_data`); :class:`TimeSeriesWriter`
writes ``basename_0000.vtu``… and a ParaView ``.pvd`` collection.

Every file is written atomically (:func:`~jaxelastic.io.files.write_atomic`). Outputs are
overwritten by default (a time series rewrites its own files); pass ``overwrite=False`` to
refuse, and ``protect=[...]`` (paths or :class:`~jaxelastic.io.read.MeshData`) to refuse
ever writing over an input mesh.

meshio is imported lazily; importing this module has no side effects.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..mesh import Mesh
from ..postprocess import stress_fields
from .files import write_atomic
from .read import MeshData, MeshIOError

__all__ = ["write_vtu", "TimeSeriesWriter", "contact_point_data", "time_labels"]


def _pad3(a: np.ndarray) -> np.ndarray:
    """Pad ``(n, 2)`` vectors with a zero z component (ParaView wants 3-vectors)."""
    return np.pad(a, ((0, 0), (0, 1))) if a.ndim == 2 and a.shape[1] == 2 else a


def _same_file(a: str, b: str) -> bool:
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    return os.path.exists(a) and os.path.exists(b) and os.path.samefile(a, b)


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
        psi, params: when both are given, add the
            :func:`~jaxelastic.postprocess.cell_fields` (J, green_strain, stress_P,
            cauchy_stress, von_mises, energy_density; in 2D stress_zz) as cell data and the
            recovered :func:`~jaxelastic.postprocess.nodal_stress` (cauchy_stress_nodal,
            von_mises_nodal) as point data.
        plane: 2D only, ``"strain"`` (default) or ``"stress"``: the out-of-plane stress
            assumed by ``von_mises`` (see :func:`~jaxelastic.postprocess.cell_fields`).
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


def time_labels(times: list[float]) -> list[str]:
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
        psi, params: optional material, to add
            :func:`~jaxelastic.postprocess.cell_fields` to every step.
        plane: 2D only, ``"strain"`` or ``"stress"`` (see
            :func:`~jaxelastic.postprocess.cell_fields`).
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
        labels = time_labels([t for t, _ in self.steps])
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
