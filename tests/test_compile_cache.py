"""The persistent compilation cache: where it goes, how it is turned off, and that a second
process loads an MJX (Warp FFI) step from it and computes the same result."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

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


EVERY_PROCESS = """
import inspect, os, sys
import jax
from jax._src import compilation_cache, compiler
from jax._src import distributed as jd
from bulbjax import compile_cache
compile_cache.enable(sys.argv[1], 0.0)
form = sys.argv[2]
if form == "without_host_callbacks":  # JAX 0.11's signature: host_callbacks gone
    real = compiler._cache_write
    def _cache_write(cache_key, compile_time_secs, module_name, backend, executable):
        return real(cache_key, compile_time_secs, module_name, backend, executable, ())
    compiler._cache_write = _cache_write
elif form == "unknown":
    compiler._cache_write = lambda key, t, name, backend, executable, callbacks, extra=None: None
print("PATCHED", compile_cache.write_from_every_process())
jd.global_state.process_id = 1  # as process 1 of a run: JAX alone would write nothing
jax.jit(lambda x: (x @ x.T).sum())(jax.numpy.ones((64, 64))).block_until_ready()
print("ENTRIES", len(os.listdir(sys.argv[1])))
"""


def test_every_process_writes_its_cache_entries_under_both_jax_signatures(tmp_path) -> None:
    """Process 1 of a run writes its compiled programs to the cache with JAX's writer taking
    host_callbacks (JAX <= 0.10) and without (0.11: on a GPU machine the old check refused it and
    process 1 recompiled at every rerun, 58 s); an unknown writer is left alone with a warning."""
    for form in ("as_installed", "without_host_callbacks", "unknown"):
        cache = tmp_path / form
        out = subprocess.run([sys.executable, "-c", EVERY_PROCESS, str(cache), form], capture_output=True,
                             text=True, timeout=300)
        assert out.returncode == 0, out.stderr[-2000:]
        patched = "PATCHED True" in out.stdout
        entries = int(out.stdout.split("ENTRIES")[1].split()[0])
        if form == "unknown":
            assert not patched and entries == 0
            assert "processes 1.. compile their programs again" in out.stderr
        else:
            assert patched and entries > 0, (form, out.stdout, out.stderr[-1000:])


@pytest.mark.parametrize("value, on", [(None, True), ("1", True), ("yes", True), ("0", False), ("off", False),
                                       (" False ", False), ("no", False), ("", False)])
def test_on_off_variables_read_one_way(monkeypatch: pytest.MonkeyPatch, value: str | None, on: bool) -> None:
    """Every on/off variable (BULBJAX_WARM_PHYSICS, the cache's off words) reads the same words."""
    if value is None:
        monkeypatch.delenv("BULBJAX_WARM_PHYSICS", raising=False)
    else:
        monkeypatch.setenv("BULBJAX_WARM_PHYSICS", value)
    assert compile_cache.env_on("BULBJAX_WARM_PHYSICS") is on
    assert compile_cache.env_on("BULBJAX_WARM_PHYSICS", default=False) is (False if value is None else on)
