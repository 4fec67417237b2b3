"""One problem over many devices and processes: partition, halo exchange, sharding.

* :mod:`~jaxelastic.parallel.partition`: cells into parts, node ownership and the padded
  global numbering (host, NumPy);
* :mod:`~jaxelastic.parallel.halo`: the per-shard local tables and the ghost-node exchange
  (:class:`Halo`);
* :mod:`~jaxelastic.parallel.sharding`: :func:`shard` a potential and its Dirichlet data
  over a device mesh;
* :mod:`~jaxelastic.parallel.distributed`: JAX's multi-process runtime from the environment
  (:func:`initialize_from_env`, :func:`host_array`);
* :mod:`~jaxelastic.parallel.traffic`: the communication volume of a sharded problem in
  compiled HLO (it compiles solver kernels, so it is imported on its own, not here).
"""

from . import distributed as distributed
from . import halo as halo
from . import partition as partition
from . import sharding as sharding
from .distributed import JAX_VARS as JAX_VARS
from .distributed import SLURM_VARS as SLURM_VARS
from .distributed import DistributedError as DistributedError
from .distributed import Environment as Environment
from .distributed import ProcessInfo as ProcessInfo
from .distributed import environment as environment
from .distributed import host_array as host_array
from .distributed import initialize_from_env as initialize_from_env
from .distributed import is_multiprocess as is_multiprocess
from .halo import Halo as Halo
from .halo import build_halo as build_halo
from .halo import node_slots as node_slots
from .partition import METHODS as METHODS
from .partition import morton_order as morton_order
from .partition import partition_cells as partition_cells
from .partition import partition_mesh as partition_mesh
from .sharding import AXIS as AXIS
from .sharding import Partition as Partition
from .sharding import collective_bytes as collective_bytes
from .sharding import device_mesh as device_mesh
from .sharding import is_sharded as is_sharded
from .sharding import shard as shard

__all__ = [
    "distributed",
    "halo",
    "partition",
    "sharding",
    "DistributedError",
    "Environment",
    "ProcessInfo",
    "environment",
    "initialize_from_env",
    "host_array",
    "is_multiprocess",
    "JAX_VARS",
    "SLURM_VARS",
    "Halo",
    "build_halo",
    "node_slots",
    "partition_cells",
    "partition_mesh",
    "METHODS",
    "morton_order",
    "shard",
    "Partition",
    "device_mesh",
    "AXIS",
    "is_sharded",
    "collective_bytes",
]
