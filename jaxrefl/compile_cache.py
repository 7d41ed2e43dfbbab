"""JAX's persistent compilation cache for jaxrefl's programs.

The per-point solvers compile once per shape bucket; on a laptop CPU that takes longer
than the fit itself on a small scan. With the cache on, a later process (the next CLI
run, a batch worker, a notebook kernel) loads the compiled programs from disk.

The CLI and `batch` turn it on; from Python call `enable()` once before the first
estimate. It lives in `jax/` under jaxrefl's cache folder: `$JAXREFL_CACHE` (shared with
the form-factor cache), else `$XDG_CACHE_HOME/jaxrefl`, else `~/.cache/jaxrefl`;
`JAXREFL_CACHE=off` disables both. A cache the user configured for JAX itself
(`jax_compilation_cache_dir`, `JAX_COMPILATION_CACHE_DIR`) is left alone.
"""

from __future__ import annotations

import logging
import os

import jax

__all__ = ["enable", "cache_dir", "base_dir"]

logger = logging.getLogger(__name__)


def base_dir() -> str | None:
    """jaxrefl's cache folder, or None where `JAXREFL_CACHE` disables caching."""
    chosen = os.environ.get("JAXREFL_CACHE")
    if chosen is not None:
        return None if chosen.strip().lower() in ("", "off", "0", "none") else chosen
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "jaxrefl")


def cache_dir() -> str | None:
    """The folder `enable` uses, or None where it is disabled."""
    base = base_dir()
    return None if base is None else os.path.join(base, "jax")


def enable() -> str | None:
    """Turn on JAX's persistent compilation cache (every program, however quick to compile)
    unless one is configured already or it is disabled; returns the folder in use."""
    current = jax.config.jax_compilation_cache_dir
    if current:
        return current
    folder = cache_dir()
    if folder is None:
        return None
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as exc:  # a read-only home: run without the cache
        logger.warning("compilation cache disabled: cannot create %s (%s)", folder, exc)
        return None
    jax.config.update("jax_compilation_cache_dir", folder)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return folder
