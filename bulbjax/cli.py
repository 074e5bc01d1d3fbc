"""Command line: `bulbjax run | fit | envs | render`."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from typing import Sequence


def _parse_learners(text: str) -> tuple[str, ...]:
    return tuple(x.strip() for x in text.split(",") if x.strip())


def _domain_ppo(cfg):
    """Apply the domain's PPO settings (the locomotion envs ask for longer rollouts) when the
    env registry offers them; an unknown env is left for `Experiment` to report."""
    from bulbjax.envs import registry

    hook = getattr(registry, "ppo_config_for", None)
    if hook is None:
        return cfg
    try:
        return cfg.replace(ppo=hook(cfg.env, cfg.ppo))
    except ValueError:
        return cfg


def build_config(args: argparse.Namespace):
    """The run's ExperimentConfig: a preset (or the defaults) with the flags that were given,
    the domain's PPO settings, then --small, --lr and --bf16 on top."""
    from bulbjax.experiment import ExperimentConfig, small_config
    from bulbjax.experiment.config import preset

    base = preset(args.preset) if args.preset else ExperimentConfig()
    given = {k: v for k, v in (("env", args.env), ("seeds", args.seeds), ("epochs", args.epochs),
                               ("sequence_length", args.sequence_length)) if v is not None}
    if args.learners is not None:
        given["learners"] = _parse_learners(args.learners)
    if args.multicolour:
        given["multicolour"] = True
    cfg = _domain_ppo(base.replace(**given))
    if args.small:
        cfg = small_config(cfg)
    if args.ppo_updates:
        cfg = cfg.replace(ppo_updates_per_epoch=args.ppo_updates)
    if args.lr is not None:
        cfg = cfg.replace(learner=dataclasses.replace(cfg.learner, lr=args.lr))
    if args.bf16:
        cfg = cfg.replace(learner=dataclasses.replace(cfg.learner, compute_dtype="bfloat16"))
    return cfg


def cmd_run(args: argparse.Namespace) -> int:
    import jax
    from tqdm import tqdm

    from bulbjax.experiment import Experiment
    from bulbjax.experiment import report
    from bulbjax.learners import check_finite

    cfg = build_config(args)
    os.makedirs(args.out, exist_ok=True)
    metrics_path = os.path.join(args.out, "metrics.jsonl")
    if os.path.exists(metrics_path):
        os.remove(metrics_path)
    with open(os.path.join(args.out, "config.json"), "w") as f:
        json.dump(dataclasses.asdict(cfg), f, indent=1)

    t0 = time.time()
    exp = Experiment(cfg)
    rs = exp.init(jax.random.PRNGKey(args.seed))
    jax.block_until_ready(rs)
    t_init = time.time() - t0
    records = []
    key = jax.random.PRNGKey(args.seed + 1)
    bar = tqdm(range(cfg.epochs), desc=f"{cfg.env} x{cfg.seeds} seeds", unit="epoch")
    t_first = None
    every = args.probe_every
    if every < 1:
        raise ValueError(f"--probe-every must be >= 1, got {every}")
    for epoch in bar:
        if args.max_minutes and time.time() - t0 > 60 * args.max_minutes:
            bar.write(f"stopping after {epoch} epochs: --max-minutes {args.max_minutes} reached")
            break
        key, k = jax.random.split(key)
        # probe every `every` epochs, at epoch 0 and at the last epoch
        rs, m = exp.epoch(rs, k, probe=epoch % every == 0 or epoch == cfg.epochs - 1)
        m = jax.device_get(m)
        if t_first is None:
            t_first = time.time() - t0 - t_init
        for name, lm in m["learners"].items():
            check_finite(lm, where=f"learner {name} at epoch {epoch}")
        recs = report.epoch_records(epoch, m, exp.spec)
        report.write_jsonl(metrics_path, recs)
        records += recs
        if recs[0]["probes"]:
            bar.set_postfix(_postfix(recs))
    wall = time.time() - t0
    done_epochs = len(records) // cfg.seeds
    title = f"{cfg.env}{' (multicolour)' if cfg.multicolour else ''}: {cfg.seeds} seeds, {done_epochs} epochs"
    plot_path = os.path.join(args.out, "fig2.png")
    report.plot(records, exp.spec, plot_path, title, solved_return=exp.env.solved_return)
    tab = report.table(records, exp.spec, last=min(3, len(report.probed(records)) // cfg.seeds))
    timing = (f"wall time {wall:.1f} s (build+init {t_init:.1f} s, first epoch incl. compile "
              f"{t_first:.1f} s) on {jax.devices()[0].device_kind}")
    with open(os.path.join(args.out, "table.md"), "w") as f:
        f.write(f"# {title}\n\n{tab}\n\n{timing}\n")
    print(f"\n{tab}\n\n{timing}\nplot: {plot_path}\nmetrics: {metrics_path}")
    return 0


def build_offline_config(args: argparse.Namespace):
    """The OfflineConfig of `bulbjax fit`: the run's settings (a preset or the defaults, with
    the flags given, --small, --lr, --bf16; SyntheticMovers at 32x32 by default), the schedule,
    and the dataset's size (CPU sizes with --small)."""
    from bulbjax.data import synthetic
    from bulbjax.experiment.offline import OfflineConfig

    if args.env is None and args.preset is None:
        raise ValueError("fit needs --env (an environment of `bulbjax envs`, or SyntheticMovers) or --preset")
    ns = argparse.Namespace(**{**vars(args), "epochs": None, "ppo_updates": None,
                               "multicolour": getattr(args, "multicolour", False)})
    synth = args.env == synthetic.NAME
    if synth:  # not an MJX env: build the run settings on a stand-in, then swap the name back
        ns.env = "CartPole"
    base = build_config(ns)
    if synth:
        base = base.replace(env=synthetic.NAME, resolution=args.resolution or 32, multicolour=False,
                            sequence_length=args.sequence_length or 8)
    elif args.resolution:
        base = base.replace(resolution=args.resolution)
    kw = dict(updates=args.updates, probe_every=args.probe_every, data_seed=args.data_seed)
    if args.small:
        kw.update(data_worlds=32, data_steps=128, heldout_steps=32)
    for name in ("data_worlds", "data_steps", "heldout_steps"):
        if getattr(args, name) is not None:
            kw[name] = getattr(args, name)
    return OfflineConfig(base=base, **kw)


def cmd_fit(args: argparse.Namespace) -> int:
    from bulbjax.experiment import offline

    cfg = build_offline_config(args)
    offline.run(cfg, args.out, cache_dir=args.cache_dir, max_minutes=args.max_minutes, seed=args.seed)
    print(f"curves: {args.out}/curves.png, {args.out}/curves.jsonl; table: {args.out}/table.md; "
          f"reconstructions: {args.out}/recon.png")
    return 0


def _postfix(recs: list[dict]) -> dict[str, str]:
    import numpy as np
    out = {"return": f"{np.nanmean([r['rl_return'] for r in recs]):.1f}"}
    for name in recs[0]["probes"]:
        for stream in ("curr", "rand"):
            v = np.nanmean([r["probes"][name][stream]["overall"]["mae_norm"] for r in recs])
            out[f"{name}/{stream}"] = f"{v:.2f}"
    return out


def cmd_envs(args: argparse.Namespace) -> int:
    from bulbjax.envs.registry import _REGISTRY, MULTICOLOUR_SUFFIX

    for name, cls in _REGISTRY.items():
        spec = ", ".join(f"{e.name}[{e.unit}]/{e.group}" for e in cls.state_spec)
        act = f"discrete({cls.num_actions})" if cls.discrete else f"box({cls.action_size})"
        variant = f"(+{MULTICOLOUR_SUFFIX})" if cls.supports_multicolour else "(versions 0-5, random)"
        print(f"{name:<20} {variant} action {act}, episode {cls.episode_length}, "
              f"solved {cls.solved_return:g}; state: {spec}")
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    import jax
    import jax.numpy as jnp
    import numpy as np

    import bulbjax

    version = args.version if args.version == "random" else int(args.version)
    env = bulbjax.make(args.env, num_envs=args.frames, resolution=args.resolution, version=version)
    state = jax.jit(env.reset)(jax.random.PRNGKey(args.seed))
    step = jax.jit(env.step)
    key = jax.random.PRNGKey(args.seed + 1)
    for _ in range(args.steps):
        key, k = jax.random.split(key)
        if env.discrete:
            a = jax.random.randint(k, (env.num_envs,), 0, env.num_actions)
        else:
            a = jax.random.uniform(k, (env.num_envs, env.action_size), minval=-1, maxval=1)
        state = step(state, a)
    strip = np.concatenate(list(np.asarray(state.pixels)), axis=1)
    _save_png(args.out, strip)
    print(f"saved {env.num_envs} frames of {args.env} after {args.steps} random steps to {args.out}")
    return 0


def _save_png(path: str, image) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    plt.imsave(path, image)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bulbjax", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="train PPO + unsupervised learners and probe their latents")
    r.add_argument("--preset", default=None,
                   help="named settings (fig2-cartpole, fig2-invpend, fig2-halfcheetah, fig2-ant); "
                        "the flags below override it")
    r.add_argument("--env", default=None, help="environment (default CartPole)")
    r.add_argument("--learners", default=None,
                   help="comma-separated: vae,vae_rpl,beta_vae,svae,pred,dsa (default the first three)")
    r.add_argument("--seeds", type=int, default=None, help="seeds run side by side (default 3)")
    r.add_argument("--epochs", type=int, default=None, help="epochs (default 50)")
    r.add_argument("--sequence-length", type=int, default=None,
                   help="window length of the sequential learners (default 24 pendulums, 16 locomotion)")
    r.add_argument("--seed", type=int, default=0, help="base PRNG seed")
    r.add_argument("--out", default="runs/latest")
    r.add_argument("--multicolour", action="store_true", help="bulb's multicolour variant")
    r.add_argument("--small", action="store_true", help="CPU-sized settings (not the paper's)")
    r.add_argument("--bf16", action="store_true", help="bf16 compute in the learners (GPU)")
    r.add_argument("--ppo-updates", type=int, default=None, help="PPO updates per epoch")
    r.add_argument("--lr", type=float, default=None, help="learners' Adam learning rate (paper: 1e-4)")
    r.add_argument("--max-minutes", type=float, default=0.0,
                   help="stop after this wall time and report the epochs done (0: no limit)")
    r.add_argument("--probe-every", type=int, default=1,
                   help="probe every k epochs (and at the first and last); plots keep epochs on the x axis")
    r.set_defaults(fn=cmd_run)
    o = sub.add_parser("fit", help="offline: train learners on one cached random-policy dataset, "
                                   "probe every M updates")
    o.add_argument("--env", default=None, help="an environment (`bulbjax envs`) or SyntheticMovers")
    o.add_argument("--preset", default=None, help="run settings of a preset (e.g. fig2-invpend)")
    o.add_argument("--learners", default=None, help="comma-separated learners (default: the preset's or vae,vae_rpl,beta_vae)")
    o.add_argument("--updates", type=int, default=5000, help="learner updates")
    o.add_argument("--probe-every", type=int, default=250, help="probe every M updates")
    o.add_argument("--seeds", type=int, default=None, help="learner seeds, vmapped (default 3)")
    o.add_argument("--sequence-length", type=int, default=None, help="window length L of sequential learners")
    o.add_argument("--resolution", type=int, default=None, help="frame size (default 64; SyntheticMovers 32)")
    o.add_argument("--multicolour", action="store_true", help="bulb's multicolour variant")
    o.add_argument("--small", action="store_true", help="CPU-sized learners and dataset (not the paper's)")
    o.add_argument("--bf16", action="store_true", help="bf16 compute in the learners (GPU)")
    o.add_argument("--lr", type=float, default=None, help="learners' Adam learning rate (paper: 1e-4)")
    o.add_argument("--data-worlds", type=int, default=None, help="worlds of the dataset (default 256)")
    o.add_argument("--data-steps", type=int, default=None, help="steps per world of the dataset (default 200)")
    o.add_argument("--heldout-steps", type=int, default=None, help="steps per world held out (default 48)")
    o.add_argument("--data-seed", type=int, default=0, help="seed of the dataset (part of its cache key)")
    o.add_argument("--cache-dir", default=None, help="dataset cache (default OUT/data)")
    o.add_argument("--seed", type=int, default=0, help="base PRNG seed of the learners")
    o.add_argument("--max-minutes", type=float, default=0.0,
                   help="stop cleanly before this wall time, probe and write the plots (0: no limit)")
    o.add_argument("--out", default="runs/fit")
    o.set_defaults(fn=cmd_fit)
    e = sub.add_parser("envs", help="list the environments")
    e.set_defaults(fn=cmd_envs)
    d = sub.add_parser("render", help="save a strip of frames")
    d.add_argument("--env", default="CartPole")
    d.add_argument("--out", default="frames.png")
    d.add_argument("--frames", type=int, default=8)
    d.add_argument("--steps", type=int, default=10)
    d.add_argument("--resolution", type=int, default=64)
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--version", default="0",
                   help="object version of the multi-object domains: 0-5, or random (one per frame)")
    d.set_defaults(fn=cmd_render)
    args = p.parse_args(argv)
    try:
        return args.fn(args)
    except (ValueError, FloatingPointError) as err:
        print(f"bulbjax: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
