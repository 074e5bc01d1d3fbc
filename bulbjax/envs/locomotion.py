"""HalfCheetah and Ant, mirroring pybullet_envs' HalfCheetahBulletEnv-v0 and AntBulletEnv-v0
(pybullet 3.2.7: `robot_locomotors.WalkerBase`, `gym_locomotion_envs.WalkerBaseBulletEnv`).

What is mirrored (the model files say what was read back from PyBullet for the bodies):
- stepping: one env step is PyBullet's `scene.global_step()`, 4 substeps of 0.0165/4 s with the
  torques held. We set the model timestep to 0.004125 s and run 4 `mjx.step` calls per env step
  (`frame_skip = 4`) rather than one 0.0165 s step: same integration step as Bullet, and contacts
  of 80 kg bodies falling at 1-2 m/s stay stable at that step size.
- action: torque = power * power_coef * clip(a, -1, 1) per joint (motor gears in the XML).
- observation = `calc_state()`: z_delta (torso z - initial z), sin/cos of the angle to the target
  (x = 1000 m) relative to the torso yaw, torso velocity rotated by -yaw times 0.3, roll, pitch,
  per joint `2 (q - mid) / (hi - lo)` and `0.1 qdot`, foot contact flags; clipped to [-5, 5].
- reward = alive + progress + electricity + joints-at-limit (+ feet collision, which PyBullet
  leaves at 0: the line is commented out there):
  progress = potential_new - potential_old, potential = -|target - body_xy| / 0.0165, where
  body_xy is the mean over PyBullet's `parts` (every link incl. the massless joint links, plus
  the stadium's floor part at the origin; see `potential_parts`); electricity =
  -2.0 mean|a * 0.1 qdot| - 0.1 mean(a^2) with the unclipped action; joints at limit =
  -0.1 * count(|scaled q| > 0.99).
- alive / termination: HalfCheetah +1 while |pitch| < 1 and none of fshin, fthigh, bshin,
  bthigh touches the floor, else -1, and its episodes never end early (HalfCheetahBulletEnv
  overrides `_isDone` to return False); Ant +1 while torso z > 0.26, else -1 and the episode ends.
  Pitch is PyBullet's Euler pitch, so a cheetah flipped onto its back reads pitch ~0 (roll = yaw
  = pi), as in PyBullet.
- reset: root at its spawn pose at rest, every actuated joint uniform in [-0.1, 0.1] rad (even
  where that is outside its range, e.g. Ant's ankles, as PyBullet does), velocities 0.

Known differences. Joint limits: Bullet's multibody limit constraint corrects small violations
but does not push back a joint that is deep (> ~0.04 rad) outside its range, it only stops it
from going further; the reset noise puts Ant's ankles 0.42-0.62 rad outside their ranges, so
under zero torque PyBullet's Ant lies down on its torso and dies after ~20 steps, while MuJoCo's
limits pull the ankles into range and the Ant stands (torso at ~0.64 m). Likewise HalfCheetah's
ffoot starts ~0.3 rad past its limit. MuJoCo's default soft limits are kept: a velocity-only limit
reproduces the Ant's collapse but lets joints creep through their limits under steady torque
(checked: bthigh past 1.1 rad under full torque), which policies would exploit. Ant's ankle
axes in the file are not unit vectors and Bullet uses them unnormalised in the dynamics, which
doubles the ankles' joint-space inertia; ant.xml adds that inertia as armature (see there).
Contacts are
MuJoCo's soft contacts, not Bullet's. Contact flags are those of the state reached by the step
(PyBullet updates `feet_contact` after `calc_state`, so its observation and HalfCheetah's alive
test read the previous step's flags); we keep flags, frame and state of one instant. A foot counts as
touching when its capsule is within `contact_margin` (1 cm) of the floor plane, computed from
the geom pose (PyBullet reports manifold points up to ~0.9 cm apart as contacts, measured).

Contact and solver settings (see `_edit_spec`): only robot-floor pairs collide (robot geoms
contype 1 / conaffinity 0, floor 1 / 1, as the MJCF files; PyBullet made no self-contacts),
pyramidal cones with condim 3, Newton solver with 4 iterations and 8 line-search iterations
(MuJoCo Playground's locomotion settings; with 8 iterations the torso heights after 100 random
steps agreed to 1 mm, and the Warp solver's cost scales with them; the in-kernel prints for
reaching these caps are turned off), semi-implicit Euler as Bullet. Capacities per world are the
worst case of capsule/sphere-plane pairs (2 contacts per capsule, 1 per sphere), so no contact is
ever dropped: HalfCheetah 8 capsules -> 16 contacts, Ant 12 capsules + 1 sphere -> 25 (32);
`njmax` = 4 rows per pyramidal contact + one per joint limit.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from bulbjax.envs.base import MjxPixelEnv
from bulbjax.envs.models import quiet_solver_limits
from bulbjax.envs.camera import CameraConfig
from bulbjax.envs.env_config import EnvConfig
from bulbjax.eval.spec import StateEntry

SCENE_DT = 0.0165  # PyBullet's scene.dt = timestep 0.0165/4 * frame_skip 4
WALK_TARGET = (1000.0, 0.0)
VEL_SCALE = 0.3  # calc_state's scaling of the torso velocity
JOINT_VEL_SCALE = 0.1  # Joint.current_relative_position's scaling of joint speeds
STATE_CLIP = 5.0
ELECTRICITY_COST = -2.0
STALL_TORQUE_COST = -0.1
JOINTS_AT_LIMIT_COST = -0.1
# bulb's default camera (env_bases: distance 3, yaw 0, pitch -30) on the robot's base, tracking its
# position with a world-fixed orientation (MuJoCo camera mode "track"), as bulb re-aims each frame.
LOCOMOTION_CAMERA = CameraConfig(distance=3.0, yaw=0.0, pitch=-30.0, body="torso", mode="track")


def locomotion_state_spec(num_joints: int, num_feet: int, raw: bool = False) -> tuple[StateEntry, ...]:
    """bulb's state names for a walker; units of the scaled (policy) state, or physical units."""
    vel = "m/s" if raw else "0.3 m/s"
    spec = [StateEntry("z_delta", "m", "position"),
            StateEntry("tgt_theta_sin", "1", "position"),
            StateEntry("tgt_theta_cos", "1", "position"),
            StateEntry("x_vel", vel, "velocity"),
            StateEntry("y_vel", vel, "velocity"),
            StateEntry("z_vel", vel, "velocity"),
            StateEntry("body_roll", "rad", "position"),
            StateEntry("body_pitch", "rad", "position")]
    for i in range(num_joints):
        spec += [StateEntry(f"j{i}_pos", "rad" if raw else "1", "position"),
                 StateEntry(f"j{i}_vel", "rad/s" if raw else "0.1 rad/s", "velocity")]
    spec += [StateEntry(f"ft{k}_contact", "1", "contact") for k in range(num_feet)]
    return tuple(spec)


def quat_to_rpy(q: jax.Array) -> jax.Array:
    """Roll, pitch, yaw of a MuJoCo (w, x, y, z) quaternion as PyBullet's getEulerFromQuaternion
    (R = Rz(yaw) Ry(pitch) Rx(roll); pitch in [-pi/2, pi/2])."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    roll = jnp.arctan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = jnp.arcsin(jnp.clip(2.0 * (w * y - z * x), -1.0, 1.0))
    yaw = jnp.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return jnp.stack([roll, pitch, yaw])


class Walker(MjxPixelEnv):
    """PyBullet's WalkerBase on MJX: subclasses name the model, joints, feet and alive rule."""

    camera = LOCOMOTION_CAMERA
    pointcloud_exclude = ("floor",)
    episode_length = 1000
    discrete = False
    num_actions = None
    frame_skip = 4
    kinematics_after_step = True  # the state reads body and geom poses
    power: float = 1.0
    power_coef: tuple[float, ...] = ()  # per joint; torque = power * power_coef * clip(a, -1, 1)
    joints: tuple[str, ...] = ()  # PyBullet's ordered_joints (also the actuator order)
    feet: tuple[str, ...] = ()  # geom of each foot link in foot_list order
    initial_z: float = 0.0  # torso z at spawn (PyBullet's initial_z)
    # (body, "com" | "origin") for every link PyBullet keeps in `parts`: real links at their
    # centre of mass, massless joint links at their joint (the child body's origin)
    potential_parts: tuple[tuple[str, str], ...] = ()
    floor_parts: int = 1  # the stadium floor is a part too, at the origin
    contact_margin: float = 0.01  # foot-floor distance (m) that counts as contact
    terminates: bool = True  # alive < 0 ends the episode (False: only the -1 is paid)
    solver_iterations: int = 4
    ls_iterations: int = 8
    # PPO settings for locomotion (see `registry.ppo_config_for`), Brax / CleanRL MuJoCo style:
    # 64 worlds x 128 steps per update, 10 epochs of 32 minibatches (256 samples), lr 3e-4,
    # gamma 0.99, GAE 0.95, clip 0.2, no entropy bonus, observation normalisation (PPO default),
    # 256x256 tanh towers, initial policy std 0.6 (exp -0.5): with std 1 half the sampled torques
    # are clipped at the +-1 limits, which wastes the early updates.
    ppo_overrides = dict(lr=3e-4, num_steps=128, update_epochs=10, num_minibatches=32, gamma=0.99,
                         gae_lambda=0.95, clip_eps=0.2, ent_coef=0.0, hidden=(256, 256),
                         init_log_std=-0.5, reward_scale=0.1)

    def __init__(self, config: EnvConfig):
        super().__init__(config)
        m = self.mj_model
        jids = [self._named(mujoco.mjtObj.mjOBJ_JOINT, j) for j in self.joints]
        # the model's motors must be PyBullet's: one per joint in this order, gear = power * coef
        if list(m.actuator_trnid[:, 0]) != jids or not np.allclose(
                m.actuator_gear[:, 0], self.power * np.asarray(self.power_coef)):
            raise ValueError(f"{self.xml_file}: motors must drive {self.joints} in order with gears "
                             f"{self.power} * {self.power_coef}")
        self._qadr = jnp.asarray(m.jnt_qposadr[jids])
        self._dadr = jnp.asarray(m.jnt_dofadr[jids])
        lo, hi = m.jnt_range[jids, 0], m.jnt_range[jids, 1]
        self._jmid = jnp.asarray(0.5 * (lo + hi), jnp.float32)
        self._jhalf = jnp.asarray(0.5 * (hi - lo), jnp.float32)
        self._torso = self._named(mujoco.mjtObj.mjOBJ_BODY, "torso")
        feet = np.array([self._geom_id(g) for g in self.feet])
        if np.any(m.geom_type[feet] != mujoco.mjtGeom.mjGEOM_CAPSULE):
            raise ValueError(f"foot geoms {self.feet} must be capsules")
        self._feet = jnp.asarray(feet)
        self._foot_radius = jnp.asarray(m.geom_size[feet, 0], jnp.float32)
        self._foot_half = jnp.asarray(m.geom_size[feet, 1], jnp.float32)  # capsule half-length
        bodies = [self._named(mujoco.mjtObj.mjOBJ_BODY, b) for b, _ in self.potential_parts]
        use_com = [kind == "com" for _, kind in self.potential_parts]
        self._part_bodies = jnp.asarray(bodies)
        self._part_com = jnp.asarray(use_com)[:, None]
        self._num_parts = len(bodies) + self.floor_parts
        self._qpos0 = jnp.asarray(m.qpos0, jnp.float32)
        self.mx = quiet_solver_limits(self.mx)

    # ----- model edits -----
    def _edit_spec(self, spec: mujoco.MjSpec) -> None:
        # Newton with few iterations, as MuJoCo Playground's locomotion envs: at dt 0.004125 the
        # solution barely changes past 4 iterations, and Warp's solver time scales with them.
        spec.option.solver = mujoco.mjtSolver.mjSOL_NEWTON
        spec.option.iterations = self.solver_iterations
        spec.option.ls_iterations = self.ls_iterations
        spec.option.cone = mujoco.mjtCone.mjCONE_PYRAMIDAL
        spec.option.integrator = mujoco.mjtIntegrator.mjINT_EULER  # semi-implicit, as Bullet

    def _named(self, kind: mujoco.mjtObj, name: str) -> int:
        i = mujoco.mj_name2id(self.mj_model, kind, name)
        if i < 0:
            raise ValueError(f"{kind.name} {name!r} not in {self.xml_file}")
        return i

    # ----- pieces of calc_state -----
    def _torso_velocity(self, data: mjx.Data) -> jax.Array:
        """World-frame linear velocity of the torso's centre of mass."""
        raise NotImplementedError

    def _body_xy(self, data: mjx.Data) -> jax.Array:
        """PyBullet's body_xyz[:2]: mean position of all parts (the floor part counts as 0)."""
        pts = jnp.where(self._part_com, data.xipos[self._part_bodies], data.xpos[self._part_bodies])
        return pts[:, :2].sum(0) / self._num_parts

    def foot_contacts(self, data: mjx.Data) -> jax.Array:
        """1.0 per foot whose capsule is within `contact_margin` of the floor plane z = 0."""
        centre = data.geom_xpos[self._feet]  # [F, 3]
        axis_z = data.geom_xmat[self._feet].reshape(-1, 3, 3)[:, 2, 2]  # z of the capsule axis
        lowest = centre[:, 2] - jnp.abs(axis_z) * self._foot_half - self._foot_radius
        return (lowest <= self.contact_margin).astype(jnp.float32)

    def _parts(self, data: mjx.Data) -> dict[str, jax.Array]:
        """Everything calc_state and the reward read, in physical units."""
        rpy = quat_to_rpy(data.xquat[self._torso])
        z = data.xipos[self._torso, 2]
        xy = self._body_xy(data)
        tgt = jnp.asarray(WALK_TARGET) - xy
        angle_to_target = jnp.arctan2(tgt[1], tgt[0]) - rpy[2]
        yaw = rpy[2]
        c, s = jnp.cos(yaw), jnp.sin(yaw)
        v = self._torso_velocity(data)
        v_body = jnp.stack([c * v[0] + s * v[1], -s * v[0] + c * v[1], v[2]])  # R_z(-yaw) v
        q, qd = data.qpos[self._qadr], data.qvel[self._dadr]
        return dict(z_delta=z - self.initial_z, angle=angle_to_target, v=v_body, rpy=rpy, z=z, xy=xy,
                    q=q, qd=qd, q_scaled=(q - self._jmid) / self._jhalf, contacts=self.foot_contacts(data))

    def _lowdim(self, data: mjx.Data) -> jax.Array:
        p = self._parts(data)
        joints = jnp.stack([p["q_scaled"], JOINT_VEL_SCALE * p["qd"]], -1).reshape(-1)
        state = jnp.concatenate([
            jnp.stack([p["z_delta"], jnp.sin(p["angle"]), jnp.cos(p["angle"])]),
            VEL_SCALE * p["v"], p["rpy"][:2], joints, p["contacts"]])
        return jnp.clip(state, -STATE_CLIP, STATE_CLIP).astype(jnp.float32)

    def _lowdim_raw(self, data: mjx.Data) -> jax.Array:
        p = self._parts(data)
        joints = jnp.stack([p["q"], p["qd"]], -1).reshape(-1)
        return jnp.concatenate([
            jnp.stack([p["z_delta"], jnp.sin(p["angle"]), jnp.cos(p["angle"])]),
            p["v"], p["rpy"][:2], joints, p["contacts"]]).astype(jnp.float32)

    # ----- dynamics hooks -----
    def _ctrl(self, action: jax.Array) -> jax.Array:
        return jnp.clip(action, -1.0, 1.0)  # the motor gear is power * power_coef

    def _reset_qpos_qvel(self, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        noise = jax.random.uniform(key, (len(self.joints),), minval=-0.1, maxval=0.1)
        qpos = self._qpos0.at[self._qadr].set(noise)
        return qpos, jnp.zeros(self.mj_model.nv)

    def _alive(self, p: dict[str, jax.Array]) -> jax.Array:
        raise NotImplementedError

    def _reward_terminated(self, data, lowdim, action, prev_data):
        p = self._parts(data)
        alive = self._alive(p)
        progress = self._progress(self._body_xy(prev_data), p["xy"])
        joint_speeds = JOINT_VEL_SCALE * p["qd"]
        electricity = (ELECTRICITY_COST * jnp.abs(action * joint_speeds).mean()
                       + STALL_TORQUE_COST * jnp.square(action).mean())
        at_limit = JOINTS_AT_LIMIT_COST * (jnp.abs(p["q_scaled"]) > 0.99).sum()
        reward = alive + progress + electricity + at_limit
        return reward.astype(jnp.float32), (alive < 0) & self.terminates

    @staticmethod
    def _progress(xy_old: jax.Array, xy_new: jax.Array) -> jax.Array:
        """potential_new - potential_old = (dist_old - dist_new) / dt, written so that float32
        keeps the small difference of two ~1000 m distances (a direct difference of the two
        potentials, ~6e4 each, would round progress to multiples of ~0.004)."""
        tx, ty = WALK_TARGET
        d_old = jnp.hypot(tx - xy_old[0], ty - xy_old[1])
        d_new = jnp.hypot(tx - xy_new[0], ty - xy_new[1])
        dx, dy = xy_new[0] - xy_old[0], xy_new[1] - xy_old[1]
        # d_old^2 - d_new^2 = dx (2 tx - x_old - x_new) + dy (2 ty - y_old - y_new)
        sq = dx * (2 * tx - xy_old[0] - xy_new[0]) + dy * (2 * ty - xy_old[1] - xy_new[1])
        return sq / (d_old + d_new) / SCENE_DT


class HalfCheetah(Walker):
    """HalfCheetahBulletEnv-v0: planar cheetah, 6 joints, 6 contact links (ffoot, fshin, fthigh,
    bfoot, bshin, bthigh); alive is -1 while the torso pitches past 1 rad or a thigh or shin
    touches the floor, but episodes always run 1000 steps. Power 0.9."""

    name = "HalfCheetah"
    xml_file = "half_cheetah.xml"
    action_size = 6
    solved_return = 3000.0  # gym registry reward_threshold of HalfCheetahBulletEnv-v0
    power = 0.9
    power_coef = (120.0, 90.0, 60.0, 140.0, 60.0, 30.0)  # robot_specific_reset's values
    joints = ("bthigh", "bshin", "bfoot", "fthigh", "fshin", "ffoot")
    feet = ("ffoot", "fshin", "fthigh", "bfoot", "bshin", "bthigh")
    initial_z = 0.7
    terminates = False  # HalfCheetahBulletEnv._isDone returns False: -1 per step, no early end
    state_spec = locomotion_state_spec(6, 6)
    raw_state_spec_ = locomotion_state_spec(6, 6, raw=True)
    # parts: 3 massless root-joint links and the torso (all at the torso origin), then per limb
    # its massless joint link and the limb (PyBullet puts the cheetah's centres of mass at the
    # body origins, as our model does); 16 links + floor = 17
    potential_parts = (("torso", "origin"),) * 4 + tuple(
        (b, "origin") for b in joints for _ in range(2))
    # bulb's multicolour roles, in its order torso, bthigh, bshin, bfoot, fthigh, fshin, ffoot
    # (the torso link also holds the head)
    colour_roles = {"torso": "pole", "head": "pole", "bthigh": "pole2", "bshin": "base",
                    "bfoot": "pole", "fthigh": "base", "fshin": "pole2", "ffoot": "third"}
    naconmax_per_world = 16  # 8 capsules x 2
    njmax = 72  # 16 contacts x 4 pyramidal rows + 6 limits, rounded up

    def _torso_velocity(self, data: mjx.Data) -> jax.Array:
        # rootx, rootz slide at the torso origin, which is the torso's centre of mass
        return jnp.stack([data.qvel[0], 0.0, data.qvel[1]])

    def _alive(self, p):
        c = p["contacts"]  # ffoot, fshin, fthigh, bfoot, bshin, bthigh
        ok = (jnp.abs(p["rpy"][1]) < 1.0) & (c[1] == 0) & (c[2] == 0) & (c[4] == 0) & (c[5] == 0)
        return jnp.where(ok, 1.0, -1.0)


class Ant(Walker):
    """AntBulletEnv-v0: free-floating torso, 8 joints (hip, ankle per leg), 4 feet; it dies when
    the torso's centre drops to 0.26 m. Power 2.5 (x power_coef 100 on every joint)."""

    name = "Ant"
    xml_file = "ant.xml"
    action_size = 8
    solved_return = 2500.0  # gym registry reward_threshold of AntBulletEnv-v0
    power = 2.5
    power_coef = (100.0,) * 8  # XmlBasedRobot's default, not changed for the Ant
    joints = ("hip_1", "ankle_1", "hip_2", "ankle_2", "hip_3", "ankle_3", "hip_4", "ankle_4")
    feet = ("left_ankle_geom", "right_ankle_geom", "third_ankle_geom", "fourth_ankle_geom")
    initial_z = 0.75
    state_spec = locomotion_state_spec(8, 4)
    raw_state_spec_ = locomotion_state_spec(8, 4, raw=True)
    # parts: torso, then per leg the welded leg link, the hip's massless link, aux, the ankle's
    # massless link, the foot; 21 links + floor = 22
    potential_parts = (("torso", "origin"),) + tuple(
        part for leg, aux, foot in (("front_left_leg", "aux_1", "front_left_foot"),
                                    ("front_right_leg", "aux_2", "front_right_foot"),
                                    ("left_back_leg", "aux_3", "left_back_foot"),
                                    ("right_back_leg", "aux_4", "right_back_foot"))
        for part in ((leg, "com"), (aux, "origin"), (aux, "com"), (foot, "origin"), (foot, "com")))
    # bulb's multicolour: torso and the four feet, roles pole, second pole, base, pole, base
    colour_roles = {"torso_geom": "pole", "left_ankle_geom": "pole2", "right_ankle_geom": "base",
                    "third_ankle_geom": "pole", "fourth_ankle_geom": "base"}
    naconmax_per_world = 32  # 12 capsules x 2 + 1 sphere = 25, rounded up
    njmax = 136  # 32 contacts x 4 pyramidal rows + 8 limits

    def _torso_velocity(self, data: mjx.Data) -> jax.Array:
        return data.qvel[0:3]  # free joint: world-frame velocity of the torso origin (= its COM)

    def _alive(self, p):
        return jnp.where(p["z"] > 0.26, 1.0, -1.0)
