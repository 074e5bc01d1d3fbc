"""A learner of one's own (docs/extending.md): defined in this file, registered with one call, and
trained, probed (MLP and linear probes) and observed by PPO in an epoch of the experiment like
the paper's learners."""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from bulbjax.epoch import Experiment, ExperimentConfig
from bulbjax.eval.probe import ProbeConfig
from bulbjax.learners import (FrameLearner, LearnerConfig, LearnerState, learner_names, make_learner,
                              register_learner, unregister_learner)
from bulbjax.report.records import epoch_records
from bulbjax.rl.ppo import PPOConfig

NAME = "tiny_pca"


@dataclasses.dataclass(frozen=True)
class TinyPCA:
    """A linear autoencoder on 8x8 average-pooled frames: the smallest learner that learns."""

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
    def _pooled(frames: jax.Array) -> jax.Array:
        x = frames.astype(jnp.float32) / 255.0
        b, h, w, c = x.shape
        return x.reshape(b, 8, h // 8, 8, w // 8, c).mean(axis=(2, 4)).reshape(b, -1)

    def init(self, key: jax.Array, frame_shape: tuple[int, int, int]) -> LearnerState:
        k1, k2 = jax.random.split(key)
        d = 8 * 8 * frame_shape[2]
        params = {"enc": nn.Dense(self.latent_dim).init(k1, jnp.zeros((1, d)))["params"],
                  "dec": nn.Dense(d).init(k2, jnp.zeros((1, self.latent_dim)))["params"]}
        return LearnerState(params, optax.adam(self.config.lr).init(params), jnp.zeros((), jnp.int32))

    def encode(self, params: Any, frames: jax.Array) -> jax.Array:
        return nn.Dense(self.latent_dim).apply({"params": params["enc"]}, self._pooled(frames))

    def update(self, state: LearnerState, frames: jax.Array, key: jax.Array) -> tuple[LearnerState, dict]:
        x = self._pooled(frames)

        def loss_fn(p: Any) -> jax.Array:
            z = nn.Dense(self.latent_dim).apply({"params": p["enc"]}, x)
            return jnp.mean((nn.Dense(x.shape[-1]).apply({"params": p["dec"]}, z) - x) ** 2)

        loss, grads = jax.value_and_grad(loss_fn)(state.params)
        updates, opt = optax.adam(self.config.lr).update(grads, state.opt_state, state.params)
        return LearnerState(optax.apply_updates(state.params, updates), opt, state.step + 1), {"loss": loss}


@pytest.fixture(scope="module")
def registered():
    """The one line a new learner needs (here inside the test: cleaned up afterwards)."""
    register_learner(NAME, lambda latent_dim, config, action_dim: TinyPCA(latent_dim, config),
                     defaults={"retain_fraction": 0.25})
    yield NAME
    unregister_learner(NAME)
    assert NAME not in learner_names()


def test_registration(registered) -> None:
    assert registered in learner_names()
    learner = make_learner(registered, 6, LearnerConfig(lr=3e-3))
    assert isinstance(learner, TinyPCA) and isinstance(learner, FrameLearner)
    assert learner.retain_fraction == 0.25 and learner.config.lr == 3e-3  # defaults, then the caller's
    with pytest.raises(ValueError, match="already registered"):
        register_learner(registered, lambda *a: None)
    with pytest.raises(ValueError, match="unknown LearnerConfig fields"):
        register_learner("other", lambda *a: None, defaults={"no_such_field": 1})
    with pytest.raises(ValueError, match="unknown learner"):
        make_learner("no_such_learner", 4)
    with pytest.raises(ValueError, match="unknown learners"):
        ExperimentConfig(env="CartPole", learners=("no_such_learner",))


def test_one_epoch_of_the_experiment(registered) -> None:
    """Trained, probed and observed by PPO (`--rl-input latent:tiny_pca`) in one epoch, beside
    nothing else: its metrics, both probes and its own replay buffer (retention 0.25)."""
    cfg = ExperimentConfig(
        env="CartPole", learners=(registered,), seeds=2, epochs=1, num_envs=4, resolution=32,
        rl_input=f"latent:{registered}",
        ppo=PPOConfig(num_envs=4, num_steps=8, num_minibatches=2, update_epochs=1),
        ppo_updates_per_epoch=1, frames_per_epoch=8, replay_capacity=32,
        learner=LearnerConfig(batch_size=8, lr=1e-2), learner_batches=3, eval_frames=8,
        probe_train_frames=16, probe=ProbeConfig(hidden=(8,), steps=10, batch_size=16), reference_steps=16)
    exp = Experiment(cfg)
    rs = exp.init(jax.random.PRNGKey(0))
    assert set(rs.buffers) == {"retain_0.25"}
    rs, m = exp.epoch(rs, jax.random.PRNGKey(1))
    m = jax.device_get(m)
    d = exp.env.state_dim
    loss = m["learners"][registered]["loss"]
    assert loss.shape == (2,) and np.all(np.isfinite(loss)) and np.all(loss > 0)
    for stream in ("curr", "rand"):
        p = m["probes"][registered][stream]
        assert p["mae"].shape == p["linear_mae"].shape == (2, d)
        assert np.all(np.isfinite(p["mae"])) and np.all(np.isfinite(p["linear_mae"]))
    assert int(jax.device_get(rs.learners[registered].step)[0]) == 3  # learner_batches updates
    rec = epoch_records(0, m, exp.spec)
    assert len(rec) == 2 and set(rec[0]["probes"]) == {registered} == set(rec[0]["linear_probes"])
    assert np.isfinite(rec[0]["learners"][registered]["loss"])
