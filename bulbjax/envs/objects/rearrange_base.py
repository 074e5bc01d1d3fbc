"""The Rearrange domain on MJX: the scene (floor, tray, robot, objects, target discs), per-world
versions, bulb's torque control and joint limits, the reset (placement, settle, random torques), the
state, reward and termination. What is mirrored from bulb and what differs: `rearrange`.
Robots: `reacher_rearrange`, `franka_rearrange`."""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from bulbjax.envs.base import EnvState, MjxPixelEnv
from bulbjax.envs.models import quiet_solver_limits
from bulbjax.envs.batch import finite_rows, where_tree
from bulbjax.envs.env_config import EnvConfig, scene_versions
from bulbjax.envs.objects.incline import _quat_mat
from bulbjax.envs.render import SCENERY_GROUP
from bulbjax.eval.spec import StateEntry

os.environ.setdefault("MUJOCO_GL", "disable")  # dm_control needs no GL context to build models
from dm_control import mjcf  # noqa: E402
from bulbjax.envs.objects.rearrange_scene import (  # noqa: F401
    SHAPE_MESH,
    BULLET_DT,
    BULLET_SUBSTEPS,
    CYLINDER_DEFAULT_DIMS,
    EE_ABOVE_OBJECTS,
    EE_XY_MAX,
    EPISODE_STEPS,
    FRICTION,
    GEOM_COLOURS,
    GEOM_INFO,
    INIT_XY,
    INIT_Z_MAX,
    NAN_RETRIES,
    NUM_LISTS,
    NUM_VERSIONS,
    OBJECT_CONAFFINITY,
    OBJECT_LISTS,
    OBJ_XYZ_MAX,
    OBJ_XYZ_MIN,
    PARK_HEIGHT,
    PROP_MAX,
    PROP_MIN,
    PROP_NAMES,
    RANDOM_TORQUE_STEPS,
    SETTLE_MAX_SPEED,
    SETTLE_MAX_SPIN,
    SETTLE_STEPS,
    TABLE_RGB,
    TARGETS,
    TARGET_HALF_HEIGHT,
    TARGET_RADIUS,
    TARGET_RGBA,
    TRAY_SCALE,
    YCB_DYNAMICS,
    _normalise,
    _slots,
    geom_model,
    is_box_or_can,
    object_half_height,
    rearrange_raw_state_spec,
    rearrange_state_spec)


class Rearrange(MjxPixelEnv):
    """bulb's RearrangeEnv on MJX; subclasses pick the robot (`_robot_model`, joints, torques,
    end effector, camera) and the object variant."""

    num_versions = NUM_VERSIONS

    variant: str = "Geom"
    # robot: joints in state order (controlled ones first), their torque limits, the end-effector
    # body, the floor colour
    joint_names: tuple[str, ...] = ()
    controlled: int = 0
    max_torque: tuple[float, ...] = ()
    ee_body: str = ""
    robot_pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # joints bulb reports in the state that do not move here (the Franka's fingers): their angles
    fixed_joint_qpos: tuple[float, ...] = ()
    floor_rgba: tuple[float, float, float, float] = (0, 0, 0, 1)
    floor_conaffinity: int = 1
    episode_length = EPISODE_STEPS
    solved_return = None  # bulb defines none for Rearrange
    discrete = False
    frame_skip = BULLET_SUBSTEPS
    kinematics_after_step = True
    always_recolour = True  # tray and geom colours follow each world's version
    naconmax_per_world = 48
    njmax = 256
    pointcloud_box = 0.5  # bulb's PTCLOUD_BOX_SIZE for Rearrange
    pointcloud_exclude = ("floor", "tray_bottom", "border0", "border1", "border2", "border3")
    supports_multicolour = False
    supports_targets = True
    # the settle simulates 30 steps: `step` resets only the ended worlds, an eighth of the batch
    # per chunk (twice the ~6% whose episode ends per step under random actions)
    reset_chunk_fraction = 1 / 8
    # ... or rather, by default, take pre-settled states from a pool of 2 x num_envs (refilled in
    # one batch when fewer than the ended worlds remain, every ~32 steps): `resets.reset_from_pool`
    reset_pool_multiple = 2

    @classmethod
    def check_sources(cls, ycb_dir: str | None = None) -> None:
        """The YCB variants read their meshes from `ycb_dir` / `$BULBJAX_YCB_DIR`: that folder
        must exist (`YcbModelsNotFound`, a one-line ValueError, names what to set)."""
        super().check_sources(ycb_dir)
        if any(name not in GEOM_INFO for objects in OBJECT_LISTS[cls.variant] for name in objects):
            from bulbjax.assets.ycb import ycb_dir as find_ycb_dir

            find_ycb_dir(ycb_dir)

    def __init__(self, config: EnvConfig):
        self.versions, self.random_version = scene_versions(self.name, config.version, NUM_VERSIONS,
                                                            note=" (6-11: black background)")
        self.lists = OBJECT_LISTS[self.variant]
        self.num_objects = len(self.lists[0])
        self.slot_names, version_slots = _slots(self.lists, self.versions)
        super().__init__(config)
        m = self.mj_model
        self._slot_bodies = np.array([m.body(f"o{k}/object").id for k in range(len(self.slot_names))])
        frames = m.body_parentid[self._slot_bodies]
        self._slot_qadr = jnp.asarray(m.jnt_qposadr[m.body_jntadr[frames]])
        self._slot_vadr = jnp.asarray(m.jnt_dofadr[m.body_jntadr[frames]])
        jids = [m.joint(self._robot_prefix + j).id for j in self.joint_names]
        self._robot_qadr = jnp.asarray(m.jnt_qposadr[jids])
        self._robot_vadr = jnp.asarray(m.jnt_dofadr[jids])
        self._ee = m.body(self._robot_prefix + self.ee_body).id
        self._version_slots = jnp.asarray(version_slots)
        self._max_torque = jnp.asarray(self.max_torque, jnp.float32)
        self._tables()
        park = np.zeros(m.nq)
        park[:] = m.qpos0
        for k in range(len(self.slot_names)):
            a = int(self._slot_qadr[k])
            park[a:a + 7] = [2.0 + 1.0 * k, 3.0, PARK_HEIGHT, 1, 0, 0, 0]
        self._qpos_park = jnp.asarray(park, jnp.float32)

    # ----- what subclasses provide -----
    _robot_prefix = "robot/"

    def _robot_model(self) -> mjcf.RootElement:
        raise NotImplementedError

    def _draw_robot_qpos(self, key: jax.Array) -> jax.Array:
        raise NotImplementedError

    def _obey_limits(self, data: mjx.Data) -> mjx.Data:
        """bulb's joint-limit handling after a step (one world)."""
        return data

    # ----- static tables -----
    def _tables(self) -> None:
        """Per-version (all 12) object properties, targets and tallest object height."""
        props = np.zeros((NUM_VERSIONS, self.num_objects, len(PROP_NAMES)))
        targets = np.zeros((NUM_VERSIONS, self.num_objects, 2))
        max_z = np.zeros(NUM_VERSIONS)
        for v in range(NUM_VERSIONS):
            for i, name in enumerate(self.lists[v % NUM_LISTS]):
                if name in GEOM_INFO:
                    g = GEOM_INFO[name]
                    row = [*GEOM_COLOURS[v % NUM_LISTS][i], *g.dims, g.shape, g.mass, *g.dynamics]
                else:
                    from bulbjax.assets import YCB_INFO
                    row = [1, 1, 1, *CYLINDER_DEFAULT_DIMS, SHAPE_MESH, YCB_INFO[name].mass, *YCB_DYNAMICS]
                props[v, i] = _normalise(np.asarray(row, float), PROP_MIN, PROP_MAX)
                targets[v, i] = TARGETS[0 if is_box_or_can(name) else 1]
                max_z[v] = max(max_z[v], 2 * object_half_height(name))
        self._props = jnp.asarray(props, jnp.float32)
        self._targets = jnp.asarray(targets, jnp.float32)
        self._max_object_z = jnp.asarray(max_z, jnp.float32)

    # ----- model -----
    def _build_spec(self) -> mujoco.MjSpec:
        root = mjcf.RootElement(model=self.name)
        root.compiler.angle = "radian"
        root.option.timestep = BULLET_DT / BULLET_SUBSTEPS
        root.option.gravity = [0, 0, -9.81]
        root.option.solver = "Newton"
        root.option.iterations = 10
        root.option.ls_iterations = 10
        root.option.integrator = "Euler"
        root.visual.headlight.ambient = [0.45, 0.45, 0.45]
        root.visual.headlight.diffuse = [0.5, 0.5, 0.5]
        root.worldbody.add("light", name="key", directional=True, pos=[0, 0, 3], dir=[0.2, 0.3, -1],
                           diffuse=[0.4, 0.4, 0.4])
        self._add_floor(root)
        self._add_tray(root)
        robot = self._robot_model()
        robot.model = self._robot_prefix.rstrip("/")
        root.worldbody.attach(robot).pos = self.robot_pos
        for k, name in enumerate(self.slot_names):
            model = self._object_model(name)
            model.model = f"o{k}"
            for geom in model.find_all("geom"):
                if geom.contype is None or geom.contype:
                    geom.conaffinity, geom.friction = OBJECT_CONAFFINITY, FRICTION
            frame = root.worldbody.attach(model)
            frame.add("freejoint")
            if self.random_version:
                model.find("body", "object").gravcomp = 1e-6  # compiled in, set per world to park
            frame.pos = [2.0 + 1.0 * k, 3.0, PARK_HEIGHT]
        if self.config.show_targets:
            self._add_targets(root)
        return mujoco.MjSpec.from_string(root.to_xml_string(), assets=root.get_assets())

    def _add_targets(self, root: mjcf.RootElement) -> None:
        """bulb's two target areas as flat discs on the tray floor, drawn only: no contacts, no
        mass, in a static body added last so that every other body's and geom's id is unchanged
        (physics is the same with and without them). In the scenery group: point clouds leave
        them out, as they leave out the tray."""
        body = root.worldbody.add("body", name="targets")
        top = 0.0005 + 2 * TARGET_HALF_HEIGHT  # on the tray bottom's top face (z 0.0005)
        for i, ((x, y), rgba) in enumerate(zip(TARGETS, TARGET_RGBA)):
            body.add("geom", name=f"target{i}", type="cylinder", size=[TARGET_RADIUS, TARGET_HALF_HEIGHT],
                     pos=[x, y, top - TARGET_HALF_HEIGHT], rgba=rgba, contype=0, conaffinity=0, mass=0,
                     group=SCENERY_GROUP)

    def _add_floor(self, root: mjcf.RootElement) -> None:
        root.worldbody.add("geom", name="floor", type="plane", size=[5, 5, 0.1], rgba=self.floor_rgba,
                           friction=FRICTION, contype=1, conaffinity=self.floor_conaffinity)

    def _add_tray(self, root: mjcf.RootElement) -> None:
        """bulb's borders.urdf at scale 0.8: the borders collide, the bottom is drawn only."""
        s = TRAY_SCALE
        tray = root.worldbody.add("body", name="tray")
        rgb = (*TABLE_RGB[0], 1)
        # a thin visual slab whose top sits just above the floor (objects rest on the floor)
        tray.add("geom", name="tray_bottom", type="box", size=[0.5 * s, 0.5 * s, 0.002], pos=[0, 0, -0.0015],
                 rgba=rgb, contype=0, conaffinity=0)
        long, thick, height = 1.05 * s / 2, 0.05 * s / 2, 0.10 * s / 2
        for i, (pos, size) in enumerate((((0.5 * s, 0, height), (thick, long, height)),
                                         ((-0.5 * s, 0, height), (thick, long, height)),
                                         ((0, 0.5 * s, height), (long, thick, height)),
                                         ((0, -0.5 * s, height), (long, thick, height)))):
            tray.add("geom", name=f"border{i}", type="box", size=size, pos=pos, rgba=rgb,
                     friction=FRICTION, contype=1, conaffinity=1)

    def _object_model(self, name: str) -> mjcf.RootElement:
        if name in GEOM_INFO:
            return geom_model(name)
        from bulbjax.assets import load_ycb_object, ycb_mjcf

        asset = load_ycb_object(name, scale=1.0, ycb_dir=self.config.ycb_dir)
        return ycb_mjcf(asset, "object", origin="com")

    def _post_put(self, mx: mjx.Model) -> mjx.Model:
        return quiet_solver_limits(mx)

    def _scheme_colours(self) -> tuple[np.ndarray, np.ndarray]:
        """Colour scheme = version: the tray's colour, and each geom object's colour where the
        version uses its slot."""
        tray = [self._geom_id(g) for g in ("tray_bottom", "border0", "border1", "border2", "border3")]
        objs = []
        if self.variant in ("Geom", "OneGeom"):
            objs = [self._geom_id(f"o{k}/visual") for k in range(len(self.slot_names))]
        rgb = np.full((NUM_VERSIONS, len(tray) + len(objs), 3), 0.5)
        _, table = _slots(self.lists, self.versions)
        for v in range(NUM_VERSIONS):
            rgb[v, :len(tray)] = TABLE_RGB[v] if v < NUM_LISTS else 0.0
            if objs and v in self.versions:
                for i, slot in enumerate(table[v]):
                    rgb[v, len(tray) + slot] = GEOM_COLOURS[v % NUM_LISTS][i]
        return np.array(tray + objs, np.int32), rgb.astype(np.float32)

    # ----- state -----
    @property
    def raw_state_spec(self) -> tuple[StateEntry, ...]:
        return rearrange_raw_state_spec(len(self.joint_names), self.num_objects)

    def _objects(self, data: mjx.Data, version: jax.Array) -> dict[str, jax.Array]:
        """One world's objects (the version's, in its list order): qpos `[M, 7]`, qvel `[M, 6]`."""
        slots = self._version_slots[version]
        q = data.qpos[self._slot_qadr[slots][:, None] + jnp.arange(7)]
        v = data.qvel[self._slot_vadr[slots][:, None] + jnp.arange(6)]
        return {"pos": q[:, :3], "quat": q[:, 3:], "vel": v}

    def _lowdim_batch(self, data: mjx.Data, params: dict[str, jax.Array]) -> jax.Array:
        lo, hi = jnp.asarray(OBJ_XYZ_MIN, jnp.float32), jnp.asarray(OBJ_XYZ_MAX, jnp.float32)

        def one(d, version):
            qpos = d.qpos[self._robot_qadr]
            qpos = jnp.concatenate([qpos, jnp.asarray(self.fixed_joint_qpos, qpos.dtype)])
            sincos = jnp.stack([jnp.sin(qpos), jnp.cos(qpos)], axis=1).reshape(-1)
            ob = self._objects(d, version)
            pos = _normalise(jnp.clip(ob["pos"], lo, hi), lo, hi)
            rot = jax.vmap(_quat_mat)(ob["quat"] / jnp.linalg.norm(ob["quat"], axis=1, keepdims=True))
            return jnp.concatenate([sincos, self._props[version].reshape(-1), pos.reshape(-1), rot.reshape(-1)])
        return jax.vmap(one)(data, params["version"]).astype(jnp.float32)

    def raw_state(self, data: mjx.Data, params: dict[str, jax.Array] | None = None) -> jax.Array:
        if params is None:
            raise ValueError(f"{self.name}.raw_state needs the worlds' params (state.params)")

        def one(d, version):
            ob = self._objects(d, version)
            per_obj = jnp.concatenate([ob["pos"], ob["quat"], ob["vel"]], axis=1).reshape(-1)
            return jnp.concatenate([d.qpos[self._robot_qadr], d.qvel[self._robot_vadr], per_obj,
                                    d.xipos[self._ee]])
        return jax.vmap(one)(data, params["version"]).astype(jnp.float32)

    def _reward_terminated_batch(self, data, lowdim, action, prev_data, params):
        lo, hi = jnp.asarray(OBJ_XYZ_MIN, jnp.float32), jnp.asarray(OBJ_XYZ_MAX, jnp.float32)

        def one(d, version):
            pos = self._objects(d, version)["pos"]
            dist = jnp.minimum(jnp.linalg.norm(pos[:, :2] - self._targets[version], axis=1), 1.0)
            finite = jnp.isfinite(d.qpos).all()
            reward = jnp.where(finite, (1.0 - dist.mean()) / EPISODE_STEPS, 0.0)
            ee = d.xipos[self._ee]
            outside = ((pos < lo) | (pos > hi)).any()
            too_high = ee[2] > EE_ABOVE_OBJECTS + self._max_object_z[version]
            away = (jnp.abs(ee[:2]) > EE_XY_MAX).any()
            return reward, outside | too_high | away | ~finite
        return jax.vmap(one)(data, params["version"])

    # ----- dynamics -----
    def _world_model(self, params: dict[str, jax.Array]) -> mjx.Model:
        if not params or not self.random_version:
            return self.mx
        n = params["version"].shape[0]
        slots = self._version_slots[params["version"]]  # [N, M]
        active = (jnp.arange(len(self.slot_names))[None, :, None] == slots[:, None, :]).any(-1)
        gravcomp = jnp.broadcast_to(self.mx.body_gravcomp, (n, *self.mx.body_gravcomp.shape))
        gravcomp = gravcomp.at[:, self._slot_bodies].set(1.0 - active.astype(jnp.float32))
        return self.mx.tree_replace({"body_gravcomp": gravcomp})

    def _torque(self, data: mjx.Data, action: jax.Array) -> jax.Array:
        """Joint torques of one world's controlled joints from an action in [-1, 1]."""
        return jnp.clip(action, -1.0, 1.0) * self._max_torque

    def _apply_action(self, data: mjx.Data, action: jax.Array) -> mjx.Data:
        return data.replace(ctrl=self._torque(data, action))

    def physics(self, data: mjx.Data, action: jax.Array, params: dict[str, jax.Array] | None = None) -> mjx.Data:
        """One env step: one of bulb's stepSimulation calls (2 MuJoCo steps, the torque held),
        bulb's joint-limit handling, then kinematics."""
        mx = self._world_model(params or {})

        def substep(d: mjx.Data, _):
            d = jax.vmap(self._apply_action)(d, action)
            return jax.vmap(mjx.step, in_axes=(None, 0))(mx, d), None

        data = jax.lax.scan(substep, data, None, length=self.frame_skip)[0]
        data = jax.vmap(self._obey_limits)(data)
        return jax.vmap(mjx.kinematics, in_axes=(None, 0))(mx, data)

    # ----- reset -----
    RESET_FIELDS = ("version", "robot_qpos", "obj_pos", "obj_quat", "torques")
    _fixed: dict[str, jax.Array] = {}

    def reset_with(self, key: jax.Array, **fixed: jax.Array) -> EnvState:
        """`reset(key)` with some per-world draws fixed (arrays with a leading `num_envs` axis,
        or broadcastable): `version` (with `version="random"`), `robot_qpos [N, J]`, `obj_pos
        [N, M, 3]` and `obj_quat [N, M, 4]` (MuJoCo's w, x, y, z; before the settle), `torques
        [N, 10, A]` (the actions of the random-torque steps). Later automatic resets draw as usual."""
        unknown = set(fixed) - set(self.RESET_FIELDS)
        if unknown:
            raise ValueError(f"unknown reset fields {sorted(unknown)}; known: {self.RESET_FIELDS}")
        if "version" in fixed and not self.random_version:
            raise ValueError(f"{self.name} was made with version={self.versions[0]}; make it with "
                             f"version='random' to set versions per world")
        shapes = {"version": (), "robot_qpos": (len(self.joint_names),), "obj_pos": (self.num_objects, 3),
                  "obj_quat": (self.num_objects, 4), "torques": (RANDOM_TORQUE_STEPS, self.controlled)}
        fixed = {k: jnp.broadcast_to(jnp.asarray(v), (self.num_envs, *shapes[k])) for k, v in fixed.items()}
        saved, self._fixed = self._fixed, fixed
        try:
            return self.reset(key)
        finally:
            self._fixed = saved

    def _draws(self, key: jax.Array) -> dict[str, jax.Array]:
        """One world's reset draws (bulb's distributions) and its advanced key."""
        key, k = jax.random.split(key)
        kv, kr, kp, kq, kt = jax.random.split(k, 5)
        version = (jax.random.randint(kv, (), 0, NUM_VERSIONS) if self.random_version
                   else jnp.asarray(self.versions[0]))
        z_min = 0.03 if "Ycb" in self.variant else 0.04
        lo = jnp.array([-INIT_XY, -INIT_XY, z_min])
        hi = jnp.array([INIT_XY, INIT_XY, INIT_Z_MAX])
        pos = jax.random.uniform(kp, (self.num_objects, 3), minval=lo, maxval=hi)
        xyzw = jax.random.uniform(kq, (self.num_objects, 4))
        xyzw = xyzw / jnp.linalg.norm(xyzw, axis=1, keepdims=True)
        torques = jax.random.uniform(kt, (RANDOM_TORQUE_STEPS, self.controlled), minval=-0.5, maxval=0.5)
        return {"version": version.astype(jnp.int32), "robot_qpos": self._draw_robot_qpos(kr), "obj_pos": pos,
                "obj_quat": xyzw[:, jnp.array([3, 0, 1, 2])], "torques": torques, "key": key}

    def _draws_fixed(self, keys: jax.Array) -> dict[str, jax.Array]:
        draws = jax.vmap(self._draws)(keys)
        return {**draws, **{k: v.astype(draws[k].dtype) for k, v in self._fixed.items()}}

    def _place(self, draws: dict[str, jax.Array]) -> mjx.Data:
        """One world before the settle: the robot at its drawn pose, the version's objects at
        their drawn poses, the other objects parked."""
        qpos = self._qpos_park.at[self._robot_qadr].set(draws["robot_qpos"])
        slots = self._version_slots[draws["version"]]
        idx = self._slot_qadr[slots][:, None] + jnp.arange(7)
        qpos = qpos.at[idx].set(jnp.concatenate([draws["obj_pos"], draws["obj_quat"]], axis=1))
        return self._data0.replace(qpos=qpos, qvel=jnp.zeros(self.mj_model.nv))

    def _settle(self, data: mjx.Data, draws: dict[str, jax.Array]) -> mjx.Data:
        """bulb's 20 free steps, then 10 steps of the drawn random torques (one scan)."""
        params = {"version": draws["version"]}
        mx = self._world_model(params)
        data = jax.vmap(mjx.forward, in_axes=(None, 0))(mx, data)  # bias forces for the first torques
        zero = jnp.zeros((SETTLE_STEPS, draws["torques"].shape[0], self.controlled))  # the batch's worlds
        actions = jnp.concatenate([zero, jnp.swapaxes(draws["torques"], 0, 1)])  # [30, N, A]
        return jax.lax.scan(lambda d, a: (self._cap_speeds(self.physics(d, a, params)), None), data, actions)[0]

    def _cap_speeds(self, data: mjx.Data) -> mjx.Data:
        """Objects' speeds capped during the settle: MuJoCo's soft contacts push objects that
        start deep in each other (or in the arm) apart faster than Bullet's capped penetration
        recovery does, and a light sphere could fly off the table."""
        idx = self._slot_vadr[:, None] + jnp.arange(6)  # [S, 6]

        def cap(v):  # [..., S, 6]
            lin, ang = v[..., :3], v[..., 3:]
            scale = lambda x, m: x * jnp.minimum(1.0, m / jnp.maximum(jnp.linalg.norm(x, axis=-1, keepdims=True), 1e-9))
            return jnp.concatenate([scale(lin, SETTLE_MAX_SPEED), scale(ang, SETTLE_MAX_SPIN)], axis=-1)
        qvel = data.qvel.at[:, idx].set(cap(data.qvel[:, idx]))
        return data.replace(qvel=qvel)

    def _reset_batch(self, keys: jax.Array, done: jax.Array, forward: bool = True):
        """bulb's reset of the worlds in `done`: draws, placement, settle; a world whose settle
        went non-finite (objects started deep in each other) is drawn again (at most
        `NAN_RETRIES` times). One settle in the graph (a while loop), none run when no world
        is done."""
        draws = self._draws_fixed(keys)
        data = jax.vmap(self._place)(draws)

        def attempt(carry):
            i, draws, data, todo = carry
            settled = self._settle(jax.vmap(self._place)(draws), draws)
            data = where_tree(todo, settled, data)
            bad = todo & ~jnp.isfinite(data.qpos).all(axis=1)
            draws = where_tree(bad, self._draws_fixed(draws["key"]), draws)
            return i + 1, draws, data, bad

        def more(carry):
            i, _, _, todo = carry
            return (i <= NAN_RETRIES) & todo.any()

        _, draws, data, _ = jax.lax.while_loop(more, attempt, (jnp.int32(0), draws, data, done))
        # Still non-finite after the redraws: the world starts from its placement before the
        # settle (finite by construction; a step that goes NaN from it is reset and counted).
        data = where_tree(done & ~finite_rows(data), jax.vmap(self._place)(draws), data)
        params = {"version": draws["version"]}
        if forward:
            data = jax.vmap(mjx.forward, in_axes=(None, 0))(self._world_model(params), data)
        return data, draws["version"], params, draws["key"]


def _variant_class(base: type, robot: str, variant: str, doc: str) -> type:
    name = f"{robot}Rearrange{variant}"
    n_obj = len(OBJECT_LISTS[variant][0])
    cls = type(name, (base,), {
        "name": name, "variant": variant, "__doc__": doc,
        "state_spec": rearrange_state_spec(len(base.joint_names) + len(base.fixed_joint_qpos), n_obj)})
    cls.__module__ = base.__module__
    return cls


_VARIANT_DOCS = {
    "Geom": "four geometric objects (cylinder, cube, two spheres) in each version's colours",
    "OneGeom": "one geometric object per version",
    "Ycb": "four YCB objects per version (meshes from `ycb_dir` / $BULBJAX_YCB_DIR)",
    "OneYcb": "one YCB object per version (meshes from `ycb_dir` / $BULBJAX_YCB_DIR)",
}
