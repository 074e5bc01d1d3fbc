"""Evaluation: alignment probes from latents to true low-dimensional state."""

from bulbjax.eval.probe import (
    ProbeConfig,
    ProbeParams,
    constant_baseline,
    fit,
    mae,
    predict,
    spread,
    summarise,
)
from bulbjax.eval.spec import StateEntry

__all__ = [
    "ProbeConfig",
    "ProbeParams",
    "StateEntry",
    "constant_baseline",
    "fit",
    "mae",
    "predict",
    "spread",
    "summarise",
]
