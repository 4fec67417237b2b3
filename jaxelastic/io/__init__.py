"""Files in and out: meshes read with meshio, VTU / ParaView output, atomic JSON.

* :mod:`~jaxelastic.io.read`: :func:`read_mesh` (Gmsh, VTU, XDMF, … with named point, cell
  and facet sets) and :class:`MeshData`;
* :mod:`~jaxelastic.io.vtk`: :func:`write_vtu` (one state, with stress fields and contact
  data), :class:`TimeSeriesWriter` (``.vtu`` steps and a ``.pvd`` collection);
* :mod:`~jaxelastic.io.files`: :func:`write_atomic`, the one atomic writer every output goes
  through, :func:`to_jsonable` and :func:`write_json`.

The stresses written with a state are computed by :mod:`jaxelastic.postprocess`.
"""

from ..deprecation import moved_attributes
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

# stress recovery moved to jaxelastic.postprocess; the old names still resolve
__getattr__ = moved_attributes(
    __name__,
    "jaxelastic.io",
    {
        n: (f"jaxelastic.postprocess:{n}", f"jaxelastic.postprocess.{n}")
        for n in ("cell_fields", "nodal_stress", "stress_fields")
    },
)
