"""Summarise a JAX profiler trace (`*.xplane.pb`, e.g. from `profile_epoch.py --trace DIR`) into a
small JSON: for every GPU, the time its streams were busy against the traced span, and the XLA
ops and kernels that took the most device time. A trace is tens of MB and needs TensorBoard to
read; this keeps what decides where an epoch's time goes, small enough to bring back from the GPU.

    python benchmarks/trace_summary.py TRACE_DIR --out summary.json [--top 40]
"""

from __future__ import annotations

import argparse
import collections
import glob
import json
import os
from typing import Any

from jax.profiler import ProfileData


def _merge(intervals: list[tuple[int, int]]) -> int:
    """Total length covered by [start, end) intervals (ns)."""
    total, end = 0, None
    start = None
    for s, e in sorted(intervals):
        if end is None or s > end:
            if end is not None:
                total += end - start
            start, end = s, e
        else:
            end = max(end, e)
    return total + (end - start if end is not None else 0)


def summarise(path: str, top: int = 40) -> dict[str, Any]:
    """Per GPU plane: busy time of all kernel streams merged, span, and the top XLA ops / kernels."""
    data = ProfileData.from_file(path)
    out: dict[str, Any] = {"trace": os.path.basename(path), "devices": {}}
    for plane in data.planes:
        if not plane.name.startswith("/device:GPU"):
            continue
        # kernel streams are summed as one line ("streams"); other lines (XLA Ops, Modules) apart
        time_ns: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
        count: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
        kernels: list[tuple[int, int]] = []
        for line in plane.lines:
            stream = line.name.startswith("Stream")
            key = "streams" if stream else line.name
            for ev in line.events:
                time_ns[key][ev.name] += ev.duration_ns
                count[key][ev.name] += 1
                if stream:
                    kernels.append((int(ev.start_ns), int(ev.start_ns + ev.duration_ns)))
        span = (max(e for _, e in kernels) - min(s for s, _ in kernels)) if kernels else 0
        dev: dict[str, Any] = {"span_ms": span / 1e6, "busy_ms": _merge(kernels) / 1e6,
                               "kernel_launches": len(kernels), "lines": {}}
        for key, c in time_ns.items():
            dev["lines"][key] = {"total_ms": sum(c.values()) / 1e6,
                                 "top": [{"name": k[:160], "ms": v / 1e6, "count": count[key][k]}
                                         for k, v in c.most_common(top)]}
        out["devices"][plane.name] = dev
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("trace_dir")
    p.add_argument("--out", required=True)
    p.add_argument("--top", type=int, default=40)
    a = p.parse_args()
    files = sorted(glob.glob(os.path.join(a.trace_dir, "**", "*.xplane.pb"), recursive=True))
    if not files:
        raise SystemExit(f"no *.xplane.pb under {a.trace_dir}: was the trace written (profile_epoch.py --trace)?")
    res = summarise(files[-1], a.top)
    with open(a.out, "w") as f:
        json.dump(res, f, indent=1)
    for dev, d in res["devices"].items():
        print(f"{dev}: span {d['span_ms']:.0f} ms, kernels busy {d['busy_ms']:.0f} ms, {d['kernel_launches']} launches")
        for line, v in d["lines"].items():
            print(f"  [{line}] total {v['total_ms']:.0f} ms")
            for row in v["top"][:15]:
                print(f"    {row['ms']:9.1f} ms x{row['count']:<6} {row['name'][:110]}")


if __name__ == "__main__":
    main()
