"""Training-data plumbing: the functional frame replay buffer and the sequence-window buffer."""

from bulbjax.data import sequence
from bulbjax.data.replay import ReplayBuffer, ReplayConfig, init, insert, retain_initial, sample
from bulbjax.data.sequence import WindowBuffer, Windows

__all__ = ["ReplayBuffer", "ReplayConfig", "WindowBuffer", "Windows", "init", "insert",
           "retain_initial", "sample", "sequence"]
