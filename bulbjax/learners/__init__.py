"""Learners and their registry.

`make_learner(name, latent_dim, config, action_dim=1)` builds a registered learner (registry.py:
a new learner is one module that calls `register_learner`, plus one import line at the end of
this file; a learner of one's own, outside bulbjax, is loaded by `load_learner_spec`, plugins.py),
among them the built-in frame learners
- `vae`: VAE_v0, plain conv VAE (beta=1, no replay retention);
- `vae_rpl`: the same model, asking replay to retain 50% of the initial frames;
- `beta_vae`: beta-VAE with beta=5 (the paper's best) and the same 50% retention;
or one of the sequential learners (train on windows, one latent per step; sequential.py)
- `svae`, `pred`, `dsa`: each with the 50% initial-replay retention, as the paper applied the
  fix to every learner after VAE_v0;
or the structured frame learner
- `spair`: SPAIR with a learned background (spair/), 64 frames per batch (the paper's
  equalised compute) and the 50% retention; its latent size follows from its config
  (G*G cells of 6 + spair_what_dim), not from `latent_dim`; its grid is 4x4 (`spair_grid`);
- `spair6`: the same with a 6x6 grid (the paper reports both; the two can train side by side).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

from bulbjax.learners.base import (
    DSA_ENCODERS,
    LEARNER_FORM_FIELDS,
    FrameLearner,
    LearnerConfig,
    LearnerState,
    SequenceLearner,
    check_finite,
    parse_learner_options,
)
from bulbjax.learners.networks import ConvEncoder, DeconvDecoder, check_frame_shape
from bulbjax.learners.plugins import load_learner_spec
from bulbjax.learners.registry import (has_frame_latent_name, is_sequential_name, learner_names, register_learner,
                                       registration, unregister_learner)
from bulbjax.learners.sequential import DSA, PRED, SEQUENTIAL_LEARNERS, SVAE, SequentialVAE
from bulbjax.learners.spair import SPAIR
from bulbjax.learners.vae import VAE


# The built-in learners (registry.py: how a new one registers itself).
def _vae(latent_dim: int, config: LearnerConfig, action_dim: int) -> VAE:
    return VAE(latent_dim=latent_dim, config=config)


def _spair(latent_dim: int, config: LearnerConfig, action_dim: int) -> SPAIR:
    return SPAIR(config=config)  # its latent size follows from its config (G*G cells)


def _sequential(cls: type[SequentialVAE]):
    def make(latent_dim: int, config: LearnerConfig, action_dim: int) -> SequentialVAE:
        return cls(latent_dim=latent_dim, config=config, action_dim=action_dim)
    return make


register_learner("vae", _vae)
register_learner("vae_rpl", _vae, defaults={"retain_fraction": 0.5})
register_learner("beta_vae", _vae, defaults={"beta": 5.0, "retain_fraction": 0.5})
for _name, _cls in SEQUENTIAL_LEARNERS.items():
    register_learner(_name, _sequential(_cls), defaults={"retain_fraction": 0.5}, sequential=True)
register_learner("spair", _spair, defaults={"batch_size": 64, "retain_fraction": 0.5})
register_learner("spair6", _spair, defaults={"batch_size": 64, "retain_fraction": 0.5, "spair_grid": 6})

# The paper's learners (`learner_names()` also has those registered after them: the modules
# imported at the end of this file, a test's own).
LEARNER_NAMES: tuple[str, ...] = learner_names()
SEQUENCE_LEARNER_NAMES: tuple[str, ...] = tuple(SEQUENTIAL_LEARNERS)
FRAME_LEARNER_NAMES: tuple[str, ...] = tuple(n for n in LEARNER_NAMES if n not in SEQUENTIAL_LEARNERS)


def resolve_config(
    name: str, config: LearnerConfig | Mapping[str, Any] | None = None
) -> LearnerConfig:
    """The config `make_learner(name, ..., config)` uses.

    Start from LearnerConfig's defaults, apply the name's preset (e.g. beta=5 for
    beta_vae), then the caller's choices, which always win. A Mapping gives those choices
    explicitly; for a LearnerConfig they are its fields that differ from LearnerConfig's
    defaults (so `LearnerConfig(lr=1e-3)` keeps vae_rpl's retention; to force a field back
    to its global default, e.g. beta=1.0 for beta_vae, pass a Mapping).
    """
    reg = registration(name)
    if config is None:
        overrides: dict[str, Any] = {}
    elif isinstance(config, LearnerConfig):
        default = LearnerConfig()
        overrides = {
            f.name: getattr(config, f.name)
            for f in dataclasses.fields(LearnerConfig)
            if getattr(config, f.name) != getattr(default, f.name)
        }
    elif isinstance(config, Mapping):
        known = {f.name for f in dataclasses.fields(LearnerConfig)}
        unknown = set(config) - known
        if unknown:
            raise ValueError(f"unknown config fields {sorted(unknown)}; known: {sorted(known)}")
        overrides = dict(config)
    else:
        raise TypeError(f"config must be a LearnerConfig, a Mapping or None, got {type(config)}")
    return LearnerConfig(**{**reg.defaults, **overrides})


def make_learner(
    name: str,
    latent_dim: int,
    config: LearnerConfig | Mapping[str, Any] | None = None,
    action_dim: int = 1,
) -> Any:
    """Build the registered learner `name` (`learner_names()`; registry.py) with its factory;
    see `resolve_config`. `action_dim` is the width of the actions the sequential learners
    condition on (one-hot size for discrete actions); the frame learners ignore it."""
    return registration(name).factory(latent_dim, resolve_config(name, config), action_dim)


def is_sequential(learner: Any) -> bool:
    """True for learners that train on windows (`SequenceLearner`), False for frame learners."""
    return bool(getattr(learner, "sequential", False))


__all__ = [
    "DSA",
    "DSA_ENCODERS",
    "FRAME_LEARNER_NAMES",
    "LEARNER_FORM_FIELDS",
    "LEARNER_NAMES",
    "PRED",
    "SEQUENCE_LEARNER_NAMES",
    "SPAIR",
    "SVAE",
    "SequenceLearner",
    "SequentialVAE",
    "is_sequential",
    "has_frame_latent_name",
    "is_sequential_name",
    "learner_names",
    "load_learner_spec",
    "register_learner",
    "registration",
    "unregister_learner",
    "parse_learner_options",
    "ConvEncoder",
    "DeconvDecoder",
    "FrameLearner",
    "LearnerConfig",
    "LearnerState",
    "VAE",
    "check_finite",
    "check_frame_shape",
    "make_learner",
    "resolve_config",
]

# Learners registered by their own modules (registry.py): one line each.
from bulbjax.learners import contrastive  # noqa: E402,F401  (stdim, curl)
