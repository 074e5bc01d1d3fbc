"""`bulbjax.make(name, ...)`: the environment registry."""

from __future__ import annotations

import dataclasses
from typing import Any

from bulbjax.envs.base import MjxPixelEnv
from bulbjax.envs.env_config import OBSERVATIONS, EnvConfig
from bulbjax.envs.locomotion import Ant, HalfCheetah
from bulbjax.envs.objects.incline import (GeomOnIncline, GeomOnInclineMd, GeomOnInclineSm, YcbOnIncline,
                                          YcbOnInclineMd, YcbOnInclineSm)
from bulbjax.envs.objects.rearrange import REARRANGE_CLASSES
from bulbjax.envs.pendulum import CartPole, CartPoleContinuous, InvertedPendulum

_REGISTRY: dict[str, type[MjxPixelEnv]] = {
    cls.name: cls for cls in (CartPole, CartPoleContinuous, InvertedPendulum, HalfCheetah, Ant,
                              GeomOnIncline, GeomOnInclineMd, GeomOnInclineSm, YcbOnIncline,
                              YcbOnInclineMd, YcbOnInclineSm, *REARRANGE_CLASSES)
}
MULTICOLOUR_SUFFIX = "Multicolour"
ENV_NAMES: tuple[str, ...] = tuple(_REGISTRY)


def env_names(with_variants: bool = True) -> list[str]:
    """Registered names; with the multicolour variants (`<Name>Multicolour`) when asked."""
    names = list(_REGISTRY)
    colour = [n + MULTICOLOUR_SUFFIX for n, c in _REGISTRY.items() if c.supports_multicolour]
    return names + colour if with_variants else names


def make(name: str, num_envs: int = 64, resolution: int = 64, render: bool | str = True,
         multicolour: bool = False, render_steps: bool = True, version: int | str = 0,
         ycb_dir: str | None = None, num_points: int = 1024, show_targets: bool = False,
         reset_chunk: int | None = None, reset_pool: int | None = None, pool_segments: int = 1,
         graph_mode: str | None = None, fuse_substeps: bool = True,
         reset_pose_branch: str = "auto") -> MjxPixelEnv:
    """A batched environment of `num_envs` worlds with `resolution`x`resolution` RGB frames.

    `name` is a registered domain (see `env_names()`); a `Multicolour` suffix, or
    `multicolour=True`, draws one of bulb's four colour schemes per episode. `render` is True
    (RGB frames), False (no renderer), or the observation: "rgb", "depth" (frames and float32
    depth in metres, `state.depth`) or "pointcloud" (`state.points`, `[N, num_points, 3]` world
    points of the scene's objects, bulb's PT mode; frames stay available through
    `render_frames`). `render_steps=False` keeps a renderer for `env.render_frames` but leaves
    frames out of `reset`/`step` (the experiment renders only the steps it stores).
    Multi-object domains take `version` (an int, or "random": one drawn per world and episode)
    and `ycb_dir` (the YCB models; default `$BULBJAX_YCB_DIR`). `show_targets=True` draws the
    Rearrange targets as visual-only discs on the tray floor (bulb's frames have none).
    `reset_chunk` is how many ended worlds `step` resets at a time (None: the domain's default,
    0: the full-batch reset; see `EnvConfig.reset_chunk`); `reset_pool` the size, as a multiple of
    `num_envs`, of the pool of pre-settled states that ended worlds take instead (None: the
    domain's default, 0: no pool; see `EnvConfig.reset_pool`), kept per block of
    `num_envs / pool_segments` consecutive worlds (the experiment: one block per seed).
    `graph_mode` is how MJX-Warp's calls use CUDA graphs on a GPU (`EnvConfig.graph_mode`);
    `fuse_substeps=False` steps the physics in MJX's separate calls (`EnvConfig.fuse_substeps`);
    `reset_pose_branch` how reset worlds get their poses (`EnvConfig.reset_pose_branch`)."""
    base = name
    if name.endswith(MULTICOLOUR_SUFFIX):
        base, multicolour = name[: -len(MULTICOLOUR_SUFFIX)], True
    if base not in _REGISTRY or (multicolour and not _REGISTRY[base].supports_multicolour):
        raise ValueError(unknown_env(name))
    if isinstance(render, str):
        if render not in OBSERVATIONS:
            raise ValueError("render must be True, False or an observation "
                             f"({', '.join(OBSERVATIONS)}), got {render!r}")
        observation, render = render, True
    else:
        observation = "rgb"
    cfg = EnvConfig(num_envs=num_envs, resolution=resolution, render=bool(render),
                    render_steps=render_steps and observation != "pointcloud", multicolour=multicolour,
                    observation=observation, num_points=num_points, version=version, ycb_dir=ycb_dir,
                    show_targets=show_targets, reset_chunk=reset_chunk, reset_pool=reset_pool,
                    pool_segments=pool_segments, graph_mode=graph_mode, fuse_substeps=fuse_substeps,
                    reset_pose_branch=reset_pose_branch)
    return _REGISTRY[base](cfg)


def env_class(name: str) -> type[MjxPixelEnv]:
    """The domain class of a registered name (a `Multicolour` suffix is accepted)."""
    base = name[: -len(MULTICOLOUR_SUFFIX)] if name.endswith(MULTICOLOUR_SUFFIX) else name
    if base not in _REGISTRY:
        raise ValueError(unknown_env(name))
    return _REGISTRY[base]


def unknown_env(name: str) -> str:
    """The one-line error of an unknown environment name: the closest names first (a typo's
    fix), then every registered one."""
    import difflib

    close = difflib.get_close_matches(name, env_names(), n=2, cutoff=0.75)
    hint = f" (did you mean {' or '.join(map(repr, close))}?)" if close else ""
    return f"unknown environment {name!r}{hint}; available: {', '.join(env_names())}"


def ppo_config_for(name: str, base: Any = None) -> Any:
    """PPO settings for a domain: `base` (default `PPOConfig()`) with the domain's
    `ppo_overrides` applied (locomotion needs longer rollouts and more epochs than the pendulums,
    whose settings are PPO's defaults)."""
    from bulbjax.rl.ppo_config import PPOConfig

    base = PPOConfig() if base is None else base
    return dataclasses.replace(base, **env_class(name).ppo_overrides)
