"""Where the domains' MJCF files are and a setting of their device models shared by the domains.

`asset_dir`: the folder of MJCF files that goes with the bulbjax code imported (inside an
installed wheel, or the checkout's top-level `mjcf_assets/`), or `$BULBJAX_MJCF_DIR`.
`quiet_solver_limits`: the device model without MuJoCo Warp's per-world prints of capped solver
iterations (locomotion and the multi-object scenes cap them on purpose)."""

from __future__ import annotations

import os
from importlib import resources

from mujoco import mjx

ASSET_DIR_ENV = "BULBJAX_MJCF_DIR"


MJCF_FOLDER = "mjcf_assets"  # top level in a checkout; `bulbjax/mjcf_assets/` in a wheel (setup.py)


def asset_dir() -> str:
    """Folder of the MJCF files: `$BULBJAX_MJCF_DIR`, else `mjcf_assets` inside the package (an
    installed wheel: setup.py maps the checkout's top-level `mjcf_assets/` to the package
    `bulbjax.mjcf_assets`, pyproject.toml's package-data ships its files), else `mjcf_assets/`
    beside the package (a checkout, imported from `sys.path` or installed editable): the files
    that go with the bulbjax code imported. The package is found through `importlib.resources`;
    MuJoCo reads files by path, so a package imported from a zip archive needs `$BULBJAX_MJCF_DIR`."""
    given = os.environ.get(ASSET_DIR_ENV)
    if given:
        return given
    package = resources.files("bulbjax")
    if not isinstance(package, os.PathLike):
        raise ValueError(f"bulbjax's MJCF files are inside an archive ({package}), which MuJoCo "
                         f"cannot read: install bulbjax unzipped, or set {ASSET_DIR_ENV} to a folder "
                         "holding them")
    for folder in (os.path.join(package, MJCF_FOLDER), os.path.join(os.path.dirname(package), MJCF_FOLDER)):
        if os.path.isdir(folder):
            return folder
    raise FileNotFoundError(f"bulbjax's MJCF files are neither in {package} nor beside it ({MJCF_FOLDER}/): "
                            f"reinstall bulbjax, or set {ASSET_DIR_ENV} to a folder holding them")


def quiet_solver_limits(mx: mjx.Model) -> mjx.Model:
    """Turn off Warp's in-kernel prints for solver / line-search iteration limits (a capped
    iteration count is the intended setting here, and on a GPU every world that hits the cap
    would print each substep); warnings of real overflows (constraints, contacts) stay on."""
    from mujoco_warp import OverflowType  # the Warp backend is what `impl="warp"` runs

    impl = mx.opt._impl
    mask = impl.warn_overflow & ~int(OverflowType.ITERATIONS | OverflowType.LS_ITERATIONS)
    return mx.replace(opt=mx.opt.replace(_impl=impl.replace(warn_overflow=mask)))
