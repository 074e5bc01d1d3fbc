"""Adapters from bulbjax's batched environments to other RL ecosystems.

- `bulbjax.interop.gym` (also `bulbjax.gym`): gymnasium `VectorEnv` / `Env` (needs the `gym` extra).
- `bulbjax.interop.brax`: Brax / MuJoCo Playground `reset(rng)` / `step(state, action)` over a
  `State` pytree, for Brax's training code (Brax optional: its `State` class is used if installed).

Submodules are imported on use, so `import bulbjax` never needs gymnasium or brax.
"""
