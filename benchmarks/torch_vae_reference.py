"""PyTorch reference of bulbjax's `vae` learner, for update-throughput comparisons.

The same network and loss as `bulbjax.learners` (VAE with `LearnerConfig` defaults):
encoder of 4x4 stride-2 convs (64, 64, 128, 256 filters, ReLU), FC 512 (ReLU), linear
mean and log-variance heads; decoder FC 512 -> FC (R/16)^2 * 256 -> 4x4 stride-2
transposed convs (128, 64, 64, 3) with ReLU between; Bernoulli (sigmoid cross-entropy)
likelihood summed over pixels and averaged over the batch, plus KL to N(0, I); Adam.
The update takes uint8 frames and scales them to [0, 1] itself, like bulbjax's.

Run as a script it times eager and `torch.compile` updates, fp32 and bf16 autocast, on
CUDA when available (else CPU), and writes one JSON object (see `main`); it is what
`bench_throughput.py` calls in a subprocess, so that torch and JAX never share a process.

`--forms` adds PyTorch's strongest forms of the same update (`FORMS`), each timed in bf16
autocast (and fp32 where asked): the whole update (forward, backward and
`Adam(capturable=True, fused=True)`) captured in one `torch.cuda.CUDAGraph` and replayed, with
eager kernels (`graph`) or with `torch.compile(mode="max-autotune-no-cudagraphs")` kernels
(`autotune-graph`), each also in the channels_last layout (`-cl`). The best of all forms is what
bulbjax's ratio is taken against.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import traceback
from dataclasses import asdict, dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

FEATURES: tuple[int, ...] = (64, 64, 128, 256)


class TorchVAE(nn.Module):
    """Conv VAE on NCHW frames in [0, 1]; `forward` returns (logits, mean, logvar)."""

    def __init__(self, latent_dim: int, resolution: int = 64, features: tuple[int, ...] = FEATURES,
                 hidden: int = 512, channels: int = 3):
        super().__init__()
        if resolution % 2 ** len(features):
            raise ValueError(f"resolution must be a multiple of {2 ** len(features)}, got {resolution}")
        self.start = resolution // 2 ** len(features)
        self.last = features[-1]
        convs: list[nn.Module] = []
        c_in = channels
        for f in features:
            # k=4, s=2, p=1 halves the side exactly, like Flax's padding='SAME'.
            convs += [nn.Conv2d(c_in, f, 4, stride=2, padding=1), nn.ReLU()]
            c_in = f
        flat = self.start * self.start * self.last
        self.encoder = nn.Sequential(*convs, nn.Flatten(), nn.Linear(flat, hidden), nn.ReLU())
        self.mean = nn.Linear(hidden, latent_dim)
        self.logvar = nn.Linear(hidden, latent_dim)
        self.dec_fc = nn.Sequential(nn.Linear(latent_dim, hidden), nn.ReLU(), nn.Linear(hidden, flat), nn.ReLU())
        deconvs: list[nn.Module] = []
        outs = (*reversed(features[:-1]), channels)
        c_in = self.last
        for i, f in enumerate(outs):
            # k=4, s=2, p=1 doubles the side exactly, like Flax's ConvTranspose padding='SAME'.
            deconvs.append(nn.ConvTranspose2d(c_in, f, 4, stride=2, padding=1))
            if i < len(outs) - 1:
                deconvs.append(nn.ReLU())
            c_in = f
        self.decoder = nn.Sequential(*deconvs)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        h = self.encoder(x)
        # Heads in fp32, like bulbjax's (autocast would otherwise run them in bf16).
        with torch.autocast(x.device.type, enabled=False):
            h = h.float()
            mean, logvar = self.mean(h), self.logvar(h)
        z = mean + torch.exp(0.5 * logvar) * torch.randn_like(mean)
        h = self.dec_fc(z).view(-1, self.last, self.start, self.start)
        return self.decoder(h).float(), mean, logvar


def vae_loss(model: nn.Module, frames_u8: torch.Tensor, beta: float = 1.0) -> torch.Tensor:
    """Negative ELBO of uint8 NCHW frames: summed sigmoid cross-entropy + beta * KL, batch mean."""
    x = frames_u8.float() / 255.0
    logits, mean, logvar = model(x)
    recon = F.binary_cross_entropy_with_logits(logits, x, reduction="none").sum(dim=(1, 2, 3)).mean()
    kl = (0.5 * (logvar.exp() + mean.square() - 1.0 - logvar)).sum(dim=-1).mean()
    return recon + beta * kl


@dataclass(frozen=True)
class TorchBenchSettings:
    """What one reference run measures."""

    batch: int = 1024
    resolution: int = 64
    latent_dim: int = 32
    steps: int = 50
    warmup: int = 5
    lr: float = 1e-4
    compile: bool = True
    channels_last: bool = False
    dtypes: tuple[str, ...] = ("float32", "bfloat16")
    seed: int = 0
    kernels_top: int = 0  # > 0: profile PROFILED_UPDATES more updates, keep this many kernels
    forms: tuple[str, ...] = ()  # of FORMS: the strongest forms (CUDA only)
    form_dtypes: tuple[str, ...] = ("bfloat16",)


PROFILED_UPDATES = 5
# the strongest forms: (compile mode or None for eager kernels, channels_last)
FORMS: dict[str, tuple[str | None, bool]] = {
    "graph": (None, False), "graph-cl": (None, True),
    "autotune-graph": ("max-autotune-no-cudagraphs", False),
    "autotune-graph-cl": ("max-autotune-no-cudagraphs", True),
}


def kernel_breakdown(step: Any, device: torch.device, top: int) -> dict[str, Any]:
    """Device time per update by kernel (torch.profiler over `PROFILED_UPDATES` more updates), to
    set beside bulbjax's (`bench_throughput.py --kernels-top`)."""
    from torch.profiler import ProfilerActivity, profile

    acts = [ProfilerActivity.CUDA] if device.type == "cuda" else [ProfilerActivity.CPU]
    with profile(activities=acts) as prof:
        for _ in range(PROFILED_UPDATES):
            step()
        _sync(device)
    rows = []
    for ev in prof.key_averages():
        us = getattr(ev, "self_device_time_total", None)
        if us is None:  # torch < 2.4 names it after CUDA
            us = getattr(ev, "self_cuda_time_total", 0) if device.type == "cuda" else ev.self_cpu_time_total
        if us > 0:
            rows.append((ev.key, us, ev.count))
    rows.sort(key=lambda r: -r[1])
    n = PROFILED_UPDATES
    return {"updates": n, "kernel_ms_per_update": sum(r[1] for r in rows) / 1e3 / n,
            "launches_per_update": sum(r[2] for r in rows) / n,
            "top": [{"name": k[:160], "ms_per_update": us / 1e3 / n, "count_per_update": c / n}
                    for k, us, c in rows[:top]]}


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_updates(settings: TorchBenchSettings, device: torch.device, dtype: str, compiled: bool) -> dict[str, Any]:
    """Time `settings.steps` Adam updates (after `settings.warmup`) of one fresh model."""
    torch.manual_seed(settings.seed)
    model = TorchVAE(settings.latent_dim, settings.resolution).to(device)
    fmt = torch.channels_last if settings.channels_last else torch.contiguous_format
    model = model.to(memory_format=fmt)
    opt_kwargs: dict[str, Any] = {"fused": True} if device.type == "cuda" else {}
    opt = torch.optim.Adam(model.parameters(), lr=settings.lr, **opt_kwargs)
    frames = torch.randint(0, 256, (settings.batch, 3, settings.resolution, settings.resolution),
                           dtype=torch.uint8, device=device).contiguous(memory_format=fmt)
    loss_fn = torch.compile(vae_loss) if compiled else vae_loss
    amp = dtype == "bfloat16"

    def step() -> torch.Tensor:
        opt.zero_grad(set_to_none=True)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=amp):
            loss = loss_fn(model, frames)
        loss.backward()
        opt.step()
        return loss.detach()

    t0 = time.perf_counter()
    for _ in range(settings.warmup):
        loss = step()
    _sync(device)
    warmup_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(settings.steps):
        loss = step()
    _sync(device)
    elapsed = time.perf_counter() - t0
    final = float(loss)
    kernels = kernel_breakdown(step, device, settings.kernels_top) if settings.kernels_top else None
    return {"mode": "compile" if compiled else "eager", "dtype": dtype, "batch": settings.batch,
            "steps": settings.steps, "warmup_steps": settings.warmup, "warmup_s": warmup_s,
            "elapsed_s": elapsed, "updates_per_s": settings.steps / elapsed,
            "final_loss": final, "finite": bool(torch.isfinite(torch.tensor(final))),
            **({"kernels": kernels} if kernels else {})}


def time_graph_updates(settings: TorchBenchSettings, device: torch.device, dtype: str, form: str) -> dict[str, Any]:
    """Time the whole update captured in one CUDA graph (`FORMS[form]`): warm-up on a side stream
    (which also compiles the loss with `torch.compile` where the form says), capture of forward,
    backward and the capturable fused Adam step, then `settings.steps` replays."""
    if device.type != "cuda":
        raise RuntimeError("CUDA graphs need a CUDA device")
    mode, channels_last = FORMS[form]
    torch.manual_seed(settings.seed)
    fmt = torch.channels_last if channels_last else torch.contiguous_format
    model = TorchVAE(settings.latent_dim, settings.resolution).to(device).to(memory_format=fmt)
    opt = torch.optim.Adam(model.parameters(), lr=settings.lr, capturable=True, fused=True)
    frames = torch.randint(0, 256, (settings.batch, 3, settings.resolution, settings.resolution),
                           dtype=torch.uint8, device=device).contiguous(memory_format=fmt)
    loss_fn = torch.compile(vae_loss, mode=mode) if mode else vae_loss
    amp = dtype == "bfloat16"

    def body() -> torch.Tensor:
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=amp):
            loss = loss_fn(model, frames)
        loss.backward()
        opt.step()
        return loss

    t0 = time.perf_counter()
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        for _ in range(max(settings.warmup, 3)):
            opt.zero_grad(set_to_none=True)
            body()
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    opt.zero_grad(set_to_none=True)
    with torch.cuda.graph(graph):
        static_loss = body()
    graph.replay()
    _sync(device)
    warmup_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(settings.steps):
        graph.replay()
    _sync(device)
    elapsed = time.perf_counter() - t0
    final = float(static_loss)
    kernels = kernel_breakdown(graph.replay, device, settings.kernels_top) if settings.kernels_top else None
    return {"mode": form, "dtype": dtype, "batch": settings.batch, "steps": settings.steps,
            "warmup_steps": settings.warmup, "warmup_s": warmup_s, "elapsed_s": elapsed,
            "updates_per_s": settings.steps / elapsed, "final_loss": final,
            "finite": bool(torch.isfinite(torch.tensor(final))), **({"kernels": kernels} if kernels else {})}


def run_reference(settings: TorchBenchSettings, device: torch.device,
                  partial: Any = None) -> dict[str, Any]:
    """All (mode, dtype) measurements; a failing one is recorded with its error and skipped.
    `partial(info)` is called with the results so far after each one (the script writes them,
    so a run cut short by its caller's timeout keeps what it measured)."""
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True

    class _Results(list):
        def append(self, r: dict[str, Any]) -> None:
            super().append(r)
            if partial is not None:
                partial({"available": True, "partial": True, "torch_version": torch.__version__,
                         "device": device.type, "settings": asdict(settings), "results": list(self)})

    results = _Results()
    modes = [False, True] if settings.compile else [False]
    for compiled in modes:
        for dtype in settings.dtypes:
            label = f"{'compile' if compiled else 'eager'} {dtype}"
            print(f"[torch] {label} ...", file=sys.stderr, flush=True)
            try:
                r = time_updates(settings, device, dtype, compiled)
                print(f"[torch] {label}: {r['updates_per_s']:.2f} updates/s "
                      f"(warm-up {r['warmup_s']:.1f} s)", file=sys.stderr, flush=True)
            except Exception as e:  # noqa: BLE001 - a failed variant must not end the benchmark
                traceback.print_exc(file=sys.stderr)
                r = {"mode": "compile" if compiled else "eager", "dtype": dtype,
                     "error": f"{type(e).__name__}: {e}"[:2000]}
            results.append(r)
            if device.type == "cuda":
                torch.cuda.empty_cache()
    for form in settings.forms:
        for dtype in settings.form_dtypes:
            label = f"{form} {dtype}"
            print(f"[torch] {label} ...", file=sys.stderr, flush=True)
            try:
                r = time_graph_updates(settings, device, dtype, form)
                print(f"[torch] {label}: {r['updates_per_s']:.2f} updates/s "
                      f"(warm-up and capture {r['warmup_s']:.1f} s)", file=sys.stderr, flush=True)
            except Exception as e:  # noqa: BLE001 - a failed form must not end the benchmark
                traceback.print_exc(file=sys.stderr)
                r = {"mode": form, "dtype": dtype, "error": f"{type(e).__name__}: {e}"[:2000]}
            results.append(r)
            if device.type == "cuda":
                torch.cuda.empty_cache()
    ok = [r for r in results if "updates_per_s" in r]
    best: dict[str, Any] = {}
    for dtype in {r["dtype"] for r in ok}:
        top = max((r for r in ok if r["dtype"] == dtype), key=lambda r: r["updates_per_s"])
        best[dtype] = {"form": top["mode"], "updates_per_s": top["updates_per_s"]}
    info: dict[str, Any] = {"available": True, "torch_version": torch.__version__, "device": device.type,
                            "settings": asdict(settings), "results": results, "best": best,
                            "cudnn_allow_tf32": torch.backends.cudnn.allow_tf32,
                            "matmul_allow_tf32": torch.backends.cuda.matmul.allow_tf32}
    if device.type == "cuda":
        info["device_name"] = torch.cuda.get_device_name(device)
        info["cuda_version"] = torch.version.cuda
        info["cudnn_version"] = torch.backends.cudnn.version()
    return info


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--batch", type=int, default=1024)
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--latent-dim", type=int, default=32)
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument("--no-compile", action="store_true", help="skip the torch.compile variants")
    p.add_argument("--channels-last", action="store_true", help="channels_last memory format")
    p.add_argument("--dtypes", default="float32,bfloat16")
    p.add_argument("--device", default="auto", help="auto (cuda if available), cuda or cpu")
    p.add_argument("--json-out", default="-", help="file for the JSON result, '-' for stdout")
    p.add_argument("--kernels-top", type=int, default=0,
                   help="profile 5 more updates per case; keep this many kernels by device time")
    p.add_argument("--forms", default="", help=f"strongest forms to add (CUDA): comma-separated of {', '.join(FORMS)}, or all")
    p.add_argument("--form-dtypes", default="bfloat16", help="dtypes of the --forms")
    a = p.parse_args(argv)
    forms = tuple(FORMS) if a.forms == "all" else tuple(f for f in a.forms.split(",") if f)
    if bad := [f for f in forms if f not in FORMS]:
        p.error(f"unknown --forms {bad}; choose from {', '.join(FORMS)} or all")
    settings = TorchBenchSettings(batch=a.batch, resolution=a.resolution, latent_dim=a.latent_dim,
                                  steps=a.steps, warmup=a.warmup, compile=not a.no_compile,
                                  channels_last=a.channels_last, dtypes=tuple(a.dtypes.split(",")),
                                  kernels_top=a.kernels_top, forms=forms,
                                  form_dtypes=tuple(a.form_dtypes.split(",")))
    name = ("cuda" if torch.cuda.is_available() else "cpu") if a.device == "auto" else a.device
    def write(obj: dict[str, Any]) -> None:
        if a.json_out != "-":
            tmp = f"{a.json_out}.tmp"
            with open(tmp, "w") as f:
                json.dump(obj, f, indent=2)
            os.replace(tmp, a.json_out)

    info = run_reference(settings, torch.device(name), partial=write)
    text = json.dumps(info, indent=2)
    if a.json_out == "-":
        print(text)
    else:
        with open(a.json_out, "w") as f:
            f.write(text)


if __name__ == "__main__":
    main()
