"""`bulbjax envs` and `bulbjax render`: the commands that look at the environments alone (no
run, no learner): every registered domain with its actions and state, and a strip of frames of
one after random steps. Their parsers are `bulbjax.cli`'s; heavy imports stay inside the
commands, so that `bulbjax --help` imports none of them."""

from __future__ import annotations

import argparse
import os


def spec_summary(spec, full_below: int = 12) -> str:
    """A state spec as `name[unit]/group` entries, or, for long specs (the multi-object
    domains' 100+ entries), as a count per group with the first and last entry of each."""
    if len(spec) <= full_below:
        return ", ".join(f"{e.name}[{e.unit}]/{e.group}" for e in spec)
    groups: dict[str, list] = {}
    for e in spec:
        groups.setdefault(e.group, []).append(e)
    parts = []
    for g, es in groups.items():
        span = es[0].name if len(es) == 1 else f"{es[0].name} .. {es[-1].name}"
        parts.append(f"{g} {len(es)} ({span})")
    return f"{len(spec)} entries: " + "; ".join(parts)


def cmd_envs(args: argparse.Namespace) -> int:
    from bulbjax.envs.registry import _REGISTRY, MULTICOLOUR_SUFFIX

    for name, cls in _REGISTRY.items():
        act = f"discrete({cls.num_actions})" if cls.discrete else f"box({cls.action_size})"
        versions = cls.num_versions
        if cls.supports_multicolour:
            variant = f"(+{MULTICOLOUR_SUFFIX})"
        else:
            variant = f"(versions 0-{versions - 1}, random)" if versions else "(one scene)"
        solved = "-" if cls.solved_return is None else f"{cls.solved_return:g}"
        print(f"{name:<24} {variant} action {act}, episode {cls.episode_length}, "
              f"solved {solved}; state: {spec_summary(cls.state_spec)}")
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    import jax
    import numpy as np

    import bulbjax
    from bulbjax.run import parse_version

    for flag, value, least in (("--frames", args.frames, 1), ("--steps", args.steps, 0),
                               ("--seed", args.seed, 0)):
        if value < least:
            raise ValueError(f"{flag} must be >= {least}, got {value}")
    version = parse_version(args.version)
    env = bulbjax.make(args.env, num_envs=args.frames, resolution=args.resolution, version=version,
                       show_targets=args.show_targets)
    state = jax.jit(env.reset)(jax.random.PRNGKey(args.seed))
    step = jax.jit(env.step)
    key = jax.random.PRNGKey(args.seed + 1)
    for _ in range(args.steps):
        key, k = jax.random.split(key)
        if env.discrete:
            a = jax.random.randint(k, (env.num_envs,), 0, env.num_actions)
        else:
            a = jax.random.uniform(k, (env.num_envs, env.action_size), minval=-1, maxval=1)
        state = step(state, a)
    strip = np.concatenate(list(np.asarray(state.pixels)), axis=1)
    save_png(args.out, strip)
    print(f"saved {env.num_envs} frames of {args.env} after {args.steps} random steps to "
          f"{args.out}")
    return 0


def save_png(path: str, image) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    plt.imsave(path, image)
