"""The epoch: one experiment's jitted init and epoch, all seeds at once (`loop.py`: `Experiment`),
the parts it is composed of (`devices`, `seeds`, `learning`, `probing`, `probe_variants`; the
environment's side in `rollouts/`: `policy`, `observations`, `streams`; the run state's types in
`state`, the layout of its random keys in `keys`), its programs compiled and laid over devices and
processes (`programs`, `groups`, `apart`), and an offline fit's programs (`offline`).

Imports `bulbjax.config` (what an experiment is built from) and the layers below it (learners,
envs, rl, data, eval); never `bulbjax.report` or `bulbjax.run`, which use this face."""

from bulbjax.config import ExperimentConfig, small_config
from bulbjax.epoch.groups import SeedGroups
from bulbjax.epoch.loop import Experiment
from bulbjax.epoch.offline import OfflineFit, Source, make_source, reference_spread
from bulbjax.epoch.probing import object_pixels, probe_targets
from bulbjax.epoch.programs import Programs
from bulbjax.epoch.state import RunState

__all__ = ["ExperimentConfig", "small_config", "Experiment", "RunState", "Programs", "SeedGroups", "OfflineFit",
           "Source", "make_source", "reference_spread", "object_pixels", "probe_targets"]
