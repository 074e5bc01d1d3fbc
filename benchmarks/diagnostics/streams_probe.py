"""Does XLA run a stream-annotated call (with a loop inside) beside the main stream's work?

Answered on one H200 (JAX 0.11.2, 2026-11-28): no. A GPU-bound scan (bf16 8192^2 products) took
84.96 ms, a latency-bound scan of 6,000 tiny steps 53.81 ms, both in one program 130.75 ms; with
either on `gpu_stream:1` (`jax.experimental.compute_on`) the program does not compile: JAX
annotates every op inside the call, and XLA finds no execution stream for the annotated ops of
the while loop's condition ("No ExecutionStreamId found for %call-start ... while/cond/lt").
docs/performance.md, "The locomotion epoch on one H200", keeps the answer.

    python benchmarks/diagnostics/streams_probe.py      # on a GPU; JAX alone, no MuJoCo
"""
import time, json, jax, jax.numpy as jnp
import inspect
from jax.experimental.compute_on import compute_on as _co

def on_stream(f, n):
    if "compute_type" in inspect.signature(_co).parameters:  # JAX >= 0.11: compute_on(f, compute_type=...)
        g = _co(f, compute_type=f"gpu_stream:{n}", out_memory_spaces=jax.memory.Space.Device)
        return g
    jf = jax.jit(f)
    def call(*a):
        with _co(f"gpu_stream:{n}"):
            return jf(*a)
    return call

def heavy(x):  # GPU-bound: big matmuls in a scan
    def body(c, _):
        return jnp.tanh((c @ c) * 1e-4).astype(c.dtype), None
    return jax.lax.scan(body, x, None, length=60)[0]

def chain(y):  # latency-bound: tiny dependent kernels in a scan
    def body(c, _):
        return jnp.sin(c) * 0.5 + jnp.cos(c) * 1e-3, None
    return jax.lax.scan(body, y, None, length=6000)[0]

hs, cs = on_stream(heavy, 1), on_stream(chain, 1)
def par_l(x, y):
    return hs(x), chain(y)
def par_c(x, y):
    return heavy(x), cs(y)
fns = {"heavy": jax.jit(lambda x, y: heavy(x)), "chain": jax.jit(lambda x, y: chain(y)),
       "both_one_stream": jax.jit(lambda x, y: (heavy(x), chain(y))),
       "heavy_on_stream1": jax.jit(par_l), "chain_on_stream1": jax.jit(par_c)}
x = jax.random.normal(jax.random.PRNGKey(0), (8192, 8192), jnp.bfloat16)
y = jnp.linspace(0, 1, 64)
out = {}
for n, f in fns.items():
    try:
        jax.block_until_ready(f(x, y)); ts = []
        for _ in range(5):
            t = time.perf_counter(); jax.block_until_ready(f(x, y)); ts.append(time.perf_counter() - t)
        out[n] = round(sorted(ts)[2] * 1e3, 2)
    except Exception as e:
        out[n] = f"error: {str(e)[:300]}"
    print(n, out[n], flush=True)
txt = fns["heavy_on_stream1"].lower(x, y).compile().as_text()
out["async_in_hlo"] = txt.count("async-start") + txt.count("AsyncStart") + txt.count("call-start")
out["jax"] = jax.__version__
print(json.dumps(out))
