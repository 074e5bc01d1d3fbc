"""Environments: batched MJX physics with Warp-rendered frames and the true low-dim state.

The core: `base` (`MjxPixelEnv`, the batched env every domain subclasses), `env_config`, `batch`,
`resets`, `camera`, `colours`, `render`, `warp_graphs`, `warp_steps` (an env step's substeps as one
MJX-Warp call), `models` (the MJCF files' folder). On it,
the single-body domains (`pendulum`, `locomotion`) and the multi-object scenes (`objects/`: Incline, Rearrange); on top,
`registry` (`bulbjax.make`), the one module here that imports the domains."""

from bulbjax.envs.base import EnvState, MjxPixelEnv, RenderInput
from bulbjax.envs.env_config import EnvConfig
from bulbjax.envs.registry import ENV_NAMES, env_names, make

__all__ = ["EnvConfig", "EnvState", "MjxPixelEnv", "RenderInput", "ENV_NAMES", "env_names", "make"]
