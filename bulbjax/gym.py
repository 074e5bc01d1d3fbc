"""`bulbjax.gym`: gymnasium adapters (`make_vec`, `make_env`, ...); see `bulbjax.interop.gym`."""

from bulbjax.interop.gym import (AUTORESET_MODES, OBS_KINDS, AdapterConfig, BulbjaxVectorEnv, GymEnv,
                                 make_env, make_vec, register_envs)

__all__ = ["AUTORESET_MODES", "OBS_KINDS", "AdapterConfig", "BulbjaxVectorEnv", "GymEnv", "make_env",
           "make_vec", "register_envs"]
