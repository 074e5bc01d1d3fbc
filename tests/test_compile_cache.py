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


def test_stable_warp_call_ids_make_retraces_lower_to_the_same_program() -> None:
    """Warp numbers each trace of an FFI call with a per-process counter written into the program,
    so a re-trace of an MJX step lowers to new text and misses the persistent cache; with
    `warp_graphs.stable_call_ids()` (on in this test session: conftest sets
    `BULBJAX_STABLE_WARP_IDS`) the id is the call's signature, so equal programs lower to equal
    text, a different call (another batch size) to another id, and the results are the same."""
    import re

    import jax
    import numpy as np

    import bulbjax
    from bulbjax.envs import warp_graphs

    assert warp_graphs.stable_call_ids(), "this Warp's jax_callable has no call_id counter to replace: recheck"
    env = bulbjax.make("CartPole", num_envs=2, resolution=16)
    s = jax.jit(env.reset)(jax.random.PRNGKey(0))
    a = jax.numpy.ones((2,), jax.numpy.int32)
    texts = [jax.jit(lambda s, a: env.step(s, a)).lower(s, a).as_text() for _ in range(2)]
    ids = [re.findall(r"call_id = (\d+)", t) for t in texts]
    assert ids[0], "the step makes no Warp FFI call: nothing to check"
    assert texts[0] == texts[1] and ids[0] == ids[1]
    other = bulbjax.make("CartPole", num_envs=3, resolution=16)
    s3 = jax.jit(other.reset)(jax.random.PRNGKey(0))
    ids3 = re.findall(r"call_id = (\d+)", jax.jit(lambda s, a: other.step(s, a)).lower(
        s3, jax.numpy.ones((3,), jax.numpy.int32)).as_text())
    assert ids3 and not set(ids3) & set(ids[0])  # another batch size: other signatures, other ids
    x, y = (jax.jit(lambda s, a: env.step(s, a))(s, a) for _ in range(2))
    np.testing.assert_array_equal(np.asarray(x.pixels), np.asarray(y.pixels))
    np.testing.assert_array_equal(np.asarray(x.lowdim), np.asarray(y.lowdim))
