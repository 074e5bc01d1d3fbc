"""Offline fits (`bulbjax fit`): learners trained on one fixed dataset, probed every M updates.

The experiment (`loop.py`) trains learners on a non-stationary replay stream while PPO learns;
this mode isolates the learners: a random-policy dataset (frames, actions, true states, episode
boundaries) is collected once, cached on disk, and every learner trains on it with the paper's
batches (1,024 frames; 1,024 // L windows of L steps for sequential learners, cut at random
starts and at episode boundaries), seeds vmapped. Every `probe_every` updates a probe is fit on
training data and scored on held-out random-policy windows (separate worlds), normalised by
the held-out states' reference spread (`bulbjax.eval.probe`). The pieces are the experiment's:
its rollout and window cutting collect the data, `train_learner` / `probe_over_seeds` train and
probe, `report` writes curves and tables.

Sources: any registered MJX environment (random policy, as π_rand), or `SyntheticMovers`
(`bulbjax.data.synthetic`: squares at constant velocities, where only sequences can win).
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from dataclasses import dataclass
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from bulbjax.data import sequence, synthetic
from bulbjax.data.sequence import Trajectories, Windows
from bulbjax.eval import probe
from bulbjax.eval.spec import StateEntry
from bulbjax.experiment import report
from bulbjax.experiment.config import OfflineConfig
from bulbjax.experiment.devices import Devices, make_mesh
from bulbjax.experiment.learning import train_learner
from bulbjax.experiment.policy import Policy
from bulbjax.experiment.probing import fit_and_score, probe_latents, probe_over_seeds, probe_targets
from bulbjax.experiment.records import clamped_share, linear_summary, nanmean, read_jsonl, write_jsonl, write_jsonl_atomic
from bulbjax.experiment.seeds import SeedGroup, Team, learner_loop, over_seeds, resolve_seed_loop, with_seed_loop
from bulbjax.learners import check_finite, is_sequential, make_learner


@dataclass(frozen=True)
class Source:
    """Where data comes from: its state spec, frame shape, action width and a collector
    `collect(key, steps) -> Trajectories [steps, data_worlds]` (host-side call, jitted inside)."""

    name: str
    spec: tuple[StateEntry, ...]
    frame_shape: tuple[int, int, int]
    action_dim: int
    collect: Callable[[jax.Array, int], Trajectories]


def make_source(config: OfflineConfig) -> Source:
    """The data source of a config: SyntheticMovers or an MJX env under the random policy."""
    c = config
    if c.synthetic:
        m = c.movers_config()
        gen = jax.jit(lambda k, steps: synthetic.generate(k, m, steps, c.data_worlds), static_argnums=1)
        return Source(synthetic.NAME, m.state_spec, m.frame_shape, m.action_dim, gen)
    b = c.base
    w = c.data_worlds
    # the experiment's env and random-policy rollout (one seed of `data_worlds` worlds); the
    # random policy observes nothing, so no learner is built
    cfg = b.replace(seeds=1, num_envs=w, frames_per_epoch=w, eval_frames=w,
                    replay_capacity=max(b.replay_capacity, w), rl_input="state")
    dev = Devices(cfg)
    policy = Policy(cfg, dev, Team({}, "vmap", SeedGroup(1, w)))

    def _steps(key: jax.Array, steps: int) -> Trajectories:
        k_reset, k_roll = jax.random.split(key)
        _, (ri, low, act, done) = policy.rollout(None, dev.env.reset(k_reset), k_roll, steps, random=True)
        return Trajectories(frames=dev.env.render_sequence(ri), actions=act, states=low, dones=done)

    collect = jax.jit(_steps, static_argnums=1)
    name = b.env + ("Multicolour" if b.multicolour and not b.env.endswith("Multicolour") else "")
    return Source(name, dev.env.state_spec, dev.env.frame_shape, policy.action_dim, collect)


def dataset_path(config: OfflineConfig, source: Source, cache_dir: str, kind: str, steps: int) -> str:
    """Cache file of a dataset, keyed by env, frame size, worlds x steps, seed and kind."""
    r = source.frame_shape[0]
    tag = f"{source.name}_{r}px_{config.data_worlds}x{steps}_seed{config.data_seed}_{kind}"
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


class OfflineFit:
    """Learners (seeds vmapped, or mapped on one GPU) on one dataset; jitted training chunks and probes."""

    def __init__(self, config: OfflineConfig, source: Source | None = None):
        self.config = c = config
        self.source = source or make_source(config)
        b = c.base
        latent = b.latent_factor * len(self.source.spec)
        # learner updates and probe encodings over seeds: lax.map (DSA vmapped, `with_seed_loop`) on
        # one GPU, vmap on the CPU
        self.seed_loop = resolve_seed_loop(b.learner_seed_loop, make_mesh(jax.devices()[:1], b.seeds, 1))
        self.learners = {n: with_seed_loop(make_learner(n, latent, b.learner, self.source.action_dim), self.seed_loop)
                         for n in b.learners}
        # what the probes regress: the state and targets derived from it (`probing.probe_targets`)
        self.targets = probe_targets(self.source.spec)
        self.spec = self.targets.spec
        self.S = b.seeds
        per_call = c.updates_per_call or (1 if jax.default_backend() == "cpu" else c.probe_every)
        self.per_call = min(per_call, c.probe_every)
        self.init = jax.jit(self._init)
        self.train = jax.jit(self._train, static_argnums=3, donate_argnums=0)
        self.probe = jax.jit(self._probe)

    def _init(self, key: jax.Array) -> dict[str, Any]:
        out = {}
        for i, (name, l) in enumerate(self.learners.items()):
            keys = jax.random.split(jax.random.fold_in(key, i), self.S)
            out[name] = jax.vmap(lambda k, l=l: l.init(k, self.source.frame_shape))(keys)
        return out

    def _sampler(self, learner: Any, data: Trajectories) -> Callable[[jax.Array], Any]:
        if is_sequential(learner):
            return lambda k: sequence.sample_windows(data, k, learner.batch_size, learner.window_length)
        return lambda k: sequence.sample_steps(data, k, learner.batch_size)[0]

    def _train(self, states: dict, data: Trajectories, key: jax.Array, updates: int) -> tuple[dict, dict]:
        """`updates` updates of every learner and seed (seeds vmapped, data shared); metrics are
        the means over the updates, per seed."""
        out, metrics = {}, {}
        unroll = True if jax.default_backend() == "cpu" else 1
        for i, (name, l) in enumerate(self.learners.items()):
            keys = jax.random.split(jax.random.fold_in(key, i), self.S)
            run = lambda st, k, l=l: train_learner(l, st, self._sampler(l, data), k, updates, unroll)  # noqa: E731
            out[name], m = over_seeds(learner_loop(self.seed_loop, l), run, states[name], keys)
            metrics[name] = jax.tree.map(lambda x: x.mean(-1), m)
        return out, metrics

    def _probe(self, states: dict, data: Trajectories, held: Windows, key: jax.Array,
               broken: jax.Array | bool = False) -> dict:
        """Probe every learner and seed: fit on training data, score on the held-out windows
        (stream `rand`). `broken=True` (a check of the check) shuffles the per-step latents
        across time steps first (`shuffle_time`); traced, so both share one compile."""
        b = self.config.base
        out = {}
        corrupt = lambda z, k: jnp.where(broken, shuffle_time(z, k), z)  # noqa: E731
        for i, (name, l) in enumerate(self.learners.items()):
            def latents_seed(k_c, k_s, st, l=l):
                if is_sequential(l):
                    train = sequence.sample_windows(data, k_s, -(-b.probe_train_frames // l.sequence_length),
                                                    l.sequence_length)
                else:
                    train = sequence.sample_steps(data, k_s, b.probe_train_frames, with_worlds=True)
                return probe_latents(l, st.params, train, {"rand": held}, k_c, b.probe,
                                     b.probe_train_frames, corrupt)

            def fit_seed(lat, k_f, k_s, st):
                return fit_and_score(lat, {"rand": held}, k_f, b.probe, targets=self.targets)

            keys = jax.random.split(jax.random.fold_in(key, i), self.S)
            k_s, k_p = jax.vmap(jax.random.split)(keys).swapaxes(0, 1)
            out[name] = probe_over_seeds(learner_loop(self.seed_loop, l), latents_seed, fit_seed, k_p, k_s,
                                         states[name])
        return out


def shuffle_time(z: jax.Array, key: jax.Array) -> jax.Array:
    """A deliberately broken latent: per-step latents `[B, L, Z]` permuted across all time steps
    of all windows, so the latent paired with a state belongs to another step."""
    flat = z.reshape((-1, z.shape[-1]))
    return jax.random.permutation(key, flat, axis=0).reshape(z.shape)


def records_of(update: int, probes: Any, losses: Any, ref_spread: np.ndarray,
               spec: tuple[StateEntry, ...], seeds: int) -> list[dict[str, Any]]:
    """One JSON-able record per seed for a probe after `update` updates."""
    p, lm = jax.device_get(probes), jax.device_get(losses)
    out = []
    for s in range(seeds):
        rec: dict[str, Any] = {"update": update, "seed": s, "ref_spread": [float(x) for x in ref_spread],
                               "learners": {n: {k: float(v[s]) for k, v in m.items()} for n, m in lm.items()},
                               "probes": {}}
        for name, streams in p.items():
            rec["probes"][name] = {st: probe.summarise(d["mae"][s], d["baseline"][s], ref_spread, spec,
                                                        spread_D=d["spread"][s])
                                   for st, d in streams.items()}
            if any("linear_mae" in d for d in streams.values()):
                rec.setdefault("linear_probes", {})[name] = {
                    st: linear_summary(d, s, ref_spread, spec) for st, d in streams.items()}
            if clamped := clamped_share(streams, s):
                rec.setdefault("probe_inputs_clamped", {})[name] = clamped
        out.append(rec)
    return out


def _config_json(c: OfflineConfig, fit: "OfflineFit", seed: int) -> dict[str, Any]:
    return json.loads(json.dumps({"offline": {k: v for k, v in dataclasses.asdict(c).items() if k != "base"},
                                  "base": dataclasses.asdict(c.base), "source": fit.source.name,
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


def run(config: OfflineConfig, out_dir: str, cache_dir: str | None = None, max_minutes: float = 0.0,
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
    from bulbjax.experiment import rundir
    from bulbjax.experiment.checkpoint import CHECKPOINT_DIR, Checkpointer

    c = config
    t0 = time.time()
    rundir.check_out_dir(out_dir, resume=resume, overwrite=overwrite, fit=True)  # nothing lost by accident
    rundir.remove_stale_temporaries(out_dir)
    cache_dir = cache_dir if cache_dir is not None else os.path.join(out_dir, "data")
    fit = OfflineFit(c)
    cfg_json = _config_json(c, fit, seed)
    if resume:
        _check_resumable(out_dir, cfg_json)
    else:
        tmp = os.path.join(out_dir, f"config.json.tmp{os.getpid()}")
        with open(tmp, "w") as f:
            json.dump(cfg_json, f, indent=1)
        os.replace(tmp, os.path.join(out_dir, "config.json"))
    data, held_traj, cached = load_or_collect(c, fit.source, cache_dir)
    held = sequence.consecutive_windows(held_traj, c.eval_length)
    ref_spread = np.asarray(jax.device_get(_ref_spread(held, fit.targets)))
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
    states = fit.init(k_init)
    records: list[dict[str, Any]] = []
    losses: dict = {n: {"loss": np.full((fit.S,), np.nan)} for n in fit.learners}
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
        recs = records_of(update, fit.probe(states, data, held, k), losses, ref_spread, fit.spec, fit.S)
        write_jsonl(path, recs)
        records.extend(recs)
        log(f"update {update:>6} ({time.time() - t0:6.1f} s): " + _summary(recs))

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
            n = min(fit.per_call, chunk - sum(sums["_n"]))
            key, k = jax.random.split(key)
            t_call = time.time()
            states, m = fit.train(states, data, k, n)
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
    write_outputs(fit, records, states, held, out_dir, time.time() - t0, t_data)
    return records


def _ref_spread(held: Windows, targets: Callable[[jax.Array], jax.Array] = lambda s: s) -> jax.Array:
    """The reference spread: the probe targets of held-out random-policy states, valid steps."""
    t = targets(held.states)
    return probe.spread(t.reshape((-1, t.shape[-1])), held.valid.reshape(-1))


def _accumulate(sums: dict, m: dict, n: int) -> dict:
    """Running sums of per-call mean metrics weighted by the call's updates."""
    out = dict(sums)
    out["_n"] = sums["_n"] + [n]
    for name, lm in m.items():
        prev = sums.get(name, {})
        out[name] = {k: prev.get(k, 0.0) + np.asarray(v) * n for k, v in lm.items()}
    return out


def _norm_text(v: float) -> str:
    """A normalised error for the log line; "excluded" for a group none of whose entries can be
    normalised (NaN: every entry constant in the data)."""
    return f"{v:.2f}" if np.isfinite(v) else "excluded"


def _summary(recs: list[dict]) -> str:
    parts = []
    for name in recs[0]["probes"]:
        g = recs[0]["probes"][name]["rand"]["groups"]
        vals = {k: nanmean([r["probes"][name]["rand"]["groups"][k]["mae_norm"] for r in recs]) for k in g}
        parts.append(f"{name} " + "/".join(_norm_text(v) for v in vals.values()))
    base = recs[0]["probes"][next(iter(recs[0]["probes"]))]["rand"]["groups"]
    parts.append("constant " + "/".join(_norm_text(g["baseline_norm"]) for g in base.values()))
    return "; ".join(parts) + f"  ({'/'.join(base)})"


def write_outputs(fit: OfflineFit, records: list[dict], states: dict, held: Windows, out_dir: str,
                  wall: float, t_data: float) -> None:
    """`curves.png` (normalised error against updates per group and learner, constant
    predictor dotted), `table.md` (last probe) and `recon.png` (held-out frames and every
    learner's reconstruction, seed 0)."""
    c = fit.config
    title = report.offline_title(fit.source.name, fit.S, records)
    timing = (f"wall time {wall:.1f} s (data {t_data:.1f} s) on {jax.devices()[0].device_kind}; "
              f"batch {c.base.learner.batch_size} frames, sequential {c.base.seq_len}-step windows")
    report.write_offline_reports(out_dir, records, fit.spec, title, footer=timing)
    save_recon_grid(fit, states, held, os.path.join(out_dir, "recon.png"))


def save_recon_grid(fit: OfflineFit, states: dict, held: Windows, path: str, n: int = 8) -> None:
    """Row 0: `n` consecutive held-out frames (one window); then one row per learner that has
    `reconstruct` (seed 0; the contrastive ones and others without it have none, and with none
    at all no figure is written). Drawn by `bulbjax.experiment.figures` (the paper's Fig. 4
    layout)."""
    from bulbjax.experiment import figures

    learners = {n: x for n, x in fit.learners.items() if hasattr(x, "reconstruct")}
    if not learners:
        if os.path.exists(path):  # an earlier fit's, in an overwritten folder
            os.remove(path)
        return
    figures.recon_figure(path, learners, figures.seed_params(states, 0), held,
                         figures.FigureConfig(frames=n), title=f"{fit.source.name}: held-out frames, seed 0")
