"""The learner registry: a name -> how to build the learner, its per-name config defaults and
whether it trains on windows.

A new learner is one module plus one line. The module defines a class that satisfies
`FrameLearner` or `SequenceLearner` (`bulbjax/learners/base.py`: what `init`, `update`, `encode`
take and return, how windows and the equal-compute rule plug in) and registers it:

    from bulbjax.learners.base import LearnerConfig
    from bulbjax.learners.registry import register_learner

    @register_learner("mine", defaults={"retain_fraction": 0.5})
    def make_mine(latent_dim: int, config: LearnerConfig, action_dim: int) -> "Mine":
        return Mine(latent_dim=latent_dim, config=config)

For a learner shipped with bulbjax, the one line imports the module from
`bulbjax/learners/__init__.py` (so that `bulbjax run --learners mine` and a resumed run find
it). A learner of one's own needs no line here: `--learners vae_rpl,mymodule:Mine` (or
`path/to/file.py:Mine`, or an installed package's entry point) imports and, if need be,
registers it (`bulbjax.learners.plugins.load_learner_spec`), and the run's config records the
spec; a script or test may also import its own module before it builds an `ExperimentConfig`.
From then on the name is accepted wherever learner names are (`ExperimentConfig.learners`,
`--learners`, `--rl-input latent:mine`), and the experiment gives the learner its replay (or
window) buffer, its update program and its probes.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Mapping

from bulbjax.learners.base import LearnerConfig

# (latent_dim, config, action_dim) -> a learner. `latent_dim` is `latent_factor` (2) x the
# state's dimension; `config` is `resolve_config(name, ...)`: LearnerConfig's defaults, the
# name's `defaults`, then the run's choices; `action_dim` is the width of the actions in
# `Windows.actions` (one-hot size for discrete actions), which only sequential learners use.
Factory = Callable[[int, LearnerConfig, int], Any]


@dataclasses.dataclass(frozen=True)
class Registration:
    """One registered learner: its `factory`, the `LearnerConfig` fields its name sets before the
    caller's choices (`defaults`, e.g. `{"retain_fraction": 0.5}`, the paper's replay fix) and
    whether it trains on windows (`sequential`: the run then keeps window buffers); whether its
    latent is of one frame alone (`frame_latent`: every frame learner's, and a sequential
    learner's that encodes each frame on its own, as ST-DIM: PPO then reads it from the frames,
    and `rl_frames` can stack the latents of several)."""

    name: str
    factory: Factory
    defaults: Mapping[str, Any]
    sequential: bool
    frame_latent: bool = True


_REGISTRY: dict[str, Registration] = {}


def register_learner(name: str, factory: Factory | None = None, *, defaults: Mapping[str, Any] | None = None,
                     sequential: bool | None = None, frame_latent: bool | None = None,
                     replace: bool = False) -> Any:
    """Register learner `name` built by `factory(latent_dim, config, action_dim)`; as a
    decorator when `factory` is left out (returns the factory unchanged). `defaults`: per-name
    `LearnerConfig` fields (checked here: an unknown field is an error). `sequential`: whether it
    trains on `Windows`; left out, the factory's own `sequential` attribute (a class with
    `sequential = True`) or False. `frame_latent`: whether its latent is one frame's (read by PPO
    through the learner's `frame_features` when it is sequential); left out, `not sequential`.
    Registering a name twice is an error unless `replace`."""
    fields = {f.name for f in dataclasses.fields(LearnerConfig)}

    def add(fn: Factory) -> Factory:
        if not name or not isinstance(name, str) or ":" in name or "," in name:
            raise ValueError(f"learner name must be a non-empty string without ':' or ',', got {name!r}")
        if name in _REGISTRY and not replace:
            raise ValueError(f"learner {name!r} is already registered (pass replace=True to replace it)")
        unknown = set(defaults or {}) - fields
        if unknown:
            raise ValueError(f"learner {name!r}: unknown LearnerConfig fields {sorted(unknown)} in defaults")
        LearnerConfig(**dict(defaults or {}))  # validated now, not at the first run
        seq = bool(getattr(fn, "sequential", False)) if sequential is None else bool(sequential)
        one_frame = (not seq) if frame_latent is None else bool(frame_latent)
        _REGISTRY[name] = Registration(name, fn, dict(defaults or {}), seq, one_frame)
        return fn

    return add if factory is None else add(factory)


def unregister_learner(name: str) -> None:
    """Remove a registered learner (tests that register one of their own clean up with it)."""
    if name not in _REGISTRY:
        raise KeyError(f"learner {name!r} is not registered")
    del _REGISTRY[name]


def registration(name: str) -> Registration:
    """The registration of `name`; an unknown name is a clear error listing the known ones."""
    if name not in _REGISTRY:
        raise ValueError(f"unknown learner {name!r}; accepted names: {', '.join(learner_names())}")
    return _REGISTRY[name]


def learner_names() -> tuple[str, ...]:
    """Every registered learner's name, in the order they were registered (built-ins first)."""
    return tuple(_REGISTRY)


def is_sequential_name(name: str) -> bool:
    """Whether the registered learner `name` trains on windows (False for an unknown name)."""
    return name in _REGISTRY and _REGISTRY[name].sequential


def has_frame_latent_name(name: str) -> bool:
    """Whether the registered learner `name`'s latent is of one frame alone (a frame learner's,
    or ST-DIM's; False for an unknown name)."""
    return name in _REGISTRY and _REGISTRY[name].frame_latent
