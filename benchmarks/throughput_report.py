"""`bench_throughput.py`'s reporting side: the PyTorch reference (`torch_vae_reference.py` run in a
subprocess: torch and JAX never share a process or GPU memory; what it measured kept when it runs
out of time), the bulbjax/PyTorch ratios per dtype, and the printed summary."""

from __future__ import annotations

import importlib.util
import json
import os
import shlex
import subprocess
import sys
import tempfile
from typing import Any

HERE = os.path.dirname(os.path.abspath(__file__))


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def run_torch_reference(s: Any) -> dict[str, Any]:
    """`torch_vae_reference.py` in a subprocess (torch and JAX never share a process or GPU memory)."""
    if importlib.util.find_spec("torch") is None:
        return {"available": False, "reason": "torch is not installed in this environment; reference skipped"}
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "torch.json")
        cmd = [sys.executable, os.path.join(HERE, "torch_vae_reference.py"), "--batch", str(s.vae_batch),
               "--resolution", str(s.resolution), "--latent-dim", str(s.latent_dim),
               "--steps", str(s.vae_steps), "--warmup", str(max(s.vae_warmup, 3)),
               "--dtypes", ",".join(s.dtypes), "--json-out", out]
        cmd += [] if s.torch_compile else ["--no-compile"]
        cmd += ["--channels-last"] if s.torch_channels_last else []
        cmd += ["--kernels-top", str(s.kernels_top)] if s.kernels_top else []
        cmd += ["--forms", s.torch_forms] if s.torch_forms else []
        log("torch reference: " + shlex.join(cmd))
        try:
            proc = subprocess.run(cmd, timeout=s.torch_timeout_s)
        except subprocess.TimeoutExpired:  # what it measured before the timeout (written after each form)
            why = f"torch reference timed out after {s.torch_timeout_s} s"
            if os.path.exists(out):
                with open(out) as f:
                    return {**json.load(f), "reason": why}
            return {"available": False, "reason": why}
        if proc.returncode != 0 or not os.path.exists(out):
            return {"available": False, "reason": f"torch reference exited with status {proc.returncode}"}
        with open(out) as f:
            return json.load(f)


def ratios(learner_rows: list[dict[str, Any]], torch_info: dict[str, Any], platform_: str) -> dict[str, Any]:
    """bulbjax updates/s divided by PyTorch's, per dtype, against eager, compiled and the faster."""
    if not torch_info.get("available"):
        return {"skipped": torch_info.get("reason", "no torch reference")}
    same = {"gpu": "cuda", "cpu": "cpu"}.get(platform_) == torch_info.get("device")
    if not same:
        return {"skipped": f"torch ran on {torch_info.get('device')}, JAX on {platform_}: not comparable"}
    out: dict[str, Any] = {}
    for row in learner_rows:
        if "updates_per_s" not in row or row.get("learner", "vae") != "vae":
            continue
        ref = {r["mode"]: r["updates_per_s"] for r in torch_info["results"]
               if r.get("dtype") == row["dtype"] and "updates_per_s" in r}
        d: dict[str, float] = {f"vs_torch_{m}": row["updates_per_s"] / v for m, v in ref.items()}
        if ref:
            d["vs_torch_best"] = row["updates_per_s"] / max(ref.values())
        variant = "" if row.get("variant", "default") == "default" else f" {row['variant']}"
        variant += xla_tag(row)
        out[f"{row['dtype']} {row.get('deconv_impl', 'transpose')} {row.get('precision', 'default')}{variant}"] = d
    return out


def xla_tag(row: dict[str, Any]) -> str:
    """` NAME` of a row's `--xla-variants` set, empty for the default compile options."""
    name = row.get("xla_variant", "xla_default")
    return "" if name == "xla_default" else f" {name}"


def fmt_rate(x: float) -> str:
    """1234567 -> '1.23 M'."""
    for div, unit in ((1e9, "G"), (1e6, "M"), (1e3, "K")):
        if x >= div:
            return f"{x / div:.3g} {unit}"
    return f"{x:.3g}"


def print_kernels(k: dict[str, Any] | None, rows: int = 6) -> None:
    """The kernel breakdown of one case (`--kernels-top`): time per update, the top kernels."""
    if not k:
        return
    devs = [v for v in k.values() if isinstance(v, dict) and "top" in v] or [k]
    for d in devs:
        busy = f", busy {d['busy_ms_per_update']:.2f}" if "busy_ms_per_update" in d else ""
        print(f"      kernels {d['kernel_ms_per_update']:.2f} ms/update{busy}, "
              f"{d['launches_per_update']:.0f} launches/update")
        for r in d["top"][:rows]:
            print(f"        {r['ms_per_update']:7.3f} ms x{r['count_per_update']:<4.0f} {r['name'][:90]}")


def print_summary(results: dict[str, Any]) -> None:
    """Tables of the figures on stdout."""
    dev = results["device"]
    print(f"\n== bulbjax throughput on {dev['device_kind']} ({dev['platform']}) ==")
    if results.get("env"):
        print(f"{'env':18} {'N':>6} {'mode':9} {'median/s':>10} {'best/s':>10} {'compile s':>9} {'first s':>8}")
        for r in results["env"]:
            if "error" in r:
                print(f"{r['env']:18} {r['batch_size']:>6} {r['mode']:9} ERROR {r['error'][:60]}")
                continue
            print(f"{r['env']:18} {r['batch_size']:>6} {r['mode']:9} {fmt_rate(r['per_s_median']):>10} "
                  f"{fmt_rate(r['per_s_best']):>10} {r['compile_s']:>9.1f} {r['first_call_s']:>8.2f}")
    if results.get("learner"):
        print(f"\nlearner updates/s at {results['settings']['vae_batch']} frames per batch (spair: 64):")
        for r in results["learner"]:
            label = (f"{r.get('learner', 'vae'):8} {r['dtype']:9} {r.get('deconv_impl', 'transpose'):9} "
                     f"{r.get('precision', 'default'):13} {r.get('variant', 'default'):10}{xla_tag(r)}")
            print(f"  bulbjax {label} " + (f"{r['updates_per_s']:8.2f}  (compile {r['compile_s']:.1f} s)"
                                           if "updates_per_s" in r else f"ERROR {r['error'][:60]}"))
            print_kernels(r.get("kernels"))
    t = results.get("torch_reference")
    if t is not None:
        if not t.get("available"):
            print(f"  torch reference skipped: {t.get('reason')}")
        else:
            for r in t["results"]:
                label = f"torch {r['mode']:7} {r['dtype']:9}"
                print(f"  {label} " + (f"{r['updates_per_s']:8.2f}  (warm-up {r['warmup_s']:.1f} s)"
                                       if "updates_per_s" in r else f"ERROR {r['error'][:60]}"))
                print_kernels(r.get("kernels"))
        for dtype, d in (results.get("ratios") or {}).items():
            if isinstance(d, dict):
                print(f"  ratio bulbjax/torch {dtype}: " + ", ".join(f"{k} {v:.2f}" for k, v in d.items()))
