"""Are frames rendered for a sequence of stored steps (`env.render_sequence`, inside one jitted call
or a scan) the frames rendered one step at a time (`env.render_frames`), and does CartPole's pole
move across the image with its angle? Prints booleans and a correlation (CPU or GPU).

    python benchmarks/diagnostics/check_render_correspondence.py
"""
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

import jax, jax.numpy as jnp, numpy as np, bulbjax
from bulbjax.envs.base import RenderInput
N = 192
env = bulbjax.make("CartPole", num_envs=N, render_steps=False)
theta = jnp.linspace(-0.6, 0.6, N)
qs = [jnp.stack([jnp.zeros(N), theta * s], 1) for s in (1.0, -1.0, 0.5)]
ris = [RenderInput(qpos=q, scheme=jnp.zeros(N, jnp.int32)) for q in qs]
single = [np.asarray(jax.jit(env.render_frames)(r)) for r in ris]
stacked = jax.tree.map(lambda *x: jnp.stack(x), *ris)
mapped = np.asarray(jax.jit(env.render_sequence)(stacked))
for k in range(3):
    print("k", k, "map==single", np.array_equal(mapped[k], single[k]))
# pole pixels: blue-dominant; mean column of blue pixels above centre should grow with theta
f = single[0]
blue = (f[..., 2] > 150) & (f[..., 0] < 100)
cols = [np.nonzero(blue[i, :28])[1].mean() if blue[i, :28].any() else np.nan for i in range(N)]
c = np.corrcoef(np.asarray(theta), np.nan_to_num(cols))[0, 1]
print("corr(theta, pole column)", c, "first/last cols", cols[:3], cols[-3:])
unrolled = np.asarray(jax.jit(lambda r: jnp.stack([env.render_frames(jax.tree.map(lambda x: x[i], r)) for i in range(3)]))(stacked))
for k in range(3):
    print("k", k, "unrolled==single", np.array_equal(unrolled[k], single[k]))
env2 = bulbjax.make("CartPole", num_envs=N)
s0 = jax.jit(env2.reset)(jax.random.PRNGKey(0))
def body(s, k):
    s = env2.step(s, jax.random.randint(k, (N,), 0, 2)); return s, (s.pixels, s.render_input)
_, (pix, ri) = jax.jit(lambda s: jax.lax.scan(body, s, jax.random.split(jax.random.PRNGKey(1), 4)))(s0)
for t in range(4):
    ref = np.asarray(jax.jit(env2.render_frames)(jax.tree.map(lambda x: x[t], ri)))
    print("scan step", t, "pixels==render_frames", np.array_equal(np.asarray(pix[t]), ref))
