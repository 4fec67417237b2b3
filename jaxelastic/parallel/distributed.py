"""Many processes, one problem: starting JAX's multi-process runtime from the environment.

A sharded solve (:func:`jaxelastic.shard`) runs unchanged when its devices belong to
several processes (one per GPU, or several CPU processes on one or many hosts): every
process runs the *same* script, builds the *same* problem, and JAX's SPMD runtime places
each shard on the device that owns it and exchanges the halos over the network. The only
extra step is :func:`initialize_from_env`, called once at the top of the script before
anything else touches JAX. It reads where it runs from the environment:

* ``JAX_COORDINATOR_ADDRESS`` (``host:port`` of process 0), ``JAX_NUM_PROCESSES`` and
  ``JAX_PROCESS_ID`` (all three, or none) — any launcher, e.g. two shells on localhost;
* else a SLURM job step (``srun``: ``SLURM_JOB_ID``, ``SLURM_STEP_NODELIST``,
  ``SLURM_NTASKS``, ``SLURM_PROCID``, ``SLURM_LOCALID``): JAX's own SLURM detection picks
  the coordinator (the first node of the step, a port derived from the job id) and the
  GPU of the task's local rank (or the one GPU a task sees under ``--gpus-per-task=1``);
* else nothing: one process, and the call does nothing.

On CPU the processes talk through gloo (``jax_cpu_collectives_implementation``); on GPU
through NCCL (JAX's default). Arrays that span processes cannot be read with
``np.asarray``: :func:`host_array` gathers one onto every process (used by
``Partition.to_natural``).

References: JAX documentation, "Distributed arrays and automatic parallelization" and
"Running JAX on multi-host/multi-process environments" (``jax.distributed``).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping

import jax
import numpy as np

__all__ = [
    "DistributedError",
    "Environment",
    "ProcessInfo",
    "environment",
    "initialize_from_env",
    "host_array",
    "is_multiprocess",
    "JAX_VARS",
    "SLURM_VARS",
]

JAX_VARS = ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID")
"""The three variables of an explicit launch (all three, or none)."""
SLURM_VARS = (
    "SLURM_JOB_ID",
    "SLURM_STEP_NODELIST",
    "SLURM_NTASKS",
    "SLURM_PROCID",
    "SLURM_LOCALID",
)
"""The variables of a SLURM job step that JAX's SLURM detection needs."""


class DistributedError(RuntimeError):
    """The multi-process environment is incomplete or inconsistent, or JAX was already
    started (the message says which variable, and what to do)."""


@dataclasses.dataclass(frozen=True)
class Environment:
    """Where this process sits, as read from the environment (nothing started yet).

    Attributes:
        source: ``"jax"`` (the ``JAX_*`` variables), ``"slurm"`` or ``"single"``.
        num_processes, process_id: this job's size and this process's rank (0-based).
        coordinator_address: ``host:port`` of process 0, or None (SLURM: chosen by JAX).
    """

    source: str
    num_processes: int
    process_id: int
    coordinator_address: str | None = None

    @property
    def multiprocess(self) -> bool:
        return self.num_processes > 1


@dataclasses.dataclass(frozen=True)
class ProcessInfo:
    """The started runtime, as :func:`initialize_from_env` returns it.

    Attributes:
        source: as in :class:`Environment`; process_id, num_processes: rank and size.
        local_devices: the devices this process drives; n_devices: all devices of the job
            (``len(jax.devices())``), which a sharded solve may use.
        platform: ``"cpu"``, ``"gpu"``, ...
    """

    source: str
    process_id: int
    num_processes: int
    local_devices: tuple
    n_devices: int
    platform: str


def _int_var(env: Mapping[str, str], name: str) -> int:
    raw = env[name]
    try:
        return int(raw)
    except ValueError:
        raise DistributedError(f"{name} must be an integer, got {raw!r}") from None


def environment(env: Mapping[str, str] | None = None) -> Environment:
    """Read the multi-process setting from ``env`` (default ``os.environ``); starts nothing.

    Raises:
        DistributedError: only some of :data:`JAX_VARS` are set, a count or rank is not an
            integer, the rank is outside ``[0, num_processes)``, or the coordinator address
            has no ``:port``.
    """
    env = os.environ if env is None else env
    have = [v for v in JAX_VARS if env.get(v)]
    if have and len(have) < len(JAX_VARS):
        missing = [v for v in JAX_VARS if v not in have]
        # JAX_COORDINATOR_ADDRESS alone may accompany a SLURM step (it overrides the
        # coordinator JAX would pick); anything else partial is a mistake
        if not (have == ["JAX_COORDINATOR_ADDRESS"] and all(v in env for v in SLURM_VARS)):
            raise DistributedError(
                f"{', '.join(have)} set but {', '.join(missing)} not: a multi-process run "
                f"needs all of {', '.join(JAX_VARS)} (or a SLURM job step, srun), or none "
                "of them for one process"
            )
    if len(have) == len(JAX_VARS):
        source, n, rank = "jax", _int_var(env, JAX_VARS[1]), _int_var(env, JAX_VARS[2])
        addr: str | None = env[JAX_VARS[0]]
    elif all(v in env for v in SLURM_VARS):
        source, n, rank = "slurm", _int_var(env, "SLURM_NTASKS"), _int_var(env, "SLURM_PROCID")
        addr = env.get(JAX_VARS[0]) or None
    else:
        return Environment("single", 1, 0)
    if n < 1 or not 0 <= rank < n:
        raise DistributedError(
            f"process id {rank} is not in [0, {n}) ({source} environment): each of the "
            f"{n} processes needs its own id 0 ... {n - 1}"
        )
    if addr is not None and (":" not in addr or not addr.rsplit(":", 1)[1].isdigit()):
        raise DistributedError(
            f"JAX_COORDINATOR_ADDRESS must be host:port (process 0's host and a free port, "
            f"the same on every process), got {addr!r}"
        )
    return Environment(source, n, rank, addr)


def initialize_from_env(
    env: Mapping[str, str] | None = None,
    *,
    cpu_collectives: str = "gloo",
    timeout_s: int = 300,
) -> ProcessInfo:
    """Start JAX's multi-process runtime from the environment (see the module docstring);
    one process: nothing is started. Call it first, before any JAX computation.

    On CPU, sets ``jax_cpu_collectives_implementation`` to ``cpu_collectives`` so that the
    processes can exchange data (without it, a computation over several processes' CPU
    devices fails). The number of CPU devices per process is JAX's ``jax_num_cpu_devices``
    (environment variable ``JAX_NUM_CPU_DEVICES``, default 1).

    Args:
        env: the environment to read (default ``os.environ``).
        cpu_collectives: ``"gloo"`` (default) or ``"mpi"``.
        timeout_s: how long to wait for every process to connect [s]; a process that never
            comes makes the others fail with JAX's error after this, never hang forever.
    Returns:
        :class:`ProcessInfo`.
    Raises:
        DistributedError: an incomplete environment (:func:`environment`), or JAX already
            running in this process (call this before anything else uses JAX).
    """
    where = environment(env)
    if not where.multiprocess:
        devs = jax.local_devices()
        return ProcessInfo("single", 0, 1, tuple(devs), len(jax.devices()), devs[0].platform)
    if jax.distributed.is_initialized():
        raise DistributedError("jax.distributed is already initialized in this process")
    jax.config.update("jax_cpu_collectives_implementation", cpu_collectives)
    kw: dict = {"initialization_timeout": int(timeout_s)}
    if where.source == "jax":
        kw.update(num_processes=where.num_processes, process_id=where.process_id)
    if where.coordinator_address is not None:
        kw.update(coordinator_address=where.coordinator_address)
    if where.source == "slurm" and not (env or os.environ).get("JAX_LOCAL_DEVICE_IDS"):
        # srun --gpus-per-task=1 leaves one visible GPU, number 0 (JAX would pick the one
        # numbered SLURM_LOCALID, which exists only when each task sees the node's GPUs)
        visible = (env or os.environ).get("CUDA_VISIBLE_DEVICES", "")
        if visible and len(visible.split(",")) == 1:
            kw.update(local_device_ids=[0])
    try:
        jax.distributed.initialize(**kw)
    except RuntimeError as e:
        if "before" in str(e) and "computation" in str(e):
            raise DistributedError(
                "JAX was already used in this process (a computation ran, or devices were "
                "listed) before initialize_from_env(): call it first, right after the imports"
            ) from None
        raise
    devs = jax.local_devices()
    return ProcessInfo(
        where.source,
        jax.process_index(),
        jax.process_count(),
        tuple(devs),
        len(jax.devices()),
        devs[0].platform,
    )


def is_multiprocess() -> bool:
    """Whether this JAX runtime spans several processes (``jax.process_count() > 1``)."""
    return jax.process_count() > 1


def host_array(a) -> np.ndarray:
    """A (possibly process-spanning) array as one NumPy array, the same on every process.

    An array whose shards all live in this process (one process, or a replicated array)
    is read directly; one spread over several processes is gathered with
    ``jax.experimental.multihost_utils.process_allgather`` (a collective: every process
    must call this for the same array, in the same order).

    Args:
        a: a ``jax.Array`` or anything ``np.asarray`` takes.
    Returns:
        the global array ``a.shape``.
    """
    if isinstance(a, jax.Array) and not (a.is_fully_addressable or a.is_fully_replicated):
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(a, tiled=True))
    return np.asarray(a)
