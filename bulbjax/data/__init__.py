"""Training-data plumbing: the functional frame replay buffer."""

from bulbjax.data.replay import ReplayBuffer, ReplayConfig, init, insert, retain_initial, sample

__all__ = ["ReplayBuffer", "ReplayConfig", "init", "insert", "retain_initial", "sample"]
