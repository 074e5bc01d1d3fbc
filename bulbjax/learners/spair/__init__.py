"""SPAIR, the structured frame learner (Crawford & Pineau 2019, with a learned background), in two
files: `learner.py` assembles the model (inference over the cell grid, the loss, `init`,
`update`, `encode`, `reconstruct`) and holds `synthetic_scene` (frames of moving boxes, for tests
and figures); `parts.py` holds what it is built from (the original's constants and network
sizes, the glimpse geometry and compositing, the networks, the priors and KLs).

Registered as `spair` and `spair6` by the `bulbjax.learners` face, the one module of
`bulbjax.learners` that imports this folder. What it may import: `bulbjax.learners.base` (the
learner interface and config) and `bulbjax.learners.networks` (the shared network pieces), and
the layers below; never another learner, the registry or the `bulbjax.learners` face
(tests/test_imports.py)."""

from bulbjax.learners.spair.learner import SPAIR, synthetic_scene

__all__ = ["SPAIR", "synthetic_scene"]
