"""Environments: batched MJX physics with Warp-rendered frames and the true low-dim state."""

from bulbjax.envs.base import EnvState, MjxPixelEnv, RenderInput
from bulbjax.envs.env_config import EnvConfig
from bulbjax.envs.registry import ENV_NAMES, env_names, make

__all__ = ["EnvConfig", "EnvState", "MjxPixelEnv", "RenderInput", "ENV_NAMES", "env_names", "make"]
