"""Is a Rearrange object's in-plane angle readable from the 64x64 frame at all?

Why: on `fig3-rearrange-geom` (version 6) no learner's probe beat the constant predictor on the
major-axis angle of the block or the cylinder (issue 37; docs/results/fig3_rearrange_geom_fixed_3xh200),
while every learner held the objects' positions. Either the frames hold the angle and the
learners' latents drop it, or 64x64 pixels hardly show it. Here a small CNN is trained from the
frames themselves (reset frames of `--resets` x `--worlds` fresh episodes, split by episode) to the
same targets the probes regress, (cos 2θ, sin 2θ) of each object's major axis
(`bulbjax.envs.rearrange_scene.angle_targets`), and scored with the probes' angle error
(`bulbjax.eval.angles.mean_angle_error`, rad, |θ̂ − θ| modulo π) on held-out frames beside the
constant predictor's (the training median). A CNN far below the constant means the angle is in
the pixels.

    python benchmarks/diagnostics/angle_from_pixels.py              # CPU, a few minutes
    python benchmarks/diagnostics/angle_from_pixels.py --small      # a smoke run
"""

from __future__ import annotations

import argparse
import json
import os
import time


def collect(env_name: str, version: int, worlds: int, resets: int, seed: int):
    """Frames `[B, 64, 64, 3]` uint8 and angle targets `[B, 2M]` of `resets` x `worlds` reset states."""
    import jax
    import numpy as np

    import bulbjax
    from bulbjax.envs import rearrange

    env = bulbjax.make(env_name, num_envs=worlds, version=version, reset_pool=0)
    reset = jax.jit(env.reset)
    to_angles = jax.jit(rearrange.angle_targets(env.state_spec))
    frames, targets = [], []
    for i in range(resets):
        s = reset(jax.random.PRNGKey(seed * 100_003 + i))
        frames.append(np.asarray(s.pixels))
        targets.append(np.asarray(to_angles(s.lowdim)))
    return np.concatenate(frames), np.concatenate(targets), [e.name for e in rearrange.angle_target_spec(env.state_spec)]


def fit_cnn(frames, targets, steps: int, seed: int, batch: int = 64, lr: float = 1e-3):
    """A small CNN (three stride-2 convolutions, one dense layer) trained with Adam on the MSE
    to the targets; returns its predict function."""
    import flax.linen as nn
    import jax
    import jax.numpy as jnp
    import optax

    class CNN(nn.Module):
        @nn.compact
        def __call__(self, x):
            x = x.astype(jnp.float32) / 255.0
            for ch in (32, 64, 64):
                x = nn.relu(nn.Conv(ch, (4, 4), strides=(2, 2))(x))
            x = nn.relu(nn.Dense(256)(x.reshape((x.shape[0], -1))))
            return nn.Dense(targets.shape[-1])(x)

    model, opt = CNN(), optax.adam(lr)
    params = model.init(jax.random.PRNGKey(seed), frames[:1])
    state = opt.init(params)
    x, y = jnp.asarray(frames), jnp.asarray(targets)

    @jax.jit
    def step(params, state, k):
        idx = jax.random.randint(k, (batch,), 0, x.shape[0])
        loss, g = jax.value_and_grad(lambda p: jnp.mean((model.apply(p, x[idx]) - y[idx]) ** 2))(params)
        upd, state = opt.update(g, state, params)
        return optax.apply_updates(params, upd), state, loss

    for k in jax.random.split(jax.random.PRNGKey(seed + 1), steps):
        params, state, _ = step(params, state, k)
    return jax.jit(lambda f: model.apply(params, f))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", default="ReacherRearrangeGeom")
    p.add_argument("--version", type=int, default=6)
    p.add_argument("--worlds", type=int, default=128)
    p.add_argument("--resets", type=int, default=24)
    p.add_argument("--steps", type=int, default=3000, help="CNN training steps (batch 64)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--small", action="store_true", help="smoke-run sizes")
    p.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "..", "results"))
    a = p.parse_args()
    if a.small:
        a.worlds, a.resets, a.steps = 8, 2, 20
    import jax.numpy as jnp
    import numpy as np

    from bulbjax.eval.angles import mean_angle_error

    t0 = time.time()
    frames, targets, names = collect(a.env, a.version, a.worlds, a.resets, a.seed)
    t_collect = time.time() - t0
    n_train = (a.resets * 4 // 5) * a.worlds or a.worlds  # whole resets (episodes) on each side
    tr, te = slice(0, n_train), slice(n_train, None)
    predict = fit_cnn(frames[tr], targets[tr], a.steps, a.seed)
    pred = np.concatenate([np.asarray(predict(frames[i:i + 256])) for i in range(n_train, len(frames), 256)])
    m = targets.shape[-1] // 2
    shape = lambda v: jnp.asarray(v).reshape((-1, m, 2))  # noqa: E731
    const = np.broadcast_to(np.median(targets[tr], axis=0), pred.shape)
    cnn_err = np.asarray(mean_angle_error(shape(pred), shape(targets[te])))
    const_err = np.asarray(mean_angle_error(shape(const), shape(targets[te])))
    objects = [n[: -len("_axis_cos2")] for n in names if n.endswith("_axis_cos2")]
    defined = np.asarray(jnp.linalg.norm(shape(targets[te]), axis=-1) > 0.5).mean(axis=0)
    res = {"env": a.env, "version": a.version, "frames_train": n_train, "frames_test": len(frames) - n_train,
           "cnn_steps": a.steps, "collect_s": round(t_collect, 1), "total_s": round(time.time() - t0, 1),
           "objects": {o: {"cnn_rad": float(cnn_err[i]), "constant_rad": float(const_err[i]),
                           "share_with_axis": float(defined[i])} for i, o in enumerate(objects)}}
    print(json.dumps(res, indent=1))
    if not a.small:
        os.makedirs(a.out, exist_ok=True)
        path = os.path.join(a.out, f"angle_from_pixels_{a.env.lower()}_v{a.version}_cpu_{time.strftime('%Y%m%d_%H%M%S')}.json")
        with open(path, "w") as f:
            json.dump(res, f, indent=1)
        print(path)


if __name__ == "__main__":
    main()
