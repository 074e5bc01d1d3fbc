"""Summarise a JAX profiler trace (`*.xplane.pb`, e.g. from `profile_epoch.py --trace DIR`) into a
small JSON: for every GPU, the time its streams were busy against the traced span, the XLA
ops and kernels that took the most device time, and the runtime's copies and fills by the op
that made them, with their mean size where the tracer records it (`copies`). A trace is tens of
MB and needs TensorBoard to read; this keeps what decides where an epoch's time goes, small
enough to bring back from the GPU.

    python benchmarks/trace_summary.py TRACE_DIR --out summary.json [--top 40]

Where TRACE_DIR holds `*.hlo.txt` (the traced executables' optimised HLO; profile_epoch.py
writes them), the device time is also split by the epoch's phase scopes (`bj.rl`,
`bj.learn.vae`, `bj.eval`, ...: `jax.named_scope`s in `Experiment._epoch`).
"""

from __future__ import annotations

import argparse
import collections
import glob
import json
import os
import re
from typing import Any, Iterator

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


SCOPE_RE = re.compile(r"bj\.[\w.]+")


def hlo_scopes(hlo_text: str) -> dict[str, str]:
    """Instruction name -> the innermost `bj.*` named scope in its op_name metadata (the epoch's
    phases: `bj.rl`, `bj.learn.vae`, ...), from an executable's optimised HLO (`compiled.as_text()`):
    the names that a trace's kernels carry in their `hlo_op` stat. An instruction without such
    metadata (XLA drops it on some fusions it makes, e.g. its GEMM fusions) takes the scope that
    most instructions of the computation it calls (`calls=%...`) carry."""
    out: dict[str, str] = {}
    body: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    calls: dict[str, str] = {}
    comp = ""
    for line in hlo_text.splitlines():
        head = re.match(r"^(?:ENTRY )?%?([\w.\-]+) .*\{\s*$", line)
        if head and " = " not in line:
            comp = head.group(1)
            continue
        m = re.match(r"^\s*(?:ROOT )?%?([\w.\-]+) = ", line)
        if not m:
            continue
        meta = re.search(r'op_name="([^"]*)"', line)
        found = SCOPE_RE.findall(meta.group(1)) if meta else []
        if found:
            out[m.group(1)] = found[-1]
            body[comp][found[-1]] += 1
        else:
            called = re.search(r"calls=%?([\w.\-]+)", line)
            if called:
                calls[m.group(1)] = called.group(1)
    for name, callee in calls.items():
        if body.get(callee):
            out[name] = body[callee].most_common(1)[0][0]
    return out


# Kernels that no XLA instruction names: MuJoCo Warp's (launched inside its FFI calls, named
# `<function>_<hash>_cuda_kernel_forward`) and the runtime's copies and fills.
_CLASSES: tuple[tuple[str, str], ...] = (("_cuda_kernel_forward", "(warp)"), ("_cuda_kernel_backward", "(warp)"),
                                         ("Memcpy", "(memcpy)"), ("Memset", "(memset)"))


def _scope_of(ev: Any, scopes: dict[str, str]) -> str:
    """The `bj.*` scope of a trace event: from a string stat that carries op_name metadata, else
    its `hlo_op` (or name) looked up in `scopes`; "(unscoped)" where neither says."""
    op = ev.name
    for k, v in ev.stats:
        if isinstance(v, str):
            found = SCOPE_RE.findall(v)
            if found:
                return found[-1]
            if k == "hlo_op":
                op = v
    op = op.lstrip("%")
    # kernels may carry the instruction name with its last "." written "_" (fusion.12 -> fusion_12)
    head, _, tail = op.rpartition("_")
    found = scopes.get(op) or scopes.get(f"{head}.{tail}" if head else op)
    if found:
        return found
    return next((cls for part, cls in _CLASSES if part in ev.name), "(unscoped)")


_BYTES_RE = re.compile(r"\b(?:size|num_bytes|bytes)[:=]\s*(\d+)")


def copy_key(ev: Any, scope: str) -> tuple[str, str, int | None]:
    """(kind, the XLA op that made it or "(no op)", bytes or None) of a runtime copy or fill
    event: which copies an epoch makes, and how big they are (a Fig. 5 epoch's 77 us copies,
    docs/performance.md), from its `hlo_op` stat and the size its tracer records (an int stat
    named size/num_bytes/bytes, or `size:N` in a string stat such as `memcpy_details`)."""
    op, size = "(no op)", None
    for k, v in ev.stats:
        if k == "hlo_op" and isinstance(v, str):
            op = v.lstrip("%")
        elif isinstance(v, int) and k in ("size", "num_bytes", "bytes"):
            size = int(v)
        elif isinstance(v, str) and size is None:
            m = _BYTES_RE.search(v)
            if m:
                size = int(m.group(1))
    return ev.name, f"{op} [{scope}]", size


def _op_events(plane: Any) -> Iterator[tuple[str, Any]]:
    """(line name, event) of the plane's ops: GPU kernel streams, or on the CPU the thunks that
    carry an `hlo_op` stat (so the same summary runs on a CPU trace)."""
    for line in plane.lines:
        for ev in line.events:
            if line.name.startswith("Stream") or (plane.name.startswith("/host:CPU")
                                                   and any(k == "hlo_op" for k, _ in ev.stats)):
                yield line.name, ev


def host_windows(data: Any, name: str) -> list[tuple[int, int]]:
    """[start, end) of every host event called `name` (e.g. profile_epoch.py's `bj_timed_no_probe`
    annotations around its timed epochs)."""
    out = []
    for plane in data.planes:
        if plane.name.startswith("/host:CPU"):
            for line in plane.lines:
                out += [(int(ev.start_ns), int(ev.start_ns + ev.duration_ns)) for ev in line.events if ev.name == name]
    return sorted(out)


def _inside(iv: tuple[int, int], windows: list[tuple[int, int]]) -> bool:
    return any(s <= iv[0] and iv[1] <= e for s, e in windows)


def summarise(path: str, top: int = 40, scopes: dict[str, str] | None = None,
              window: str | None = None) -> dict[str, Any]:
    """Per device plane (every GPU, or the host CPU where there is none): busy time of all op
    streams merged, span, the top XLA ops / kernels, and device time by the epoch's phase scope
    (`scopes`: `hlo_scopes` of the traced executables). `window`: only the device events that
    lie inside host events of that name (their count and total length under `windows`), so that
    a trace of a whole run can be summarised over its timed epochs."""
    data = ProfileData.from_file(path)
    scopes = scopes or {}
    wins = host_windows(data, window) if window else []
    if window and not wins:
        raise SystemExit(f"no host event named {window!r} in {path}")
    planes = [p for p in data.planes if p.name.startswith("/device:GPU")]
    if not planes:
        planes = [p for p in data.planes if p.name.startswith("/host:CPU")]
    out: dict[str, Any] = {"trace": os.path.basename(path), "devices": {}}
    for plane in planes:
        time_ns: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
        count: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
        kernels: list[tuple[int, int]] = []
        by_scope: dict[str, list[tuple[int, int]]] = collections.defaultdict(list)
        unscoped: collections.Counter = collections.Counter()
        copies: dict[tuple[str, str], list[int]] = collections.defaultdict(lambda: [0, 0, 0, 0])
        for line in plane.lines:  # non-kernel lines (XLA Ops, XLA Modules) summed by name
            if not line.name.startswith("Stream") and plane.name.startswith("/device:GPU"):
                for ev in line.events:
                    if wins and not _inside((int(ev.start_ns), int(ev.start_ns + ev.duration_ns)), wins):
                        continue
                    time_ns[line.name][ev.name] += ev.duration_ns
                    count[line.name][ev.name] += 1
        for _, ev in _op_events(plane):
            iv = (int(ev.start_ns), int(ev.start_ns + ev.duration_ns))
            if wins and not _inside(iv, wins):
                continue
            kernels.append(iv)
            time_ns["streams"][ev.name] += ev.duration_ns
            count["streams"][ev.name] += 1
            scope = _scope_of(ev, scopes)
            by_scope[scope].append(iv)
            if scope == "(unscoped)":
                unscoped[ev.name] += ev.duration_ns
            if ev.name.startswith(("Memcpy", "Memset")):
                kind, where, size = copy_key(ev, scope)
                c = copies[(kind, where)]  # count, ns, bytes, events with a size
                c[0] += 1
                c[1] += ev.duration_ns
                c[2] += size or 0
                c[3] += size is not None
        span = (max(e for _, e in kernels) - min(s for s, _ in kernels)) if kernels else 0
        dev: dict[str, Any] = {"span_ms": span / 1e6, "busy_ms": _merge(kernels) / 1e6,
                               "kernel_launches": len(kernels), "lines": {}, "scopes": {}}
        for key, c in time_ns.items():
            dev["lines"][key] = {"total_ms": sum(c.values()) / 1e6,
                                 "top": [{"name": k[:160], "ms": v / 1e6, "count": count[key][k]}
                                         for k, v in c.most_common(top)]}
        for scope, ivs in sorted(by_scope.items(), key=lambda kv: -sum(e - s for s, e in kv[1])):
            dev["scopes"][scope] = {"kernel_ms": sum(e - s for s, e in ivs) / 1e6,
                                    "busy_ms": _merge(ivs) / 1e6, "launches": len(ivs)}
        dev["unscoped_top"] = [{"name": k[:160], "ms": v / 1e6} for k, v in unscoped.most_common(top)]
        dev["copies"] = [{"kind": kind, "op": where[:160], "count": c[0], "ms": c[1] / 1e6,
                          "mean_bytes": (c[2] / c[3]) if c[3] else None}
                         for (kind, where), c in sorted(copies.items(), key=lambda kv: -kv[1][1])[:top]]
        out["devices"][plane.name] = dev
    if wins:
        out["windows"] = {"name": window, "count": len(wins), "total_ms": sum(e - s for s, e in wins) / 1e6}
    return out


def summarise_dir(trace_dir: str, top: int = 40, window: str | None = None) -> dict[str, Any]:
    """`summarise` of the newest `*.xplane.pb` under `trace_dir`, with the phase scopes of the
    `*.hlo.txt` files beside it (profile_epoch.py writes them; other traces have none)."""
    files = sorted(glob.glob(os.path.join(trace_dir, "**", "*.xplane.pb"), recursive=True))
    if not files:
        raise FileNotFoundError(f"no *.xplane.pb under {trace_dir}: was the trace written (profile_epoch.py --trace)?")
    scopes: dict[str, str] = {}
    for h in sorted(glob.glob(os.path.join(trace_dir, "**", "*.hlo.txt"), recursive=True)):
        with open(h) as f:
            scopes.update(hlo_scopes(f.read()))
    return summarise(files[-1], top, scopes, window)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("trace_dir")
    p.add_argument("--out", required=True)
    p.add_argument("--top", type=int, default=40)
    p.add_argument("--window", default="", help="only device events inside host events of this name "
                                                 "(profile_epoch.py: bj_timed_no_probe, bj_timed_probe)")
    a = p.parse_args()
    try:
        res = summarise_dir(a.trace_dir, a.top, a.window or None)
    except FileNotFoundError as err:
        raise SystemExit(str(err)) from None
    with open(a.out, "w") as f:
        json.dump(res, f, indent=1)
    for dev, d in res["devices"].items():
        print(f"{dev}: span {d['span_ms']:.0f} ms, kernels busy {d['busy_ms']:.0f} ms, {d['kernel_launches']} launches")
        for scope, v in d["scopes"].items():
            print(f"  scope {scope:24} kernels {v['kernel_ms']:9.1f} ms, busy {v['busy_ms']:9.1f} ms, x{v['launches']}")
        for line, v in d["lines"].items():
            print(f"  [{line}] total {v['total_ms']:.0f} ms")
            for row in v["top"][:15]:
                print(f"    {row['ms']:9.1f} ms x{row['count']:<6} {row['name'][:110]}")
        for row in d["copies"][:8]:
            size = "size not recorded" if row["mean_bytes"] is None else f"{row['mean_bytes'] / 1e6:.3f} MB each"
            print(f"  copies {row['ms']:9.1f} ms x{row['count']:<6} {row['kind']} by {row['op'][:70]} ({size})")


if __name__ == "__main__":
    main()
