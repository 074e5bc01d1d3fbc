"""benchmarks/trace_summary.py: a profiler trace split by the epoch's named phase scopes, and the
render contexts' Warp device (`warp_devices`)."""

from __future__ import annotations

import glob
import importlib.util
import os
from types import SimpleNamespace

import jax
import jax.numpy as jnp

from bulbjax.envs.render import warp_devices

HERE = os.path.dirname(os.path.abspath(__file__))


def _trace_summary():
    path = os.path.join(os.path.dirname(HERE), "benchmarks", "trace_summary.py")
    spec = importlib.util.spec_from_file_location("trace_summary", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_trace_split_by_phase_scope(tmp_path) -> None:
    """A jitted function with two named scopes, one ~30x the work of the other: the summary finds
    both scopes from the executable's HLO and gives the heavy one more device time."""
    ts = _trace_summary()

    def f(x):
        with jax.named_scope("bj.heavy"):
            y = jax.lax.fori_loop(0, 30, lambda i, a: jnp.tanh(a @ x), x)
        with jax.named_scope("bj.light"):
            z = jnp.tanh(y @ x)
        return z

    x = jnp.full((384, 384), 0.01, jnp.float32)
    comp = jax.jit(f).lower(x).compile()
    scopes = ts.hlo_scopes(comp.as_text())
    assert set(scopes.values()) >= {"bj.heavy", "bj.light"}
    jax.block_until_ready(comp(x))
    with jax.profiler.trace(str(tmp_path)):
        for _ in range(3):
            jax.block_until_ready(comp(x))
    (pb,) = glob.glob(str(tmp_path / "**" / "*.xplane.pb"), recursive=True)
    out = ts.summarise(pb, scopes=scopes)
    (dev,) = out["devices"].values()
    got = dev["scopes"]
    assert "bj.heavy" in got and "bj.light" in got, got
    assert got["bj.heavy"]["busy_ms"] > 5 * got["bj.light"]["busy_ms"] > 0, got
    assert dev["busy_ms"] <= dev["span_ms"] + 1e-6


def test_scope_of_fusions_without_metadata_and_named_kernels() -> None:
    """A fusion XLA left without op_name metadata takes the scope of the computation it calls;
    Warp's kernels and the runtime's copies are named as such, not left unscoped."""
    ts = _trace_summary()
    hlo = """HloModule m

%fused_dot.7 (p0: f32[4,4], p1: f32[4,4]) -> f32[4,4] {
  %p0 = f32[4,4]{1,0} parameter(0)
  %p1 = f32[4,4]{1,0} parameter(1)
  ROOT %dot.1 = f32[4,4]{1,0} dot(%p0, %p1), lhs_contracting_dims={1}, rhs_contracting_dims={0}, metadata={op_name="jit(f)/bj.learn.vae/transpose(jvp(dot_general))"}
}

ENTRY %main (a: f32[4,4]) -> f32[4,4] {
  %a = f32[4,4]{1,0} parameter(0)
  %gemm_fusion_dot.611 = f32[4,4]{1,0} fusion(%a, %a), kind=kCustom, calls=%fused_dot.7
  ROOT %add.3 = f32[4,4]{1,0} add(%gemm_fusion_dot.611, %a), metadata={op_name="jit(f)/bj.rl/add"}
}
"""
    scopes = ts.hlo_scopes(hlo)
    assert scopes["gemm_fusion_dot.611"] == "bj.learn.vae"
    assert scopes["add.3"] == "bj.rl"
    ev = lambda name, **stats: SimpleNamespace(name=name, stats=list(stats.items()))  # noqa: E731
    assert ts._scope_of(ev("gemm_fusion_dot_611"), scopes) == "bj.learn.vae"
    assert ts._scope_of(ev("_linesearch_iterative_kernel_691522b3_cuda_kernel_forward"), scopes) == "(warp)"
    assert ts._scope_of(ev("MemcpyD2D"), scopes) == "(memcpy)"
    assert ts._scope_of(ev("loop_add_fusion_9"), scopes) == "(unscoped)"


def test_warp_devices_follow_jax() -> None:
    """Render contexts go on the CUDA ordinal of the JAX device they serve (Warp's own default is
    whichever CUDA context was current); off the GPU none is named (Warp's single CPU device)."""
    assert warp_devices() is None  # CPU here
    gpus = [SimpleNamespace(platform="gpu", local_hardware_id=i) for i in (1, 0)]
    assert warp_devices(gpus) == ["cuda:1", "cuda:0"]
    assert warp_devices(gpus[:1]) == ["cuda:1"]


def test_copies_are_named_by_their_op_and_size() -> None:
    """The runtime's copies and fills are counted by the XLA op that made them and the size the
    tracer records (an int stat, or `size:N` in a string one), so a trace says which copies an
    epoch makes and how big they are."""
    ts = _trace_summary()
    ev = lambda name, **stats: SimpleNamespace(name=name, stats=list(stats.items()))  # noqa: E731
    assert ts.copy_key(ev("MemcpyD2D", hlo_op="%ffi_call.169", memcpy_details="kind_src:device size:4096 async:1"),
                       "bj.rl") == ("MemcpyD2D", "ffi_call.169 [bj.rl]", 4096)
    assert ts.copy_key(ev("MemcpyD2D", num_bytes=512), "(memcpy)") == ("MemcpyD2D", "(no op) [(memcpy)]", 512)
    assert ts.copy_key(ev("Memset 3", correlation_id=7), "(memset)")[2] is None
