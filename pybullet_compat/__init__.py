"""The original PyBullet domains of bulb (pybullet_envs 3.2.7) beside bulbjax's MJX mirrors.

`BulletPixelEnv` (one env: frame + true state, full-state get/set), `SerialVecEnv` and
`ProcessVecEnv` (N envs with auto-reset, in-process or one process per env), and the parity
suite (`python -m pybullet_compat.parity`). Needs the `pybullet` extra:
`pip install -e '.[pybullet]'`. Importing this package does not import JAX.
"""

from pybullet_compat.envs import DOMAINS, BulletPixelEnv, DomainSpec, StepResult, domain

__all__ = ["DOMAINS", "BulletPixelEnv", "DomainSpec", "StepResult", "domain"]
