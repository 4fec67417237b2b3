"""Give freed heap memory back to the operating system between host Newton steps.

glibc ``malloc`` keeps freed blocks of its heaps (one arena per thread: XLA's CPU thread
pool, the host callbacks, NumPy) for reuse instead of returning them, and blocks freed in
one arena cannot serve another thread's request. Between the compiled pieces of a host
Newton step (the Python loop of :func:`jaxelastic.solvers.newton.minimize`) the element Hessians,
XLA temporaries and the AMG refresh's sparse products are freed and allocated again, and
the process's resident set creeps up by hundreds of MB that hold nothing live (measured
at 146k tets: steady RSS 1.1–1.3 GB with 0.65 GB live, peak 1.36–1.51 GB; with the free
memory trimmed after each step, see ``docs/guide/linear-solvers.md``).

:func:`release_free_memory` calls glibc's ``malloc_trim(0)``, which returns the free
pages of every arena to the kernel; it frees nothing that is live and does not change
any result. Elsewhere (musl, macOS, Windows) it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools

__all__ = ["release_free_memory", "map_large_blocks"]


@functools.cache
def _libc(name: str, argtypes: tuple, restype):
    """The C library's function ``name`` with its signature, or ``None`` where the C
    library (or the function: glibc only) is missing."""
    lib = ctypes.util.find_library("c")
    if lib is None:
        return None
    try:
        fn = getattr(ctypes.CDLL(lib), name)
    except (OSError, AttributeError):
        return None
    fn.argtypes = list(argtypes)
    fn.restype = restype
    return fn


def _malloc_trim():
    """glibc's ``malloc_trim(size_t pad) -> int`` or ``None``."""
    return _libc("malloc_trim", (ctypes.c_size_t,), ctypes.c_int)


def release_free_memory() -> bool:
    """Return the heap's free pages to the operating system (glibc ``malloc_trim(0)``).

    Returns: whether anything was released (``False`` also where unsupported).
    """
    fn = _malloc_trim()
    return bool(fn(0)) if fn is not None else False


M_MMAP_THRESHOLD = -3  # glibc mallopt parameter (malloc.h)


def _mallopt():
    """glibc's ``mallopt(int param, int value) -> int`` or ``None``."""
    return _libc("mallopt", (ctypes.c_int, ctypes.c_int), ctypes.c_int)


def map_large_blocks(threshold: int = 8 << 20) -> bool:
    """Serve every ``malloc`` of ``threshold`` bytes or more by its own ``mmap`` from now
    on, for the whole process (glibc ``mallopt(M_MMAP_THRESHOLD, threshold)``).

    glibc raises its mmap threshold each time a mapped block is freed (up to 32 MB), so
    after the first few element-Hessian-sized temporaries every block below 32 MB comes
    from the arenas and stays resident once freed; a fixed threshold returns each freed
    large block to the kernel at once. A process-wide setting: the command-line entry
    point and the solver benchmark call it; a library import does not. Default 8 MiB: at
    511k tets 1 MiB saved 126 MiB more but made the warm twist solve about 4% slower
    (fresh page faults on every XLA temporary of 1–8 MB).

    Returns: whether the setting was accepted (``False`` where unsupported).
    """
    fn = _mallopt()
    return bool(fn(M_MMAP_THRESHOLD, int(threshold))) if fn is not None else False
