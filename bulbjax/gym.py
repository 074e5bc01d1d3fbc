"""`bulbjax.gym`: gymnasium adapters (`make_vec`, `make_env`, ...); see `bulbjax.interop.gym`.

Importing it (or `bulbjax.interop.gym`) registers every domain as `bulbjax/<Name>-v0`, so that
`gymnasium.make("bulbjax/CartPole-v0", obs="pixels")` and `gymnasium.make_vec(...)` work (and the
env carries its spec, which gymnasium's `check_env` looks for)."""

from bulbjax.interop.gym import (AUTORESET_MODES, OBS_KINDS, AdapterConfig, BulbjaxVectorEnv, GymEnv,
                                 InvalidAction, make_env, make_vec, register_envs)

__all__ = ["AUTORESET_MODES", "OBS_KINDS", "AdapterConfig", "BulbjaxVectorEnv", "GymEnv", "InvalidAction",
           "make_env", "make_vec", "register_envs"]
