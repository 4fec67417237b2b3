"""Test configuration: float64 everywhere, strict rank and dtype promotion (as equinox
does), and 4 host CPU devices for the sharding tests (tests/test_sharding.py).

``--xla_force_host_platform_device_count=4`` must be in ``XLA_FLAGS`` before jax is
imported. It changes nothing for single-device code (every array still lives on device 0
unless placed elsewhere); measured on twist n = 8 with matrix-free CG and with the direct
solver, cold and warm, with and without the flag: no slowdown (loaded 2-core machine).
"""

import os

_FLAG = "--xla_force_host_platform_device_count"
if _FLAG not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + f" {_FLAG}=4").strip()

# The CLI's persistent compilation cache (jaxelastic.cli.cache_dir) goes to one temporary
# directory per test session (set by the controller, inherited by the xdist workers and by
# every subprocess), never into ~/.cache: in-process CLI tests that do not pass --no-cache
# would otherwise enable the user's cache for the rest of their worker, and the run time
# would depend on what earlier runs left there.
if "JAXELASTIC_CACHE_DIR" not in os.environ:
    import atexit
    import shutil
    import tempfile

    _CACHE = tempfile.mkdtemp(prefix="jaxelastic-test-cache-")
    os.environ["JAXELASTIC_CACHE_DIR"] = _CACHE
    atexit.register(shutil.rmtree, _CACHE, ignore_errors=True)

import jax  # noqa: E402  (after XLA_FLAGS)

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")

# One persistent compilation cache per test session, shared by the xdist workers (the
# directory above): many tests compile the same programs (the same Newton pieces on meshes
# of the same shape, from different closures), and a worker takes what the other already
# compiled. Measured on tests/test_dynamics.py + tests/test_implicit.py in one process,
# cold cache: 91.3 -> 81.9 CPU s. Tests that count compilations switch it off
# (jax_enable_compilation_cache); the in-process CLI tests set the same directory.
jax.config.update("jax_compilation_cache_dir", os.environ["JAXELASTIC_CACHE_DIR"])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
# No JAX size limit (as in the library's default cache, jaxelastic.cache): with one, JAX
# locks the directory and, on every write, reads the size and access time of every entry
# to decide evictions — with the several thousand entries of a test session that took the
# default tier from 7.0 to 9.9 minutes (system time 106 -> 199 s). Without the lock a
# worker may read an entry the other is still writing; the entry is compressed, so the
# read fails in decompression, JAX warns and compiles instead.


def pytest_collection_modifyitems(config, items):
    """Tests marked ``slow`` run only when the ``-m`` expression names ``slow``: the second
    tier ``pytest -m extended`` leaves out the tests marked both ``extended`` and ``slow``
    (``-m slow`` or ``-m "extended or slow"`` runs them)."""
    if "slow" in (config.getoption("markexpr") or ""):
        return
    slow = [item for item in items if item.get_closest_marker("slow") is not None]
    if slow:
        config.hook.pytest_deselected(items=slow)
        items[:] = [item for item in items if item.get_closest_marker("slow") is None]
