"""JAX's persistent compilation cache, on by default for the CLI (issue 13).

A six-learner epoch takes minutes to compile; with the cache a rerun of the same configuration
loads the compiled executables from disk and starts in seconds. The cache lives in
`$BULBJAX_COMPILE_CACHE` if set (`off`, `0` or empty turns it off), else under the bulbjax
cache directory (`$BULBJAX_CACHE_DIR`, default `~/.cache/bulbjax`) in `jax/`. Library use
(`import bulbjax`) leaves JAX's settings alone: call `enable()` yourself.
"""

from __future__ import annotations

import os

OFF_VALUES = ("", "0", "off", "false", "no")


def cache_dir() -> str | None:
    """The directory the cache would use, or None when `$BULBJAX_COMPILE_CACHE` turns it off."""
    env = os.environ.get("BULBJAX_COMPILE_CACHE")
    if env is not None:
        return None if env.strip().lower() in OFF_VALUES else os.path.expanduser(env)
    root = os.environ.get("BULBJAX_CACHE_DIR") or os.path.join("~", ".cache", "bulbjax")
    return os.path.join(os.path.expanduser(root), "jax")


def enable(path: str | None = None, min_compile_secs: float = 1.0) -> str | None:
    """Point JAX's persistent compilation cache at `path` (default `cache_dir()`); executables
    that took at least `min_compile_secs` to compile are stored. Returns the directory used, or
    None when the cache is off. Safe to call more than once."""
    import jax

    path = path or cache_dir()
    if path is None:
        return None
    os.makedirs(path, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", min_compile_secs)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path
