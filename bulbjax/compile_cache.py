"""JAX's persistent compilation cache, on by default for the CLI (issue 13).

A six-learner epoch takes minutes to compile; with the cache a rerun of the same configuration
loads the compiled executables from disk and starts in seconds. The cache lives in
`$BULBJAX_COMPILE_CACHE` if set (`off`, `0` or empty turns it off), else under the bulbjax
cache directory (`$BULBJAX_CACHE_DIR`, default `~/.cache/bulbjax`) in `jax/`. Library use
(`import bulbjax`) leaves JAX's settings alone: call `enable()` yourself. `bulbjax reproduce`
notes in it which of its jobs' programs it holds (`mark_warm`, `warm_keys`), for warm start-ups in
its estimate.
"""

from __future__ import annotations

import json
import os

OFF_VALUES = ("", "0", "off", "false", "no")


def env_on(name: str, default: bool = True) -> bool:
    """Whether the project's on/off variable `name` is on: unset -> `default`, any of `OFF_VALUES`
    (the empty string too, as `BULBJAX_COMPILE_CACHE=` turns the cache off) -> False, else True.
    One reading for every such variable, so `0`, `off` and an empty value mean the same everywhere."""
    env = os.environ.get(name)
    return default if env is None else env.strip().lower() not in OFF_VALUES


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


def write_from_every_process() -> bool:
    """Let every process of a multi-process run write its own compile-cache entries (JAX writes
    from process 0 only, to spare shared file systems concurrent writes of one entry). bulbjax's
    processes compile different programs (each process's seed groups are other constants), so
    without this the programs of processes 1.. were compiled again on every rerun and resume
    while process 0 waited for them at the first collective (issue 56: the silent minute before
    a resumed two-GPU epoch). Entries of programs shared by all processes (the small cross-process
    collectives) compile faster than the cache's threshold and are not written. Replaces
    `jax._src.compiler._cache_write` by a function that does its checks and write for any process.
    JAX's function took `host_callbacks` last up to 0.10 and not in 0.11 (seen on a GPU machine
    with 0.11.2, where the check below refused it and process 1 recompiled at each rerun: 58 s);
    both forms are taken. Any other form changes nothing: a warning says so, returns False."""
    import inspect
    import warnings

    from jax._src import compilation_cache, compiler, config
    from jax._src import distributed as jax_distributed

    real = getattr(compiler, "_cache_write", None)
    if real is not None and getattr(real, "_bulbjax_every_process", False):
        return True
    base = ["cache_key", "compile_time_secs", "module_name", "backend", "executable"]
    params = list(inspect.signature(real).parameters) if real is not None else None
    put = getattr(compilation_cache, "put_executable_and_time", None)
    put_params = list(inspect.signature(put).parameters)[:5] if put is not None else None
    if params not in (base, base + ["host_callbacks"]) or put_params != [
            "cache_key", "module_name", "executable", "backend", "compile_time"]:
        warnings.warn("this JAX's compile-cache writer is not one bulbjax knows: only process 0 writes "
                      "compile-cache entries, so processes 1.. compile their programs again on every "
                      "rerun and resume of a multi-process run", stacklevel=2)
        return False

    def cache_write(cache_key, compile_time_secs, module_name, backend, executable, *rest):
        if jax_distributed.global_state.process_id == 0:
            return real(cache_key, compile_time_secs, module_name, backend, executable, *rest)
        host_callbacks = rest[0] if rest else ()
        if host_callbacks or compile_time_secs < config.persistent_cache_min_compile_time_secs.value:
            return None
        try:
            put(cache_key, module_name, executable, backend, int(compile_time_secs))
        except Exception as ex:  # noqa: BLE001  (as JAX's own: a cache that cannot be written is no error)
            warnings.warn(f"Error writing persistent compilation cache entry for '{module_name}': "
                          f"{type(ex).__name__}: {ex}")
        return None

    cache_write._bulbjax_every_process = True  # type: ignore[attr-defined]
    compiler._cache_write = cache_write
    return True


WARM_FILE = "bulbjax_warm.json"  # in the cache directory: what has compiled into it, per device kind


def mark_warm(kind: str, key: str) -> None:
    """Note that a job timed by `key` (`bulbjax reproduce`'s row: a preset, `<preset> fp32`)
    reached its first epoch on a `kind` host with this cache: its programs are in it, so the next
    job of that key starts warm. The note travels with the cache directory (a cache carried to the
    next GPU allocation keeps it), so a plan made there estimates warm start-ups. It cannot see a
    change of code or JAX that changes the programs (they compile again: that job's estimate is
    then short by a cold start-up less a warm one). Nothing when the cache is off; a cache that
    cannot be written is said in a warning, never an error (the note only shortens an estimate)."""
    path = cache_dir()
    if path is None:
        return
    table = _warm_table(path)
    if key in table.get(kind, []):
        return
    table[kind] = sorted({*table.get(kind, []), key})
    tmp = os.path.join(path, f"{WARM_FILE}.tmp{os.getpid()}")
    try:
        os.makedirs(path, exist_ok=True)
        with open(tmp, "w") as f:
            json.dump(table, f, indent=1)
        os.replace(tmp, os.path.join(path, WARM_FILE))
    except OSError as ex:
        import warnings

        warnings.warn(f"the compile cache {path} takes no note of {key!r} ({ex}): later plans estimate "
                      "its first job cold", stacklevel=2)


def warm_keys(kind: str) -> frozenset[str]:
    """The keys `mark_warm` noted for `kind` in this cache (none when the cache is off)."""
    path = cache_dir()
    return frozenset(_warm_table(path).get(kind, [])) if path is not None else frozenset()


def _warm_table(path: str) -> dict[str, list[str]]:
    try:
        with open(os.path.join(path, WARM_FILE)) as f:
            table = json.load(f)
    except (OSError, ValueError):  # none yet, or unreadable: nothing known warm (a cold estimate)
        return {}
    return table if isinstance(table, dict) else {}
