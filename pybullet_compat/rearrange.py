"""bulb's ReacherRearrange robot set-up on PyBullet, beside bulbjax's ReacherRearrange mirror:
joint trajectories under zero and random torques while nothing is touched.

The PyBullet side follows bulb's `ReacherBulletSimulation` (facts in
`../shared/reference/bulb-multiobject.md`): the reacher loaded with `loadMJCF` (here bulbjax's
`mjcf_assets/reacher_rearrange.xml`, as bulb's own `reacher.xml` is not in the stored
repository), `plane.urdf` underneath, gravity -9.81, time step 0.01 s with 2 substeps and 5 solver iterations,
the motors of the controlled joints (0 and 2) disabled, torque control, and after every
`stepSimulation` a joint beyond (31/32, 26/32) pi put back on that limit with its velocity
reversed. No objects: this measures the arm alone.

The reacher's base is welded (`rearrange_scene.load_reacher`, shared with the full PyBullet env):
`loadMJCF` makes the MJCF's root body a free body, and before this the 0.06 kg base was thrown
about by the arm's reaction torques (1-4 m in 0.1 s) and the joints ran into PyBullet's 100 rad/s
cap within a step. The report checks the weld (`pybullet_base_drift_m`, 0).

Finding (docs/parity/rearrange_report.json, 8 episodes x 60 steps): with the base welded the two
still differ, now only because `loadMJCF` ignores the MJCF's geom masses (density-1000 links:
shoulder 0.36, elbow 0.30, hand 0.21 kg instead of 2, 2, 0.2), joint damping (0 instead of 1) and
armature (0 instead of 1). PyBullet's joint-space inertia is 0.025-0.038 (joint 0) and 0.008
(joint 1) kg m^2 against the mirror's 1.09-1.13 and 1.02, so under random torques (U[-1, 1] x 3
N m per step) PyBullet's joints travel 1.2 and 2.3 rad in 0.6 s against bulbjax's 0.04 and 0.02,
and the angles differ by 0.009 rad (mean; max 0.024) after one step, 0.42 (max 1.6) after 10 and
1.4 after 60; under full opposite torques 0.040 after one step and 1.1-1.2 from step 10 on, with
PyBullet's undamped joints reaching the 100 rad/s cap in 3 of 8 episodes. Zero torques agree to
1e-7 rad. That nothing else separates them is checked by plain MuJoCo stepping the same MJCF with
PyBullet's link masses, inertias and centres of mass, no damping or armature
(`pybullet_dynamics_trajectories`): it follows PyBullet within 1.2e-5 rad after one step and
0.002 rad (mean; full torque 0.03) after 10, before the undamped, bouncing arm's chaos separates
them. bulb's own `reacher.xml` is not in the stored repository, so whether bulb's arm was as light
as PyBullet makes this file is unknown; the bulbjax mirror follows the reference's numbers (2 kg
links, armature 1, damping 1).

    python -m pybullet_compat.rearrange --episodes 8 --steps 60 --out docs/parity/rearrange_report.json
"""

from __future__ import annotations

import argparse
import json
import os
from typing import Any

import numpy as np

FINDING = ("With the base welded (loadMJCF leaves it free), PyBullet's arm differs from bulbjax's only by "
           "what loadMJCF ignores: geom masses (density 1000: 0.36/0.30/0.21 kg links instead of 2/2/0.2), "
           "joint damping and armature (0 instead of 1), so its joint-space inertia is 30-130x smaller and "
           "undamped: random torques move it 1.2/2.3 rad in 0.6 s against bulbjax's 0.04/0.02, angles differ "
           "by 0.4 rad after 10 steps, and full torques reach PyBullet's 100 rad/s cap. Zero torques agree; "
           "MuJoCo with PyBullet's link dynamics and no damping/armature follows PyBullet within 1.2e-5 "
           "rad after one step. bulb's reacher.xml is not stored, so bulb's true arm dynamics are unknown; bulbjax "
           "follows the reference's numbers.")
CONTROLLED = (0, 2)
TORQUE_LIMITS = np.array([3.0, 3.0])
JOINT_LIMITS = np.array([31 / 32, 26 / 32]) * np.pi


class ReacherBullet:
    """One PyBullet reacher as bulb sets it up (no objects, no tray)."""

    def __init__(self, mjcf_path: str | None = None):
        import pybullet
        import pybullet_data
        from pybullet_utils import bullet_client

        from pybullet_compat.rearrange_scene import load_reacher

        self.p = pybullet
        self.sim = bullet_client.BulletClient(connection_mode=pybullet.DIRECT)
        self.sim.setAdditionalSearchPath(pybullet_data.getDataPath())
        self.sim.loadURDF("plane.urdf", [0, 0, 0])
        self.robot = load_reacher(self.sim, mjcf_path)  # base welded, as in rearrange_env
        self.sim.setGravity(0, 0, -9.81)
        self.sim.setTimeStep(0.01)
        self.sim.setPhysicsEngineParameter(numSolverIterations=5, numSubSteps=2)
        self.sim.setJointMotorControlArray(self.robot, CONTROLLED, pybullet.VELOCITY_CONTROL, forces=[0.0, 0.0])

    def base_position(self) -> np.ndarray:
        """Where the arm's base is (it is welded: stays at the origin)."""
        return np.asarray(self.sim.getBasePositionAndOrientation(self.robot)[0])

    def link_masses(self) -> list[float]:
        return [self.sim.getDynamicsInfo(self.robot, j)[0] for j in range(self.sim.getNumJoints(self.robot))]

    def joint_damping(self) -> list[float]:
        return [self.sim.getJointInfo(self.robot, j)[6] for j in CONTROLLED]

    def reset(self, qpos: np.ndarray) -> None:
        for j, q in zip(CONTROLLED, qpos):
            self.sim.resetJointState(self.robot, j, targetValue=float(q), targetVelocity=0.0)

    def qpos(self) -> np.ndarray:
        return np.array([s[0] for s in self.sim.getJointStates(self.robot, CONTROLLED)])

    def qvel(self) -> np.ndarray:
        return np.array([s[1] for s in self.sim.getJointStates(self.robot, CONTROLLED)])

    def step(self, action: np.ndarray) -> None:
        """bulbjax's action in [-1, 1] (bulb's (a - 0.5) * 2 in [0, 1]) as torque, one
        stepSimulation, bulb's limit clamp."""
        torque = np.clip(np.asarray(action) * TORQUE_LIMITS, -TORQUE_LIMITS, TORQUE_LIMITS)
        self.sim.setJointMotorControlArray(self.robot, CONTROLLED, self.p.TORQUE_CONTROL, forces=torque.tolist())
        self.sim.stepSimulation()
        q, v = self.qpos(), self.qvel()
        for i, j in enumerate(CONTROLLED):
            if abs(q[i]) > JOINT_LIMITS[i]:
                self.sim.resetJointState(self.robot, j, targetValue=float(JOINT_LIMITS[i] * np.sign(q[i])),
                                         targetVelocity=float(-v[i]))


def bulbjax_trajectories(starts: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Joint angles and speeds `[T + 1, E, 2]` of bulbjax's ReacherRearrangeGeom from `starts` [E, 2]
    under `actions` [T, E, 2], objects parked in the tray's corners (out of reach), no reset torques."""
    import jax
    import jax.numpy as jnp

    import bulbjax

    e = len(starts)
    env = bulbjax.make("ReacherRearrangeGeom", num_envs=e, render=False, version=0)
    corners = jnp.asarray([[0.31, 0.31, 0.06], [0.31, -0.31, 0.06], [-0.31, 0.31, 0.06], [-0.31, -0.31, 0.06]])
    state = jax.jit(lambda k: env.reset_with(
        k, robot_qpos=jnp.asarray(starts, jnp.float32), obj_pos=corners, obj_quat=jnp.asarray([1.0, 0, 0, 0]),
        torques=0.0))(jax.random.PRNGKey(0))
    physics = jax.jit(lambda d, a: env.physics(d, a, state.params))
    data = state.data
    q, qd = [np.asarray(data.qpos[:, env._robot_qadr])], [np.asarray(data.qvel[:, env._robot_vadr])]
    for a in actions:
        data = physics(data, jnp.asarray(a, jnp.float32))
        q.append(np.asarray(data.qpos[:, env._robot_qadr]))
        qd.append(np.asarray(data.qvel[:, env._robot_vadr]))
    return np.stack(q), np.stack(qd)


def pybullet_trajectories(starts: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Joint angles and speeds `[T + 1, E, 2]` of `ReacherBullet` from `starts` [E, 2] under
    `actions` [T, E, 2], and the farthest its (welded) base got from where it was loaded (m)."""
    sim = ReacherBullet()
    base0 = sim.base_position()
    q = np.zeros((len(actions) + 1, len(starts), 2))
    qd = np.zeros_like(q)
    drift = 0.0
    for i, q0 in enumerate(starts):
        sim.reset(q0)
        q[0, i] = sim.qpos()
        for t, a in enumerate(actions[:, i]):
            sim.step(a)
            q[t + 1, i], qd[t + 1, i] = sim.qpos(), sim.qvel()
            drift = max(drift, float(np.linalg.norm(sim.base_position() - base0)))
    return q, qd, drift


def pybullet_dynamics_trajectories(starts: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """Joint angles `[T + 1, E, 2]` of plain MuJoCo (CPU) stepping the same MJCF with what PyBullet's
    `loadMJCF` made of it: `ReacherBullet`'s link masses, inertias and centres of mass, no damping,
    no armature, PyBullet's 100 rad/s joint speed cap; 2 semi-implicit Euler substeps of 0.005 s
    per step (Bullet's) and bulb's limit clamp. If this follows `ReacherBullet`, the importer's
    dynamics -- not the two engines -- are what separates PyBullet from bulbjax's arm."""
    import mujoco

    from pybullet_compat.rearrange_scene import reacher_mjcf_path

    sim = ReacherBullet()
    model = mujoco.MjModel.from_xml_path(reacher_mjcf_path())
    model.dof_damping[:] = 0.0
    model.dof_armature[:] = 0.0
    for link in range(sim.sim.getNumJoints(sim.robot)):
        name = sim.sim.getJointInfo(sim.robot, link)[12].decode()
        body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
        if body < 0:
            continue  # the importer's massless joint links (link0_2, link0_4)
        mass, _, inertia, ipos, iquat = sim.sim.getDynamicsInfo(sim.robot, link)[:5]
        model.body_mass[body], model.body_inertia[body], model.body_ipos[body] = mass, inertia, ipos
        model.body_iquat[body] = (iquat[3], iquat[0], iquat[1], iquat[2])
    model.opt.timestep, model.opt.integrator = 0.005, mujoco.mjtIntegrator.mjINT_EULER
    data = mujoco.MjData(model)
    out = np.zeros((len(actions) + 1, len(starts), 2))
    for i, q0 in enumerate(starts):
        mujoco.mj_resetData(model, data)
        data.qpos[:] = out[0, i] = q0
        for t, a in enumerate(actions[:, i]):
            data.ctrl[:] = np.clip(np.asarray(a) * TORQUE_LIMITS, -TORQUE_LIMITS, TORQUE_LIMITS)
            for _ in range(2):
                mujoco.mj_step(model, data)
                data.qvel[:] = np.clip(data.qvel, -100.0, 100.0)
            over = np.abs(data.qpos) > JOINT_LIMITS
            data.qpos[over] = JOINT_LIMITS[over] * np.sign(data.qpos[over])
            data.qvel[over] = -data.qvel[over]
            out[t + 1, i] = data.qpos
    return out


def _angle_diff(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs(np.angle(np.exp(1j * (a - b))))


def run(episodes: int = 8, steps: int = 60, seed: int = 0) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    starts = rng.uniform(-0.75 * np.pi, 0.75 * np.pi, (episodes, 2))
    sim = ReacherBullet()
    report: dict[str, Any] = {
        "domain": "ReacherRearrange (arm only, no contact)", "episodes": episodes, "steps": steps, "dt": 0.01,
        "pybullet_base": "welded (loadMJCF's free root body given mass 0)",
        "pybullet_link_masses_kg": sim.link_masses(), "pybullet_joint_damping": sim.joint_damping(),
        "mjcf_link_masses_kg": "base 1, shoulder 2, elbow 2, hand 0.2; armature 1, damping 1 per joint",
        "finding": FINDING,
        "kinds": {}}
    at = sorted({1, 10, 30, steps})
    for kind in ("zero", "random", "full"):
        if kind == "zero":
            actions = np.zeros((steps, episodes, 2))
        elif kind == "random":
            actions = rng.uniform(-1, 1, (steps, episodes, 2))
        else:  # full torque on joint 0, opposite on joint 1
            actions = np.broadcast_to(np.array([1.0, -1.0]), (steps, episodes, 2)).copy()
        pb, pb_vel, drift = pybullet_trajectories(starts, actions)
        mj, mj_vel = bulbjax_trajectories(starts, actions)
        same = pybullet_dynamics_trajectories(starts, actions)
        diff, diff_same = _angle_diff(pb, mj), _angle_diff(pb, same)
        report["kinds"][kind] = {
            "max_abs_diff_rad_at": {str(t): float(diff[t].max()) for t in at},
            "mean_abs_diff_rad_at": {str(t): float(diff[t].mean()) for t in at},
            "mean_abs_diff_rad_at_end": float(diff[-1].mean()),
            "mean_travel_rad_pybullet": np.abs(pb[-1] - pb[0]).mean(0).tolist(),
            "mean_travel_rad_bulbjax": np.abs(mj[-1] - mj[0]).mean(0).tolist(),
            "max_joint_speed_rad_s_pybullet": np.abs(pb_vel).max((0, 1)).tolist(),
            "max_joint_speed_rad_s_bulbjax": np.abs(mj_vel).max((0, 1)).tolist(),
            "pybullet_base_drift_m": drift,
            "mujoco_with_pybullet_dynamics": {
                "max_abs_diff_rad_at": {str(t): float(diff_same[t].max()) for t in at},
                "mean_abs_diff_rad_at": {str(t): float(diff_same[t].mean()) for t in at},
                "mean_travel_rad": np.abs(same[-1] - same[0]).mean(0).tolist()}}
    return report


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--episodes", type=int, default=8)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--out", default="docs/parity/rearrange_report.json")
    args = ap.parse_args()
    report = run(args.episodes, args.steps)
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(report, f, indent=1)
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
