"""The environment registry without building a model: every env's state spec is the bulb
original's, `bulbjax envs` lists every env with its versions, and bad names, resolutions,
world counts and versions are refused with a message that says what is accepted."""

from __future__ import annotations

from typing import Any

import pytest

import bulbjax
from bulbjax.envs.registry import _REGISTRY


@pytest.mark.parametrize("name, spec", [
    ("CartPole", [("theta", "rad", "position"), ("theta_vel", "rad/s", "velocity"),
                  ("x", "m", "position"), ("x_vel", "m/s", "velocity")]),
    ("CartPoleContinuous", [("theta", "rad", "position"), ("theta_vel", "rad/s", "velocity"),
                            ("x", "m", "position"), ("x_vel", "m/s", "velocity")]),
    ("InvertedPendulum", [("x", "m", "position"), ("x_vel", "m/s", "velocity"),
                          ("theta_cos", "1", "position"), ("theta_sin", "1", "position"),
                          ("theta_vel", "rad/s", "velocity")]),
])
def test_state_spec_matches_bulb(name: str, spec: list[tuple[str, str, str]]) -> None:
    got = _REGISTRY[name].state_spec  # class attribute: no model build needed
    assert [tuple(e) for e in got] == spec
    assert [(e.name, e.unit, e.group) for e in got] == spec


def test_unknown_env_name_lists_available() -> None:
    with pytest.raises(ValueError) as e:
        bulbjax.make("CartPol", num_envs=2)
    msg = str(e.value)
    assert "CartPol" in msg and "did you mean 'CartPole'?" in msg  # the closest name first
    for name in ("CartPole", "CartPoleContinuous", "InvertedPendulum", "CartPoleMulticolour"):
        assert name in msg
    assert set(bulbjax.env_names()) >= {"CartPole", "CartPoleContinuous", "InvertedPendulum",
                                        "CartPoleMulticolour", "InvertedPendulumMulticolour"}
    with pytest.raises(ValueError, match="unknown environment 'Pendulum3D'; available") as e:
        bulbjax.make("Pendulum3D", num_envs=2)  # nothing close: no guess
    assert "did you mean" not in str(e.value)


@pytest.mark.parametrize("resolution", [0, 3000, 64.5, 7, "64"])
def test_bad_resolution_raises(resolution: Any) -> None:
    with pytest.raises(ValueError, match=r"resolution must be an integer .*\[8, 1024\]"):
        bulbjax.make("CartPole", num_envs=2, resolution=resolution)


@pytest.mark.parametrize("num_envs", [0, -1, 2.0])
def test_bad_num_envs_raises(num_envs: Any) -> None:
    with pytest.raises(ValueError, match="num_envs must be a positive integer"):
        bulbjax.make("CartPole", num_envs=num_envs)


def test_cli_envs_lists_versions_and_summarises_long_specs(capsys) -> None:
    """`bulbjax envs`: every registered env once; the Rearrange families say versions 0-11
    (6-11: black background), Incline 0-5; short specs in full, the multi-object ones as counts
    per group that add up to the spec's length."""
    import re

    from bulbjax.cli import main
    from bulbjax.envs.registry import _REGISTRY

    assert main(["envs"]) == 0
    lines = {l.split()[0]: l for l in capsys.readouterr().out.splitlines() if l.strip()}
    assert set(lines) == set(_REGISTRY)
    assert "versions 0-11" in lines["FrankaRearrangeYcb"] and "versions 0-11" in lines["ReacherRearrangeGeom"]
    assert "versions 0-5" in lines["YcbOnIncline"]
    assert "theta_vel[rad/s]/velocity" in lines["CartPole"]
    spec = _REGISTRY["ReacherRearrangeGeom"].state_spec
    m = re.search(r"state: (\d+) entries: (.*)$", lines["ReacherRearrangeGeom"])
    assert m and int(m.group(1)) == len(spec)
    counts = [int(x) for x in re.findall(r"(?:^|; )\w+ (\d+) \(", m.group(2))]
    assert sum(counts) == len(spec) and len(counts) == len({e.group for e in spec})


def test_version_is_refused_by_single_scene_domains():
    """`version` selects objects in the multi-object domains; a single-scene domain refuses any
    other value than 0 instead of ignoring it (e.g. `bulbjax run --env CartPole --version 3`)."""
    import bulbjax

    with pytest.raises(ValueError, match="no object versions"):
        bulbjax.make("CartPole", num_envs=2, version=3, render=False)
    with pytest.raises(ValueError, match="no object versions"):
        bulbjax.make("InvertedPendulum", num_envs=2, version="random", render=False)
