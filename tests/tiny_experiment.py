"""The tiny experiment configurations the tests share (test_experiment, test_experiment_config,
test_config, test_run and test_recon, the last two with their differences replaced): CartPole
at 32 px, 2 seeds, 8 frames an epoch."""

from __future__ import annotations

import dataclasses

from bulbjax.epoch import ExperimentConfig
from bulbjax.eval.probe import ProbeConfig
from bulbjax.learners import LearnerConfig
from bulbjax.rl.ppo import PPOConfig

SEEDS = 2


def tiny_config() -> ExperimentConfig:
    return ExperimentConfig(
        env="CartPole", learners=("vae", "vae_rpl"), seeds=SEEDS, epochs=2, num_envs=4,
        resolution=32, ppo=PPOConfig(num_envs=4, num_steps=8, num_minibatches=2, update_epochs=1),
        ppo_updates_per_epoch=1, frames_per_epoch=8, replay_capacity=32,
        learner=LearnerConfig(batch_size=8, conv_features=(8, 8, 8, 8), hidden=16, lr=1e-3),
        learner_batches=2, eval_frames=8, probe_train_frames=16,
        probe=ProbeConfig(hidden=(16,), steps=20, batch_size=16), reference_steps=16)


ALL = ("vae", "vae_rpl", "beta_vae", "svae", "pred", "dsa")


def tiny_six_config() -> ExperimentConfig:
    """All six learners side by side; one batch per epoch and DSA's single LSTM keep the CPU
    compile short (the bilstm default is covered in test_sequential_learners)."""
    return dataclasses.replace(
        tiny_config(), learners=ALL, learner_batches=1, sequence_length=4,
        learner=LearnerConfig(batch_size=8, conv_features=(8, 8, 8, 8), hidden=16, lr=1e-3,
                              pred_horizon=2, dsa_encoder="lstm"))
