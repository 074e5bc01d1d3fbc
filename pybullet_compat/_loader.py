"""Import pybullet and the original `pybullet_envs` classes, whatever gym is installed.

`pybullet_envs/__init__.py` (pybullet 3.2.7) registers its envs through
`gym.envs.registration.registry.env_specs`, which exists up to gym 0.23 (the version the
`pybullet` extra pins below Python 3.12; gym 0.23 imports distutils, so 3.12 gets gym 0.26). With a newer gym that package import fails, but the env modules
themselves only need `gym.Env`, `gym.spaces` and `gym.utils.seeding`, which every gym has. So
we import the env modules directly (never `gym.make`) and, when the package's `__init__` fails,
load the package without it. `pkg_resources` (for `parse_version` only) is shimmed where a
recent setuptools (Python 3.12 venvs have none) lacks it.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import os
import sys
import types
from typing import Any, Iterator

INSTALL_HINT = "pip install -e '.[pybullet]'  (pybullet==3.2.7; gym 0.23.1, or 0.26.2 on Python >= 3.12)"


def _require(module: str) -> Any:
    try:
        return importlib.import_module(module)
    except ImportError as err:  # pragma: no cover - depends on the install
        raise ImportError(f"pybullet_compat needs {module!r}: {INSTALL_HINT}") from err


def _shim_pkg_resources() -> None:
    """Provide `pkg_resources.parse_version` if setuptools no longer ships pkg_resources."""
    try:
        import pkg_resources  # noqa: F401
        return
    except ImportError:
        pass
    try:
        from packaging.version import parse as parse_version
    except ImportError:  # pragma: no cover
        def parse_version(v: str) -> tuple[int, ...]:
            return tuple(int(p) for p in v.split(".") if p.isdigit())
    shim = types.ModuleType("pkg_resources")
    shim.parse_version = parse_version  # type: ignore[attr-defined]
    sys.modules["pkg_resources"] = shim


def _import_pybullet_envs() -> None:
    """Import the `pybullet_envs` package, bypassing its gym registration if that fails."""
    if "pybullet_envs" in sys.modules:
        return
    try:
        importlib.import_module("pybullet_envs")
        return
    except AttributeError:  # gym >= 0.24: registry has no `env_specs`
        sys.modules.pop("pybullet_envs", None)
    spec = importlib.util.find_spec("pybullet_envs")
    if spec is None or not spec.submodule_search_locations:  # pragma: no cover
        raise ImportError(f"pybullet_envs not found: {INSTALL_HINT}")
    pkg = types.ModuleType("pybullet_envs")
    pkg.__path__ = list(spec.submodule_search_locations)  # type: ignore[attr-defined]
    pkg.__file__ = spec.origin
    sys.modules["pybullet_envs"] = pkg
    # the env modules import their siblings as top-level modules (`from robot_bases import ...`)
    here = pkg.__path__[0]
    if here not in sys.path:
        sys.path.append(here)


_CLASSES = {
    "CartPoleBulletEnv": ("pybullet_envs.bullet.cartpole_bullet", "CartPoleBulletEnv"),
    "InvertedPendulumBulletEnv": ("pybullet_envs.gym_pendulum_envs", "InvertedPendulumBulletEnv"),
    "HalfCheetahBulletEnv": ("pybullet_envs.gym_locomotion_envs", "HalfCheetahBulletEnv"),
    "AntBulletEnv": ("pybullet_envs.gym_locomotion_envs", "AntBulletEnv"),
}


def pybullet() -> Any:
    """The `pybullet` module (clear error if it is not installed)."""
    return _require("pybullet")


def env_class(name: str) -> type:
    """The original pybullet_envs class `name` (e.g. 'CartPoleBulletEnv')."""
    if name not in _CLASSES:
        raise ValueError(f"unknown pybullet_envs class {name!r}; known: {', '.join(_CLASSES)}")
    _require("pybullet")
    _require("gym")
    _shim_pkg_resources()
    _import_pybullet_envs()
    module, attr = _CLASSES[name]
    return getattr(importlib.import_module(module), attr)


@contextlib.contextmanager
def quiet_c_stdout() -> Iterator[None]:
    """Send file descriptor 1 to /dev/null for the block: pybullet's C code prints
    ('argv[0]=', 'current_dir=') on connect, which would clutter tables and test output."""
    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)
