"""Description of one entry of an environment's true low-dimensional state."""

from __future__ import annotations

from typing import NamedTuple


class StateEntry(NamedTuple):
    """One state dimension: ``name`` (unique within an env), ``unit`` (e.g. 'm', 'rad', 'm/s',
    'rad/s', '1' for contacts) and ``group`` used to aggregate errors ('position', 'velocity',
    'contact', ...)."""

    name: str
    unit: str
    group: str
