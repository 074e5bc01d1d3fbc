"""The device layer of an experiment: the `(seeds, worlds)` mesh, the environment built for one
device's worlds, a render context per device, the env calls under `shard_map`, and the
shardings and placements of the run state and its keys.

The physics and the renderer are Warp kernels that XLA cannot partition, so env calls run under
`shard_map`, each device stepping and rendering its own worlds (the env is built for the worlds
of one device, with one render context per device); the rest (PPO, learners, replay, probes) is
left to XLA's partitioner, guided by `Devices.state_shardings`. On one device nothing of this is
used and the code is the unsharded one.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

import bulbjax
from bulbjax.config import ExperimentConfig
from bulbjax.envs.base import EnvState, MjxPixelEnv
from bulbjax.envs.render import warp_devices
from bulbjax.epoch.seeds import SeedGroup
from bulbjax.epoch.state import RunState

SEED_AXIS, WORLD_AXIS = "seeds", "worlds"


def make_mesh(devices: Sequence[jax.Device], seeds: int, worlds: int) -> Mesh:
    """A `(seeds, worlds)` mesh over as many of `devices` as the run can use: the seed axis
    takes the largest divisor of `seeds` that fits, the world axis (each seed's worlds split
    further) the largest divisor of `worlds` that fits in the devices left. Seeds come first
    because a seed's PPO and learner updates are not split, only replicated, over the world
    axis. E.g. 6 seeds on 2 or 6 devices: 2 x 1 or 6 x 1; 12 seeds on 8: 6 x 1 (6 devices
    used); 1 seed of 64 worlds on 4: 1 x 4."""
    devices = list(devices)
    n = len(devices)
    ds = max(d for d in range(1, min(seeds, n) + 1) if seeds % d == 0)
    dw = max(d for d in range(1, min(worlds, n // ds) + 1) if worlds % d == 0)
    return Mesh(np.array(devices[: ds * dw], dtype=object).reshape(ds, dw), (SEED_AXIS, WORLD_AXIS))


class Devices:
    """The mesh of a run's `devices` (default: the first device alone) and the environment of
    its worlds, with the calls that step, reset and render them on every device.

    `devices` are laid out as a `(seeds, worlds)` mesh (`make_mesh`): everything a seed owns is
    sharded over the seed axis, the worlds of the simulators over both axes. With fewer seeds
    than devices the world axis takes the other devices: physics and rendering split, PPO and
    learner updates of a seed replicated on its devices. Worlds are laid out flat, `[S*N, ...]`,
    seed-major (`per_seed`, `flat`); `group`: the run's seeds these are (default all; reset keys
    are theirs of the whole run, `SeedGroup.world_keys`)."""

    def __init__(self, config: ExperimentConfig, devices: Sequence[jax.Device] | None = None,
                 group: SeedGroup | None = None):
        c = config
        self.seeds, self.worlds = c.seeds, c.num_envs
        self.group = group or SeedGroup(c.seeds, c.num_envs)
        self.mesh = make_mesh(devices or jax.devices()[:1], c.seeds, c.num_envs)
        self.sharded = self.mesh.size > 1
        try:
            # a reset pool per seed (its share of worlds on a device): a seed's resets do not
            # depend on the other seeds in the batch, as with each world's own reset keys
            self.env: MjxPixelEnv = bulbjax.make(c.env, num_envs=c.seeds * c.num_envs // self.mesh.size,
                                                 resolution=c.resolution, render=True,
                                                 render_steps=False, multicolour=c.multicolour,
                                                 version=c.version, graph_mode=c.graph_mode,
                                                 pool_segments=c.seeds // self.mesh.shape[SEED_AXIS])
        except ValueError as err:
            if c.env.startswith(("HalfCheetah", "Ant")):
                raise ValueError(f"{err}. HalfCheetah and Ant come with the locomotion environments "
                                 "(issue 3); the fig2-halfcheetah / fig2-ant presets run once they are "
                                 "registered (check with `bulbjax envs`)") from err
            raise
        if self.sharded or warp_devices(self.local_mesh_devices()) != warp_devices():
            self._per_device_renderer()  # (also one GPU that is not JAX's default)
        self._rep = NamedSharding(self.mesh, P())
        # The env's step and reset as jitted functions of their own, called inside the run's
        # programs: JAX traces and lowers a nested jit once per argument shapes and reuses it at
        # every other call site (XLA inlines it again), where the bare functions were traced and
        # lowered at each of an epoch's 6 step and init's 5 reset sites: MJX-Warp's physics,
        # ~45% of tracing init and the epoch (profiled on the CPU, fig2-invpend). Not the render
        # call: `_render_local` swaps the renderer while tracing.
        self._step, self._reset_keys = jax.jit(self.env.step), jax.jit(self.env.reset_keys)
        self._physics_warm = False  # `warm_physics` ran: the kernels are loaded in this process

    # ------------------------------------------------------------------ rendering per device
    def _per_device_renderer(self) -> None:
        """One render context per device of the mesh, for the worlds of one device. On GPUs Warp
        looks the context up by the GPU a kernel runs on. Warp has a single CPU device, so
        XLA's host devices (`--xla_force_host_platform_device_count`) would share one context
        and race on its buffers (seen: frames of one device's worlds in the other's); there
        each mesh device gets its own context, picked by its index (`_render_local`)."""
        from bulbjax.envs.render import Renderer

        r, env = self.env.renderer, self.env
        self._renderers: list[Renderer] = []
        devs = warp_devices(self.local_mesh_devices())
        if devs is not None:
            env.renderer = Renderer(env.mj_model, env.num_envs, env.resolution, depth=r.depth, devices=devs)
        else:
            self._renderers = [Renderer(env.mj_model, env.num_envs, env.resolution, depth=r.depth)
                               for _ in range(self.mesh.size)]

    def local_mesh_devices(self) -> list[jax.Device]:
        """The mesh's devices of this process (all of them in a single-process run)."""
        return [d for d in self.mesh.devices.flat if d.process_index == jax.process_index()]

    def _render_local(self, render_inputs: Any) -> jax.Array:
        """`env.render_sequence` of this device's worlds (inside `shard_map`), with this
        device's own render context where the contexts are not per device already (CPU)."""
        if not self._renderers:
            return self.env.render_sequence(render_inputs)

        def with_renderer(r: Any) -> Callable:
            def f(ri: Any) -> jax.Array:
                old, self.env.renderer = self.env.renderer, r  # swapped while tracing only
                try:
                    return self.env.render_sequence(ri)
                finally:
                    self.env.renderer = old
            return f

        index = jax.lax.axis_index((SEED_AXIS, WORLD_AXIS))
        return jax.lax.switch(index, [with_renderer(r) for r in self._renderers], render_inputs)

    # ------------------------------------------------------------------ shardings and placements
    def state_shardings(self, rs: RunState) -> RunState:
        """Shardings of a RunState: per-seed parts over the seed axis, simulator worlds (and the
        policy's windows of them) over both axes, the reference spread and the epoch counter
        replicated."""
        seed = NamedSharding(self.mesh, P(SEED_AXIS))
        world = NamedSharding(self.mesh, P((SEED_AXIS, WORLD_AXIS)))

        def each(tree: Any, sh: NamedSharding) -> Any:
            return jax.tree.map(lambda _: sh, tree)

        seed_world = NamedSharding(self.mesh, P(SEED_AXIS, WORLD_AXIS))  # [S, N, ...] per world
        return RunState(ppo=each(rs.ppo, seed), learners=each(rs.learners, seed),
                        buffers=each(rs.buffers, seed), windows=each(rs.windows, seed),
                        train_env=each(rs.train_env, world), curr_env=each(rs.curr_env, world),
                        rand_env=each(rs.rand_env, world),
                        policy_history=each(rs.policy_history, seed_world),
                        ref_spread=self._rep, epoch=self._rep, probe_set=each(rs.probe_set, seed),
                        pending={k: each(v, seed if k == "fresh" else self._rep) for k, v in rs.pending.items()})

    @property
    def replicated(self) -> NamedSharding:
        """The sharding of what every device holds whole (keys, flags, metrics)."""
        return self._rep

    def abstract_key(self) -> jax.ShapeDtypeStruct:
        return jax.ShapeDtypeStruct((2,), jnp.uint32, sharding=self._rep)

    def abstract_flag(self) -> jax.ShapeDtypeStruct:
        """The `flag` argument of `epoch_flag` (a boolean scalar, replicated)."""
        return jax.ShapeDtypeStruct((), jnp.bool_, sharding=self._rep)

    def put_flag(self, probe: bool) -> jax.Array:
        return jax.device_put(np.bool_(probe), self._rep)

    def put_key(self, key: jax.Array) -> jax.Array:
        """A host-side PRNG key placed on the mesh (replicated)."""
        return jax.device_put(key, self._rep)

    # ------------------------------------------------------------------ env calls on every device
    def on_worlds(self, f: Callable, in_specs: Any, out_specs: Any) -> Callable:
        """`f` run per device on its own worlds (`shard_map`) when sharded, else `f` itself."""
        if not self.sharded:
            return f
        return jax.shard_map(f, mesh=self.mesh, in_specs=in_specs, out_specs=out_specs, check_vma=False)

    def env_reset(self, key: jax.Array) -> EnvState:
        """`env.reset(key)` of all S*N worlds (`env.reset_keys` of `split(key, S*N)`, the group's
        share of the run's); sharded, each device resets its own worlds from the same per-world
        keys as one device would."""
        keys = self.group.world_keys(key)
        if not self.sharded:
            return self._reset_keys(keys)
        w = P((SEED_AXIS, WORLD_AXIS))
        return self.on_worlds(self._reset_keys, (w,), w)(keys)

    def env_step(self, es: EnvState, action: jax.Array) -> EnvState:
        w = P((SEED_AXIS, WORLD_AXIS))
        return self.on_worlds(self._step, (w, w), w)(es, action)

    def warm_physics(self, key: jax.Array) -> None:
        """Run the env's reset, one step and one frame of every world in a small program of their
        own, and wait for it: MuJoCo Warp builds (or loads from its kernel cache) the kernels of
        the scene at their first launch, so a run that calls this in a background thread while
        XLA compiles init and the epoch finds them built when init runs (issue 56: on a fresh
        machine the build was ~45 s of running init on an H100). Uses the same jitted step and
        reset as the run's programs, traced after them, so their compile-cache keys are not moved."""
        if self._physics_warm:  # a later run of the same experiment in this process (tests)
            return
        w = self.S * self.N
        act = (jnp.zeros((w,), jnp.int32) if self.env.discrete
               else jnp.zeros((w, self.env.action_size), jnp.float32))

        def one_step(k: jax.Array) -> jax.Array:
            es = self.env_step(self.env_reset(k), act)
            return self.render_sequence(jax.tree.map(lambda x: x[None], es.render_input))

        jax.block_until_ready(jax.jit(one_step)(self.put_key(key)))
        self._physics_warm = True

    def render_sequence(self, render_inputs: Any) -> jax.Array:
        """Frames `[K, S*N, H, W, 3]` of stored steps `[K, S*N]`."""
        if not self.sharded:
            return self.env.render_sequence(render_inputs)
        kw = P(None, (SEED_AXIS, WORLD_AXIS))
        return self.on_worlds(self._render_local, (kw,), kw)(render_inputs)

    # ------------------------------------------------------------------ the worlds' layout
    @property
    def S(self) -> int:
        return self.seeds

    @property
    def N(self) -> int:
        return self.worlds

    def per_seed(self, x: jax.Array) -> jax.Array:
        """[S*N, ...] -> [S, N, ...]."""
        return x.reshape((self.S, self.N) + x.shape[1:])

    def flat(self, x: jax.Array) -> jax.Array:
        """[S, N, ...] -> [S*N, ...]."""
        return x.reshape((self.S * self.N,) + x.shape[2:])
