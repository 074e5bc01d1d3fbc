"""Batched MJX environments that report a frame and the true low-dimensional state every step.

Brax / MuJoCo Playground style: pure `reset(key)` and `step(state, action)` over an `EnvState`
pytree, batched over `num_envs` worlds (physics vmapped over worlds, MuJoCo Warp kernels), with
automatic reset when an episode ends. A domain subclasses `MjxPixelEnv` and fills in its model
file, camera, reset distribution, state, reward and termination.
"""

from __future__ import annotations

import os
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
from mujoco import mjx

from bulbjax.envs import warp_graphs, warp_steps
from bulbjax.envs.batch import add_counts, nonfinite, prng_key, where_tree
from bulbjax.envs.camera import PAN_CAMERAS, CameraConfig, add_bulb_camera, pan_cameras, static_view, view_poses
from bulbjax.envs.colours import NUM_SCHEMES, scheme_table
from bulbjax.envs.env_config import EnvConfig, check_config, pose_select
from bulbjax.envs.models import asset_dir
from bulbjax.envs.render import PointCloudRenderer, Renderer, exclude_from_pointcloud
from bulbjax.envs.resets import (chunk_size, make_pool, pool_keys_at_reset, pool_multiple, reset_from_pool,
                                 reset_in_chunks)
from bulbjax.eval.spec import StateEntry


@struct.dataclass
class RenderInput:
    """What is needed to render a stored step later: joint positions, colour scheme and the
    poses of mocap bodies (scenery posed per world, e.g. the incline; `[N, 0, ...]` if none)."""

    qpos: jax.Array  # [N, nq]
    scheme: jax.Array  # [N] int32
    mocap_pos: jax.Array | None = None  # [N, nmocap, 3]
    mocap_quat: jax.Array | None = None  # [N, nmocap, 4]


@struct.dataclass
class EnvState:
    """Batched state of `num_envs` worlds after a reset or a step."""

    data: mjx.Data
    obs: jax.Array  # [N, obs_size] policy input (true state by default)
    lowdim: jax.Array  # [N, D] true low-dimensional state, in the state spec's order
    pixels: jax.Array  # [N, H, W, 3] uint8 (H = W = 0 when rendering is off)
    reward: jax.Array  # [N]
    done: jax.Array  # [N] 1.0 where this step ended an episode (terminated or truncated)
    truncated: jax.Array  # [N] 1.0 where it ended by the time limit only
    step_count: jax.Array  # [N] int32 steps into the current episode
    episode_return: jax.Array  # [N] running return of the current episode
    scheme: jax.Array  # [N] int32 colour scheme of the current episode
    key: jax.Array  # [N, 2] per-world PRNG keys
    info: dict[str, jax.Array]  # episode_return / episode_length of the episode that just ended
    # Per-world physical parameters drawn at each reset (e.g. mass, friction); {} if none.
    params: dict[str, jax.Array] = struct.field(default_factory=dict)
    # Per-world int32 counts since `reset` (`COUNTS`): worlds reset because their physics went
    # non-finite, the non-finite entries seen then, action entries that were NaN or out of range.
    counts: dict[str, jax.Array] = struct.field(default_factory=dict)
    depth: jax.Array | None = None  # [N, H, W] float32 metres (observation "depth"), else None
    points: jax.Array | None = None  # [N, P, 3] float32 world points (observation "pointcloud")
    # Pre-settled initial states for `step`'s resets (`resets.make_pool`: fields `[N, f, ...]`,
    # cursor `[N]`); {} for domains without a pool (EnvConfig.reset_pool).
    pool: dict[str, Any] = struct.field(default_factory=dict)

    @property
    def render_input(self) -> RenderInput:
        return RenderInput(qpos=self.data.qpos, scheme=self.scheme,
                           mocap_pos=self.data.mocap_pos, mocap_quat=self.data.mocap_quat)


# `EnvState.counts`: what `step` repaired, per world, since `reset`.
COUNTS = ("nonfinite_resets", "nonfinite_entries", "actions_fixed")


class MjxPixelEnv:
    """Base class; subclasses set the class attributes and the `_` methods below."""

    name: str = ""
    xml_file: str = ""
    camera: CameraConfig
    state_spec: tuple[StateEntry, ...] = ()
    episode_length: int = 1000
    solved_return: float | None = None  # the return counted as solved; None: the domain has none
    discrete: bool = False
    num_actions: int | None = None
    action_size: int = 1
    colour_roles: dict[str, str] = {}  # geom name -> colour role, for multicolour
    njmax: int = 8
    naconmax_per_world: int = 1
    frame_skip: int = 1  # physics steps (of the model's timestep) per env step, action held
    # `mjx.step` leaves body/geom poses one physics step behind qpos; domains whose state or
    # reward reads poses (not only qpos/qvel) set this to recompute kinematics after stepping.
    kinematics_after_step: bool = False
    # Domains whose action reads what only MJX's full forward pass computes (the Franka's gravity
    # compensation reads qfrc_bias) keep that pass after each step, not the kinematics pass alone.
    forward_after_step: bool = False
    # PPOConfig fields this domain wants changed from PPO's defaults (`registry.ppo_config_for`)
    ppo_overrides: dict[str, Any] = {}
    # Physical-unit version of the state (`state.info["lowdim_raw"]`, `raw_state`); empty means
    # the state is already in physical units and the raw state equals `lowdim`.
    raw_state_spec_: tuple[StateEntry, ...] = ()
    # Point clouds: the cameras (bulb's pan cameras around the domain camera's target), the cube
    # half-size that points are clipped to, and the geoms left out (scenery such as the floor).
    pointcloud_box: float = 1.3
    pointcloud_exclude: tuple[str, ...] = ()
    supports_multicolour: bool = True  # a `<Name>Multicolour` variant exists
    supports_targets: bool = False  # `show_targets` draws something
    num_versions: int = 0  # object versions (multi-object domains); 0: one scene, `version` must stay 0
    # Resets in `step` (`_reset_done`): domains whose reset simulates reset the ended worlds only,
    # this fraction of num_envs per chunk; 0: the full-batch reset (cheap draws: pendulums, locomotion).
    reset_chunk_fraction: float = 0.0
    # ... unless they draw from a pool of pre-settled states (`resets.reset_from_pool`) of this
    # many times num_envs entries (EnvConfig.reset_pool); 0: no pool.
    reset_pool_multiple: int = 0
    # Per-world draws that a domain's `reset_with` fixes (`[num_envs, ...]`, gathered per chunk).
    _fixed: dict[str, jax.Array] = {}

    @classmethod
    def check_sources(cls, ycb_dir: str | None = None) -> None:
        """Raise this domain's one-line error (a ValueError) when something it reads from outside
        bulbjax is missing: the YCB meshes (`ycb_dir`, default `$BULBJAX_YCB_DIR`), pybullet's
        Panda. Why: `bulbjax run` checks this before it makes its run folder, and the constructor
        before it builds anything, so a missing download fails at once and leaves nothing behind.
        Nothing is read from outside by default."""

    def __init__(self, config: EnvConfig):
        check_config(config)
        self.check_sources(config.ycb_dir)
        self.reset_chunk = chunk_size(config.reset_chunk, self.reset_chunk_fraction, config.num_envs)
        self.reset_pool = pool_multiple(config.reset_pool, self.reset_pool_multiple)
        self.pool_size = self.reset_pool * config.num_envs
        self.pool_segments = int(config.pool_segments)  # blocks of worlds with a pool each
        if config.show_targets and not self.supports_targets:
            raise ValueError(f"{self.name} has no targets to draw; show_targets is for the Rearrange domains")
        if not self.num_versions and config.version != 0:
            raise ValueError(f"{self.name} has one scene, no object versions (got version={config.version!r}); "
                             "versions are for the Incline and Rearrange domains")
        self.config = config
        self.num_envs = config.num_envs
        self.resolution = config.resolution
        spec = self._build_spec()
        self._edit_spec(spec)
        add_bulb_camera(spec, self.camera)
        pan = config.observation == "pointcloud"
        if pan:
            exclude_from_pointcloud(spec, self.pointcloud_exclude)
            for i, cam in enumerate(pan_cameras(self.camera)):
                add_bulb_camera(spec, cam, name=f"pan{i}")
        self.mj_model = spec.compile()
        warp_graphs.install()  # keep every CUDA graph an epoch captures (GPU), see warp_graphs
        warp_graphs.wait_at_exit()  # a script ending mid-step exits (Warp's callbacks need the GIL)
        # on this process's first device: MJX's default is the first device of all processes,
        # which under jax.distributed is another process's (arrays this process cannot address)
        device = jax.local_devices()[0]
        self.mx = self._post_put(mjx.put_model(self.mj_model, device=device, impl="warp",
                                               graph_mode=warp_graphs.graph_mode(config.graph_mode, device)))
        # With cameras and lights fixed in the world, `step` recomputes only the kinematics of the
        # worlds it resets (`_poses`): the template Data they start from holds the view's poses.
        static = static_view(self.mj_model)
        self._pose_pass = "kinematics" if static and not self.forward_after_step else "forward"
        self._pose_select = pose_select(config.reset_pose_branch, self._pose_pass, device.platform)  # `_poses`
        view = ({k: jax.device_put(np.asarray(v, np.float32), device) for k, v in view_poses(self.mj_model).items()}
                if static else {})
        self._data0 = mjx.make_data(self.mj_model, device=device, impl="warp", njmax=self.njmax,
                                    naconmax=self.naconmax_per_world * self.num_envs).tree_replace(view)
        if self.reset_pool:  # the pool's refill settles pool_size worlds in one batch
            self._pool_data0 = mjx.make_data(self.mj_model, device=device, impl="warp", njmax=self.njmax,
                                             naconmax=self.naconmax_per_world * self.pool_size).tree_replace(view)
        self.renderer = None
        if config.render:
            self.renderer = Renderer(self.mj_model, self.num_envs, self.resolution,
                                     depth=config.observation == "depth")
        self.point_renderer = PointCloudRenderer(
            self.mj_model, self.num_envs, [f"pan{i}" for i in range(len(PAN_CAMERAS))],
            config.num_points, self.pointcloud_box) if pan else None
        self._renders_steps = config.render and config.render_steps
        self._base_rgba = jnp.asarray(self.mj_model.geom_rgba)
        ids, rgb = self._scheme_colours()
        self._colour_ids, self._scheme_rgb = jnp.asarray(ids, jnp.int32), jnp.asarray(rgb, jnp.float32)
        self._recolour = bool(self._colour_ids.size) and (config.multicolour or self.always_recolour)
        # `physics` in one Warp call where that saves calls and the action holds the controls only
        self._fused_substeps = (config.fuse_substeps and (self.frame_skip > 1 or self.kinematics_after_step)
                                and type(self)._apply_action is MjxPixelEnv._apply_action
                                and warp_steps.available())

    # ----- to be provided by domains -----
    always_recolour: bool = False  # apply `_scheme_colours` even without multicolour

    def _build_spec(self) -> mujoco.MjSpec:
        """The model before edits: `xml_file` from the asset folder (domains may compose one)."""
        return mujoco.MjSpec.from_file(os.path.join(asset_dir(), self.xml_file))

    def _edit_spec(self, spec: mujoco.MjSpec) -> None:
        """Hook to edit the model before compiling (e.g. add a floor)."""

    def _post_put(self, mx: mjx.Model) -> mjx.Model:
        """Hook to adjust the device model (e.g. solver warnings: `models.quiet_solver_limits`)."""
        return mx

    def _scheme_colours(self) -> tuple[np.ndarray, np.ndarray]:
        """Geom ids `[G]` and their RGB under each colour scheme `[S, G, 3]` (multicolour roles)."""
        roles = {self._geom_id(g): r for g, r in self.colour_roles.items()}
        return scheme_table(roles) if roles else (np.zeros(0, np.int32), np.zeros((NUM_SCHEMES, 0, 3)))

    def _reset_qpos_qvel(self, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        raise NotImplementedError

    def _lowdim(self, data: mjx.Data) -> jax.Array:
        raise NotImplementedError

    def _lowdim_raw(self, data: mjx.Data) -> jax.Array:
        """State in physical units (override together with `raw_state_spec_`)."""
        return self._lowdim(data)

    def _ctrl(self, action: jax.Array) -> jax.Array:
        raise NotImplementedError

    def _reward_terminated(self, data: mjx.Data, lowdim: jax.Array, action: jax.Array,
                           prev_data: mjx.Data) -> tuple[jax.Array, jax.Array]:
        """Reward and termination of one world after a step from `prev_data` under `action`
        (the validated env action, before `_ctrl`)."""
        raise NotImplementedError

    def _world_model(self, params: dict[str, jax.Array]) -> mjx.Model:
        """The device model with this batch's per-world parameters (fields with a leading world
        axis, which the Warp kernels index per world); the shared model when there are none."""
        return self.mx

    def _apply_action(self, data: mjx.Data, action: jax.Array) -> mjx.Data:
        """Put the action into one world's Data before each physics substep (default: controls)."""
        return data.replace(ctrl=self._ctrl(action))

    # ----- public API -----
    @property
    def state_dim(self) -> int:
        return len(self.state_spec)

    @property
    def obs_size(self) -> int:
        return self.state_dim

    @property
    def raw_state_spec(self) -> tuple[StateEntry, ...]:
        """Spec of `state.info["lowdim_raw"]` (physical units; the state spec when unscaled)."""
        return self.raw_state_spec_ or self.state_spec

    def raw_state(self, data: mjx.Data, params: dict[str, jax.Array] | None = None) -> jax.Array:
        """`[N, len(raw_state_spec)]` physical-unit state of batched `data` (after kinematics);
        `params` are the worlds' per-episode parameters (`state.params`) where the domain has any."""
        return jax.vmap(self._lowdim_raw)(data).astype(jnp.float32)

    @property
    def frame_shape(self) -> tuple[int, int, int]:
        return (self.resolution, self.resolution, 3)

    def reset(self, key: jax.Array) -> EnvState:
        """Start `num_envs` episodes; `key` is one PRNG key (`jax.random.PRNGKey(seed)`, or a
        typed `jax.random.key(seed)`); anything else is a ValueError that says so."""
        return self.reset_keys(jax.random.split(prng_key(key), self.num_envs))

    def reset_keys(self, keys: jax.Array) -> EnvState:
        """Start `num_envs` episodes from per-world keys `[num_envs, 2]` (`reset(key)` splits
        one key; a caller that shards worlds over devices hands each device its share)."""
        pool = make_pool(self, pool_keys_at_reset(keys, self.reset_pool)) if self.reset_pool else {}
        data, scheme, params, keys = self._reset_batch(keys, jnp.ones(self.num_envs, bool))
        zeros = jnp.zeros(self.num_envs)
        lowdim = self._lowdim_batch(data, params)
        obs, data = self._observe(data, scheme, keys)
        return EnvState(
            data=data, obs=lowdim, lowdim=lowdim, pixels=obs["pixels"],
            reward=zeros, done=zeros, truncated=zeros,
            step_count=jnp.zeros(self.num_envs, jnp.int32), episode_return=zeros, scheme=scheme,
            key=keys, info={"episode_return": zeros, "episode_length": jnp.zeros(self.num_envs, jnp.int32),
                            "lowdim_raw": self.raw_state(data, params)},
            params=params, depth=obs.get("depth"), points=obs.get("points"),
            counts={k: jnp.zeros(self.num_envs, jnp.int32) for k in COUNTS}, pool=pool)

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        """Apply `action` to every world, step physics, reset worlds whose episode ended.

        Bad input and bad physics never reach the returned state. An action of the wrong shape
        or dtype is a ValueError when traced; NaN entries of a continuous action become 0 and
        the others are clipped to the action space [-1, 1] (bulb's wrappers clip to it; a
        discrete action is clipped to [0, num_actions)), each entry changed counted in
        `counts["actions_fixed"]`. A world whose physics goes non-finite (any NaN or inf in
        qpos, qvel, the state or the reward) ends its episode as terminated, with reward 0, and
        is reset like any ended episode (so its frames, state and replay are the new episode's),
        counted in `counts["nonfinite_resets"]` (and its bad entries in `"nonfinite_entries"`).
        For finite, in-range input all of this is the identity: the results are bit for bit
        those without it."""
        action = self._check_action(action)
        action, fixed = self._repair_action(action)
        data = self.physics(state.data, action, state.params)
        lowdim = self._lowdim_batch(data, state.params)
        reward, terminated = self._reward_terminated_batch(data, lowdim, action, state.data, state.params)
        bad_entries = (nonfinite(data.qpos) + nonfinite(data.qvel) + nonfinite(lowdim)
                       + (~jnp.isfinite(reward)).astype(jnp.int32))
        bad = bad_entries > 0
        terminated = terminated | bad
        reward = jnp.where(bad, 0.0, reward)
        step_count = state.step_count + 1
        truncated = (step_count >= self.episode_length) & ~terminated
        done = terminated | truncated
        ep_return = state.episode_return + reward

        split = jax.vmap(jax.random.split)(state.key)
        pool = state.pool
        if pool and not self._fixed:  # the next pool entries; fixed draws take the chunked path
            data, scheme, params, pool = reset_from_pool(self, split[:, 1], done, data, state.scheme,
                                                         state.params, pool)
        else:
            data, scheme, params = self._reset_done(split[:, 1], done, data, state.scheme, state.params)
        data = self._poses(self._world_model(params), data, done)
        obs_lowdim = jnp.where(done[:, None], self._lowdim_batch(data, params), lowdim)
        info = {"episode_return": jnp.where(done, ep_return, 0.0),
                "episode_length": jnp.where(done, step_count, 0),
                "lowdim_raw": self.raw_state(data, params)}
        obs, data = self._observe(data, scheme, split[:, 0])
        return EnvState(
            data=data, obs=obs_lowdim, lowdim=obs_lowdim, pixels=obs["pixels"],
            reward=reward, done=done.astype(jnp.float32), truncated=truncated.astype(jnp.float32),
            step_count=jnp.where(done, 0, step_count), episode_return=jnp.where(done, 0.0, ep_return),
            scheme=scheme, key=split[:, 0], info=info, params=params,
            depth=obs.get("depth"), points=obs.get("points"), pool=pool,
            counts=add_counts(state.counts, nonfinite_resets=bad.astype(jnp.int32),
                               nonfinite_entries=bad_entries, actions_fixed=fixed))

    def physics(self, data: mjx.Data, action: jax.Array, params: dict[str, jax.Array] | None = None) -> mjx.Data:
        """One env step of physics for every world, without rewards, resets or frames: the
        action applied at every one of `frame_skip` substeps, then (where the state reads body
        poses) a kinematics pass. `params` are the worlds' per-episode physical parameters
        (`state.params`). `step` is this plus the episode bookkeeping; the parity mirror calls
        it alone to keep stepping past an episode's end."""
        mx = self._world_model(params or {})
        if self._fused_substeps:  # one MJX-Warp call for the substeps and the kinematics
            step = warp_steps.multi_step(self.frame_skip, self.kinematics_after_step)
            return jax.vmap(step, in_axes=(None, 0))(mx, jax.vmap(self._apply_action)(data, action))

        def substep(d: mjx.Data) -> mjx.Data:
            d = jax.vmap(self._apply_action)(d, action)
            return jax.vmap(mjx.step, in_axes=(None, 0))(mx, d)

        if self.frame_skip == 1:
            data = substep(data)
        else:
            data = jax.lax.scan(lambda d, _: (substep(d), None), data, None, length=self.frame_skip)[0]
        if self.kinematics_after_step:
            data = jax.vmap(mjx.kinematics, in_axes=(None, 0))(mx, data)
        return data

    def render_frames(self, render_input: RenderInput) -> jax.Array:
        """Frames `[num_envs, H, W, 3]` of stored joint positions (e.g. a subset of a rollout)."""
        return self.render_sequence(jax.tree.map(lambda x: x[None], render_input))[0]

    def render_sequence(self, render_inputs: RenderInput) -> jax.Array:
        """Frames `[K, num_envs, H, W, 3]` of `K` stored steps (`render_inputs` with leading K).

        The renders run in a scan that threads the renderer's output Data from one to the next,
        which keeps them in order (see `Renderer.__call__`)."""
        if self.renderer is None:
            raise ValueError(f"{self.name} was made with render=False; make it with render=True to get frames")

        def body(data: mjx.Data, ri: RenderInput):
            data = data.replace(qpos=ri.qpos)
            if ri.mocap_pos is not None:
                data = data.replace(mocap_pos=ri.mocap_pos, mocap_quat=ri.mocap_quat)
            data = jax.vmap(mjx.forward, in_axes=(None, 0))(self.mx, data)
            frames, _, data = self._render(data, ri.scheme)
            return data, frames

        data0 = jax.vmap(lambda q: self._data0.replace(qpos=q))(render_inputs.qpos[0])
        return jax.lax.scan(body, data0, render_inputs)[1]

    # ----- internals -----
    def _poses(self, mx: mjx.Model, data: mjx.Data, done: jax.Array) -> mjx.Data:
        """`data` after `step`'s resets with the poses of its new qpos, where something reads them.

        `mjx.step` computes positions before integrating, so poses lag the new qpos by one step
        (a reset world's are those of the state it replaced); frames and the state of domains with
        `kinematics_after_step` read them. With a `static_view` (cameras and lights fixed in the
        world) the kinematics pass gives them all (`_pose_pass`). Otherwise (a camera that follows
        a body, or `forward_after_step`) it is MJX's full forward pass, the only Warp call that
        also places cameras, at the cost of a physics step. It runs on every world when frames
        are rendered, unless `physics` has just computed the kinematics every other world needs:
        then, as without frames, its result is kept only in steps where some world was reset
        (`EnvConfig.reset_pose_branch`: computed only then, or in every step, so that a GPU's
        host never waits to read whether a world was reset). Neither changes what
        the next step computes: `mjx.step` starts with its own forward pass, and only its
        integration writes the solver's warm start."""
        kinematics = self._pose_pass == "kinematics"
        fn = mjx.kinematics if kinematics else mjx.forward
        poses = lambda d: jax.vmap(fn, in_axes=(None, 0))(mx, d)  # noqa: E731
        rendered = self._renders_steps or self.point_renderer is not None
        if rendered and not (kinematics and self.kinematics_after_step):
            return poses(data)
        if self._pose_select:  # EnvConfig.reset_pose_branch: no predicate read on the host
            some, new = done.any(), poses(data)
            return jax.tree.map(lambda a, b: jnp.where(some, a, b), new, data)
        return jax.lax.cond(done.any(), poses, lambda d: d, data)

    def _reward_terminated_batch(self, data: mjx.Data, lowdim: jax.Array, action: jax.Array,
                                 prev_data: mjx.Data, params: dict[str, jax.Array]) -> tuple[jax.Array, jax.Array]:
        """`_reward_terminated` of every world (domains whose reward needs `params` override this)."""
        return jax.vmap(self._reward_terminated)(data, lowdim, action, prev_data)

    def _lowdim_batch(self, data: mjx.Data, params: dict[str, jax.Array]) -> jax.Array:
        """`[N, D]` state of batched Data (domains whose state holds per-world parameters
        override this)."""
        return jax.vmap(self._lowdim)(data)

    def _reset_batch(self, keys: jax.Array, done: jax.Array, forward: bool = True
                     ) -> tuple[mjx.Data, jax.Array, dict[str, jax.Array], jax.Array]:
        """Fresh episodes for every world (`done` says which will be used: domains whose reset
        simulates, e.g. an initial fall, skip the work when none is): Data, colour scheme,
        per-world parameters and the advanced keys."""
        data, scheme, keys = jax.vmap(self._reset_one, in_axes=(0, None))(keys, forward)
        return data, scheme, {}, keys

    def _reset_done(self, keys: jax.Array, done: jax.Array, data: mjx.Data, scheme: jax.Array,
                    params: dict[str, jax.Array]) -> tuple[mjx.Data, jax.Array, dict[str, jax.Array]]:
        """Data, colour scheme and parameters with the worlds in `done` reset from their `keys`
        (without the forward pass) and the others as given.

        With `reset_chunk` K > 0 only the ended worlds are reset, K at a time
        (`resets.reset_in_chunks`); no work when none is done. K = 0 resets every world and keeps
        the done ones (right for resets without simulation)."""
        if not self.reset_chunk:
            fresh, fresh_scheme, fresh_params, _ = self._reset_batch(keys, done, forward=False)
            return (where_tree(done, fresh, data), jnp.where(done, fresh_scheme, scheme),
                    where_tree(done, fresh_params, params))
        return reset_in_chunks(self, keys, done, data, scheme, params)

    def _reset_one(self, key: jax.Array, forward: bool = True) -> tuple[mjx.Data, jax.Array, jax.Array]:
        key, k_state, k_colour = jax.random.split(key, 3)
        qpos, qvel = self._reset_qpos_qvel(k_state)
        data = self._data0.replace(qpos=qpos, qvel=qvel)
        if forward:
            data = mjx.forward(self.mx, data)
        scheme = (jax.random.randint(k_colour, (), 0, NUM_SCHEMES) if self.config.multicolour
                  else jnp.zeros((), jnp.int32))
        return data, scheme.astype(jnp.int32), key

    def _observe(self, data: mjx.Data, scheme: jax.Array, keys: jax.Array) -> tuple[dict[str, jax.Array], mjx.Data]:
        """What `reset`/`step` report besides the state: frames (and depth) when rendering
        steps, a point cloud in "pointcloud" mode."""
        out: dict[str, jax.Array] = {"pixels": jnp.zeros((self.num_envs, 0, 0, 3), jnp.uint8)}
        if self._renders_steps:
            out["pixels"], depth, data = self._render(data, scheme)
            if depth is not None:
                out["depth"] = depth
        if self.point_renderer is not None:
            out["points"], data = self.point_renderer(self.mx, data, keys)
        return out, data

    def _render(self, data: mjx.Data, scheme: jax.Array) -> tuple[jax.Array, jax.Array | None, mjx.Data]:
        mx = self.mx
        if self._recolour:
            rgba = jnp.broadcast_to(self._base_rgba, (self.num_envs, *self._base_rgba.shape))
            rgba = rgba.at[:, self._colour_ids, :3].set(self._scheme_rgb[scheme])
            mx = mx.tree_replace({"geom_rgba": rgba})
        return self.renderer(mx, data)

    def _check_action(self, action: Any) -> jax.Array:
        action = jnp.asarray(action)
        if self.discrete:
            if action.shape != (self.num_envs,) or not jnp.issubdtype(action.dtype, jnp.integer):
                raise ValueError(f"{self.name} takes integer actions of shape ({self.num_envs},) in "
                                 f"[0, {self.num_actions}); got {action.dtype} {action.shape}")
            return action.astype(jnp.int32)
        if action.shape != (self.num_envs, self.action_size) or not jnp.issubdtype(action.dtype, jnp.floating):
            raise ValueError(f"{self.name} takes float actions of shape ({self.num_envs}, {self.action_size}) "
                             f"in [-1, 1]; got {action.dtype} {action.shape}")
        return action.astype(jnp.float32)

    def _repair_action(self, action: jax.Array) -> tuple[jax.Array, jax.Array]:
        """A checked action made safe: NaN -> 0, then clipped to the action space (continuous
        [-1, 1], discrete [0, num_actions)); and per world the number of entries changed."""
        if self.discrete:
            fixed = (action < 0) | (action >= self.num_actions)
            return jnp.clip(action, 0, self.num_actions - 1), fixed.astype(jnp.int32)
        fixed = ~jnp.isfinite(action) | (action < -1.0) | (action > 1.0)
        action = jnp.clip(jnp.where(jnp.isnan(action), 0.0, action), -1.0, 1.0)
        return action, fixed.sum(axis=1).astype(jnp.int32)

    def _geom_id(self, name: str) -> int:
        gid = mujoco.mj_name2id(self.mj_model, mujoco.mjtObj.mjOBJ_GEOM, name)
        if gid < 0:
            raise ValueError(f"geom {name!r} not in {self.xml_file or self.name}")
        return gid

