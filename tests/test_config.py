"""The configuration layer (`bulbjax.run.settings`, `config_from_dict`): presets resolve with
their domain's PPO settings, overrides and learner options apply in the documented order (the
flags given win over `--small`), `fit` and `--resume` resolve through the same steps, config.json
reads back as written, and bad values are errors that name what was wrong and what is accepted.
No environment is built here."""

from __future__ import annotations

import dataclasses
import json

import pytest

from bulbjax.config import PRESETS, ExperimentConfig, config_from_dict, preset, small_config
from bulbjax.envs.registry import ppo_config_for
from bulbjax.run.settings import SMALL_DATASET, parse_learners, parse_version, resolve, resolve_offline, resolve_resume

from tiny_experiment import tiny_config


def test_presets_resolve_with_their_domain_ppo():
    for name, cfg in PRESETS.items():
        out = resolve(name)
        assert out.replace(ppo=cfg.ppo) == cfg  # the preset itself, PPO aside
        assert out.ppo == ppo_config_for(cfg.env, cfg.ppo)
    cheetah = resolve("fig2-halfcheetah")
    assert (cheetah.ppo.num_steps, cheetah.ppo.lr) == (128, 3e-4) and cheetah.ppo.num_envs == cheetah.num_envs
    assert resolve("fig2-cartpole").ppo == PRESETS["fig2-cartpole"].ppo  # the pendulums keep PPO's defaults
    assert resolve("fig2-halfcheetah", domain_ppo=False).ppo == PRESETS["fig2-halfcheetah"].ppo
    assert resolve() == ExperimentConfig().replace(ppo=ppo_config_for("CartPole"))


def test_multi_object_presets_fix_the_papers_black_background_scene():
    """Issue 37: fig3/fig5 run on one fixed black-background version (bulb's 6-11), the random
    setting is its own named preset, and fig5 puts SPAIR 4x4 and 6x6 beside VAE_rpl on YCB."""
    from bulbjax.envs.objects.rearrange_scene import GEOM_INFO, OBJECT_LISTS, NUM_LISTS, NUM_VERSIONS

    fixed, rand, ycb = (resolve(n) for n in ("fig3-rearrange-geom", "fig3-rearrange-geom-random",
                                             "fig5-rearrange-ycb"))
    for cfg in (fixed, ycb):
        assert isinstance(cfg.version, int) and NUM_LISTS <= cfg.version < NUM_VERSIONS  # black background
    # the fixed Geom scene holds the paper's "objects of various sizes": a cylinder, the block, two spheres
    assert set(OBJECT_LISTS["Geom"][fixed.version % NUM_LISTS]) == {"cylinder", "cube", "sphere", "sphere1"}
    assert all(n in GEOM_INFO for n in OBJECT_LISTS["Geom"][fixed.version % NUM_LISTS])
    assert rand.version == "random" and rand.replace(version=fixed.version) == fixed
    assert (fixed.env, ycb.env) == ("ReacherRearrangeGeom", "ReacherRearrangeYcb")
    assert ycb.learners == ("vae_rpl", "spair", "spair6")
    assert (ycb.seeds, ycb.learner_batches, ycb.ppo_updates_per_epoch, ycb.learner.lr) == (3, 10, 2, 1e-4)
    assert resolve("fig3-rearrange-geom", overrides={"version": "random"}) == rand


def test_overrides_and_learner_options_apply():
    cfg = resolve("fig2-invpend", overrides={"seeds": 2, "epochs": 7, "learners": "vae, dsa", "version": "0",
                                             "learner_seed_loop": "map"},
                  learner={"lr": 3e-4, "compute_dtype": "bfloat16"}, learner_options=["lr=1e-3", "channel_pad=8"])
    assert (cfg.seeds, cfg.epochs, cfg.learners, cfg.version, cfg.learner_seed_loop) == (2, 7, ("vae", "dsa"), 0, "map")
    # options after the typed learner fields: lr from the option, dtype from `learner`
    assert (cfg.learner.lr, cfg.learner.compute_dtype, cfg.learner.channel_pad) == (1e-3, "bfloat16", 8)
    assert cfg.learner.sequence_length == cfg.seq_len == 24  # the config keeps the two in step
    assert resolve(overrides={"env": "Ant"}).ppo == ppo_config_for("Ant")  # the overridden env's PPO
    assert resolve(overrides={"version": "random", "env": "GeomOnIncline"}).version == "random"
    assert parse_learners(" vae,, svae ") == ("vae", "svae") and parse_version(3) == 3


def test_ppo_options_apply_last():
    # from a latent the preset's normaliser freeze is off (step 3); an option given wins over it
    # and over the preset's and domain's PPO settings; `none` clears an optional field
    latent = resolve("fig2-invpend", overrides={"rl_input": "latent:vae_rpl"})
    assert latent.ppo.obs_norm_updates == 0 and latent.ppo.min_log_std == -2.0
    cfg = resolve("fig2-invpend", overrides={"rl_input": "latent:vae_rpl"},
                  ppo_options=["ent_coef=0.01", "min_log_std=none", "obs_norm_updates=300", "hidden=32,32",
                               "normalize_obs=false", "lr_schedule=cosine"])
    assert (cfg.ppo.ent_coef, cfg.ppo.min_log_std, cfg.ppo.obs_norm_updates, cfg.ppo.hidden) == (0.01, None, 300, (32, 32))
    assert cfg.ppo.normalize_obs is False and cfg.ppo.lr_schedule == "cosine"
    assert cfg.ppo.anneal_updates == latent.ppo.anneal_updates  # the rest as resolved before
    assert resolve("fig2-invpend", small=True, ppo_options=["lr=5e-4"]).ppo.lr == 5e-4


def test_small_is_cpu_sized_and_the_flags_given_win():
    base = resolve("fig2-halfcheetah")
    small = resolve("fig2-halfcheetah", small=True)
    assert small == small_config(base)
    assert (small.num_envs, small.ppo.num_envs, small.ppo.num_steps, small.seq_len) == (16, 16, 64, 8)
    assert small.ppo.lr == 3e-4  # the domain's PPO settings survive --small
    given = resolve("fig2-cartpole", small=True, overrides={"ppo_updates_per_epoch": 2, "sequence_length": 12,
                                                            "seeds": 1})
    assert (given.ppo_updates_per_epoch, given.seq_len, given.seeds, given.num_envs) == (2, 12, 1, 16)


@pytest.mark.parametrize("kw, match", [
    (dict(preset="fig3"), "available: fig2-cartpole"),
    (dict(overrides={"seed": 1}), "no settable fields \\['seed'\\].*seeds"),
    (dict(overrides={"ppo": None}), "no settable fields \\['ppo'\\]"),
    (dict(overrides={"env": "Pendulum"}), "unknown environment 'Pendulum'; available: .*CartPole"),
    (dict(overrides={"version": "-1"}), "--version must be a non-negative int or 'random'"),
    (dict(overrides={"learners": "vae,vea"}), "unknown learners \\['vea'\\]"),
    (dict(overrides={"seeds": 0}), "seeds must be >= 1"),
    (dict(overrides={"learner_seed_loop": "pmap"}), "learner_seed_loop must be one of"),
    (dict(overrides={"graph_mode": "cuda"}), "graph_mode must be one of none, jax, warp"),
    (dict(learner={"learning_rate": 1e-3}), "LearnerConfig has no fields \\['learning_rate'\\]; its fields: .*lr"),
    (dict(learner_options=["channelpad=1"]), "KEY one of"),
    (dict(learner_options=["batch_size=big"]), "'big' is not a int"),
    (dict(ppo_options=["entropy=0.01"]), "PPO option 'entropy=0.01' must be KEY=VALUE with KEY one of: .*ent_coef"),
    (dict(ppo_options=["num_steps=none"]), "does not fit num_steps .*only the optional fields take none"),
    (dict(ppo_options=["lr=fast"]), "'fast' does not fit lr"),
    (dict(ppo_options=["lr_schedule=step"]), "lr_schedule must be one of"),
    (dict(preset="fig2-ant", base=ExperimentConfig()), "a preset .* or a base config, not both"),
])
def test_bad_settings_are_clear_errors(kw, match):
    with pytest.raises(ValueError, match=match):
        resolve(**kw)


def test_offline_fit_resolves_through_the_same_steps():
    synth = resolve_offline(overrides={"env": "SyntheticMovers", "learners": "vae,svae"}, small=True,
                            dataset={"data_steps": 64}, updates=10, probe_every=5)
    b = synth.base
    assert (b.env, b.resolution, b.seq_len, b.multicolour, b.learners) == ("SyntheticMovers", 32, 8, False,
                                                                           ("vae", "svae"))
    assert b.ppo == dataclasses.replace(small_config(ExperimentConfig()).ppo, num_envs=b.num_envs)  # no domain PPO
    assert (synth.data_worlds, synth.data_steps, synth.heldout_steps) == (SMALL_DATASET["data_worlds"], 64,
                                                                         SMALL_DATASET["heldout_steps"])
    assert (synth.updates, synth.probe_every) == (10, 5)
    sized = resolve_offline(overrides={"env": "SyntheticMovers", "resolution": 48, "sequence_length": 6})
    assert (sized.base.resolution, sized.base.seq_len, sized.data_worlds) == (48, 6, 256)
    pend = resolve_offline("fig2-invpend", overrides={"resolution": 32}, small=True)
    assert pend.base == resolve("fig2-invpend", overrides={"resolution": 32}, small=True)
    with pytest.raises(ValueError, match="fit needs --env"):
        resolve_offline()
    with pytest.raises(ValueError, match="data_steps=4 is shorter than a training window"):
        resolve_offline(overrides={"env": "SyntheticMovers", "learners": "svae"}, dataset={"data_steps": 4})


def test_resume_starts_from_the_runs_own_config(tmp_path):
    saved = resolve("fig2-halfcheetah", small=True, overrides={"seeds": 2, "epochs": 5})
    with open(tmp_path / "config.json", "w") as f:
        json.dump({"experiment": dataclasses.asdict(saved), "run": {"seed": 7, "probe_every": 3}}, f)
    r = resolve_resume(str(tmp_path), keep=4)
    cfg, opts = r.config, r.options
    assert cfg == saved and (opts.seed, opts.probe_every, opts.keep) == (7, 3, 4)
    assert r.saved.config == saved and r.saved.run_dir == str(tmp_path) and r.saved.processes == 1
    r.check()  # the resolved settings are the run's own
    longer = resolve_resume(str(tmp_path), overrides={"epochs": 9}, seed=1)
    assert longer.config == saved.replace(epochs=9) and longer.options.seed == 1
    with pytest.raises(ValueError, match=r"--resume .*seed: saved 7, given 1"):
        longer.check()
    # the flags given apply to the saved settings; the domain's PPO only with a new env
    lr = resolve_resume(str(tmp_path), learner={"lr": 0.5}).config
    assert lr.learner.lr == 0.5 and lr.ppo == saved.ppo
    ant = resolve_resume(str(tmp_path), overrides={"env": "Ant"}).config
    assert ant.ppo == ppo_config_for("Ant", saved.ppo)
    anew = resolve_resume(str(tmp_path), "fig2-invpend").config
    assert anew == resolve("fig2-invpend").replace(epochs=saved.epochs)
    with pytest.raises(ValueError, match="config.json does not exist"):
        resolve_resume(str(tmp_path / "nowhere"))


def test_a_resume_reads_the_runs_config_once(tmp_path, monkeypatch):
    """`bulbjax run --resume` reads the run's config.json once, in `resolve_resume`, and hands
    the `Resume` down: the checks before the processes start and the run itself read no more."""
    import bulbjax.run as run_face
    from bulbjax import cli
    from bulbjax.run import resume as resume_mod

    saved = resolve(None, small=True, overrides={"env": "CartPole", "learners": "vae", "seeds": 1, "epochs": 2})
    d = tmp_path / "r"
    d.mkdir()
    with open(d / "config.json", "w") as f:
        json.dump({"experiment": dataclasses.asdict(saved), "run": {"seed": 0, "probe_every": 1}}, f)
    reads, got = [], {}
    real = resume_mod.read_run_config
    monkeypatch.setattr(resume_mod, "read_run_config", lambda run_dir: reads.append(run_dir) or real(run_dir))
    monkeypatch.setattr(run_face, "run", lambda cfg, opts, out, **kw: got.update(kw, cfg=cfg))
    assert cli.main(["run", "--resume", str(d), "--epochs", "4", "--layout", "single"]) == 0
    assert reads == [str(d)] and isinstance(got["resume"], run_face.Resume)
    assert got["cfg"] == saved.replace(epochs=4) and got["resume"].saved.config == saved


def test_a_frame_learners_latent_gets_the_entropy_bonus_unless_set():
    """PPO from a frame learner's latent (positions only) collapses its action noise without an
    entropy bonus (docs/results/rl_inputs_frames_h200): a fresh run gets LATENT_ENT_COEF, the
    user's ent_coef wins, and the state, pixels and sequential learners' latents keep 0."""
    from bulbjax.run.settings import LATENT_ENT_COEF

    def ent(rl_input, learners="vae_rpl,dsa", options=()):
        return resolve("fig2-invpend", overrides={"learners": learners, "rl_input": rl_input},
                       ppo_options=options).ppo.ent_coef

    assert LATENT_ENT_COEF > 0
    assert ent("latent:vae_rpl") == LATENT_ENT_COEF
    assert ent("latent:curl", learners="curl") == LATENT_ENT_COEF
    assert ent("latent:vae_rpl", options=["ent_coef=0"]) == 0.0
    assert ent("latent:vae_rpl", options=["ent_coef=0.03"]) == 0.03
    assert ent("state") == ent("pixels") == ent("latent:dsa") == 0.0
    saved = resolve("fig2-invpend", overrides={"learners": "vae_rpl", "rl_input": "latent:vae_rpl"},
                    ppo_options=["ent_coef=0"])
    assert resolve(base=saved, domain_ppo=False).ppo.ent_coef == 0.0  # a resumed run keeps its own


def test_ppo_from_pixels_gets_the_pixel_learning_rate_unless_set():
    """PPO's conv torso learnt the pole in 1 of 3 seeds at the pendulums' lr 1e-3 and in 3 of 3 at
    3e-4 (docs/results/rl_inputs_pixels_h200): a fresh pixel run gets PIXEL_LR, the user's lr
    wins, state and latent inputs keep the domain's lr, and a resumed run keeps its own."""
    from bulbjax.run.settings import PIXEL_LR

    def lr(rl_input, options=()):
        return resolve("fig2-invpend", overrides={"learners": "vae_rpl", "rl_input": rl_input},
                       ppo_options=options).ppo.lr

    state_lr = lr("state")
    assert state_lr > PIXEL_LR  # the pendulums' lr: what pixels now do not get
    assert lr("pixels") == PIXEL_LR
    assert lr("latent:vae_rpl") == state_lr
    assert lr("pixels", options=["lr=1e-3"]) == 1e-3
    assert lr("pixels", options=["lr=1e-4"]) == 1e-4
    saved = resolve("fig2-invpend", overrides={"learners": "vae_rpl", "rl_input": "pixels"}, ppo_options=["lr=1e-3"])
    assert resolve(base=saved, domain_ppo=False).ppo.lr == 1e-3


def test_config_json_round_trip():
    """A config written as config.json reads back equal; one from before a field existed reads
    back with what it ran with."""
    for c in [*PRESETS.values(), small_config(PRESETS["fig2-cartpole"]), tiny_config()]:
        assert config_from_dict(json.loads(json.dumps(dataclasses.asdict(c)))) == c
    with pytest.raises(ValueError, match="another version"):
        config_from_dict({"envv": "CartPole"})
    # a config.json from before the conv forms existed reads back with the forms it ran with
    old = dataclasses.asdict(PRESETS["fig2-invpend"])
    for k in ("channel_pad", "bias_grad", "edge_layers", "lstm_grad"):
        del old["learner"][k]
    got = config_from_dict(json.loads(json.dumps(old))).learner
    assert (got.channel_pad, got.bias_grad, got.edge_layers, got.lstm_grad) == (1, "reduce", "strided", "autodiff")
    new = PRESETS["fig2-invpend"].learner
    assert (new.channel_pad, new.bias_grad, new.edge_layers, new.lstm_grad) == (0, "auto", "auto", "written")
