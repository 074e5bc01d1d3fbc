"""GeomOnIncline and YcbOnIncline: one object slides down an incline, pushed along its own axis,
mirroring bulb's `BlockOnInclineEnv` (facts: `../shared/reference/bulb-multiobject.md`).

The scene is composed with `dm_control.mjcf` (`incline_scene`, which also holds bulb's numbers): a
plane, the incline (a mocap box, so that its pitch is per world Data), and the object(s) attached
as sub-models with free joints (`bulbjax.assets`).
What is mirrored:
- episode 50 steps; an env step is 4 of bulb's `stepSimulation` calls (dt 0.01 s, 2 solver
  substeps each), so MuJoCo steps 0.005 s, 8 per env step; the push force is applied at every one.
- action a in [-1, 1] (clipped): a force of 2a N (bulb's action space [-2, 2]) along the
  object's own z axis, at its centre of mass.
- reset: mass U[0.05, 0.5] kg, lateral friction U[0.1, 0.5] (object and incline), pitch
  U[0.25, 0.5] rad, texture id in 0..5, per world; the object placed at (-0.05, 0, 0.7) with
  roll pi/2, pitch and yaw pi/2 + e (one e in +-pi/16, as bulb uses the same draw twice); then
  bulb's initial fall: single `stepSimulation`s until x passes U[0.05, 0.15] (at most 50).
- done when x >= 1, x <= 0 or |y| >= 0.1; reward 1 - |x - 0.5|.
- state (bulb's order, scaled to [0, 1] by bulb's ranges and clipped as bulb clips): texture id,
  version, (friction,) pitch, distance from the start position (0 while x < 0), speed.

Parameters per world: mass (body mass and inertia scaled together, as PyBullet's
`changeDynamics(mass=...)` does), friction and gravity compensation (to park the objects of the
other versions when `version="random"`) are model fields with a leading world axis, which the
Warp kernels index per world; the pitch is the incline's mocap pose in Data.

Known differences from bulb: bulb's `incline.urdf` and the `cylinder`/`cylinder_short` URDFs are
not in the stored repository: the incline is a 2.4 x 0.6 x 0.04 m box (long enough that the slide
range 0 <= x <= 1 lies on it at every pitch) whose top face collides as a plane, `cylinder` has radius 0.06 and half-height 0.06 (the
reference's numbers), `cylinder_short` radius 0.06 and half-height 0.03 (assumed). Bullet
multiplies the friction coefficients of a contact (0.1-0.5 each -> 0.01-0.25) while MuJoCo takes
the larger one, so both geoms get friction^2 here. Contacts are MuJoCo's soft contacts; Bullet's
restitution (0.1 block; 1.0 cylinder_large, times the incline's 0) and rolling friction (0.001)
are left out. The plane's and incline's textures are drawn as their mean colours. bulb loads
its own processed `textured_ok.obj` meshes (not in the stored repository) with the body frame at
the mesh origin; the YCB files' origins lie up to 0.11 m (tomato soup can) from the objects, so
here each YCB object's body frame is its centre of mass (the state's position is the COM).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from bulbjax.envs.base import EnvState, MjxPixelEnv
from bulbjax.envs.models import quiet_solver_limits
from bulbjax.envs.batch import finite_rows, where_tree
from bulbjax.envs.env_config import EnvConfig, scene_versions
from bulbjax.envs.objects.incline_scene import (  # noqa: F401  (the domain's constants, one import away)
    BULLET_DT, BULLET_SUBSTEPS, CAMERA, CLIP_DIST, CLIP_SPEED, EPISODE_STEPS, FALL_STEPS, FRICTION,
    GEOM_COLOURS, GEOM_PLANE_COLOUR, INCLINE_COLOURS, INCLINE_HALF, INCLINE_POS, MASS, MAX_FORCE, MAX_X,
    MAX_Y, MIN_X, NAN_RETRIES, NUM_TEXTURES, NUM_VERSIONS, PARK_HEIGHT, PITCH, SCALES, START_EPS, START_POS,
    START_X, STEPS_PER_ACTION, TARGET_X, YCB_INCLINE_COLOURS, YCB_OBJECTS, YCB_PLANE_COLOURS, build_scene,
    geom_object, incline_state_spec)
from bulbjax.eval.spec import StateEntry

if TYPE_CHECKING:
    from dm_control import mjcf


def _subtree_matrix(parent: np.ndarray) -> np.ndarray:
    """0/1 matrix, (j, i) 1 where body j is body i or below it: masses times it are MuJoCo's
    `body_subtreemass`."""
    inside = np.eye(len(parent))
    for j in range(1, len(parent)):
        i = j
        while i:
            i = parent[i]
            inside[j, i] = 1.0
    return inside


def _rpy_quat(roll: jax.Array, pitch: jax.Array, yaw: jax.Array) -> jax.Array:
    """MuJoCo (w, x, y, z) quaternion of PyBullet's Euler angles (R = Rz(yaw) Ry(pitch) Rx(roll))."""
    cr, sr = jnp.cos(roll / 2), jnp.sin(roll / 2)
    cp, sp = jnp.cos(pitch / 2), jnp.sin(pitch / 2)
    cy, sy = jnp.cos(yaw / 2), jnp.sin(yaw / 2)
    return jnp.stack([cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
                      cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy])


def _quat_mat(q: jax.Array) -> jax.Array:
    w, x, y, z = q[0], q[1], q[2], q[3]
    return jnp.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


class Incline(MjxPixelEnv):
    """bulb's BlockOnInclineEnv on MJX; subclasses pick the object family and scale."""

    num_versions = NUM_VERSIONS

    variant: str = "Geom"
    scale: float = 2.5
    report_friction: bool = False  # bulb's report_fric: friction in the state, before the pitch
    state_spec = incline_state_spec(False)
    camera = CAMERA
    episode_length = EPISODE_STEPS
    solved_return = None  # bulb defines none for the Incline domains
    discrete = False
    action_size = 1
    frame_skip = STEPS_PER_ACTION * BULLET_SUBSTEPS
    kinematics_after_step = True
    always_recolour = True  # plane and incline colours follow each world's texture id
    naconmax_per_world = 16
    njmax = 80
    pointcloud_exclude = ("plane", "incline")
    supports_multicolour = False
    ppo_overrides = {"lr": 3e-4}
    # the fall simulates up to 50 steps: `step` resets only the ended worlds, an eighth of the
    # batch per chunk (twice the ~6% whose episode ends per step under random actions)
    reset_chunk_fraction = 1 / 8
    # ... or rather, by default, take pre-settled states from a pool of 2 x num_envs (refilled in
    # one batch when fewer than the ended worlds remain, every ~32 steps): `resets.reset_from_pool`
    reset_pool_multiple = 2

    def __init__(self, config: EnvConfig):
        self.versions, self.random_version = scene_versions(self.name, config.version, NUM_VERSIONS)
        super().__init__(config)
        m = self.mj_model
        # attaching a sub-model makes a frame body that carries the free joint; the object's
        # body (geoms, inertia) is its child at the identity pose
        self._obj_bodies = np.array([m.body(f"obj{v}/object").id for v in self.versions])
        frames = m.body_parentid[self._obj_bodies]
        self._obj_qadr = jnp.asarray(m.jnt_qposadr[m.body_jntadr[frames]])
        self._obj_vadr = jnp.asarray(m.jnt_dofadr[m.body_jntadr[frames]])
        self._obj_geoms = np.array([g for g in range(m.ngeom) if m.geom_bodyid[g] in set(self._obj_bodies)
                                    and m.geom_contype[g]])
        self._incline_geom = self._geom_id("incline_surface")
        self._mass0 = jnp.asarray(m.body_mass[self._obj_bodies], jnp.float32)
        self._in_subtree = jnp.asarray(_subtree_matrix(m.body_parentid), jnp.float32)
        self._qpos_park = jnp.asarray(np.concatenate([
            [0.5 + 2.0 * i, 0.2, PARK_HEIGHT, 1.0, 0.0, 0.0, 0.0] for i in range(len(self.versions))]), jnp.float32)

    # ----- model -----
    def _build_spec(self) -> mujoco.MjSpec:
        return build_scene(self.name, self.versions, self._object_model)

    def _object_model(self, version: int) -> mjcf.RootElement:
        return geom_object(version, self.scale)

    def _post_put(self, mx: mjx.Model) -> mjx.Model:
        return quiet_solver_limits(mx)

    def _scheme_colours(self) -> tuple[np.ndarray, np.ndarray]:
        plane, incline = (YCB_PLANE_COLOURS, YCB_INCLINE_COLOURS) if self.variant == "Ycb" else (
            (GEOM_PLANE_COLOUR,) * NUM_TEXTURES, INCLINE_COLOURS)
        ids = np.array([self._geom_id("plane"), self._geom_id("incline")], np.int32)
        return ids, np.stack([np.array(plane), np.array(incline)], axis=1).astype(np.float32)

    # ----- state -----
    @property
    def raw_state_spec(self) -> tuple[StateEntry, ...]:
        pos = [StateEntry(f"pos_{a}", "m", "position") for a in "xyz"]
        quat = [StateEntry(f"quat_{a}", "1", "orientation") for a in "wxyz"]
        lin = [StateEntry(f"vel_{a}", "m/s", "velocity") for a in "xyz"]
        ang = [StateEntry(f"angvel_{a}", "rad/s", "angular_velocity") for a in "xyz"]
        static = [StateEntry("texture_id", "1", "static"), StateEntry("version", "1", "static"),
                  StateEntry("mass", "kg", "static"), StateEntry("friction", "1", "static"),
                  StateEntry("theta", "rad", "static"), StateEntry("distance", "m", "position"),
                  StateEntry("speed", "m/s", "velocity")]
        return tuple(pos + quat + lin + ang + static)

    def _slot(self, params: dict[str, jax.Array]) -> jax.Array:
        """Index of the world's object among the model's objects."""
        return params["version"] if self.random_version else jnp.zeros_like(params["version"])

    def _object_qpos(self, data: mjx.Data, slot: jax.Array) -> jax.Array:
        return jax.lax.dynamic_slice(data.qpos, (self._obj_qadr[slot],), (7,))

    def _object_qvel(self, data: mjx.Data, slot: jax.Array) -> jax.Array:
        return jax.lax.dynamic_slice(data.qvel, (self._obj_vadr[slot],), (6,))

    def _physical(self, data: mjx.Data, params: dict[str, jax.Array]) -> dict[str, jax.Array]:
        """One world's object pose and velocities (world frame) and bulb's travelled distance
        and speed."""
        slot = self._slot(params)
        q, v = self._object_qpos(data, slot), self._object_qvel(data, slot)
        pos = q[:3]
        dist = jnp.where(pos[0] < MIN_X, 0.0, jnp.linalg.norm(pos - jnp.asarray(START_POS)))
        return {"pos": pos, "quat": q[3:7], "lin": v[:3], "ang": v[3:6], "dist": dist,
                "speed": jnp.linalg.norm(v[:3])}

    def _lowdim_batch(self, data: mjx.Data, params: dict[str, jax.Array]) -> jax.Array:
        def one(d, p):
            ph = self._physical(d, p)
            raw = [p["texture"].astype(jnp.float32), p["version"].astype(jnp.float32)]
            lo = [0.0, 0.0]
            hi = [float(NUM_TEXTURES), float(NUM_VERSIONS)]
            if self.report_friction:
                raw, lo, hi = raw + [p["friction"]], lo + [FRICTION[0]], hi + [FRICTION[1]]
            raw = jnp.stack(raw + [p["theta"], ph["dist"], ph["speed"]])
            lo = jnp.asarray(lo + [PITCH[0], MIN_X, 0.0])
            hi = jnp.asarray(hi + [PITCH[1], CLIP_DIST, CLIP_SPEED])
            return (jnp.clip(raw, lo, hi) - lo) / (hi - lo)
        return jax.vmap(one)(data, params).astype(jnp.float32)

    def raw_state(self, data: mjx.Data, params: dict[str, jax.Array] | None = None) -> jax.Array:
        if params is None:
            raise ValueError(f"{self.name}.raw_state needs the worlds' params (state.params)")

        def one(d, p):
            ph = self._physical(d, p)
            static = jnp.stack([p["texture"].astype(jnp.float32), p["version"].astype(jnp.float32),
                                p["mass"], p["friction"], p["theta"], ph["dist"], ph["speed"]])
            return jnp.concatenate([ph["pos"], ph["quat"], ph["lin"], ph["ang"], static])
        return jax.vmap(one)(data, params).astype(jnp.float32)

    def _reward_terminated_batch(self, data, lowdim, action, prev_data, params):
        def one(d, p):
            x, y = self._physical(d, p)["pos"][:2]
            finite = jnp.isfinite(d.qpos).all()  # a world gone non-finite ends its episode
            reward = jnp.where(finite, 1.0 - jnp.abs(x - TARGET_X), 0.0)
            return reward, (x >= MAX_X) | (x <= MIN_X) | (jnp.abs(y) >= MAX_Y) | ~finite
        return jax.vmap(one)(data, params)

    # ----- dynamics -----
    def _world_model(self, params: dict[str, jax.Array]) -> mjx.Model:
        if not params:
            return self.mx
        n = params["mass"].shape[0]
        mx = self.mx
        slots = jnp.arange(len(self.versions))
        active = (slots[None, :] == self._slot(params)[:, None]).astype(jnp.float32)  # [N, V]
        ratio = params["mass"][:, None] / self._mass0[None, :]  # [N, V]
        body_mass = jnp.broadcast_to(mx.body_mass, (n, *mx.body_mass.shape)).at[:, self._obj_bodies].set(
            params["mass"][:, None] * jnp.ones_like(ratio))
        body_inertia = jnp.broadcast_to(mx.body_inertia, (n, *mx.body_inertia.shape)).at[:, self._obj_bodies].multiply(
            ratio[..., None])
        gravcomp = jnp.broadcast_to(mx.body_gravcomp, (n, *mx.body_gravcomp.shape)).at[:, self._obj_bodies].set(
            1.0 - active)
        # the subtree masses must follow the masses: MuJoCo divides by them for the subtree COM,
        # and left compiled, the float32 mass matrix about a COM at mass/mass0 times the object's
        # position went NaN (issue 40, docs/soak.md)
        subtreemass = body_mass @ self._in_subtree
        mu = params["friction"] ** 2  # Bullet multiplies the two coefficients; MuJoCo takes the max
        friction = jnp.broadcast_to(mx.geom_friction, (n, *mx.geom_friction.shape))
        friction = friction.at[:, self._obj_geoms, 0].set(mu[:, None]).at[:, self._incline_geom, 0].set(mu)
        return mx.tree_replace({"body_mass": body_mass, "body_inertia": body_inertia,
                                "body_subtreemass": subtreemass, "body_gravcomp": gravcomp,
                                "geom_friction": friction})

    def physics(self, data: mjx.Data, action: jax.Array, params: dict[str, jax.Array] | None = None) -> mjx.Data:
        """One env step: 4 of bulb's stepSimulation calls (8 MuJoCo steps) with the push applied
        at each, then kinematics."""
        if not params:
            raise ValueError(f"{self.name}.physics needs the worlds' params (state.params)")
        force = jnp.clip(action[:, 0], -1.0, 1.0) * MAX_FORCE
        data = self._substeps(data, params, force, self.frame_skip)
        return jax.vmap(mjx.kinematics, in_axes=(None, 0))(self._world_model(params), data)

    def _substeps(self, data: mjx.Data, params: dict[str, jax.Array], force: jax.Array, steps: int) -> mjx.Data:
        """`steps` MuJoCo steps of every world with `force` [N] along the object's own z axis."""
        mx = self._world_model(params)
        slot = self._slot(params)
        bodies = jnp.asarray(self._obj_bodies)

        def set_force(d: mjx.Data, f: jax.Array, s: jax.Array) -> mjx.Data:
            b = bodies[s]
            axis = _quat_mat(self._object_qpos(d, s)[3:7])[:, 2]
            return d.replace(xfrc_applied=jnp.zeros_like(d.xfrc_applied).at[b, :3].set(f * axis))

        def one(d: mjx.Data, _):
            d = jax.vmap(set_force)(d, force, slot)
            return jax.vmap(mjx.step, in_axes=(None, 0))(mx, d), None
        return jax.lax.scan(one, data, None, length=steps)[0]

    # ----- reset -----
    RESET_FIELDS = ("mass", "friction", "theta", "texture", "version", "eps", "start_x")

    def reset_with(self, key: jax.Array, **fixed: jax.Array) -> EnvState:
        """`reset(key)` with some of the per-world draws fixed (arrays `[num_envs]` or scalars):
        `mass`, `friction`, `theta`, `texture`, `version` (with `version="random"`), `eps` (the
        orientation noise) and `start_x` (where the initial fall ends). For controlled
        experiments (tests, parity sweeps); the later automatic resets draw as usual."""
        unknown = set(fixed) - set(self.RESET_FIELDS)
        if unknown:
            raise ValueError(f"unknown reset fields {sorted(unknown)}; known: {self.RESET_FIELDS}")
        if "version" in fixed and not self.random_version:
            raise ValueError(f"{self.name} was made with version={self.versions[0]}; make it with "
                             f"version='random' to set versions per world")
        fixed = {k: jnp.broadcast_to(jnp.asarray(v), (self.num_envs,)) for k, v in fixed.items()}
        saved, self._fixed = self._fixed, fixed
        try:
            return self.reset(key)
        finally:
            self._fixed = saved

    _fixed: dict[str, jax.Array] = {}

    def _reset_batch(self, keys: jax.Array, done: jax.Array, forward: bool = True):
        """bulb's reset for every world: parameters drawn, the object placed above the incline,
        then the initial fall (skipped when no world is done)."""
        draws = self._draws_fixed(keys)
        data, params, start_x = jax.vmap(self._place)(draws)
        data = jax.lax.cond(done.any(), lambda d: self._fall(d, params, start_x, done), lambda d: d, data)
        for _ in range(NAN_RETRIES):
            # Rarely (blocks started in deep contact) MJX-Warp's step returns NaN for a world:
            # such a world is drawn again, as MuJoCo Playground resets non-finite worlds.
            bad = done & ~jnp.isfinite(data.qpos).all(axis=1)
            again = self._draws_fixed(draws["key"])
            draws = where_tree(bad, again, draws)
            placed, params, start_x = jax.vmap(self._place)(draws)
            data = where_tree(bad, placed, data)
            data = jax.lax.cond(bad.any(), lambda d: self._fall(d, params, start_x, bad), lambda d: d, data)
        # Still non-finite after the redraws: the world starts where its object was placed, above
        # the incline before the fall (finite by construction), so no reset hands on NaN.
        placed = jax.vmap(self._place)(draws)[0]
        data = where_tree(done & ~finite_rows(data), placed, data)
        if forward:
            data = jax.vmap(mjx.forward, in_axes=(None, 0))(self._world_model(params), data)
        return data, params["texture"], params, draws["key"]

    def _draws_fixed(self, keys: jax.Array) -> dict[str, jax.Array]:
        """Every world's draws, with those fixed by `reset_with` put in."""
        draws = jax.vmap(self._draws)(keys)
        return {**draws, **{k: v.astype(draws[k].dtype) for k, v in self._fixed.items()}}

    def _draws(self, key: jax.Array) -> dict[str, jax.Array]:
        """One world's random reset draws (bulb's distributions) and its advanced key."""
        key, k = jax.random.split(key)
        km, kf, kt, ktex, kv, ke, ks = jax.random.split(k, 7)
        u = lambda kk, lo_hi: jax.random.uniform(kk, (), minval=lo_hi[0], maxval=lo_hi[1])
        version = (jax.random.randint(kv, (), 0, NUM_VERSIONS) if self.random_version
                   else jnp.asarray(self.versions[0]))
        return {"mass": u(km, MASS), "friction": u(kf, FRICTION), "theta": u(kt, PITCH),
                "texture": jax.random.randint(ktex, (), 0, NUM_TEXTURES).astype(jnp.int32),
                "version": version.astype(jnp.int32), "eps": u(ke, (-START_EPS, START_EPS)),
                "start_x": u(ks, START_X), "key": key}

    def _place(self, draws: dict[str, jax.Array]):
        """One world's Data before the fall: objects parked, the world's object at bulb's start
        pose, the incline at its pitch; the episode's parameters and where the fall ends."""
        params = {k: draws[k] for k in ("mass", "friction", "theta", "texture", "version")}
        half, eps = jnp.pi / 2, draws["eps"]
        pose = jnp.concatenate([jnp.asarray(START_POS), _rpy_quat(half, half + eps, half + eps)])
        qpos = jax.lax.dynamic_update_slice(self._qpos_park, pose, (self._slot(params) * 7,))
        theta = params["theta"]
        data = self._data0.replace(
            qpos=qpos, qvel=jnp.zeros(self.mj_model.nv),
            mocap_pos=jnp.asarray([INCLINE_POS], jnp.float32),
            mocap_quat=jnp.stack([jnp.cos(theta / 2), 0.0, jnp.sin(theta / 2), 0.0])[None])
        return data, params, draws["start_x"]

    def _fall(self, data: mjx.Data, params: dict[str, jax.Array], start_x: jax.Array, done: jax.Array) -> mjx.Data:
        """bulb's initial fall: one stepSimulation at a time, for the worlds in `done`, until
        the object's x passes `start_x` (at most 50)."""
        slot = self._slot(params)
        zero = jnp.zeros(start_x.shape[0])  # the batch's worlds (a reset chunk's in `step`)

        def cond(carry):
            i, _, active = carry
            return (i < FALL_STEPS) & active.any()

        def body(carry):
            i, d, active = carry
            moved = self._substeps(d, params, zero, BULLET_SUBSTEPS)
            d = where_tree(active, moved, d)
            x = jax.vmap(lambda dd, s: self._object_qpos(dd, s)[0])(d, slot)
            return i + 1, d, active & (x <= start_x)

        return jax.lax.while_loop(cond, body, (jnp.int32(0), data, done))[1]


class GeomOnIncline(Incline):
    """GeomOnIncline (scale 2.5): blocks and cylinders in one colour per version."""

    name = "GeomOnIncline"


class GeomOnInclineMd(GeomOnIncline):
    name, scale = "GeomOnInclineMd", SCALES["Md"]


class GeomOnInclineSm(GeomOnIncline):
    name, scale = "GeomOnInclineSm", SCALES["Sm"]


class YcbOnIncline(Incline):
    """YcbOnIncline (scale 2.5): bulb's six YCB objects (sugar box, pudding box, gelatin box,
    tomato soup can, tuna fish can, master chef can) at bulb's scale times 2.5, meshes from
    `ycb_dir` / $BULBJAX_YCB_DIR through `bulbjax.assets` (decimated, textured where a texture
    map exists, convex hull for contacts, inertia from the mesh at bulb's mass)."""

    name = "YcbOnIncline"
    variant = "Ycb"

    @classmethod
    def check_sources(cls, ycb_dir: str | None = None) -> None:
        """The meshes come from `ycb_dir` / `$BULBJAX_YCB_DIR`: that folder must exist
        (`YcbModelsNotFound`, a one-line ValueError, names what to set)."""
        super().check_sources(ycb_dir)
        from bulbjax.assets.ycb import ycb_dir as find_ycb_dir

        find_ycb_dir(ycb_dir)

    def _object_model(self, version: int) -> mjcf.RootElement:
        from bulbjax.assets import load_ycb_object, ycb_mjcf

        asset = load_ycb_object(YCB_OBJECTS[version], scale=self.scale, ycb_dir=self.config.ycb_dir)
        return ycb_mjcf(asset, "object", origin="com")


class YcbOnInclineMd(YcbOnIncline):
    name, scale = "YcbOnInclineMd", SCALES["Md"]


class YcbOnInclineSm(YcbOnIncline):
    name, scale = "YcbOnInclineSm", SCALES["Sm"]
