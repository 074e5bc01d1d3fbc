"""`bulbjax reproduce`: the paper's experiment plan as data (`plan`), its cost (`estimate`), one
process per GPU taking jobs from a queue (`queue`, `jobs`) and the results page (`results`).
`reproduce(...)` is the command as a function."""

from bulbjax.reproduce.main import reproduce

__all__ = ["reproduce"]
