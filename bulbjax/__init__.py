"""bulbjax: the bulb evaluation suite for unsupervised representation learning, on MJX.

`bulbjax.make` and `bulbjax.env_names` load the environments (MuJoCo, MJX, MuJoCo Warp) when first
used, not at `import bulbjax`: the learners, probes and reports (`bulbjax.learners`,
`bulbjax.eval`, ...) import without the physics packages, e.g. to time a learner's update on a
machine that has JAX but not MuJoCo."""

from __future__ import annotations

from typing import Any

__all__ = ["make", "env_names"]
__version__ = "0.1.0"


def __getattr__(name: str) -> Any:
    """`make` and `env_names` from `bulbjax.envs`, and any subpackage (`bulbjax.envs`, ...),
    imported on first use (PEP 562), as an eager `import bulbjax` made them available."""
    import importlib
    import importlib.util

    if name in __all__:
        value = getattr(importlib.import_module("bulbjax.envs"), name)
    elif importlib.util.find_spec(f"{__name__}.{name}") is not None:
        value = importlib.import_module(f"{__name__}.{name}")
    else:
        raise AttributeError(f"module 'bulbjax' has no attribute {name!r}")
    globals()[name] = value
    return value
