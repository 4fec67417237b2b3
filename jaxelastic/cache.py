"""JAX's persistent compilation cache, on by default for the library and the CLI.

Compiling the pieces of a solve takes seconds; the arithmetic of a small one takes
milliseconds. With the persistent cache a second process loads the compiled executables
from disk instead (tracing and lowering still run: they make the cache key).

* **When**: lazily, at the library's first solve (:func:`jaxelastic.solve`, hence also
  dynamics, fits and scenes) or mesh construction (:func:`jaxelastic.box`,
  :func:`jaxelastic.rectangle`) — never at import, and never if the user has configured a
  cache already (``jax_compilation_cache_dir`` set, e.g. by ``JAX_COMPILATION_CACHE_DIR``
  or ``jax.config.update``) or turned JAX's cache off
  (``jax_enable_compilation_cache = False``); the CLI calls :func:`enable_persistent_cache`
  itself (``--no-cache`` turns it off there).
* **Where**: ``$JAXELASTIC_CACHE_DIR``, default ``$XDG_CACHE_HOME/jaxelastic/jax`` or
  ``~/.cache/jaxelastic/jax`` (:func:`cache_dir`).
* **How much**: at most ``$JAXELASTIC_CACHE_MAX_MB`` megabytes (default
  :data:`DEFAULT_MAX_MB`): once per process, when the cache is enabled, the least recently
  written entries beyond it are deleted (:func:`prune_cache`). A scene shape takes a few
  MB. JAX's own size limit is not used: with one, JAX reads the size and access time of
  every entry at every write to decide evictions (about 40 µs per entry: 0.2 s per
  compiled program in a cache of 5,000 entries, measured on the 2-core test machine).
* **Off**: ``JAXELASTIC_CACHE=0`` (also ``off``, ``false``, ``no``).
* **Several processes at once**: JAX writes an entry with a plain file write and without a
  lock, so a process may read an entry another one is half-way through writing; the entry
  is compressed, its decompression fails, JAX warns ("Error reading persistent compilation
  cache entry") and compiles instead. An entry pruned while another process reads the
  directory is a cache miss there.
* **Never cached by JAX**: executables holding a host callback (``jax.pure_callback``), see
  ``docs/guide/compilation.md``.
"""

from __future__ import annotations

import os
import threading

__all__ = [
    "DEFAULT_MAX_MB",
    "cache_dir",
    "cache_max_bytes",
    "enable_persistent_cache",
    "ensure_persistent_cache",
    "persistent_cache_dir",
    "prune_cache",
]

DEFAULT_MAX_MB = 2048
"""Default size limit of the cache directory [MB] (``$JAXELASTIC_CACHE_MAX_MB``)."""

_OFF = ("0", "off", "false", "no")
_lock = threading.Lock()
_checked = False


def cache_dir() -> str:
    """Directory of the persistent compilation cache: ``$JAXELASTIC_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/jaxelastic/jax``, else ``~/.cache/jaxelastic/jax``."""
    env = os.environ.get("JAXELASTIC_CACHE_DIR")
    if env:
        return os.path.abspath(os.path.expanduser(env))
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "jaxelastic", "jax")


def cache_max_bytes() -> int:
    """Size limit of the cache [bytes]: ``$JAXELASTIC_CACHE_MAX_MB`` (default
    :data:`DEFAULT_MAX_MB`) megabytes."""
    text = os.environ.get("JAXELASTIC_CACHE_MAX_MB", "").strip()
    try:
        mb = float(text) if text else float(DEFAULT_MAX_MB)
    except ValueError:
        raise ValueError(
            f"JAXELASTIC_CACHE_MAX_MB must be a number of megabytes, got {text!r}"
        ) from None
    if not mb > 0:
        raise ValueError(f"JAXELASTIC_CACHE_MAX_MB must be > 0, got {text!r}")
    return int(mb * 2**20)


def persistent_cache_dir() -> str | None:
    """The directory JAX's persistent compilation cache uses now, or None if it is off."""
    import jax

    cfg = jax.config
    if not cfg.jax_enable_compilation_cache:  # pyright: ignore[reportAttributeAccessIssue]
        return None
    return cfg.jax_compilation_cache_dir  # pyright: ignore[reportAttributeAccessIssue]


def enable_persistent_cache(path: str | None = None, max_bytes: int | None = None) -> str:
    """Switch JAX's persistent compilation cache on in ``path`` (default :func:`cache_dir`)
    for every executable, after pruning it to ``max_bytes`` (default
    :func:`cache_max_bytes`, :func:`prune_cache`). Returns the directory.

    Raises:
        OSError: the directory cannot be created.
    """
    import jax

    path = cache_dir() if path is None else os.path.abspath(os.path.expanduser(path))
    os.makedirs(path, exist_ok=True)
    prune_cache(path, cache_max_bytes() if max_bytes is None else int(max_bytes))
    jax.config.update("jax_compilation_cache_dir", path)
    # every executable: the small ones (op-by-op, outputs) add up to seconds per run
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


def prune_cache(path: str, max_bytes: int) -> int:
    """Delete the least recently written entries of the cache directory ``path`` (JAX's
    ``<key>-cache`` files, with their ``<key>-atime`` files) until the entries take at most
    ``max_bytes``. One scan of the directory; files that vanish or cannot be removed
    meanwhile (another process) are skipped. Returns the number of entries deleted."""
    entries = []
    try:
        with os.scandir(path) as it:
            for e in it:
                if e.name.endswith("-cache"):
                    try:
                        st = e.stat()
                    except OSError:
                        continue
                    entries.append((st.st_mtime_ns, st.st_size, e.name))
    except OSError:
        return 0
    total = sum(size for _, size, _ in entries)
    deleted = 0
    for _, size, name in sorted(entries):
        if total <= max_bytes:
            break
        try:
            os.remove(os.path.join(path, name))
        except OSError:
            continue
        total -= size
        deleted += 1
        try:
            os.remove(os.path.join(path, name[: -len("-cache")] + "-atime"))
        except OSError:
            pass
    return deleted


def ensure_persistent_cache(enable: bool = True) -> str | None:
    """The library's default: enable the cache (:func:`enable_persistent_cache`) once per
    process unless the user configured one, turned JAX's off, or set
    ``JAXELASTIC_CACHE=0``. Cheap after the first call. Returns the directory it enabled,
    or None. ``enable=False``: never enable the default in this process (``--no-cache``)."""
    global _checked
    if _checked:
        return None
    with _lock:
        if _checked:
            return None
        _checked = True
        if not enable:
            return None
        import jax

        cfg = jax.config
        if os.environ.get("JAXELASTIC_CACHE", "").strip().lower() in _OFF:
            return None
        if cfg.jax_compilation_cache_dir is not None:  # pyright: ignore[reportAttributeAccessIssue]
            return None  # the user's own cache
        if not cfg.jax_enable_compilation_cache:  # pyright: ignore[reportAttributeAccessIssue]
            return None
        try:
            return enable_persistent_cache()
        except OSError:
            return None  # e.g. a read-only home: run without the cache
