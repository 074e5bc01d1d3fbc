"""Test-session settings: one persistent JAX compilation cache shared by every process of a test
session (issue 38).

Most of the suite's time is XLA compiling tiny jitted epochs, env steps and learners. A session
compiles some programs more than once: a subprocess rebuilds what its parent already compiled
(`test_run`'s resumed process, the stretches of `test_kill_resume`), a test builds a second
`Experiment` of a configuration it compiled before, and files share configurations. With one
cache directory for the session, the second compile of a program loads the executable from disk
(the same executable, so the same numbers). The directory is fresh for each session, so a test
never reads what another session (or other code) compiled, and it is removed at the end.

The pytest process (and each xdist worker, which inherits its environment) sets JAX's own cache
variables, which every Python subprocess also reads, and `$BULBJAX_COMPILE_CACHE`, which the
CLI's `compile_cache.enable()` reads. A cache the caller chose (`$BULBJAX_COMPILE_CACHE` set,
`off` included) is left alone.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile

MIN_COMPILE_SECS = "0.5"  # programs that compile faster than this are not worth a disk round trip

_created: str | None = None
if "BULBJAX_COMPILE_CACHE" not in os.environ:
    _created = tempfile.mkdtemp(prefix="bulbjax-test-jax-cache-")
    os.environ["BULBJAX_COMPILE_CACHE"] = _created
_cache = os.environ["BULBJAX_COMPILE_CACHE"]
if _cache.strip().lower() not in ("", "0", "off", "false", "no"):  # compile_cache.OFF_VALUES (importing
    # bulbjax here would import JAX before it reads the variables below)
    os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", _cache)
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", MIN_COMPILE_SECS)
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")
    if "jax" in sys.modules:  # a plugin imported JAX before this file: its config read the environment already
        from bulbjax import compile_cache

        compile_cache.enable(os.environ["JAX_COMPILATION_CACHE_DIR"], float(MIN_COMPILE_SECS))


# Measured and not used: XLA's CPU backend at LLVM -O0 for the session
# (`--xla_backend_optimization_level=0`) cut one compile-bound file from 118 s to 70 s, but the
# whole suite went from ~73 to 89 min: tests that run real work (tests/test_ppo.py's pixel PPO
# bandit: 1,173 s) ran far slower unoptimised. `--xla_llvm_disable_expensive_passes` alone gave
# 107 s on the same file (noise level). The session's compile cache below is what is kept.


def pytest_unconfigure(config) -> None:
    """The process that made the session's cache removes it (under xdist: the controller, after
    its workers have finished)."""
    if _created is not None and not hasattr(config, "workerinput"):
        shutil.rmtree(_created, ignore_errors=True)


# Files by their time in the 2-worker suite, longest first (measured on a 2-core CPU; each is a
# few jitted epochs compiled in a module fixture or a subprocess). `--dist loadfile` hands files to
# the two workers in collection order; sending the long ones first lets the short ones fill the
# gaps at the end, so both workers finish together. xdist's default order (most tests first) put
# single-test files such as test_kill_resume and test_distributed at the very end, on one worker.
LONGEST_FIRST = (
    "test_experiment.py", "test_object_probe.py", "test_distributed.py", "test_sharding.py", "test_ppo.py",
    "test_synthetic.py", "test_run.py", "test_rl_latent.py", "test_recon.py", "test_rl_sequential.py",
    "test_contrastive.py", "test_reset_pool.py", "test_chunked_reset.py", "test_kill_resume.py",
    "test_extending.py", "test_ppo_stability.py",
)


def pytest_configure(config) -> None:
    if hasattr(config.option, "loadscopereorder"):  # xdist: keep the order below
        config.option.loadscopereorder = False


def pytest_collection_modifyitems(config, items) -> None:
    """Long files first, then the others by their number of tests (xdist's own order), the tests
    of a file in their order."""
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    count: dict[str, int] = {}
    for item in items:
        count[item.path.name] = count.get(item.path.name, 0) + 1
    items.sort(key=lambda item: (rank.get(item.path.name, len(rank)), -count[item.path.name]))
