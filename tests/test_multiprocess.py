"""Across processes: :mod:`jaxelastic.parallel.distributed` and a 2-process sharded twist.

Fast: reading the environment (``JAX_*`` variables, a SLURM step, incomplete or
inconsistent settings refused with the variable named), the one-process no-op and
:func:`~jaxelastic.parallel.distributed.host_array`.

Slow: ``scripts/distributed_twist.py`` started as two processes on localhost (one CPU
device each, gloo collectives, a free port), solving the twist sharded across them; the
answer must equal this process's unsharded solve to 1e-12 relative. The processes run
under a deadline: on a failure or a timeout both are killed and the test fails with the
tail of each one's output (it never hangs).
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic as je
from jaxelastic import verification as benchmarks
from jaxelastic.parallel.distributed import (
    DistributedError,
    environment,
    host_array,
    initialize_from_env,
)

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "distributed_twist.py"
N = 4  # twist cells per edge: 384 tets, 375 dofs
DEADLINE_S = 420  # both processes: compile (twice, on a loaded 2-core machine) and solve

SLURM = dict(
    SLURM_JOB_ID="42",
    SLURM_STEP_NODELIST="node[01-02]",
    SLURM_NTASKS="8",
    SLURM_PROCID="3",
    SLURM_LOCALID="3",
)


# ---------------------------------------------------------------------------------------
# the environment (fast)
# ---------------------------------------------------------------------------------------


def test_environment_single_process_by_default():
    e = environment({})
    assert (e.source, e.num_processes, e.process_id, e.multiprocess) == ("single", 1, 0, False)


def test_environment_jax_variables():
    env = dict(JAX_COORDINATOR_ADDRESS="10.0.0.1:1234", JAX_NUM_PROCESSES="4", JAX_PROCESS_ID="2")
    e = environment(env)
    assert (e.source, e.num_processes, e.process_id) == ("jax", 4, 2)
    assert e.coordinator_address == "10.0.0.1:1234" and e.multiprocess


def test_environment_slurm_step():
    e = environment(SLURM)
    assert (e.source, e.num_processes, e.process_id, e.coordinator_address) == (
        "slurm",
        8,
        3,
        None,
    )
    # an explicit coordinator may accompany a SLURM step
    e = environment(dict(SLURM, JAX_COORDINATOR_ADDRESS="node01:5000"))
    assert (e.source, e.coordinator_address) == ("slurm", "node01:5000")


@pytest.mark.parametrize(
    "env, words",
    [
        (dict(JAX_NUM_PROCESSES="2"), ["JAX_NUM_PROCESSES set", "JAX_PROCESS_ID"]),
        (
            dict(JAX_COORDINATOR_ADDRESS="h:1", JAX_NUM_PROCESSES="2", JAX_PROCESS_ID="2"),
            ["process id 2", "[0, 2)"],
        ),
        (
            dict(JAX_COORDINATOR_ADDRESS="h:1", JAX_NUM_PROCESSES="two", JAX_PROCESS_ID="0"),
            ["JAX_NUM_PROCESSES must be an integer", "'two'"],
        ),
        (
            dict(JAX_COORDINATOR_ADDRESS="localhost", JAX_NUM_PROCESSES="2", JAX_PROCESS_ID="0"),
            ["host:port", "'localhost'"],
        ),
    ],
)
def test_environment_refuses_incomplete_or_wrong_settings(env, words):
    with pytest.raises(DistributedError) as e:
        environment(env)
    for w in words:
        assert w in str(e.value)


def test_initialize_from_env_is_a_no_op_for_one_process():
    info = initialize_from_env({})
    assert (info.source, info.process_id, info.num_processes) == ("single", 0, 1)
    assert info.n_devices == len(jax.devices()) and not jax.distributed.is_initialized()


def test_host_array_reads_a_local_array():
    a = jnp.arange(6.0).reshape(3, 2)
    np.testing.assert_array_equal(host_array(a), np.asarray(a))
    assert isinstance(host_array([1, 2]), np.ndarray)


# ---------------------------------------------------------------------------------------
# two processes on localhost (extended tier; 89 s on a loaded 2-core machine, 2026-12-04)
# ---------------------------------------------------------------------------------------


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _tail(path: Path, n: int = 3000) -> str:
    text = path.read_text(errors="replace") if path.exists() else ""
    lines = [ln for ln in text.splitlines() if not ln.startswith(("W1", "I1", "W0", "I0"))]
    return "\n".join(lines)[-n:]


def _run_processes(n_proc: int, out: Path, logs: Path) -> None:
    """Start ``n_proc`` processes of the script; wait for all under the deadline; on a
    failure or timeout kill the rest and fail with their output."""
    port = _free_port()
    base = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_", "SLURM_"))}
    base.pop("XLA_FLAGS", None)  # one CPU device per process (not the tests' 4)
    base.update(JAX_PLATFORMS="cpu", JAX_NUM_CPU_DEVICES="1", PYTHONUNBUFFERED="1")
    procs = []
    for i in range(n_proc):
        env = dict(
            base,
            JAX_COORDINATOR_ADDRESS=f"127.0.0.1:{port}",
            JAX_NUM_PROCESSES=str(n_proc),
            JAX_PROCESS_ID=str(i),
        )
        log = logs / f"process_{i}.log"
        cmd = [sys.executable, str(SCRIPT), "--n", str(N), "--out", str(out), "--timeout", "120"]
        with open(log, "w") as f:
            procs.append((subprocess.Popen(cmd, env=env, stdout=f, stderr=subprocess.STDOUT), log))
    deadline = time.monotonic() + DEADLINE_S
    failed = None
    try:
        while time.monotonic() < deadline:
            codes = [p.poll() for p, _ in procs]
            if any(c not in (None, 0) for c in codes):
                failed = "a process failed"
                break
            if all(c == 0 for c in codes):
                return
            time.sleep(0.5)
        else:
            failed = f"timed out after {DEADLINE_S} s"
    finally:
        for p, _ in procs:
            if p.poll() is None:
                p.kill()
                p.wait(timeout=30)
    report = "\n".join(
        f"--- process {i} (exit {p.returncode}):\n{_tail(log)}" for i, (p, log) in enumerate(procs)
    )
    pytest.fail(f"2-process twist: {failed}\n{report}")


@pytest.mark.extended
def test_two_processes_solve_the_twist_like_one(tmp_path):
    out, logs = tmp_path / "out", tmp_path
    _run_processes(2, out, logs)
    res = json.loads((out / "result.json").read_text())
    assert res["processes"] == 2 and len(res["devices"]) == 2 and res["sharded"]
    assert res["partition"]["shards"] == 2 and min(res["partition"]["cells"]) > 0
    x_mp = np.load(out / "x.npy")
    b = benchmarks.twist(N)
    solver = je.Newton(linear=je.CG(), rtol=1e-10)
    x_1 = np.asarray(je.solve(b.pot, b.bc, solver=solver).x)
    u_1 = x_1 - np.asarray(b.mesh.points)
    err = np.abs(x_mp - x_1).max() / np.abs(u_1).max()
    assert err <= 1e-12, f"2 processes vs 1: relative difference {err:.2e}"
