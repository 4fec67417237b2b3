"""Files in and out: meshes read with meshio, VTU / ParaView output, atomic JSON.

* :mod:`~jaxelastic.io.read`: :func:`read_mesh` (Gmsh, VTU, XDMF, … with named point, cell
  and facet sets) and :class:`MeshData`;
* :mod:`~jaxelastic.io.vtk`: :func:`write_vtu` (one state, with stress fields and contact
  data), :class:`TimeSeriesWriter` (``.vtu`` steps and a ``.pvd`` collection);
* :mod:`~jaxelastic.io.files`: :func:`write_atomic`, the one atomic writer every output goes
  through, :func:`to_jsonable` and :func:`write_json`.

The stresses written with a state are computed by :mod:`jaxelastic.postprocess`.
"""

from . import files as files
from . import read as read
from . import vtk as vtk
from .files import to_jsonable as to_jsonable
from .files import write_atomic as write_atomic
from .files import write_json as write_json
from .read import MeshData as MeshData
from .read import MeshIOError as MeshIOError
from .read import read_mesh as read_mesh
from .vtk import TimeSeriesWriter as TimeSeriesWriter
from .vtk import contact_point_data as contact_point_data
from .vtk import write_vtu as write_vtu

__all__ = [
    "files",
    "read",
    "vtk",
    "to_jsonable",
    "write_atomic",
    "write_json",
    "MeshData",
    "MeshIOError",
    "read_mesh",
    "TimeSeriesWriter",
    "contact_point_data",
    "write_vtu",
]

_MOVED = ("cell_fields", "nodal_stress", "stress_fields")
"""Stress recovery moved to :mod:`jaxelastic.postprocess`; the old names still resolve."""


def __getattr__(name: str):
    """``jaxelastic.io.cell_fields`` and friends, with a DeprecationWarning."""
    if name in _MOVED:
        import warnings

        from .. import postprocess

        warnings.warn(
            f"jaxelastic.io.{name} is deprecated and will be removed: use "
            f"jaxelastic.postprocess.{name}",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(postprocess, name)
    raise AttributeError(f"module 'jaxelastic.io' has no attribute {name!r}")
