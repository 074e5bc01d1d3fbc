"""Throughput of bulbjax: environment steps and rendered frames per second, VAE updates per second.

1. Environments (`--envs`, `--batch-sizes`): `--steps` calls of `env.step` inside one jitted
   `jax.lax.scan` with random actions, physics only (render=False) and with 64x64 Warp frames
   (render=True: physics step + render + low-dim state). Compile time (lower + compile), first
   call and `--repeats` timed calls are reported separately; rates use the median call.
2. Learners (`--learners`, default `vae`): updates per second at `--vae-batch` frames (sequential
   learners: `vae_batch // L` windows of L steps; spair: its own 64-frame batch), fp32 and bf16
   compute, each decoder form of `--deconv-impls` (transpose / subpixel / dgrad: same parameters, same
   function) and each fp32 matmul/conv precision of `--precisions` (JAX's `default`, or
   `tensorfloat32`, what PyTorch's cuDNN convolutions use by default), one jitted update (donated
   state) called `--vae-steps` times after warm-up; and, in a subprocess on the same device, the
   PyTorch reference of `torch_vae_reference.py` (eager and torch.compile, fp32
   and bf16 autocast), with the bulbjax/PyTorch ratios.

Results are printed and written (after every measurement, so a run cut short keeps what it had)
to `<out-dir>/throughput_<device>_<timestamp>.json` and `<out-dir>/throughput_<device>_latest.json`.

GPU: python benchmarks/bench_throughput.py
CPU smoke run: python benchmarks/bench_throughput.py --batch-sizes 8 --steps 10 --vae-batch 16 --vae-steps 3
"""

from __future__ import annotations

import argparse
import datetime as dt
import gc
import glob
import itertools
import os
import shlex
import statistics
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from typing import Any, Callable

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
# Use this working tree's bulbjax (and its MJCF files), not an installed copy.
sys.path.insert(0, REPO)

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import bulbjax  # noqa: E402
from bench_record import ResultWriter, device_info, device_slug, git_commit, versions  # noqa: E402  (this folder)
from throughput_report import fmt_rate, print_summary, ratios, run_torch_reference  # noqa: E402  (this folder)
from bulbjax.data.sequence import Windows  # noqa: E402
from bulbjax.learners import (LearnerConfig, check_finite, is_sequential, make_learner,  # noqa: E402
                              parse_learner_options)
from bulbjax.xla_options import parse_named_options  # noqa: E402

MODES: tuple[str, ...] = ("physics", "rendered")
PARTS: tuple[str, ...] = ("env", "learner", "torch")
DTYPES: tuple[str, ...] = ("float32", "bfloat16")


@dataclass(frozen=True)
class BenchSettings:
    """Everything one benchmark run measures (recorded in the JSON)."""

    envs: tuple[str, ...] = ("CartPole", "InvertedPendulum")
    batch_sizes: tuple[int, ...] = (1024, 4096)
    steps: int = 100
    repeats: int = 5
    resolution: int = 64
    vae_batch: int = 1024
    vae_steps: int = 50
    vae_warmup: int = 3
    latent_dim: int = 32
    dtypes: tuple[str, ...] = DTYPES
    learners: tuple[str, ...] = ("vae",)
    deconv_impls: tuple[str, ...] = ("transpose", "subpixel", "dgrad")
    precisions: tuple[str, ...] = ("default",)
    rnn_unroll: int = 1  # sequential learners' LSTM steps per scan iteration (LearnerConfig.rnn_unroll)
    # named LearnerConfig overrides timed side by side (`--variants`), e.g. (("pad8", (("channel_pad", 8),)),)
    variants: tuple[tuple[str, tuple[tuple[str, Any], ...]], ...] = (("default", ()),)
    # named sets of XLA compile options timed side by side (`--xla-variants`), e.g.
    # (("conv_fusion", (("xla_gpu_experimental_enable_conv_fusion", True),)),): same program, other compiler
    xla_variants: tuple[tuple[str, tuple[tuple[str, Any], ...]], ...] = (("xla_default", ()),)
    parts: tuple[str, ...] = PARTS
    torch_compile: bool = True
    torch_channels_last: bool = False
    torch_timeout_s: float = 900.0
    torch_forms: str = ""  # torch_vae_reference.py --forms: the strongest forms (whole update in a CUDA graph)
    seed: int = 0
    out_dir: str = os.path.join(HERE, "results")
    verbose: bool = False
    kernels_top: int = 0  # > 0: profile 5 more updates per case, keep the top kernels (JAX and torch)

    def __post_init__(self) -> None:
        if not self.envs or not self.batch_sizes:
            raise ValueError("give at least one environment and one batch size")
        if any(b < 1 for b in self.batch_sizes):
            raise ValueError(f"batch sizes must be positive, got {self.batch_sizes}")
        for name, v in (("steps", self.steps), ("repeats", self.repeats), ("vae_batch", self.vae_batch),
                        ("vae_steps", self.vae_steps), ("latent_dim", self.latent_dim)):
            if v < 1:
                raise ValueError(f"{name} must be >= 1, got {v}")
        if self.vae_warmup < 0:
            raise ValueError(f"vae_warmup must be >= 0, got {self.vae_warmup}")
        if bad := set(self.dtypes) - set(DTYPES):
            raise ValueError(f"unknown dtypes {sorted(bad)}; choose from {DTYPES}")
        if bad := set(self.parts) - set(PARTS):
            raise ValueError(f"unknown parts {sorted(bad)}; choose from {PARTS}")

    def check_envs(self) -> None:
        """Unknown environment names are an error, checked only when the environments are timed:
        `bulbjax.env_names()` loads MuJoCo and Warp, which `--parts learner,torch` does without."""
        if "env" in self.parts and (bad := set(self.envs) - set(bulbjax.env_names())):
            raise ValueError(f"unknown envs {sorted(bad)}; available: {bulbjax.env_names()}")


# ----------------------------------------------------------------------------- helpers


def log(msg: str) -> None:
    """Progress line on stderr, with wall-clock time."""
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def timed(fn: Callable[[], Any]) -> tuple[Any, float]:
    """Run `fn`, block on its result, return (result, seconds)."""
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - t0


# ----------------------------------------------------------------------------- environments


def random_actions(env: Any, key: jax.Array) -> jax.Array:
    """Uniform random actions for all worlds (flat draws: cheaper to compile on XLA:CPU)."""
    if env.discrete:
        return jax.random.randint(key, (env.num_envs,), 0, env.num_actions, dtype=jnp.int32)
    n = env.num_envs * env.action_size
    return jax.random.uniform(key, (n,), minval=-1.0, maxval=1.0).reshape(env.num_envs, env.action_size)


def make_rollout(env: Any, steps: int) -> Callable[[Any, jax.Array], tuple[Any, jax.Array]]:
    """Jitted `(state, key) -> (state, key)`: `steps` env steps with random actions in one scan."""

    def body(carry: tuple[Any, jax.Array], _: None) -> tuple[tuple[Any, jax.Array], None]:
        state, key = carry
        key, k_act = jax.random.split(key)
        return (env.step(state, random_actions(env, k_act)), key), None

    def rollout(state: Any, key: jax.Array) -> tuple[Any, jax.Array]:
        return jax.lax.scan(body, (state, key), None, length=steps)[0]

    return jax.jit(rollout)


def bench_env(name: str, num_envs: int, mode: str, s: BenchSettings) -> dict[str, Any]:
    """One (environment, batch size, mode) measurement."""
    render = mode == "rendered"
    key = jax.random.PRNGKey(s.seed)
    t0 = time.perf_counter()
    env = bulbjax.make(name, num_envs=num_envs, resolution=s.resolution, render=render)
    make_s = time.perf_counter() - t0
    state, reset_s = timed(lambda: jax.jit(env.reset)(key))
    rollout = make_rollout(env, s.steps)
    t0 = time.perf_counter()
    compiled = rollout.lower(state, key).compile()
    compile_s = time.perf_counter() - t0
    (state, key), first_s = timed(lambda: compiled(state, key))
    calls = []
    for _ in range(s.repeats):
        (state, key), t = timed(lambda: compiled(state, key))
        calls.append(t)
    med, best = statistics.median(calls), min(calls)
    per_call = num_envs * s.steps
    out = {"env": name, "mode": mode, "batch_size": num_envs, "steps": s.steps, "repeats": s.repeats,
           "resolution": s.resolution if render else None,
           "unit": "frames/s" if render else "env steps/s",
           "make_s": make_s, "reset_with_compile_s": reset_s, "compile_s": compile_s, "first_call_s": first_s,
           "call_s": calls, "median_call_s": med,
           "per_s_median": per_call / med, "per_s_best": per_call / best}
    if render:
        px = np.asarray(state.pixels)
        out["pixels_shape"] = list(px.shape)
        out["pixels_mean"] = float(px.mean())  # sanity: not a blank frame
    del env, rollout, compiled, state
    gc.collect()
    return out


def run_envs(s: BenchSettings, w: ResultWriter) -> None:
    rows: list[dict[str, Any]] = w.results.setdefault("env", [])
    for name in s.envs:
        for n in s.batch_sizes:
            for mode in MODES:
                log(f"env {name} N={n} {mode} ...")
                try:
                    r = bench_env(name, n, mode, s)
                    log(f"  {fmt_rate(r['per_s_median'])} {r['unit']} (best {fmt_rate(r['per_s_best'])}); "
                        f"compile {r['compile_s']:.1f} s, first call {r['first_call_s']:.2f} s")
                except Exception as e:  # noqa: BLE001 - record and go on to the next case
                    log(f"  FAILED: {type(e).__name__}: {e}")
                    r = {"env": name, "mode": mode, "batch_size": n, "error": f"{type(e).__name__}: {e}"[:2000]}
                rows.append(r)
                w.write()


# ----------------------------------------------------------------------------- learner


def learner_batch(learner: Any, name: str, s: BenchSettings, rng: np.random.Generator) -> Any:
    """A random batch in the learner's input layout: uint8 frames [B, R, R, 3], or `Windows`
    [B // L, L, ...] for the sequential learners."""
    shape = (s.resolution, s.resolution, 3)
    if not is_sequential(learner):
        n = learner.batch_size if name == "spair" else s.vae_batch
        return jax.device_put(rng.integers(0, 256, (n, *shape), dtype=np.uint8))
    b, lw = learner.batch_size, learner.window_length
    return Windows(frames=jax.device_put(rng.integers(0, 256, (b, lw, *shape), dtype=np.uint8)),
                   actions=jnp.asarray(rng.uniform(-1, 1, (b, lw, 1)), jnp.float32),
                   states=jnp.zeros((b, lw, 4), jnp.float32), valid=jnp.ones((b, lw), bool))


def parse_variant(text: str) -> tuple[str, tuple[tuple[str, Any], ...]]:
    """`NAME[=KEY:VALUE;...]` -> (NAME, ((KEY, VALUE), ...)), each KEY a `LearnerConfig` field and
    VALUE converted to that field's type (e.g. `pad8=channel_pad:8;bias_grad:split`)."""
    name, _, rest = text.partition("=")
    if not name:
        raise ValueError(f"variant {text!r} has no name")
    items = [kv.replace(":", "=", 1) for kv in rest.split(";") if kv]
    return name, tuple(parse_learner_options(items).items())


def parse_xla_variant(text: str) -> tuple[str, tuple[tuple[str, Any], ...]]:
    """`NAME[=KEY:VALUE;...]` -> (NAME, ((KEY, VALUE), ...)) as `parse_named_options` reads it
    (hashable, for the frozen settings)."""
    name, options = parse_named_options(text)
    if not name:
        raise ValueError(f"XLA variant {text!r} has no name")
    return name, tuple(options.items())


def bench_vae(dtype: str, s: BenchSettings, name: str = "vae", impl: str = "transpose",
              precision: str = "default", overrides: tuple[tuple[str, Any], ...] = (),
              xla_options: tuple[tuple[str, Any], ...] = ()) -> dict[str, Any]:
    """Updates per second of learner `name` at `s.vae_batch` frames, compute dtype `dtype`,
    decoder form `impl`, matmul/conv precision `precision` (JAX's default_matmul_precision),
    `LearnerConfig` fields `overrides` (a `--variants` entry), XLA compile options `xla_options`
    (an `--xla-variants` entry)."""
    learner = make_learner(name, latent_dim=s.latent_dim, action_dim=1,
                           config=LearnerConfig(batch_size=s.vae_batch, compute_dtype=dtype,
                                                deconv_impl=impl, rnn_unroll=s.rnn_unroll,
                                                **dict(overrides)))
    shape = (s.resolution, s.resolution, 3)
    key = jax.random.PRNGKey(s.seed)
    k_init, k_steps = jax.random.split(key)
    state, init_s = timed(lambda: jax.jit(learner.init, static_argnums=1)(k_init, shape))
    rng = np.random.default_rng(s.seed)
    frames = learner_batch(learner, name, s, rng)
    keys = list(jax.random.split(k_steps, s.vae_warmup + s.vae_steps))
    update = jax.jit(learner.update, donate_argnums=0)
    t0 = time.perf_counter()
    with jax.default_matmul_precision(None if precision == "default" else precision):
        compiled = update.lower(state, frames, keys[0]).compile(compiler_options=dict(xla_options) or None)
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for k in keys[: s.vae_warmup]:
        state, metrics = compiled(state, frames, k)
    jax.block_until_ready(state)
    warmup_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for k in keys[s.vae_warmup:]:
        state, metrics = compiled(state, frames, k)
    jax.block_until_ready((state, metrics))
    elapsed = time.perf_counter() - t0
    check_finite(metrics, f"{name} {dtype} benchmark")
    kernels = kernel_breakdown(compiled, state, frames, keys, s.kernels_top) if s.kernels_top else None
    batch = learner.batch_size if name == "spair" or is_sequential(learner) else s.vae_batch
    return {"learner": name, "dtype": dtype, "deconv_impl": impl, "precision": precision,
            "batch": batch, "frames_per_batch": batch * getattr(learner, "window_length", 1),
            "resolution": s.resolution, "rnn_unroll": s.rnn_unroll,
            "latent_dim": s.latent_dim, "steps": s.vae_steps, "warmup_steps": s.vae_warmup,
            "init_s": init_s, "compile_s": compile_s, "warmup_s": warmup_s, "elapsed_s": elapsed,
            "updates_per_s": s.vae_steps / elapsed, "final_loss": float(metrics["loss"]),
            **({"kernels": kernels} if kernels else {})}


PROFILED_UPDATES = 5


def kernel_breakdown(compiled: Any, state: Any, frames: Any, keys: list[jax.Array], top: int) -> dict[str, Any]:
    """Device time per update by kernel, from a JAX profiler trace of `PROFILED_UPDATES` more
    updates (`trace_summary.summarise`): what the update waits on, to set beside torch's kernels
    (`torch_vae_reference.py --kernels-top`). The trace itself is deleted; only the summary stays."""
    from trace_summary import summarise  # benchmarks/ is the script's folder

    with tempfile.TemporaryDirectory() as tmp:
        with jax.profiler.trace(tmp):
            for k in keys[:PROFILED_UPDATES]:
                state, _ = compiled(state, frames, k)
            jax.block_until_ready(state)
        files = sorted(glob.glob(os.path.join(tmp, "**", "*.xplane.pb"), recursive=True))
        if not files:
            return {"error": "the profiler wrote no trace"}
        summary = summarise(files[-1], top=top)
    n = min(PROFILED_UPDATES, len(keys))
    out: dict[str, Any] = {"updates": n}
    for plane, dev in summary["devices"].items():
        kern = dev["lines"].get("streams", {"total_ms": 0.0, "top": []})
        out[plane] = {"busy_ms_per_update": dev["busy_ms"] / n, "span_ms_per_update": dev["span_ms"] / n,
                      "kernel_ms_per_update": kern["total_ms"] / n,
                      "launches_per_update": dev["kernel_launches"] / n,
                      "top": [{"name": r["name"], "ms_per_update": r["ms"] / n, "count_per_update": r["count"] / n}
                              for r in kern["top"]]}
    return out


def run_learner(s: BenchSettings, w: ResultWriter) -> None:
    rows: list[dict[str, Any]] = w.results.setdefault("learner", [])
    for name in s.learners:
        impls = s.deconv_impls if name != "spair" else s.deconv_impls[:1]  # spair has no deconv
        for impl in impls:
            for dtype in s.dtypes:
                for prec in (s.precisions if dtype == "float32" else ("default",)):
                    for (variant, overrides), (xname, xopts) in itertools.product(s.variants, s.xla_variants):
                        log(f"learner {name} {dtype} {impl} precision={prec} variant={variant} "
                            f"xla={xname} batch={s.vae_batch} ...")
                        tag = {"variant": variant, "overrides": dict(overrides), "xla_variant": xname,
                               "xla_options": dict(xopts)}
                        try:
                            r = {**bench_vae(dtype, s, name, impl, prec, overrides, xopts), **tag}
                            log(f"  {r['updates_per_s']:.2f} updates/s; compile {r['compile_s']:.1f} s")
                        except Exception as e:  # noqa: BLE001
                            log(f"  FAILED: {type(e).__name__}: {e}")
                            r = {"learner": name, "dtype": dtype, "deconv_impl": impl, "precision": prec,
                                 **tag, "error": f"{type(e).__name__}: {e}"[:2000]}
                        rows.append(r)
                        w.write()


# ----------------------------------------------------------------------------- main


def parse_args(argv: list[str] | None = None) -> BenchSettings:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    d = BenchSettings()
    p.add_argument("--envs", default=",".join(d.envs), help="comma-separated environment names")
    p.add_argument("--batch-sizes", default=",".join(map(str, d.batch_sizes)),
                   help="comma-separated numbers of worlds (e.g. 8,32 on CPU)")
    p.add_argument("--steps", type=int, default=d.steps, help="env steps per jitted scan")
    p.add_argument("--repeats", type=int, default=d.repeats, help="timed scans per case")
    p.add_argument("--resolution", type=int, default=d.resolution)
    p.add_argument("--vae-batch", type=int, default=d.vae_batch)
    p.add_argument("--vae-steps", type=int, default=d.vae_steps, help="timed updates")
    p.add_argument("--vae-warmup", type=int, default=d.vae_warmup, help="untimed updates after compile")
    p.add_argument("--latent-dim", type=int, default=d.latent_dim)
    p.add_argument("--dtypes", default=",".join(d.dtypes), help="learner compute dtypes")
    p.add_argument("--learners", default=",".join(d.learners), help="learners to time (vae, svae, pred, dsa, spair, ...)")
    p.add_argument("--rnn-unroll", type=int, default=d.rnn_unroll,
                   help="sequential learners: LSTM steps per scan iteration (same function; try the window length)")
    p.add_argument("--deconv-impls", default=",".join(d.deconv_impls), help="decoder forms: transpose, subpixel, dgrad")
    p.add_argument("--variants", default=",".join(v for v, _ in d.variants),
                   help="learner configs timed side by side, comma-separated NAME[=KEY:VALUE;...] with KEY a "
                        "LearnerConfig field, e.g. default,pad8=channel_pad:8,split=bias_grad:split")
    p.add_argument("--xla-variants", default=",".join(v for v, _ in d.xla_variants),
                   help="XLA compile-option sets timed side by side, comma-separated NAME[=KEY:VALUE;...], "
                        "e.g. xla_default,cf=xla_gpu_experimental_enable_conv_fusion:true (a + in a VALUE is a comma: "
                        "cb=xla_gpu_enable_command_buffer:FUSION+CUBLAS+WHILE)")
    p.add_argument("--precisions", default=",".join(d.precisions),
                   help="fp32 matmul/conv precisions: default, tensorfloat32, highest")
    p.add_argument("--parts", default=",".join(d.parts), help=f"subset of {','.join(PARTS)}")
    p.add_argument("--no-torch-compile", action="store_true", help="reference: eager only")
    p.add_argument("--torch-channels-last", action="store_true", help="reference: channels_last layout")
    p.add_argument("--torch-timeout", type=float, default=d.torch_timeout_s, help="seconds")
    p.add_argument("--torch-forms", default=d.torch_forms,
                   help="reference: PyTorch's strongest forms too (torch_vae_reference.py --forms), e.g. all")
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--out-dir", default=d.out_dir)
    p.add_argument("--verbose", action="store_true", help="keep Warp's per-module load messages")
    p.add_argument("--kernels-top", type=int, default=d.kernels_top,
                   help="profile 5 more updates of every learner case (and of torch) and keep this many "
                        "kernels with the most device time in the JSON (0: no profile)")
    a = p.parse_args(argv)
    split = lambda text: tuple(x.strip() for x in text.split(",") if x.strip())  # noqa: E731
    return BenchSettings(
        envs=split(a.envs), batch_sizes=tuple(int(x) for x in split(a.batch_sizes)), steps=a.steps,
        repeats=a.repeats, resolution=a.resolution, vae_batch=a.vae_batch, vae_steps=a.vae_steps,
        vae_warmup=a.vae_warmup, latent_dim=a.latent_dim, dtypes=split(a.dtypes), parts=split(a.parts),
        learners=split(a.learners), deconv_impls=split(a.deconv_impls), precisions=split(a.precisions),
        rnn_unroll=a.rnn_unroll, variants=tuple(parse_variant(v) for v in split(a.variants)),
        xla_variants=tuple(parse_xla_variant(v) for v in split(a.xla_variants)),
        torch_compile=not a.no_torch_compile, torch_channels_last=a.torch_channels_last,
        torch_forms=a.torch_forms,
        torch_timeout_s=a.torch_timeout, seed=a.seed, out_dir=a.out_dir,
        verbose=a.verbose, kernels_top=a.kernels_top)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    s = parse_args(argv)
    s.check_envs()
    if s.verbose:  # importing bulbjax.envs made Warp quiet; turn its module-load messages back on
        import warp

        warp.config.log_level, warp.config.quiet = warp.LOG_INFO, False
    stamp = dt.datetime.now().strftime("%Y%m%d_%H%M%S")
    t_start = time.perf_counter()
    results: dict[str, Any] = {
        "command": shlex.join(["python", os.path.relpath(os.path.abspath(sys.argv[0]), REPO), *sys.argv[1:]])
        if argv is None else shlex.join(["bench_throughput", *argv]),
        "argv": sys.argv if argv is None else argv,
        "timestamp": stamp, "settings": asdict(s), "git_commit": git_commit(), "versions": versions(),
    }
    # The PyTorch reference runs first, before JAX takes (and preallocates) the accelerator.
    torch_info = run_torch_reference(s) if "torch" in s.parts else None
    results["device"] = device_info()
    w = ResultWriter(s.out_dir, device_slug(results["device"]["device_kind"]), stamp, results)
    if torch_info is not None:
        results["torch_reference"] = torch_info
    w.write()
    log(f"JAX device: {results['device']['device_kind']} ({results['device']['platform']}); "
        f"writing {w.paths[0]}")
    if "env" in s.parts:
        run_envs(s, w)
    if "learner" in s.parts:
        run_learner(s, w)
    if torch_info is not None and "learner" in s.parts:
        results["ratios"] = ratios(results["learner"], torch_info, results["device"]["platform"])
    results["total_s"] = time.perf_counter() - t_start
    w.write()
    print_summary(results)
    print(f"\nwritten: {w.paths[0]}\n         {w.paths[1]}")
    return results


if __name__ == "__main__":
    main()
