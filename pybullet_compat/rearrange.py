"""bulb's ReacherRearrange robot set-up on PyBullet, beside bulbjax's ReacherRearrange mirror:
joint trajectories under zero and random torques while nothing is touched.

The PyBullet side follows bulb's `ReacherBulletSimulation` (facts in
`../shared/reference/bulb-multiobject.md`): the reacher loaded with `loadMJCF` (here bulbjax's
`mjcf_assets/reacher_rearrange.xml`, as bulb's own `reacher.xml` is not in the stored repository),
`plane.urdf` underneath, gravity -9.81, time step 0.01 s with 2 substeps and 5 solver iterations,
the motors of the controlled joints (0 and 2) disabled, torque control, and after every
`stepSimulation` a joint beyond (31/32, 26/32) pi put back on that limit with its velocity
reversed. No objects: this measures the arm alone.

Finding (docs/parity/rearrange_report.json): the two do not agree, and the cause is on the
PyBullet side of this set-up, not a parity of bulb's arm. PyBullet's `loadMJCF` of
`reacher_rearrange.xml` ignores the geoms' `mass` (links get density-1000 masses: shoulder 0.36
kg, elbow 0.30 kg), the joints' damping and armature (`getJointInfo` damping 0), and gives
joint 0's child link (`link0_2`, the importer's joint link) zero mass: joint 0 then reaches
PyBullet's 100 rad/s velocity cap within one step even at 0.3 N m. Zero torques agree exactly
(nothing moves in either). bulb's own `reacher.xml` is not in the stored repository, so whether
bulb's arm was as light as PyBullet makes this file is unknown; the bulbjax mirror follows the
reference's numbers (2 kg links, armature 1, damping 1).

    python -m pybullet_compat.rearrange --episodes 8 --steps 60 --out docs/parity/rearrange_report.json
"""

from __future__ import annotations

import argparse
import json
import os
from typing import Any

import numpy as np

FINDING = ("PyBullet's loadMJCF ignores geom masses (density 1000), joint damping and armature, and gives "
           "joint 0's importer link zero mass: joint 0 hits PyBullet's 100 rad/s cap in one step under any "
           "torque. The trajectories differ for that reason; zero torques agree. bulb's reacher.xml is not "
           "stored, so bulb's true arm dynamics are unknown; bulbjax follows the reference's numbers.")
CONTROLLED = (0, 2)
TORQUE_LIMITS = np.array([3.0, 3.0])
JOINT_LIMITS = np.array([31 / 32, 26 / 32]) * np.pi


class ReacherBullet:
    """One PyBullet reacher as bulb sets it up (no objects, no tray)."""

    def __init__(self, mjcf_path: str | None = None):
        import pybullet
        import pybullet_data
        from pybullet_utils import bullet_client

        from bulbjax.envs.base import asset_dir

        self.p = pybullet
        self.sim = bullet_client.BulletClient(connection_mode=pybullet.DIRECT)
        self.sim.setAdditionalSearchPath(pybullet_data.getDataPath())
        self.sim.loadURDF("plane.urdf", [0, 0, 0])
        path = mjcf_path or os.path.join(asset_dir(), "reacher_rearrange.xml")
        self.robot = self.sim.loadMJCF(path)[0]
        self.sim.setGravity(0, 0, -9.81)
        self.sim.setTimeStep(0.01)
        self.sim.setPhysicsEngineParameter(numSolverIterations=5, numSubSteps=2)
        self.sim.setJointMotorControlArray(self.robot, CONTROLLED, pybullet.VELOCITY_CONTROL, forces=[0.0, 0.0])

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


def bulbjax_trajectories(starts: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """Joint angles `[T + 1, E, 2]` of bulbjax's ReacherRearrangeGeom from `starts` [E, 2] under
    `actions` [T, E, 2], objects parked in the tray's corners (out of reach), no reset torques."""
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
    data, out = state.data, [np.asarray(state.data.qpos[:, env._robot_qadr])]
    for a in actions:
        data = physics(data, jnp.asarray(a, jnp.float32))
        out.append(np.asarray(data.qpos[:, env._robot_qadr]))
    return np.stack(out)


def pybullet_trajectories(starts: np.ndarray, actions: np.ndarray) -> np.ndarray:
    sim = ReacherBullet()
    out = np.zeros((len(actions) + 1, len(starts), 2))
    for i, q0 in enumerate(starts):
        sim.reset(q0)
        out[0, i] = sim.qpos()
        for t, a in enumerate(actions[:, i]):
            sim.step(a)
            out[t + 1, i] = sim.qpos()
    return out


def run(episodes: int = 8, steps: int = 60, seed: int = 0) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    starts = rng.uniform(-0.75 * np.pi, 0.75 * np.pi, (episodes, 2))
    sim = ReacherBullet()
    report: dict[str, Any] = {
        "domain": "ReacherRearrange (arm only, no contact)", "episodes": episodes, "steps": steps, "dt": 0.01,
        "pybullet_link_masses_kg": sim.link_masses(), "pybullet_joint_damping": sim.joint_damping(),
        "mjcf_link_masses_kg": "base 1, shoulder 2, elbow 2, hand 0.2; armature 1, damping 1 per joint",
        "finding": FINDING,
        "kinds": {}}
    for kind in ("zero", "random", "full"):
        if kind == "zero":
            actions = np.zeros((steps, episodes, 2))
        elif kind == "random":
            actions = rng.uniform(-1, 1, (steps, episodes, 2))
        else:  # full torque on joint 0, opposite on joint 1
            actions = np.broadcast_to(np.array([1.0, -1.0]), (steps, episodes, 2)).copy()
        pb = pybullet_trajectories(starts, actions)
        mj = bulbjax_trajectories(starts, actions)
        diff = np.abs(np.angle(np.exp(1j * (pb - mj))))
        travel_pb = np.abs(pb[-1] - pb[0]).mean(0)
        travel_mj = np.abs(mj[-1] - mj[0]).mean(0)
        report["kinds"][kind] = {
            "max_abs_diff_rad_at": {str(t): float(diff[t].max()) for t in (1, 10, 30, steps)},
            "mean_abs_diff_rad_at_end": float(diff[-1].mean()),
            "mean_travel_rad_pybullet": travel_pb.tolist(), "mean_travel_rad_bulbjax": travel_mj.tolist()}
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
