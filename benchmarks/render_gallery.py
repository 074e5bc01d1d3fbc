"""Frames of every version of the multi-object domains, for the docs: one PNG per domain, a row
per version (Incline 0-5, Rearrange 0-11), a column per step of one episode under zero action
(every `--every` steps).

    python benchmarks/render_gallery.py --envs GeomOnIncline,YcbOnIncline --out docs/images
    python benchmarks/render_gallery.py --envs ReacherRearrangeGeom,FrankaRearrangeYcb --steps 6 --out docs/images
"""

from __future__ import annotations

import argparse
import os

import jax
import jax.numpy as jnp
import numpy as np
from PIL import Image

import bulbjax
from bulbjax.envs.objects.rearrange import Rearrange


def gallery(name: str, steps: int, every: int, scale: int, seed: int) -> np.ndarray:
    cls = bulbjax.envs.registry.env_class(name)
    rearrange, n = issubclass(cls, Rearrange), cls.num_versions
    env = bulbjax.make(name, num_envs=n, version="random")
    versions = jnp.arange(n)
    fixed = {"version": versions} if rearrange else {"version": versions, "texture": versions}
    state = jax.jit(lambda k: env.reset_with(k, **fixed))(jax.random.PRNGKey(seed))
    step = jax.jit(env.step)
    columns = [np.asarray(state.pixels)]
    for t in range(1, steps + 1):
        state = step(state, jnp.zeros((n, env.action_size)))
        if t % every == 0:
            columns.append(np.asarray(state.pixels))
    grid = np.concatenate([np.concatenate(list(col), axis=0) for col in columns], axis=1)
    return np.kron(grid, np.ones((scale, scale, 1), np.uint8))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--envs", default="GeomOnIncline,YcbOnIncline")
    p.add_argument("--out", default="docs/images")
    p.add_argument("--steps", type=int, default=12)
    p.add_argument("--every", type=int, default=3)
    p.add_argument("--scale", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    os.makedirs(args.out, exist_ok=True)
    for name in args.envs.split(","):
        path = os.path.join(args.out, f"{name}.png")
        Image.fromarray(gallery(name, args.steps, args.every, args.scale, args.seed)).save(path)
        print(f"{name}: every version (rows) over {args.steps} steps -> {path}")


if __name__ == "__main__":
    main()
