"""The package installs like any other (issue 58): a wheel built from the sources carries every
file bulbjax reads at run time (the MJCF models: the checkout's top-level `mjcf_assets/`, shipped
as `bulbjax/mjcf_assets/` by setup.py's package_dir mapping and pyproject.toml's package-data,
issue 66), and installed into an empty folder outside the checkout it makes every environment
family and runs `bulbjax envs` from another working directory, with the checkout's own copy out
of reach; on a machine without the NVIDIA driver, without Warp's line about it. The wheel
carries the licence file and says MIT in its metadata, the current way (issue 65)."""

from __future__ import annotations

import email.parser
import importlib.util
import os
import shutil
import subprocess
import sys
import zipfile

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MJCF = os.path.join(ROOT, "mjcf_assets")  # the design's top-level folder of MJCF models
WHEEL_MJCF = "bulbjax/mjcf_assets"  # where the wheel carries them (setup.py's package_dir)
# what a build reads: the project files, its readme and licence, and the packages it finds
SOURCES = ("pyproject.toml", "setup.py", "README.md", "LICENSE", "bulbjax", "pybullet_compat", "mjcf_assets")


def _pip(*args: str, cwd: str) -> str:
    """Run pip; its stdout and stderr together."""
    r = subprocess.run([sys.executable, "-m", "pip", *args], cwd=cwd, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, f"pip {' '.join(args)}:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return r.stdout + r.stderr


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> tuple[str, str]:
    """The wheel built (no build isolation: the test extra brings `wheel` and setuptools >= 77)
    from a copy of the sources (the checkout stays untouched by build/ and egg-info); returns its
    path and the build's output (`pip wheel -v`: setuptools' warnings included)."""
    pytest.importorskip("wheel", reason="setuptools < 70.1 builds wheels with `wheel` (test extra)")
    pytest.importorskip("setuptools", minversion="77",
                        reason="the SPDX `license` of pyproject.toml needs setuptools >= 77 (test extra)")
    tmp = tmp_path_factory.mktemp("packaging")
    src = tmp / "src"
    src.mkdir()
    for name in SOURCES:
        path = os.path.join(ROOT, name)
        if os.path.isdir(path):
            shutil.copytree(path, src / name,
                            ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
        else:
            shutil.copy(path, src / name)
    log = _pip("wheel", "--no-deps", "--no-build-isolation", "-v", "-w", str(tmp / "wheels"), str(src),
               cwd=str(tmp))
    wheels = os.listdir(tmp / "wheels")
    assert len(wheels) == 1 and wheels[0].endswith(".whl"), wheels
    return str(tmp / "wheels" / wheels[0]), log


@pytest.fixture(scope="module")
def installed(built, tmp_path_factory) -> str:
    """The wheel installed with `pip install --target` into an empty folder; returns that folder."""
    wheel = built[0]
    tmp = tmp_path_factory.mktemp("site")
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
    models = sorted(f for f in os.listdir(MJCF) if f.endswith(".xml"))
    assert models, f"no MJCF files in {MJCF}"
    missing = [m for m in models if f"{WHEEL_MJCF}/{m}" not in names]
    assert not missing, f"the wheel lacks the MJCF files {missing} (setup.py, pyproject.toml's package-data)"
    assert not [n for n in names if n.startswith("mjcf_assets/")], "the MJCF files belong inside bulbjax/"
    site = tmp / "site"
    _pip("install", "--no-deps", "--no-index", "-q", "--target", str(site), wheel, cwd=str(tmp))
    return str(site)


def test_wheel_carries_the_licence(built):
    """LICENSE (MIT) is in the wheel's dist-info and its metadata says MIT as an SPDX expression
    (`License-Expression`), and the build warns of no deprecated licence form (issue 65: none
    was shipped, and `license = { text = "MIT" }` drew setuptools' deprecation warning)."""
    wheel, log = built
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
        licences = [n for n in names if n.endswith(".dist-info/licenses/LICENSE")]
        assert licences, f"no LICENSE in the wheel's dist-info: {sorted(n for n in names if 'dist-info' in n)}"
        assert z.read(licences[0]).decode().startswith("MIT License")
        metadata = z.read(next(n for n in names if n.endswith(".dist-info/METADATA"))).decode()
    headers = email.parser.Parser().parsestr(metadata)
    assert headers["License-Expression"] == "MIT", metadata[:1500]
    assert headers.get_all("License-File") == ["LICENSE"], metadata[:1500]
    assert headers["License"] is None, "the deprecated free-text License field is set"
    warned = [line for line in log.splitlines() if "licen" in line.lower() and "deprecat" in line.lower()]
    assert not warned, "\n".join(warned)


def _python(site: str, cwd: str, *args: str) -> subprocess.CompletedProcess:
    """Python with only the installed copy on PYTHONPATH, in `cwd` (outside the checkout), no
    MJCF folder given."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "BULBJAX_MJCF_DIR")}
    env["PYTHONPATH"] = site
    return subprocess.run([sys.executable, *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=600)


def _model_files() -> dict[str, list[str]]:
    """The MJCF files each registered environment reads from the asset folder (`xml_file`,
    `robot_file`); the domains composed in code read none."""
    from bulbjax.envs.registry import _REGISTRY

    files = {name: [f for f in (getattr(cls, "xml_file", ""), getattr(cls, "robot_file", "")) if f]
             for name, cls in _REGISTRY.items()}
    assert any(files.values()), files
    return files


def test_mjcf_assets_at_the_top_level():
    """The design's layout: the MJCF models in the checkout's top-level `mjcf_assets/` (issue 66),
    every file an environment loads among them, none left in the old `bulbjax/envs/mjcf/`; and
    `asset_dir()` of a bulbjax imported from this checkout reads that folder."""
    from bulbjax.envs import models as base

    assert os.path.isdir(MJCF), MJCF
    need = sorted({f for fs in _model_files().values() for f in fs})
    missing = [f for f in need if not os.path.isfile(os.path.join(MJCF, f))]
    assert not missing, f"{MJCF} lacks {missing}"
    assert not os.path.exists(os.path.join(ROOT, "bulbjax", "envs", "mjcf"))
    if os.path.realpath(base.__file__).startswith(os.path.realpath(ROOT) + os.sep) and not os.environ.get(base.ASSET_DIR_ENV):
        assert os.path.realpath(base.asset_dir()) == os.path.realpath(MJCF), base.asset_dir()


def test_installed_wheel_makes_every_family(installed, tmp_path):
    """From the installed copy alone: `asset_dir()` is its `bulbjax/mjcf_assets/`, every registered
    environment that needs no YCB models is made (each family: pendulums, locomotion, Incline,
    Reacher and Franka Rearrange; the Ycb variants read the same package files plus the YCB data
    set), and CartPole resets."""
    names = [n for n in _model_files() if "Ycb" not in n]
    families = ["CartPole", "InvertedPendulum", "HalfCheetah", "Ant", "GeomOnIncline", "ReacherRearrangeGeom",
                "FrankaRearrangeGeom"]
    if importlib.util.find_spec("pybullet_data") is None:  # the Panda is pybullet_data's (the pybullet extra)
        names = [n for n in names if not n.startswith("Franka")]
        families.remove("FrankaRearrangeGeom")
    code = ("import os, sys, jax, bulbjax\n"
            "from bulbjax.envs.models import asset_dir\n"
            f"site = os.path.realpath({installed!r})\n"
            "here = os.path.realpath(bulbjax.__file__)\n"
            "assert here.startswith(site + os.sep), here\n"
            f"assert os.path.realpath(asset_dir()) == os.path.join(site, {WHEEL_MJCF!r}), asset_dir()\n"
            f"for name in {names!r}:\n"
            "    bulbjax.make(name, num_envs=2, render=False)\n"
            "    print('made', name)\n"
            "env = bulbjax.make('CartPole', num_envs=2, render=False)\n"
            "state = jax.jit(env.reset)(jax.random.PRNGKey(0))\n"
            "print('lowdim', state.lowdim.shape)\n")
    r = _python(installed, str(tmp_path), "-c", code)
    assert r.returncode == 0, r.stderr[-4000:]
    assert "lowdim (2, 4)" in r.stdout
    made = [line.split()[1] for line in r.stdout.splitlines() if line.startswith("made ")]
    assert made == names, r.stdout
    assert set(families) <= set(made), made
    from bulbjax.envs import render

    if not render._cuda_driver_loads():  # a CPU-only machine: Warp's no-driver line is not printed
        assert "NVIDIA CUDA driver" not in r.stderr, r.stderr


def test_installed_cli_lists_the_environments(installed, tmp_path):
    r = _python(installed, str(tmp_path), "-m", "bulbjax", "envs")
    assert r.returncode == 0, r.stderr[-4000:]
    names = [line.split()[0] for line in r.stdout.splitlines() if line.strip()]
    assert "CartPole" in names and "ReacherRearrangeGeom" in names, r.stdout


WITHOUT_PHYSICS = """
import sys

class NoPhysics:  # as on a machine with JAX but without MuJoCo and Warp installed
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("mujoco", "warp", "mujoco_warp"):
            raise ImportError(f"No module named {name!r}")

sys.meta_path.insert(0, NoPhysics())
import jax
import bulbjax
from bulbjax.learners import LearnerConfig, make_learner
from bulbjax.eval import probe
from bulbjax.xla_options import parse_compiler_options

learner = make_learner("vae", latent_dim=4, action_dim=1,
                       config=LearnerConfig(batch_size=4, conv_features=(8, 8, 8, 8), hidden=16))
state = learner.init(jax.random.PRNGKey(0), (64, 64, 3))
assert parse_compiler_options(["xla_cpu_enable_fast_math=false"]) == {"xla_cpu_enable_fast_math": False}
assert "mujoco" not in sys.modules and "warp" not in sys.modules
try:
    bulbjax.make("CartPole")
except ImportError as e:
    print("make:", e)
"""


def test_learners_and_probes_import_without_the_physics_packages() -> None:
    """`import bulbjax` loads no environment: a learner builds and initialises, the probes and the
    XLA options import, where MuJoCo and Warp cannot be imported (the learner benchmarks run so on
    a GPU machine without the physics wheels); `bulbjax.make` then says which package is missing."""
    out = subprocess.run([sys.executable, "-c", WITHOUT_PHYSICS], capture_output=True, text=True, cwd=ROOT,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "make: No module named 'mujoco'" in out.stdout, out.stdout
