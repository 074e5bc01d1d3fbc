"""The multi-object scenes, mirroring bulb's `BlockOnInclineEnv` and `RearrangeEnv` (facts:
`../shared/reference/bulb-multiobject.md`), each a domain of objects (geoms or YCB meshes,
`bulbjax.assets`) composed with `dm_control.mjcf`, with physical parameters and object versions
drawn per world at reset (`state.params`) and the reset pool on by default:
- Incline (`GeomOnIncline`, `YcbOnIncline` and their sizes): the env classes in `incline`, bulb's
  numbers and the scene in `incline_scene`;
- Rearrange (`ReacherRearrange*`, `FrankaRearrange*`): what is mirrored and the classes by name
  in `rearrange`, the domain in `rearrange_base`, bulb's numbers and the scene parts in
  `rearrange_scene`, the two robots in `reacher_rearrange` and `franka_rearrange`.

What they may import: the core of `bulbjax.envs` (`base`, `batch`, `camera`, `env_config`,
`render`, ...) and the layers below (`bulbjax.eval`, `bulbjax.assets`); never the single-body
domains (`pendulum`, `locomotion`) nor the registry, the one module of `bulbjax.envs` that
imports them (tests/test_imports.py)."""
