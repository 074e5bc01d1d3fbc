"""Frame learners and their registry.

`make_learner(name, latent_dim, config)` builds one of:
- `vae`: VAE_v0, plain conv VAE (beta=1, no replay retention);
- `vae_rpl`: the same model, asking replay to retain 50% of the initial frames;
- `beta_vae`: beta-VAE with beta=5 (the paper's best) and the same 50% retention.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

from bulbjax.learners.base import (
    FrameLearner,
    LearnerConfig,
    LearnerState,
    check_finite,
)
from bulbjax.learners.networks import ConvEncoder, DeconvDecoder, check_frame_shape
from bulbjax.learners.vae import VAE

# Per-name defaults, applied on top of LearnerConfig's defaults.
_PRESETS: dict[str, dict[str, Any]] = {
    "vae": {},
    "vae_rpl": {"retain_fraction": 0.5},
    "beta_vae": {"beta": 5.0, "retain_fraction": 0.5},
}
LEARNER_NAMES: tuple[str, ...] = tuple(_PRESETS)


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
    if name not in _PRESETS:
        raise ValueError(f"unknown learner {name!r}; accepted names: {', '.join(LEARNER_NAMES)}")
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
    return LearnerConfig(**{**_PRESETS[name], **overrides})


def make_learner(
    name: str, latent_dim: int, config: LearnerConfig | Mapping[str, Any] | None = None
) -> VAE:
    """Build the frame learner `name` (one of LEARNER_NAMES); see `resolve_config`."""
    return VAE(latent_dim=latent_dim, config=resolve_config(name, config))


__all__ = [
    "LEARNER_NAMES",
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
