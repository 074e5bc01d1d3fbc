"""Sequence windows for the sequential learners, and a functional replay buffer of windows.

A window is `L` consecutive steps of one world: frames, the action that led into each frame,
true states, and a `valid` mask. Windows never cross an episode boundary: a window is cut where
its episode ends and the remaining steps are padding (the last valid step repeated, action 0,
`valid=False`); learners leave padded steps out of their losses and probes out of their fits.

Step convention (matches the experiment's rollouts, where step `t` stores the state *after*
the `t`-th env step, and the env auto-resets): `done[t] = 1` means step `t` ended an episode,
so frame `t` already shows the next episode's first state. A window starting at `t0` is
therefore valid up to (not including) the first `t > t0` with `done[t] = 1`; `done[t0]` itself
is fine (the window then starts on a fresh episode).

The buffer keeps the frame buffer's semantics (`bulbjax.data.replay`): fixed capacity (in
windows: the frame budget divided by the window length), empty slots filled first, then a
uniformly random subset of the non-retained slots replaced, and `retain_initial` protecting a
share of the initial random-policy windows for the whole run.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from bulbjax.data import replay


@struct.dataclass
class Windows:
    """A batch of windows; leading axes `[..., B, L]` (any extra leading axes, e.g. seeds)."""

    frames: jax.Array  # uint8 [..., B, L, H, W, 3]
    actions: jax.Array  # float32 [..., B, L, A]: action that led into each frame (one-hot if discrete)
    states: jax.Array  # float32 [..., B, L, D]: true low-dimensional state of each frame
    valid: jax.Array  # bool [..., B, L]: False on padding after an episode boundary

    @property
    def length(self) -> int:
        """Steps per window, L."""
        return self.valid.shape[-1]

    def head(self, length: int) -> "Windows":
        """The first `length` steps of every window."""
        if length > self.length:
            raise ValueError(f"windows have {self.length} steps, asked for the first {length}")
        axis = self.valid.ndim - 1  # every field shares the leading [..., B, L] axes
        return jax.tree.map(lambda x: jax.lax.slice_in_dim(x, 0, length, axis=axis), self)


def window_indices(dones: jax.Array, starts: jax.Array, length: int) -> tuple[jax.Array, jax.Array]:
    """Where each window's steps come from: `dones [T, N]`, `starts [N]` -> `(src, valid)`, each
    `[length, N]`. `src[i, n]` is the time index of step `i` of world `n`'s window (the last
    valid step once the episode has ended) and `valid[i, n]` says whether step `i` is still in
    the episode the window started in. Needs `starts + length <= T` (clamped otherwise)."""
    t, n = dones.shape
    if length > t:
        raise ValueError(f"window length {length} exceeds the {t} stored steps")
    starts = jnp.clip(starts, 0, t - length)
    idx = starts[None, :] + jnp.arange(length)[:, None]  # [L, N]
    d = jnp.take_along_axis(dones, idx, axis=0) > 0
    d = d.at[0].set(False)  # a done at the start step only means the window starts an episode
    valid = jnp.cumsum(d, axis=0) == 0
    src = starts[None, :] + jnp.cumsum(valid, axis=0) - 1
    return src.astype(jnp.int32), valid


def gather_steps(x: jax.Array, src: jax.Array) -> jax.Array:
    """`x [T, N, ...]` at `src [L, N]` time indices -> `[L, N, ...]` (each world its own times)."""
    return x[src, jnp.arange(src.shape[1])[None, :]]


def cut_windows(frames: jax.Array, states: jax.Array, actions: jax.Array, dones: jax.Array,
                starts: jax.Array, length: int) -> Windows:
    """Windows `[N, length]` from rendered steps: frames `[T, N, H, W, 3]`, states `[T, N, D]`,
    actions `[T, N, A]` (leading into each frame), dones `[T, N]`, one start per world `[N]`."""
    src, valid = window_indices(dones, starts, length)
    w = Windows(frames=gather_steps(frames, src), states=gather_steps(states, src),
                actions=gather_steps(actions, src) * valid[..., None], valid=valid)
    return jax.tree.map(lambda x: x.swapaxes(0, 1), w)


@struct.dataclass
class WindowBuffer:
    """Replay state of windows; same invariants as `replay.ReplayBuffer` with windows as items."""

    windows: Windows  # leading [C, L]
    retained: jax.Array  # bool [C]
    size: jax.Array  # int32 [], filled slots are the prefix [0, size)
    num_dropped: jax.Array  # int32 [], windows dropped because no slot was replaceable

    @property
    def capacity(self) -> int:
        return self.retained.shape[-1]


def capacity_in_windows(frame_capacity: int, length: int) -> int:
    """Window slots for the same frame budget as a frame buffer (paper: 5,000 frames)."""
    c = frame_capacity // length
    if c < 1:
        raise ValueError(f"a {frame_capacity}-frame budget holds no window of {length} steps")
    return c


def init(capacity: int, length: int, frame_shape: tuple[int, int, int], state_dim: int,
         action_dim: int) -> WindowBuffer:
    """Empty buffer of `capacity` windows of `length` steps."""
    if capacity <= 0 or length <= 0:
        raise ValueError(f"capacity and length must be positive, got {capacity}, {length}")
    c, l = capacity, length
    return WindowBuffer(
        windows=Windows(frames=jnp.zeros((c, l, *frame_shape), jnp.uint8),
                        actions=jnp.zeros((c, l, action_dim), jnp.float32),
                        states=jnp.zeros((c, l, state_dim), jnp.float32),
                        valid=jnp.zeros((c, l), bool)),
        retained=jnp.zeros((c,), bool), size=jnp.zeros((), jnp.int32),
        num_dropped=jnp.zeros((), jnp.int32))


def insert(buf: WindowBuffer, key: jax.Array, windows: Windows) -> WindowBuffer:
    """Write `B` new windows: empty slots first, then a random subset of non-retained slots."""
    b = windows.valid.shape[0]
    if b > buf.capacity:
        raise ValueError(f"insert batch of {b} windows exceeds capacity {buf.capacity}")
    shapes = jax.tree.map(lambda x: x.shape[1:], buf.windows)
    if jax.tree.map(lambda x: x.shape[1:], windows) != shapes:
        raise ValueError(f"window shapes {jax.tree.map(lambda x: x.shape, windows)} do not match "
                         f"the buffer's per-window shapes {shapes}")
    slots, ok = replay._choose_slots(buf, key, b)
    target = jnp.where(ok, slots, buf.capacity)  # out of range -> dropped
    new = jax.tree.map(lambda store, x: store.at[target].set(x.astype(store.dtype), mode="drop"),
                       buf.windows, windows)
    return buf.replace(windows=new, size=jnp.minimum(buf.size + b, buf.capacity).astype(jnp.int32),
                       num_dropped=buf.num_dropped + (b - jnp.sum(ok, dtype=jnp.int32)))


def retain_initial(buf: WindowBuffer, key: jax.Array, fraction: float | jax.Array) -> WindowBuffer:
    """Protect a random `round(fraction * size)` of the filled windows for the rest of the run
    (the replay-of-initial-frames fix, applied to windows); see `replay.retain_initial`."""
    return replay.retain_initial(buf, key, fraction)  # type: ignore[arg-type]  # same fields used


def sample(buf: WindowBuffer, key: jax.Array, batch: int) -> Windows:
    """`batch` windows drawn uniformly with replacement among the filled slots."""
    idx = replay.materialised(jax.random.randint(key, (batch,), 0, jnp.maximum(buf.size, 1)))
    return jax.tree.map(lambda x: x[idx], buf.windows)


# ---------------------------------------------------------------------------- offline datasets
@struct.dataclass
class Trajectories:
    """Rendered rollouts of `N` worlds for `T` steps: an offline dataset (`bulbjax fit`). Same
    step convention as above; windows are cut from it on the fly at random starts."""

    frames: jax.Array  # uint8 [T, N, H, W, 3]
    actions: jax.Array  # float32 [T, N, A]: action that led into each frame (one-hot if discrete)
    states: jax.Array  # float32 [T, N, D]
    dones: jax.Array  # float32 [T, N]: 1 where step t ended an episode

    @property
    def steps(self) -> int:
        return self.dones.shape[0]

    @property
    def worlds(self) -> int:
        return self.dones.shape[1]


def sample_windows(traj: Trajectories, key: jax.Array, batch: int, length: int) -> Windows:
    """`batch` windows `[batch, length]` at uniformly random (world, start) pairs, cut at
    episode boundaries like `cut_windows`."""
    if length > traj.steps:
        raise ValueError(f"window length {length} exceeds the {traj.steps} stored steps")
    k_w, k_t = jax.random.split(key)
    world = jax.random.randint(k_w, (batch,), 0, traj.worlds)
    start = jax.random.randint(k_t, (batch,), 0, traj.steps - length + 1)
    src, valid = window_indices(traj.dones[:, world], start, length)  # [L, B]
    pick = lambda x: x[src, world[None, :]].swapaxes(0, 1)  # noqa: E731  [B, L, ...]
    return Windows(frames=pick(traj.frames), states=pick(traj.states),
                   actions=pick(traj.actions) * valid.T[..., None], valid=valid.T)


def sample_steps(traj: Trajectories, key: jax.Array, batch: int,
                 with_worlds: bool = False) -> tuple[jax.Array, ...]:
    """`batch` (frame, state) pairs drawn uniformly over all steps and worlds; `with_worlds`
    adds each pair's world index (int32), e.g. for the probe's validation split by world."""
    k_t, k_w = jax.random.split(key)
    t = jax.random.randint(k_t, (batch,), 0, traj.steps)
    n = jax.random.randint(k_w, (batch,), 0, traj.worlds)
    if with_worlds:
        return traj.frames[t, n], traj.states[t, n], n.astype(jnp.int32)
    return traj.frames[t, n], traj.states[t, n]


def consecutive_windows(traj: Trajectories, length: int) -> Windows:
    """Every world's steps cut into consecutive windows of `length` (and at episode
    boundaries): `[(T // length) * N, length]`, the held-out layout of the experiment."""
    rounds = traj.steps // length
    if rounds < 1:
        raise ValueError(f"window length {length} exceeds the {traj.steps} stored steps")
    starts = jnp.broadcast_to((jnp.arange(rounds) * length)[:, None], (rounds, traj.worlds))
    w = jax.vmap(lambda s: cut_windows(traj.frames, traj.states, traj.actions, traj.dones, s, length))(starts)
    return jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), w)
