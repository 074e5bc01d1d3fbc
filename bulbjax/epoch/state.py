"""The run state an epoch carries, and the pieces of it a phase hands to the next.

Everything a seed owns (PPO, learners, replay buffers) carries a leading seed axis `[S, ...]`;
the simulators of all seeds are one batch of `S * N` worlds (`[S*N, ...]`), reshaped to
`[S, N]` wherever a per-seed function needs them. Types only: what fills them is the policy
side (`policy`), the data side (`streams`), learning, probing and the epoch (`loop`).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from bulbjax.data import replay, sequence
from bulbjax.envs.base import EnvState
from bulbjax.rl.ppo import PPOState


@struct.dataclass
class PolicyHistory:
    """What PPO's latent of a sequential learner is read from, per world: the last L steps up to
    and including the current one, cut at the start of the world's current episode, laid out as
    a training window whose episode ends at the current step (`bulbjax.data.sequence`): the
    `count` steps held, oldest first, then padding (the current frame repeated, action 0). The
    latent PPO sees is the learner's per-step latent at step `count - 1` of this window. With
    `rl_frames` K > 1 (pixels or a frame learner's latent) the same window of L = K steps holds
    the frames PPO stacks (`Policy.stacked_frames`). Part of the run state: carried from epoch to
    epoch and checkpointed with the worlds it follows.

    Cost: memory `S x N x L` frames per set of worlds (train and held-out current-policy: fig2
    with L = 24, 2 x 113 MB). Per step and world, on top of the frame a frame learner would
    encode (rendered once, its conv features computed once and kept, `PolicyWindow`): the
    learner's part after the convs over the L steps (SVAE: an LSTM of L steps; DSA: its two
    sequence encoders; PRED: two FC layers on the L steps' features) and a shift of the window
    (L frames, features and actions copied). Once per rollout (each PPO update's, each held-out
    stream's): L conv passes per world, the features of the history under the new params."""

    frames: jax.Array  # uint8 [S, N, L, H, W, 3]
    actions: jax.Array  # float32 [S, N, L, A]: the action that led into each frame (0 on padding)
    count: jax.Array  # int32 [S, N]: steps of the current episode held, 1..L

    @property
    def valid(self) -> jax.Array:
        """bool [S, N, L]: the steps held (False on padding), as `Windows.valid`."""
        return jnp.arange(self.frames.shape[2]) < self.count[..., None]


@struct.dataclass
class PolicyWindow:
    """A `PolicyHistory` with its frames' `frame_features` under the learner's current params
    (the carry of a rollout: features are computed once per frame, and again for the whole
    history once per rollout, since the params change between epochs)."""

    history: PolicyHistory
    features: jax.Array  # float32 [S, N, L, F]


@struct.dataclass
class Rendered:
    """Frames of stored steps, uint8 `[..., S*N, H, W, 3]`, kept in place of their render inputs
    where the policy rendered them already (PPO on pixels or a latent): `Streams.frames_at`
    gathers them instead of rendering the steps again (replay, windows, held-out windows). Costs
    the memory of an epoch's frames (fig2: 128 steps x 384 worlds, ~600 MB); saves about a
    quarter of a probing fig2 epoch's renders (~24k of ~92k frames)."""

    frames: jax.Array


# What a frame-observing policy carries from step to step (`Policy.view`): every world's
# current frame `[S, N, H, W, 3]` (pixels, a frame learner's latent), its `PolicyWindow`
# (a sequential learner's latent), its `PolicyHistory` of the last `rl_frames` > 1 frames, or
# None (the true state, the random policy).
PolicyView = jax.Array | PolicyWindow | PolicyHistory | None


def history_of(view: PolicyView) -> PolicyHistory | None:
    """The worlds' `PolicyHistory` a rollout hands on: a sequential learner's window, the last
    `rl_frames` frames, else None."""
    if isinstance(view, PolicyWindow):
        return view.history
    return view if isinstance(view, PolicyHistory) else None


@struct.dataclass
class RunState:
    """Carry of the jitted epoch."""

    ppo: PPOState  # [S]
    learners: dict[str, Any]  # name -> LearnerState [S]
    buffers: dict[str, replay.ReplayBuffer]  # retention key -> frame buffer [S]
    windows: dict[str, sequence.WindowBuffer]  # retention key -> window buffer [S] (sequential learners)
    train_env: EnvState  # [S*N] worlds driven by PPO; frames for replay come from here
    curr_env: EnvState  # [S*N] held-out worlds under the current policy (never in replay)
    rand_env: EnvState  # [S*N] held-out worlds under the random policy (never in replay)
    # PPO on a sequential learner's latent: "train" and "curr" worlds' windows; {} otherwise
    policy_history: dict[str, PolicyHistory]
    ref_spread: jax.Array  # [D] reference spread of every state entry (random policy, at init)
    epoch: jax.Array
    # the common probe set's random-policy part, kept from init (`probe_variants.ProbeSet`, [S]);
    # None without the "common" probe variant (no leaves: checkpoints of runs without it unchanged)
    probe_set: Any = None
    # the next epoch's environment work, done (`ExperimentConfig.overlap`, "pipeline"/"streams"):
    # its metrics, the keys of its learning, held-out rollouts and probes, and its new steps for
    # the common probe set; {} in a run that does each epoch's environment work in that epoch
    # (no leaves: its checkpoints unchanged)
    pending: dict[str, Any] = struct.field(default_factory=dict)


class EnvBatch(NamedTuple):
    """An epoch's new data for the learners' side (`Experiment.env_data`): the frames of its
    rollouts and their states, its windows (and their start steps), the keys of its replay
    insert, learning, held-out rollouts and probes, and the metrics of its PPO phase. What moves
    to the learners' device in a run with the learners apart (`bulbjax.epoch.apart`)."""

    frames: jax.Array
    states: jax.Array
    windows: Any  # `Windows` of the epoch, or None without sequential learners
    index: Any  # the windows' start steps, or None
    k_rep: jax.Array
    k_learn: jax.Array
    k_eval: jax.Array
    k_probe: jax.Array
    rl: dict  # rl_return, rl_episodes, nonfinite_resets, ppo


class EnvStage(NamedTuple):
    """What `Experiment.env_stage` hands on to the rest of an epoch."""

    ppo: PPOState
    train_env: EnvState
    buffers: dict
    windows: dict
    train_hist: PolicyHistory | None
    metrics: dict
    epoch: jax.Array
    k_learn: jax.Array
    k_eval: jax.Array
    k_probe: jax.Array
    # the epoch's new steps of the current policy for the common probe set (`probe_variants`)
    fresh: Any = None
