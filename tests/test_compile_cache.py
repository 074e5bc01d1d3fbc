"""The persistent compilation cache: where it goes, how it is turned off, and that a second
process loads an MJX (Warp FFI) step from it and computes the same result."""

from __future__ import annotations

import os
import subprocess
import sys

from bulbjax import compile_cache

SCRIPT = """
import sys
from bulbjax import compile_cache
compile_cache.enable(sys.argv[1], 0.0)
import jax, bulbjax
env = bulbjax.make("CartPole", num_envs=2, resolution=16)
s = jax.jit(env.reset)(jax.random.PRNGKey(0))
s = jax.jit(env.step)(s, jax.numpy.ones((2,), jax.numpy.int32))
print("RESULT", int(s.pixels.sum()), repr(float(s.lowdim.sum())))
"""


def test_cache_dir_settings(monkeypatch, tmp_path) -> None:
    monkeypatch.delenv("BULBJAX_COMPILE_CACHE", raising=False)
    monkeypatch.setenv("BULBJAX_CACHE_DIR", str(tmp_path))
    assert compile_cache.cache_dir() == os.path.join(str(tmp_path), "jax")
    monkeypatch.setenv("BULBJAX_COMPILE_CACHE", "off")
    assert compile_cache.cache_dir() is None and compile_cache.enable() is None
    monkeypatch.setenv("BULBJAX_COMPILE_CACHE", str(tmp_path / "c"))
    assert compile_cache.cache_dir() == str(tmp_path / "c")


def test_second_process_reads_the_cache(tmp_path) -> None:
    cache = str(tmp_path / "jax")

    def run() -> str:
        out = subprocess.run([sys.executable, "-c", SCRIPT, cache], capture_output=True, text=True,
                             timeout=600, check=True).stdout
        return [ln for ln in out.splitlines() if ln.startswith("RESULT")][0]

    first = run()
    entries = set(os.listdir(cache))
    assert entries, "nothing was written to the cache"
    assert run() == first  # same numbers from the cached executables
    assert set(os.listdir(cache)) == entries  # nothing new compiled: every executable came from the cache
