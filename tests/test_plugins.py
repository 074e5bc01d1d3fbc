"""A learner of one's own from the command line, with no edit of bulbjax (issue 58 item 10;
`bulbjax.learners.plugins`, docs/extending.md): a module or file OUTSIDE the package, named as
`--learners vae_rpl,MODULE:NAME` (or `path/to/file.py:NAME`, `NEWNAME=...`, an installed
package's `bulbjax.learners` entry point), recorded in the run's config.json so that `report`
and `--resume` find it with no flag, and a one-line error for every way it can fail.

The tests without a compile run in `make test`; `test_cli_run_resume_report_fit` is the whole
path through `bulbjax run --small`, `--resume`, `report` and `fit` in fresh processes (slow tier:
each process compiles an experiment, ~2 minutes apiece on 2 cores)."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import textwrap

import pytest

from bulbjax.learners import plugins, registry

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# A learner in a file of its own, as a researcher would write it: a linear autoencoder on 8x8
# average-pooled frames (tests/test_extending.py's TinyPCA), not registered by its module.
LEARNER_SOURCE = textwrap.dedent('''
    import dataclasses
    from typing import Any, ClassVar

    import flax.linen as nn
    import jax
    import jax.numpy as jnp
    import optax

    from bulbjax.learners import LearnerConfig, LearnerState, register_learner


    @dataclasses.dataclass(frozen=True)
    class TinyPCA:
        latent_dim: int
        config: LearnerConfig = LearnerConfig()
        sequential: ClassVar[bool] = False

        @property
        def retain_fraction(self) -> float:
            return self.config.retain_fraction

        @property
        def batch_size(self) -> int:
            return self.config.batch_size

        @staticmethod
        def _pooled(frames):
            x = frames.astype(jnp.float32) / 255.0
            b, h, w, c = x.shape
            return x.reshape(b, 8, h // 8, 8, w // 8, c).mean(axis=(2, 4)).reshape(b, -1)

        def init(self, key, frame_shape):
            k1, k2 = jax.random.split(key)
            d = 8 * 8 * frame_shape[2]
            params = {"enc": nn.Dense(self.latent_dim).init(k1, jnp.zeros((1, d)))["params"],
                      "dec": nn.Dense(d).init(k2, jnp.zeros((1, self.latent_dim)))["params"]}
            opt = optax.adam(self.config.lr).init(params)
            return LearnerState(params, opt, jnp.zeros((), jnp.int32))

        def encode(self, params, frames):
            return nn.Dense(self.latent_dim).apply({"params": params["enc"]}, self._pooled(frames))

        def update(self, state, frames, key):
            x = self._pooled(frames)

            def loss_fn(p):
                z = nn.Dense(self.latent_dim).apply({"params": p["enc"]}, x)
                return jnp.mean((nn.Dense(x.shape[-1]).apply({"params": p["dec"]}, z) - x) ** 2)

            loss, grads = jax.value_and_grad(loss_fn)(state.params)
            updates, opt = optax.adam(self.config.lr).update(grads, state.opt_state, state.params)
            new = LearnerState(optax.apply_updates(state.params, updates), opt, state.step + 1)
            return new, {"loss": loss}


    @register_learner("tiny_registered", defaults={"retain_fraction": 0.25})
    def make_tiny(latent_dim, config, action_dim):
        return TinyPCA(latent_dim, config)


    NOT_A_LEARNER = 3
''')


@pytest.fixture
def plugin_dir(tmp_path, monkeypatch):
    """A folder outside the package with `my_learners.py` (on sys.path) and a broken module; the
    learners it registers, the modules and the loader's memory are removed afterwards."""
    folder = tmp_path / "plugins"
    folder.mkdir()
    (folder / "my_learners.py").write_text(LEARNER_SOURCE)
    (folder / "broken_learners.py").write_text("raise RuntimeError('the GPU is on fire')\n")
    monkeypatch.syspath_prepend(str(folder))
    before = set(registry._REGISTRY)
    loaded, provider = dict(plugins._LOADED), dict(plugins._PROVIDER)
    mods = set(sys.modules)
    yield folder
    for name in set(registry._REGISTRY) - before:
        registry.unregister_learner(name)
    for memory, saved in ((plugins._LOADED, loaded), (plugins._PROVIDER, provider)):
        memory.clear()
        memory.update(saved)
    for m in set(sys.modules) - mods:
        if "learners" in m:
            del sys.modules[m]


def test_spec_forms_register_once(plugin_dir):
    load = plugins.load_learner_spec
    assert load("my_learners:TinyPCA") == "TinyPCA"  # a class: registered under its name
    assert load("my_learners:TinyPCA") == "TinyPCA"  # idempotent
    assert load("my_learners:make_tiny") == "tiny_registered"  # a factory its import registered
    assert load("my_learners:tiny_registered") == "tiny_registered"  # a name its import registered
    assert registry.registration("tiny_registered").defaults == {"retain_fraction": 0.25}
    assert load("pca=my_learners:TinyPCA") == "pca"  # the same class under another name
    path = str(plugin_dir / "my_learners.py")
    assert load(f"filepca={path}:TinyPCA") == "filepca"  # an imported module's file: that module
    other = plugin_dir / "sub" / "other_learners.py"
    other.parent.mkdir()
    other.write_text(LEARNER_SOURCE.replace("tiny_registered", "tiny_file"))
    assert load(f"{other}:make_tiny") == "tiny_file"  # a file: a module of its own
    assert plugins.spec_of("tiny_file") == f"{other}:make_tiny" and plugins.spec_of("vae") is None
    assert plugins.spec_of("tiny_registered") == "my_learners:TinyPCA"  # the import registering it
    from bulbjax.learners import make_learner

    learner = make_learner("pca", 6)
    assert type(learner).__name__ == "TinyPCA" and learner.latent_dim == 6
    assert not registry.is_sequential_name("pca")


@pytest.mark.parametrize("spec, message", [
    ("no_such_module:Mine", r"learner 'no_such_module:Mine': cannot import 'no_such_module' "
                            r"\(ModuleNotFoundError: No module named 'no_such_module'\); put its "
                            r"folder on PYTHONPATH"),
    ("broken_learners:Mine", r"cannot import 'broken_learners' \(RuntimeError: the GPU is on fire\)$"),
    ("my_learners:Nope", r"my_learners has no 'Nope'; it has the learner classes TinyPCA$"),
    ("my_learners:vae", r"my_learners has no 'vae'"),  # a built-in's name is no module's learner
    ("my_learners:NOT_A_LEARNER", r"int 3 is neither a learner class \(with init, update, encode\)"),
    ("my_learners:dataclasses", r"module .* is neither a learner class"),
    ("vae=my_learners:TinyPCA", r"the name 'vae' is another learner's; give this one another name"),
    ("no/such/file.py:Mine", r"no such file '.*no/such/file.py'"),
    ("my_learners:", r"must read MODULE:NAME or path/to/file.py:NAME"),
])
def test_spec_errors_are_one_line(plugin_dir, spec, message):
    with pytest.raises(ValueError, match=message) as caught:
        plugins.load_learner_spec(spec)
    assert "\n" not in str(caught.value)


# Learners with init, update and encode but short of the rest of the protocol (issue 65 item 2).
SHORT_SOURCE = textwrap.dedent('''
    import dataclasses
    from typing import ClassVar

    from bulbjax.learners import LearnerConfig


    @dataclasses.dataclass(frozen=True)
    class Bare:
        latent_dim: int
        config: LearnerConfig = LearnerConfig()
        sequential: ClassVar[bool] = False

        def init(self, key, frame_shape): ...
        def update(self, state, frames, key): ...
        def encode(self, params, frames): ...


    @dataclasses.dataclass(frozen=True)
    class BareWindows(Bare):
        sequential: ClassVar[bool] = True

        @property
        def retain_fraction(self):
            return 0.0

        @property
        def batch_size(self):
            return 4


    def make_bare(latent_dim, config, action_dim):
        return Bare(latent_dim, config)
''')


@pytest.mark.parametrize("attr, message", [
    ("Bare", "Bare is no frame learner: it lacks retain_fraction, batch_size; add them as "
             "docs/extending.md's 'A new learner' lists (FrameLearner, bulbjax/learners/base.py)"),
    ("make_bare", "Bare is no frame learner: it lacks retain_fraction, batch_size; add them as "
                  "docs/extending.md's 'A new learner' lists (FrameLearner, bulbjax/learners/base.py)"),
    ("BareWindows", "BareWindows is no sequential learner: it lacks action_dim, sequence_length, "
                    "window_length; add them as docs/extending.md's 'A new learner' lists "
                    "(SequenceLearner, bulbjax/learners/base.py)"),
])
def test_a_learner_short_of_the_protocol_is_refused_in_one_line(plugin_dir, attr, message):
    """init, update and encode alone pass no longer: every member docs/extending.md lists as
    required is checked when the spec loads, and nothing stays registered."""
    (plugin_dir / "short_learners.py").write_text(SHORT_SOURCE)
    with pytest.raises(ValueError) as caught:
        plugins.load_learner_spec(f"short_learners:{attr}")
    assert str(caught.value) == f"learner 'short_learners:{attr}': {message}"
    assert attr not in registry._REGISTRY and "Bare" not in registry._REGISTRY


def test_run_refuses_a_short_learner_before_making_its_folder(plugin_dir, tmp_path, capsys):
    """`bulbjax run --learners vae_rpl,FILE.py:Bare`: one line, exit status 2, no run folder
    (it used to trace, fail with a long traceback and leave a folder holding only log.txt)."""
    from bulbjax import cli

    source = plugin_dir / "short_file.py"
    source.write_text(SHORT_SOURCE)
    out = tmp_path / "run"
    assert cli.main(["run", "--small", "--learners", f"vae_rpl,{source}:Bare", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"bulbjax: error: learner '{source}:Bare': Bare is no frame learner: it lacks "
                   "retain_fraction, batch_size; add them as docs/extending.md's 'A new learner' "
                   "lists (FrameLearner, bulbjax/learners/base.py)")
    assert not out.exists()


def test_learners_flag_records_the_specs(plugin_dir, monkeypatch, tmp_path):
    """`--learners vae_rpl,MODULE:NAME` -> the registered names, and the specs in the config
    (a file's path absolute); `--rl-input latent:MODULE:NAME` names the learner; the config
    reads back from JSON, and one written before the field still loads."""
    from bulbjax.config import config_from_dict
    from bulbjax.run.settings import resolve

    monkeypatch.chdir(plugin_dir)
    source = LEARNER_SOURCE.replace("tiny_registered", "tiny_file")
    (plugin_dir / "file_learners.py").write_text(source)
    cfg = resolve(overrides={"learners": "vae_rpl,my_learners:TinyPCA,./file_learners.py:make_tiny",
                             "rl_input": "latent:my_learners:TinyPCA"}, small=True)
    assert cfg.learners == ("vae_rpl", "TinyPCA", "tiny_file") and cfg.rl_learner == "TinyPCA"
    file_spec = f"{plugin_dir}/file_learners.py:make_tiny"  # the path made absolute
    assert cfg.learner_modules == ("my_learners:TinyPCA", file_spec)
    assert config_from_dict(json.loads(json.dumps(dataclasses.asdict(cfg)))) == cfg
    old = dataclasses.asdict(resolve(overrides={"learners": "vae_rpl"}))
    assert old["learner_modules"] == ()
    del old["learner_modules"]  # a config.json written before the field
    assert config_from_dict(old).learner_modules == ()
    # the record follows the learners: another --learners keeps the specs still in use only
    again = resolve(base=cfg, overrides={"learners": "vae_rpl,tiny_file", "rl_input": "state"})
    assert again.learner_modules == (file_spec,)
    assert cfg.replace(learners=("vae_rpl",), rl_input="state").learner_modules == ()
    # a learner loaded from Python, then named: recorded all the same (`bulbjax reproduce`)
    name = plugins.load_learner_spec("pca=my_learners:TinyPCA")
    named = cfg.replace(learners=("vae_rpl", name), rl_input="state")
    assert named.learner_modules == ("pca=my_learners:TinyPCA",)
    with pytest.raises(ValueError, match=r"unknown learners \['mine'\]; accepted: .*MODULE:NAME"):
        resolve(overrides={"learners": "vae_rpl,mine"})


def test_installed_package_entry_point(plugin_dir):
    """An installed package's learners (entry point group `bulbjax.learners`) by name."""
    from bulbjax.config import ExperimentConfig

    info = plugin_dir / "my_learners-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: my-learners\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[bulbjax.learners]\ntinyep = my_learners:TinyPCA\n")
    assert plugins.entry_point_spec("tinyep") == "tinyep=my_learners:TinyPCA"
    cfg = ExperimentConfig(env="CartPole", learners=("vae_rpl", "tinyep"))
    assert cfg.learner_modules == ("tinyep=my_learners:TinyPCA",)
    assert plugins.parse_learner_list("vae_rpl,tinyep") == ("vae_rpl", "tinyep")
    alone = ExperimentConfig(env="CartPole", learners=("tinyep",))
    assert alone.learner_modules == ("tinyep=my_learners:TinyPCA",)


def _synthetic_run(path, learners: tuple[str, ...], modules: tuple[str, ...]) -> None:
    """A run folder as `bulbjax run` leaves it (config.json naming the specs, metrics.jsonl)."""
    from bulbjax.config import ExperimentConfig
    from run_folders import write_synthetic_run

    write_synthetic_run(str(path), ExperimentConfig(env="CartPole", learners=learners,
                                                    learner_modules=modules, seeds=2, epochs=2))


def _bulbjax(args: list[str], cwd: str, pythonpath: list[str]) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(pythonpath)}
    return subprocess.run([sys.executable, "-m", "bulbjax", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=900)


def test_fresh_process_reads_the_learner_from_config_json(plugin_dir, tmp_path):
    """`bulbjax report` in a new process (no flag) imports the learner the run's config.json
    names; without the module on its path it is a one-line error naming the spec and why."""
    run = str(tmp_path / "run")
    _synthetic_run(run, ("vae_rpl", "TinyPCA"), ("my_learners:TinyPCA",))
    r = _bulbjax(["report", run, "--out", str(tmp_path / "redrawn")], str(tmp_path),
                 [ROOT, str(plugin_dir)])
    assert r.returncode == 0, r.stderr[-3000:]
    table = (tmp_path / "redrawn" / "table.md").read_text()
    assert "| TinyPCA | π_curr |" in table and "| vae_rpl | π_curr |" in table
    r = _bulbjax(["report", run], str(tmp_path), [ROOT])
    err = [line for line in r.stderr.splitlines() if line.startswith("bulbjax:")]
    assert r.returncode == 2 and len(err) == 1, r.stderr[-3000:]
    assert err[0] == (f"bulbjax: error: {run}/config.json names a learner 'my_learners:TinyPCA': "
                      "cannot import 'my_learners' (ModuleNotFoundError: No module named "
                      "'my_learners'); put its folder on PYTHONPATH (or install its package)")


def _table_learners(path: str) -> set[str]:
    with open(path) as f:
        return {line.split("|")[1].strip() for line in f if line.startswith("| ") and "π_" in line}


@pytest.mark.slow
def test_cli_run_resume_report_fit(plugin_dir, tmp_path):
    """The whole path in fresh processes, as a researcher would type it: `bulbjax run --small
    --learners vae_rpl,my_learners:TinyPCA` stopped after one epoch, `--resume` without the flag
    to the second, `report` on the folder (elsewhere), and `fit` with the learner as a file path
    (relative to the working directory)."""
    path = [ROOT, str(plugin_dir)]
    run = str(tmp_path / "run")
    tiny = ["--seeds", "1", "--small", "--ppo-updates", "1", "--ppo-option", "num_steps=16"]
    r = _bulbjax(["run", "--env", "CartPole", "--learners", "vae_rpl,my_learners:TinyPCA",
                  "--epochs", "2", "--stop-after", "1", *tiny, "--out", run], str(tmp_path), path)
    assert r.returncode == 0, r.stderr[-4000:]
    saved = json.load(open(os.path.join(run, "config.json")))["experiment"]
    assert saved["learners"] == ["vae_rpl", "TinyPCA"]
    assert saved["learner_modules"] == ["my_learners:TinyPCA"]
    r = _bulbjax(["run", "--resume", run], str(tmp_path), path)
    assert r.returncode == 0, r.stderr[-4000:]
    recs = [json.loads(line) for line in open(os.path.join(run, "metrics.jsonl"))]
    assert [x["epoch"] for x in recs] == [0, 1]
    assert all(x["learners"]["TinyPCA"]["loss"] > 0 and "TinyPCA" in x["probes"] for x in recs)
    r = _bulbjax(["report", run, "--out", str(tmp_path / "fig2")], str(tmp_path), path)
    assert r.returncode == 0, r.stderr[-4000:]
    rows = _table_learners(str(tmp_path / "fig2" / "table.md"))
    assert {"TinyPCA", "vae_rpl", "TinyPCA (linear)"} <= rows
    fit = str(tmp_path / "fit")
    r = _bulbjax(["fit", "--env", "SyntheticMovers", "--small", "--learners",
                  "vae_rpl,plugins/my_learners.py:TinyPCA", "--seeds", "1", "--updates", "2",
                  "--probe-every", "1", "--data-worlds", "8", "--data-steps", "16",
                  "--heldout-steps", "8", "--out", fit], str(tmp_path), [ROOT])
    assert r.returncode == 0, r.stderr[-4000:]
    assert {"TinyPCA", "vae_rpl"} <= _table_learners(os.path.join(fit, "table.md"))
