"""Experiments: the jitted epoch (RL, replay, learners, probes) and its reports."""

from bulbjax.experiment.config import ExperimentConfig, small_config
from bulbjax.experiment.loop import Experiment
from bulbjax.experiment.state import RunState

__all__ = ["ExperimentConfig", "small_config", "Experiment", "RunState"]
