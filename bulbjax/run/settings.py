"""One place where a run's settings are resolved: a preset (or a saved config, or the defaults),
the overrides a user gave, the domain's PPO settings, `--small`, and learner options, in one
fixed order and checked, for every entry point (`bulbjax run`, `run --resume`, `bulbjax fit`, the
benchmarks). A command line only maps its flags to these functions' arguments; text values
(`learners="vae,dsa"`, `version="random"`, `KEY=VALUE` options) are parsed and checked here.

The order (`resolve`):
  1. the base: a saved config (`base`), else the preset named, else `ExperimentConfig()`;
  2. `overrides`: ExperimentConfig fields (env, seeds, epochs, learners, version, ...);
  3. the domain's PPO settings (`envs.registry.ppo_config_for`: locomotion's longer rollouts);
     a preset's observation-normaliser freeze only from the true state (`rl_input="state"`);
     an entropy bonus (`LATENT_ENT_COEF`) where PPO observes a frame learner's latent and no
     bonus is set, and a learning rate of at most `PIXEL_LR` where it observes pixels (a fresh
     run's only: a resumed run keeps its saved PPO settings);
  4. `small`: CPU sizes (`small_config`); the overrides given win over its sizes;
  5. `learner`, then `learner_options`: LearnerConfig fields (lr, compute_dtype, ...);
  6. `ppo_options`: PPOConfig fields (`KEY=VALUE` text), last, so they win over the preset's and
     the domain's PPO settings and over step 3's freeze rule.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping, Sequence

from bulbjax.config import ExperimentConfig, RunOptions, preset as named_preset, small_config
from bulbjax.data import synthetic
from bulbjax.envs import registry
from bulbjax.learners import LearnerConfig, is_sequential_name, parse_learner_options
from bulbjax.learners.plugins import load_learner_spec, parse_learner_list
from bulbjax.offline_config import OfflineConfig
from bulbjax.rl.ppo_config import parse_ppo_options
from bulbjax.run.resume import Resume, SavedRun

# `bulbjax fit --small`: a CPU-sized dataset (worlds, steps per world, held-out steps per world).
SMALL_DATASET: dict[str, int] = {"data_worlds": 32, "data_steps": 128, "heldout_steps": 32}


def parse_learners(text: str | Sequence[str]) -> tuple[str, ...]:
    """`"vae, vae_rpl, mod:Mine"` (a command line's comma-separated list) or a sequence ->
    learner names (a learner of one's own loaded: `learners.plugins.parse_learner_list`)."""
    return parse_learner_list(text)


def parse_version(text: int | str) -> int | str:
    """An object version: "random" or a non-negative int (also as text)."""
    if text == "random":
        return text
    try:
        v = int(text)
    except (TypeError, ValueError):
        v = -1
    if v < 0:
        raise ValueError(f"--version must be a non-negative int or 'random', got {text!r}")
    return v


# PPO's entropy bonus when it observes a frame learner's latent (unless the user sets ent_coef):
# measured on InvertedPendulum, VAE_rpl's latent of two frames, 3 seeds, 300 epochs, one H200:
# 3 of 3 seeds reach 950 with it, 0 of 3 without (docs/results/rl_inputs_frames_h200).
LATENT_ENT_COEF = 0.01

# PPO's learning rate (at most) when it observes pixels and trains its conv torso (unless the user
# sets lr): measured on InvertedPendulum, two frames, 3 seeds, one H200: with 3e-4 all 3 seeds
# reach 950 (epochs 31, 50, 87), with the pendulums' 1e-3 one of 3 in 500 epochs (the same seed
# with and without an entropy bonus; docs/results/rl_inputs_pixels_h200).
PIXEL_LR = 3e-4

_NESTED = {"ppo", "learner", "probe"}  # set through their own arguments (`learner=`) or the preset


def _overrides(overrides: Mapping[str, Any]) -> dict[str, Any]:
    """The overrides as ExperimentConfig field values (text parsed); unknown fields are an error."""
    fields = {f.name for f in dataclasses.fields(ExperimentConfig)} - _NESTED
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise ValueError(f"ExperimentConfig has no settable fields {unknown}; these can be overridden: "
                         f"{', '.join(sorted(fields))} (learner settings: learner=... or KEY=VALUE options)")
    out = dict(overrides)
    if "learners" in out:  # learners of one's own loaded (the config records their specs)
        out["learners"] = parse_learner_list(out["learners"])
    if str(out.get("rl_input", "")).count(":") > 1:  # latent:MODULE:NAME
        out["rl_input"] = "latent:" + load_learner_spec(out["rl_input"].split(":", 1)[1])
    if "version" in out:
        out["version"] = parse_version(out["version"])
    if isinstance(out.get("probe_variants"), str):
        out["probe_variants"] = parse_probe_variants(out["probe_variants"])
    return out


def parse_probe_variants(text: str) -> tuple[str, ...]:
    """`"common,window"` (a command line's list) -> ("common", "window"); "none" or "" -> ()."""
    names = tuple(x.strip() for x in text.split(",") if x.strip())
    return () if names in ((), ("none",)) else names


def _learner(base: LearnerConfig, learner: Mapping[str, Any], options: Sequence[str]) -> LearnerConfig:
    fields = {f.name for f in dataclasses.fields(LearnerConfig)}
    unknown = sorted(set(learner) - fields)
    if unknown:
        raise ValueError(f"LearnerConfig has no fields {unknown}; its fields: {', '.join(sorted(fields))}")
    out = dataclasses.replace(base, **learner) if learner else base
    if options:
        out = dataclasses.replace(out, **parse_learner_options(options))
    return out


def resolve(preset: str | None = None, *, base: ExperimentConfig | None = None,
            overrides: Mapping[str, Any] | None = None, learner: Mapping[str, Any] | None = None,
            learner_options: Sequence[str] = (), small: bool = False,
            domain_ppo: bool = True, ppo_options: Sequence[str] = ()) -> ExperimentConfig:
    """A run's ExperimentConfig, in the order of the module doc: `base` or the preset named
    (unknown names list the presets) or the defaults; `overrides` (ExperimentConfig fields; text
    accepted for `learners` and `version`); the domain's PPO settings unless `domain_ppo` is
    False (an unknown env is an error naming the registered ones); `small`'s CPU sizes, under
    the overrides; `learner` (LearnerConfig fields), then `learner_options` (`KEY=VALUE` text);
    `ppo_options` (`KEY=VALUE` PPOConfig fields, e.g. `ent_coef=0.01`). Every step's config checks itself: a bad value is a ValueError that names it."""
    if base is not None and preset:
        raise ValueError(f"give a preset ({preset!r}) or a base config, not both")
    cfg = base if base is not None else named_preset(preset) if preset else ExperimentConfig()
    given = _overrides(overrides or {})
    if given:
        cfg = cfg.replace(**given)
    if domain_ppo:
        cfg = cfg.replace(ppo=registry.ppo_config_for(cfg.env, cfg.ppo))
        if cfg.rl_learner is not None and not is_sequential_name(cfg.rl_learner) and not cfg.ppo.ent_coef:
            # a frame learner's latent holds positions, not velocities: without an entropy bonus
            # PPO's action noise collapses at the random policy's return in most seeds (VAE_rpl,
            # CURL); with 0.01 every seed keeps exploring (docs/ppo.md, "From a latent or pixels").
            # `--ppo-option ent_coef=0` undoes it.
            cfg = cfg.replace(ppo=dataclasses.replace(cfg.ppo, ent_coef=LATENT_ENT_COEF))
        if cfg.rl_input == "pixels" and cfg.ppo.lr > PIXEL_LR:
            # Adam's steps of 1e-3 on the shared conv torso: in 2 of 3 seeds it never came to
            # encode the pole; `--ppo-option lr=...` sets another
            cfg = cfg.replace(ppo=dataclasses.replace(cfg.ppo, lr=PIXEL_LR))
    if cfg.rl_input != "state" and cfg.ppo.obs_norm_updates:
        # the presets' normaliser freeze was measured from the true state; latents and pixels
        # keep moving as the learners train, so the normaliser keeps following them
        cfg = cfg.replace(ppo=dataclasses.replace(cfg.ppo, obs_norm_updates=0))
    if small:
        cfg = small_config(cfg)
        if given:  # what the user set wins over --small's sizes (e.g. --ppo-updates, --sequence-length)
            cfg = cfg.replace(**given)
    lc = _learner(cfg.learner, learner or {}, learner_options)
    if lc != cfg.learner:
        cfg = cfg.replace(learner=lc)
    if ppo_options:
        cfg = cfg.replace(ppo=dataclasses.replace(cfg.ppo, **parse_ppo_options(ppo_options)))
    return cfg


def resolve_resume(run_dir: str, preset: str | None = None, *, overrides: Mapping[str, Any] | None = None,
                   learner: Mapping[str, Any] | None = None, learner_options: Sequence[str] = (),
                   small: bool = False, seed: int | None = None, probe_every: int | None = None,
                   ppo_options: Sequence[str] = (), **stretch: Any) -> Resume:
    """A resumed run (`bulbjax run --resume RUN_DIR`), resolved once: its own config.json, read
    here and only here (`Resume.saved`), with what was given on top, as a fresh run would apply
    it to the saved settings (a `preset` builds the config anew; the domain's PPO settings only
    with a new `env`); its epochs unless `epochs` is overridden; its seed and probe_every unless
    given (`Resume.config`, `Resume.options`). `stretch`: the RunOptions that may change between
    stretches (checkpoint_every, keep, ...). `Resume.check` (and `run`, handed the Resume) then
    refuses whatever changes what the run computes."""
    saved = SavedRun.read(run_dir)
    overrides = dict(overrides or {})
    kw = dict(overrides=overrides, learner=learner, learner_options=learner_options, small=small,
              ppo_options=ppo_options)
    cfg = resolve(preset, **kw) if preset else resolve(base=saved.config, domain_ppo="env" in overrides, **kw)
    if "epochs" not in overrides:
        cfg = cfg.replace(epochs=saved.config.epochs)
    ident = saved.identity
    opts = RunOptions(seed=ident["seed"] if seed is None else seed,
                      probe_every=ident["probe_every"] if probe_every is None else probe_every, **stretch)
    return Resume(saved, cfg, opts)


def resolve_run(preset: str | None = None, *, resume: str | None = None, seed: int | None = None,
                probe_every: int | None = None, stretch: Mapping[str, Any] | None = None,
                **settings: Any) -> tuple[ExperimentConfig, RunOptions, Resume | None]:
    """`bulbjax run`'s settings, resolved once: a fresh run's config (`resolve`) and options (seed
    0 and probe_every 1 unless given), or, with `resume` (a run folder), the resumed run's
    (`resolve_resume`), whose `Resume` comes third: the checks and `run` take it and read the
    run's config.json no more. `stretch`: the RunOptions that may change between stretches
    (checkpoint_every, keep, ...); `settings`: `resolve`'s keyword arguments."""
    stretch = dict(stretch or {})
    if resume:
        r = resolve_resume(resume, preset, seed=seed, probe_every=probe_every, **settings, **stretch)
        return r.config, r.options, r
    cfg = resolve(preset, **settings)
    opts = RunOptions(seed=0 if seed is None else seed, probe_every=1 if probe_every is None else probe_every,
                      **stretch)
    return cfg, opts, None


def resolve_offline(preset: str | None = None, *, overrides: Mapping[str, Any] | None = None,
                    learner: Mapping[str, Any] | None = None, learner_options: Sequence[str] = (),
                    small: bool = False, dataset: Mapping[str, int] | None = None,
                    ppo_options: Sequence[str] = (),
                    **schedule: Any) -> OfflineConfig:
    """An offline fit's config (`bulbjax fit`): the run settings as `resolve` gives them, from a
    preset or an `env` among the overrides (a registered one, or SyntheticMovers: 32x32 frames
    and windows of 8 unless given, one colour scheme, no PPO settings); the dataset's size
    (`small`: `SMALL_DATASET`; `dataset`: data_worlds, data_steps, heldout_steps on top); the
    schedule (`updates`, `probe_every`, `data_seed`, ...: OfflineConfig fields)."""
    overrides = dict(overrides or {})
    env = overrides.get("env")
    if env is None and not preset:
        raise ValueError("fit needs --env (an environment of `bulbjax envs`, or SyntheticMovers) or --preset")
    synth = env == synthetic.NAME
    if env is not None and not synth and env not in registry.env_names():
        raise ValueError(f"unknown environment {env!r}; available: {', '.join(registry.env_names())} "
                         f"and, for `bulbjax fit` only, {synthetic.NAME}")
    if synth:  # SyntheticMovers' own defaults, under what was given
        overrides = {"resolution": 32, "sequence_length": 8, **overrides, "multicolour": False}
    base = resolve(preset, overrides=overrides, learner=learner, learner_options=learner_options,
                   small=small, domain_ppo=not synth, ppo_options=ppo_options)
    # an offline fit computes the present probe only (its probes: `offline.Offline`)
    base = base.replace(probe_variants=())
    sizes = {**(SMALL_DATASET if small else {}), **(dataset or {})}
    return OfflineConfig(base=base, **sizes, **schedule)
