"""Driving an offline fit (`bulbjax fit`) on a machine: its dataset collected once and cached on
disk (`load_or_collect`), its folder (`config.json`, `curves.jsonl`, checkpoints), a budget of
wall time, and resume. The fit's programs are `bulbjax.epoch.offline` (`OfflineFit`), its records
and reports `bulbjax.report.offline`."""

from __future__ import annotations

import dataclasses
import json
import os
import time
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from bulbjax.offline_config import OfflineConfig
from bulbjax.data import sequence
from bulbjax.data.sequence import Trajectories
from bulbjax.epoch import OfflineFit, Source, reference_spread
from bulbjax.learners import check_finite
from bulbjax.report import read_jsonl, records_of, summary_line, write_jsonl, write_jsonl_atomic, write_outputs
from bulbjax.run import rundir
from bulbjax.run.checkpoint import CHECKPOINT_DIR, Checkpointer


def dataset_path(config: OfflineConfig, source: Source, cache_dir: str, kind: str, steps: int) -> str:
    """Cache file of a dataset, keyed by env, object version (where not 0), frame size, worlds x
    steps, seed and kind: two fits that share a `--cache-dir` read the same file only when it
    holds their data (the versions of a multi-object domain are other scenes)."""
    r = source.frame_shape[0]
    version = config.base.version
    name = source.name + (f"_v{version}" if version != 0 else "")
    tag = f"{name}_{r}px_{config.data_worlds}x{steps}_seed{config.data_seed}_{kind}"
    if config.synthetic:
        m = config.movers_config()
        tag += f"_k{m.num_objects}s{m.size:g}v{m.max_speed:g}e{m.episode_length}"
    return os.path.join(cache_dir, tag + ".npz")


def load_or_collect(config: OfflineConfig, source: Source, cache_dir: str | None
                    ) -> tuple[Trajectories, Trajectories, bool]:
    """(training data, held-out data, whether both came from the cache). Collected once with
    the data seed (held-out: another key, so other worlds) and saved under `cache_dir`."""
    key = jax.random.PRNGKey(config.data_seed)
    out, cached = [], True
    for kind, steps, k in (("train", config.data_steps, jax.random.fold_in(key, 0)),
                           ("heldout", config.heldout_steps, jax.random.fold_in(key, 1))):
        path = dataset_path(config, source, cache_dir, kind, steps) if cache_dir else None
        if path and os.path.exists(path):
            with np.load(path) as z:
                traj = Trajectories(**{f: jnp.asarray(z[f]) for f in ("frames", "actions", "states", "dones")})
        else:
            cached = False
            traj = source.collect(k, steps)
            if path:
                os.makedirs(cache_dir, exist_ok=True)
                tmp = path + ".tmp.npz"
                np.savez(tmp, **{f: np.asarray(getattr(traj, f)) for f in ("frames", "actions", "states", "dones")})
                os.replace(tmp, path)
        out.append(traj)
    return out[0], out[1], cached


def _config_json(c: OfflineConfig, offline: OfflineFit, seed: int) -> dict[str, Any]:
    return json.loads(json.dumps({"offline": {k: v for k, v in dataclasses.asdict(c).items() if k != "base"},
                                  "base": dataclasses.asdict(c.base), "source": offline.source.name,
                                  "seed": seed}, default=str))


def _check_resumable(out_dir: str, now: dict[str, Any]) -> None:
    """A fit continues only with the settings it was started with (`updates` may grow)."""
    path = os.path.join(out_dir, "config.json")
    if not os.path.exists(path):
        raise ValueError(f"--resume: {path} does not exist; is {out_dir} the --out of a `bulbjax fit`?")
    with open(path) as f:
        saved = json.load(f)
    saved.get("base", {}).setdefault("learner_modules", [])  # fits written before the field
    diff = [k for k in sorted(set(saved["offline"]) | set(now["offline"]))
            if k != "updates" and saved["offline"].get(k) != now["offline"].get(k)]
    diff += [k for k in ("base", "source", "seed") if saved.get(k) != now.get(k)]
    if diff:
        raise ValueError(f"--resume: {out_dir} was fitted with other settings ({', '.join(diff)} differ); "
                         "give the same flags as its first call (only --updates may change)")


def fit(config: OfflineConfig, out_dir: str, cache_dir: str | None = None, max_minutes: float = 0.0,
        seed: int = 0, log: Callable[[str], None] = print, resume: bool = False,
        overwrite: bool = False) -> list[dict[str, Any]]:
    """The whole offline fit: data (cached), training, a probe at update 0 and every
    `probe_every` updates (and at the end), `curves.jsonl`, `curves.png`, `table.md`,
    `recon.png`, `config.json` under `out_dir`. Stops cleanly after `max_minutes` of wall time
    (then the last chunk is probed and everything is written) and checkpoints the learners, the
    key chain and the update count under `out_dir/checkpoints` (the newest only). `resume`
    continues such a fit, same settings (a larger `updates` extends it), appending to
    `curves.jsonl`: a fit longer than one stretch of GPU time is several calls. A fresh fit
    refuses a folder that holds a fit (ValueError naming it) unless `overwrite`, which replaces
    its curves and checkpoints (the dataset cache stays). Returns all records."""
    c = config
    t0 = time.time()
    rundir.check_out_dir(out_dir, resume=resume, overwrite=overwrite, fit=True)  # nothing lost by accident
    rundir.remove_stale_temporaries(out_dir)
    cache_dir = cache_dir if cache_dir is not None else os.path.join(out_dir, "data")
    offline = OfflineFit(c)
    cfg_json = _config_json(c, offline, seed)
    if resume:
        _check_resumable(out_dir, cfg_json)
    else:
        tmp = os.path.join(out_dir, f"config.json.tmp{os.getpid()}")
        with open(tmp, "w") as f:
            json.dump(cfg_json, f, indent=1)
        os.replace(tmp, os.path.join(out_dir, "config.json"))
    data, held_traj, cached = load_or_collect(c, offline.source, cache_dir)
    held = sequence.consecutive_windows(held_traj, c.eval_length)
    ref_spread = np.asarray(jax.device_get(reference_spread(held, offline.targets)))
    t_data = time.time() - t0
    log(f"data: {data.frames.shape[1]} worlds x {data.steps} steps for training, "
        f"{held.valid.size} held-out steps ({'cache' if cached else 'collected'}, {t_data:.1f} s)")
    path = os.path.join(out_dir, "curves.jsonl")
    if not resume:  # a fresh fit: curves and checkpoints of an earlier fit in this folder go
        if os.path.exists(path):
            os.remove(path)
        rundir.remove_tree(os.path.join(out_dir, CHECKPOINT_DIR))
    ckpt = Checkpointer(out_dir, keep=1, cleanup_tmp=True)
    key = jax.random.PRNGKey(seed)
    k_init, key = jax.random.split(key)
    states = offline.init(k_init)
    records: list[dict[str, Any]] = []
    losses: dict = {n: {"loss": np.full((offline.S,), np.nan)} for n in offline.learners}
    done = 0
    if resume:
        states, host, done = ckpt.restore(states)
        key = jnp.asarray(host["key"], jnp.uint32)
        records = [r for r in read_jsonl(path, tolerate_partial=True) if r["update"] <= done]
        write_jsonl_atomic(path, records)  # drop probes written after the checkpoint
        log(f"resuming at update {done} of {c.updates} ({len(records)} records)")

    def do_probe(update: int) -> None:
        nonlocal key
        key, k = jax.random.split(key)
        recs = records_of(update, offline.probe(states, data, held, k), losses, ref_spread, offline.spec, offline.S)
        write_jsonl(path, recs)
        records.extend(recs)
        log(f"update {update:>6} ({time.time() - t0:6.1f} s): " + summary_line(recs))

    if not resume:
        do_probe(0)
    stopped, last_call = False, 0.0
    while done < c.updates and not stopped:
        chunk = min(c.probe_every, c.updates - done)
        sums: dict = {"_n": []}
        while sum(sums["_n"]) < chunk:
            # stop before a call that would not end within the budget (its length: the last one's)
            if max_minutes and time.time() - t0 + last_call > 60 * max_minutes:
                stopped = True
                break
            n = min(offline.per_call, chunk - sum(sums["_n"]))
            key, k = jax.random.split(key)
            t_call = time.time()
            states, m = offline.train(states, data, k, n)
            m = jax.device_get(m)
            last_call = time.time() - t_call
            for name, lm in m.items():
                check_finite(lm, where=f"learner {name} before update {done + chunk}")
            sums = _accumulate(sums, m, n)
        n_done = sum(sums["_n"])
        if n_done == 0:
            log(f"stopping after {done} updates: --max-minutes {max_minutes} reached")
            break
        losses = {name: {k: v / n_done for k, v in lm.items()} for name, lm in sums.items() if name != "_n"}
        done += n_done
        if stopped:
            log(f"stopping after {done} updates: --max-minutes {max_minutes} reached")
        do_probe(done)
    ckpt.save(done, states, {"key": [int(x) for x in np.asarray(jax.device_get(key)).ravel()]})
    ckpt.close()
    write_outputs(offline, records, states, held, out_dir, time.time() - t0, t_data)
    return records


def _accumulate(sums: dict, m: dict, n: int) -> dict:
    """Running sums of per-call mean metrics weighted by the call's updates."""
    out = dict(sums)
    out["_n"] = sums["_n"] + [n]
    for name, lm in m.items():
        prev = sums.get(name, {})
        out[name] = {k: prev.get(k, 0.0) + np.asarray(v) * n for k, v in lm.items()}
    return out
