"""Rearrange parity: where the objects lie after bulb's reset, in the PyBullet original
(`pybullet_compat.rearrange_env`) and in bulbjax's MJX mirror (`bulbjax.envs.objects.rearrange`).

Both run bulb's reset (objects dropped at random poses, 20 settle steps, 10 steps of random
torques) from the SAME draws: `--resets` PyBullet resets (seeds 0..R-1) record their draws (robot
pose -- for the Franka PyBullet's IK solution --, object positions and quaternions, torques), and
the mirror replays them with `reset_with` in R worlds. The mirror's own draws (`reset`, its own
IK) are summarised too. Per object of the version's list: height z (m; COM), tilt (deg, the
angle between the object's z axis and the world's), xy travel from the drop point, speed at the
end of the reset, and counts of objects off the tray floor (z above its resting half-height +
2 cm: leaning on or lying on another object) or outside |x|, |y| < 0.4; paired differences per
reset; the end effector's distance between the two; episodes that end at once.

    python -m pybullet_compat.parity_rearrange --names ReacherRearrangeGeom,FrankaRearrangeGeom \\
        --resets 32 --out docs/parity/rearrange_settle.json
"""

from __future__ import annotations

import argparse
import json
import os
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from pybullet_compat import rearrange_env as pbr
from pybullet_compat import rearrange_scene as pbs


@dataclass(frozen=True)
class SettleConfig:
    """One comparison: domain, version, number of resets, YCB folder."""

    name: str = "ReacherRearrangeGeom"
    version: int = 0
    resets: int = 32
    ycb_dir: str | None = None
    seed: int = 0


def tilt_deg(quat_wxyz: np.ndarray) -> np.ndarray:
    """Angle (deg) between each object's z axis and the world's z axis; quat [..., 4] (w, x, y, z)."""
    q = quat_wxyz / np.linalg.norm(quat_wxyz, axis=-1, keepdims=True)
    zz = 1 - 2 * (q[..., 1] ** 2 + q[..., 2] ** 2)  # R[2, 2]
    return np.degrees(np.arccos(np.clip(zz, -1.0, 1.0)))


def pybullet_resets(cfg: SettleConfig, **env_kwargs: Any) -> dict[str, np.ndarray]:
    """R resets of the PyBullet original (`env_kwargs` to its constructor): draws and the settled poses."""
    env = pbr.RearrangeBulletEnv(cfg.name, cfg.version, render=False, ycb_dir=cfg.ycb_dir, **env_kwargs)
    out: dict[str, list] = {k: [] for k in ("robot_qpos", "obj_pos", "obj_quat", "torques", "pos", "quat", "speed",
                                            "ee", "terminated", "robot_q")}
    for i in range(cfg.resets):
        env.reset(seed=cfg.seed + i)
        for k, v in env.last_draws.items():
            out[k].append(v)
        pos, quat = env.object_poses()
        lin, _ = env.object_velocities()
        out["pos"].append(pos)
        out["quat"].append(quat)
        out["speed"].append(np.linalg.norm(lin, axis=1))
        out["ee"].append(env.ee_position())
        out["robot_q"].append(env.joint_states()[0][:env.spec.action_size])
        out["terminated"].append(env.reward_terminated()[1])
    half_z = np.array([o.half_z for o in env.objects])
    env.close()
    res = {k: np.asarray(v) for k, v in out.items()}
    res["half_z"] = half_z
    return res


def mirror_resets(cfg: SettleConfig, draws: dict[str, np.ndarray] | None) -> dict[str, np.ndarray]:
    """R worlds of the MJX mirror reset from `draws` (`reset_with`), or from its own draws."""
    import jax
    import jax.numpy as jnp

    import bulbjax

    env = bulbjax.make(cfg.name, num_envs=cfg.resets, render=False, version=cfg.version, ycb_dir=cfg.ycb_dir)
    key = jax.random.PRNGKey(cfg.seed)
    if draws is None:
        state = jax.jit(env.reset)(key)
    else:
        fixed = {k: jnp.asarray(draws[k], jnp.float32) for k in ("robot_qpos", "obj_pos", "obj_quat", "torques")}
        state = jax.jit(lambda k, f: env.reset_with(k, **f))(key, fixed)
    raw = np.asarray(state.info["lowdim_raw"], np.float64)
    j, m = len(env.joint_names), env.num_objects
    per = raw[:, 2 * j:2 * j + 13 * m].reshape(-1, m, 13)
    ee = raw[:, -3:]
    pos, quat = per[..., :3], per[..., 3:7]
    max_z = np.asarray(env._max_object_z)[cfg.version]
    outside = ((pos < pbs.OBJ_XYZ_MIN) | (pos > pbs.OBJ_XYZ_MAX)).any(axis=(1, 2))
    term = outside | (ee[:, 2] > pbs.EE_ABOVE_OBJECTS + max_z) | (np.abs(ee[:, :2]) > pbs.EE_XY_MAX).any(1)
    return {"pos": pos, "quat": quat, "speed": np.linalg.norm(per[..., 7:10], axis=-1), "ee": ee,
            "terminated": term | ~np.isfinite(raw).all(1), "robot_q": raw[:, :j]}


def summarise(r: dict[str, np.ndarray], half_z: np.ndarray, drop_xy: np.ndarray | None,
              robot_q0: np.ndarray | None = None) -> dict[str, Any]:
    """Per object: z, tilt, travel and speed statistics, off-floor and off-tray counts; the arm's
    joint travel from `robot_q0` when given."""
    tilt = tilt_deg(r["quat"])
    z = r["pos"][..., 2]
    objs = []
    for k in range(z.shape[1]):
        row = {"z_mean": float(z[:, k].mean()), "z_std": float(z[:, k].std()), "z_min": float(z[:, k].min()),
               "z_max": float(z[:, k].max()), "tilt_mean_deg": float(tilt[:, k].mean()),
               "upright_share": float((tilt[:, k] < 20).mean()),
               "on_side_share": float(((tilt[:, k] > 70) & (tilt[:, k] < 110)).mean()),
               "upside_down_share": float((tilt[:, k] > 160).mean()),
               "above_floor_rest": int((z[:, k] > half_z[k] + 0.02).sum()),
               "speed_mean": float(r["speed"][:, k].mean()), "speed_max": float(r["speed"][:, k].max()),
               "off_tray": int((np.abs(r["pos"][:, k, :2]) > 0.4).any(1).sum())}
        if drop_xy is not None:
            travel = np.linalg.norm(r["pos"][:, k, :2] - drop_xy[:, k], axis=1)
            row["travel_mean"], row["travel_max"] = float(travel.mean()), float(travel.max())
        objs.append(row)
    out: dict[str, Any] = {"objects": objs, "terminated_at_reset": int(np.asarray(r["terminated"]).sum())}
    if robot_q0 is not None:  # how far the arm moved during the reset (settle and random torques)
        out["robot_travel_rad_mean"] = np.abs(r["robot_q"] - robot_q0).mean(0).tolist()
    return out


def compare(cfg: SettleConfig) -> dict[str, Any]:
    """The settle comparison of one domain (see the module docstring)."""
    pb = pybullet_resets(cfg)
    mj = mirror_resets(cfg, pb)
    own = mirror_resets(cfg, None)
    drop = pb["obj_pos"][..., :2]
    names = pbs.OBJECT_LISTS[pbs.rearrange_domain(cfg.name).variant][cfg.version % pbs.NUM_LISTS]
    report = {"config": asdict(cfg), "objects": list(names), "half_z": pb["half_z"].tolist(),
              "pybullet": summarise(pb, pb["half_z"], drop, pb["robot_qpos"]),
              "mjx_same_draws": summarise(mj, pb["half_z"], drop, pb["robot_qpos"]),
              "mjx_own_draws": summarise(own, pb["half_z"], None), "paired_same_draws": paired(pb, mj)}
    if "Franka" in cfg.name:  # the Panda with the URDF's (the mirror's) link inertias
        urdf = pybullet_resets(cfg, inertia_from_file=True)
        if not np.allclose(urdf["robot_qpos"], pb["robot_qpos"]):
            raise RuntimeError("the two PyBullet runs drew different resets")
        report["pybullet_urdf_inertia"] = summarise(urdf, pb["half_z"], drop, pb["robot_qpos"])
        report["paired_same_draws_urdf_inertia"] = paired(urdf, mj)
    return report


def paired(pb: dict[str, np.ndarray], mj: dict[str, np.ndarray]) -> dict[str, Any]:
    """Per-reset differences of the settled poses (same draws in both simulators)."""
    cls = lambda t: np.digitize(t, [20, 70, 110, 160])  # noqa: E731  upright / tilted / side / tilted / down
    ee = np.linalg.norm(pb["ee"] - mj["ee"], axis=1)
    return {"z_abs_diff_mean": np.abs(pb["pos"][..., 2] - mj["pos"][..., 2]).mean(0).tolist(),
            "xy_dist_mean": np.linalg.norm(pb["pos"][..., :2] - mj["pos"][..., :2], axis=-1).mean(0).tolist(),
            "tilt_class_agreement": (cls(tilt_deg(pb["quat"])) == cls(tilt_deg(mj["quat"]))).mean(0).tolist(),
            "ee_dist_mean": float(ee.mean()), "ee_dist_max": float(ee.max())}


def markdown(reports: list[dict[str, Any]]) -> str:
    """One table row per domain and object: PyBullet vs MJX (same draws), MJX own draws in brackets."""
    lines = ["| domain | object | z mean +- std (m): PyBullet / MJX [own] | upright / on side share | "
             "above rest | travel (m) | speed (m/s) | paired |dz| / |dxy| (m) |",
             "|---|---|---|---|---|---|---|---|"]
    for r in reports:
        for k, name in enumerate(r["objects"]):
            a, b, c = (r[s]["objects"][k] for s in ("pybullet", "mjx_same_draws", "mjx_own_draws"))
            p = r["paired_same_draws"]
            lines.append(
                f"| {r['config']['name']}-v{r['config']['version']} | {name} | "
                f"{a['z_mean']:.3f} +- {a['z_std']:.3f} / {b['z_mean']:.3f} +- {b['z_std']:.3f} [{c['z_mean']:.3f}] | "
                f"{a['upright_share']:.2f}, {a['on_side_share']:.2f} / {b['upright_share']:.2f}, {b['on_side_share']:.2f} | "
                f"{a['above_floor_rest']} / {b['above_floor_rest']} | {a['travel_mean']:.3f} / {b['travel_mean']:.3f} | "
                f"{a['speed_mean']:.2f} / {b['speed_mean']:.2f} | "
                f"{p['z_abs_diff_mean'][k]:.3f} / {p['xy_dist_mean'][k]:.3f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--names", default="ReacherRearrangeGeom,FrankaRearrangeGeom")
    ap.add_argument("--version", type=int, default=0)
    ap.add_argument("--resets", type=int, default=32)
    ap.add_argument("--ycb-dir", default=os.environ.get("BULBJAX_YCB_DIR"))
    ap.add_argument("--out", default="docs/parity/rearrange_settle.json")
    args = ap.parse_args()
    reports = []
    for name in args.names.split(","):
        cfg = SettleConfig(name, args.version, args.resets, args.ycb_dir)
        reports.append(compare(cfg))
        print(f"{name}: done", flush=True)
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        json.dump({"reports": reports}, f, indent=1)
    print(markdown(reports))
    for r in reports:
        if "pybullet_urdf_inertia" in r:
            u, pu = r["pybullet_urdf_inertia"], r["paired_same_draws_urdf_inertia"]
            print(r["config"]["name"], "PyBullet with the URDF's inertias: arm travel (rad)",
                  np.round(u["robot_travel_rad_mean"], 2).tolist(), "| end effector apart (m): mean",
                  round(pu["ee_dist_mean"], 3), "| paired |dxy| (m)", np.round(pu["xy_dist_mean"], 3).tolist(),
                  "| speed (m/s)", [round(o["speed_mean"], 2) for o in u["objects"]], "| ended at reset",
                  u["terminated_at_reset"])
        print(r["config"]["name"], "ended at reset: PyBullet", r["pybullet"]["terminated_at_reset"], "MJX",
              r["mjx_same_draws"]["terminated_at_reset"], "MJX own", r["mjx_own_draws"]["terminated_at_reset"],
              "| end effector apart (m): mean", round(r["paired_same_draws"]["ee_dist_mean"], 3), "max",
              round(r["paired_same_draws"]["ee_dist_max"], 3), "| arm travel (rad): PyBullet",
              np.round(r["pybullet"]["robot_travel_rad_mean"], 2).tolist(), "MJX",
              np.round(r["mjx_same_draws"]["robot_travel_rad_mean"], 2).tolist())


if __name__ == "__main__":
    main()
