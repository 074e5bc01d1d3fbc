"""Package discovery, the one part of the build that pyproject.toml cannot say: the MJCF models
live in the top-level `mjcf_assets/` folder of the checkout and ship inside the wheel as the
package `bulbjax.mjcf_assets` (a `package_dir` mapping; `[tool.setuptools.packages.find]` cannot
add a package from outside the tree it searches, and listing every package by hand would drop the
next new one from the wheel). Everything else is in pyproject.toml, its package-data included.
An editable install (`pip install -e .`) maps `bulbjax.mjcf_assets` to the same folder;
tests/test_packaging.py builds the wheel, checks the files are in it, and makes every family
from the installed copy."""

from setuptools import find_namespace_packages, setup

MJCF_PACKAGE, MJCF_FOLDER = "bulbjax.mjcf_assets", "mjcf_assets"

setup(
    packages=find_namespace_packages(include=["bulbjax*", "pybullet_compat*"]) + [MJCF_PACKAGE],
    package_dir={MJCF_PACKAGE: MJCF_FOLDER},
)
