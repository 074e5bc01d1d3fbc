"""bulb's four multicolour schemes; one is drawn uniformly at every reset."""

from __future__ import annotations

import numpy as np

YELLOW, CYAN, MAGENTA, BLUE = (1, 1, 0), (0, 1, 1), (1, 0, 1), (0, 0, 1)
BLACK, GREEN, RED = (0, 0, 0), (0, 1, 0), (1, 0, 0)

#: role -> colour under each of the 4 schemes (rows: scheme 0..3)
SCHEMES: dict[str, np.ndarray] = {
    "base": np.array([YELLOW, CYAN, MAGENTA, BLUE], np.float32),
    "pole": np.array([BLUE, BLACK, GREEN, RED], np.float32),
    "pole2": np.array([RED, BLUE, YELLOW, BLACK], np.float32),
    "third": np.array([(0.8, 0.8, 0.8), (0.7, 0, 0.7), (0.7, 0, 0), (0, 0.8, 0.8)], np.float32),
}
NUM_SCHEMES = 4


def scheme_table(geom_roles: dict[int, str]) -> tuple[np.ndarray, np.ndarray]:
    """Geom ids and their RGB under every scheme: ids `[G]`, colours `[NUM_SCHEMES, G, 3]`."""
    ids = np.array(sorted(geom_roles), np.int32)
    for g in ids:
        if geom_roles[int(g)] not in SCHEMES:
            raise ValueError(f"unknown colour role {geom_roles[int(g)]!r}; known: {sorted(SCHEMES)}")
    rgb = np.stack([SCHEMES[geom_roles[int(g)]] for g in ids], axis=1)
    return ids, rgb
