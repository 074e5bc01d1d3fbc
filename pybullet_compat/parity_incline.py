"""Parity of the Incline domains: bulbjax's MJX mirror (`bulbjax.envs.objects.incline`) against the
PyBullet original (`pybullet_compat.incline`), from the same episode parameters and states.

Comparisons (each side keeps stepping after an episode would end; errors are only taken while
neither side has ended its episode: x in (0, 1), |y| < 0.1):
- trajectories of the object's distance travelled and speed (bulb's state entries, metres and
  m/s), under zero push and under one fixed random push sequence, in two set-ups:
  'same_state' -- PyBullet is put in the MJX world's post-reset state (pose and velocities), so
  only the slide differs; 'own_reset' -- each simulator runs bulb's whole reset (initial fall
  from the same pose to the same start_x) from the same draws, as a user of either sees it;
- sweeps of friction, mass (under a constant push against the slide, where mass matters) and
  pitch: distance travelled after `sweep_steps` steps against the parameter on both sides (the
  MJX slide must speed up and slow down as PyBullet's does);
- the analytic slide: the object put flat on the incline moving down the slope at v0; the
  fitted acceleration along the slope against a = g (sin theta - mu cos theta) + F / m with
  mu = friction^2 (Bullet multiplies the two coefficients; the mirror gives both geoms
  friction^2), for PyBullet as bulb runs it (its base damping 0.04 |v| (1 + |v|) adds to the
  expected deceleration), PyBullet without damping, and MJX.

`python -m pybullet_compat.parity_incline [--name GeomOnIncline --version 0 ...]` prints the
tables and writes docs/parity/incline_report.json.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
import warnings
from dataclasses import asdict, replace
from typing import Any, Callable

import numpy as np

from pybullet_compat import incline as pbi
from pybullet_compat.parity_incline_sides import BulletSide, InclineMirror, InclineParityConfig

DEFAULT_JSON = os.path.join("docs", "parity", "incline_report.json")
DIST, SPEED, X = 18, 19, 0  # indices in the raw layout (pybullet_compat.incline.RAW_NAMES)


# ---------------------------------------------------------------------------------- metrics
def ended(raw: np.ndarray) -> np.ndarray:
    """[T + 1, n] bool: the episode has ended by this entry (bulb's termination, sticky)."""
    x, y = raw[..., 0], raw[..., 1]
    end = (x >= pbi.MAX_X) | (x <= pbi.MIN_X) | (np.abs(y) >= pbi.MAX_Y) | ~np.isfinite(raw).all(-1)
    end[0] = False
    return np.maximum.accumulate(end, axis=0)


def trajectory_errors(pb: np.ndarray, mj: np.ndarray, dt: float, checkpoints: tuple[float, ...]) -> dict[str, Any]:
    """Distance and speed errors (|PyBullet - MJX|) vs time while neither episode has ended."""
    live = ~(ended(pb) | ended(mj))  # [T + 1, n]
    out: dict[str, Any] = {"live_starts_per_step": live.sum(1).tolist()}
    with warnings.catch_warnings():  # steps where every start has ended give NaN (null in JSON)
        warnings.simplefilter("ignore", RuntimeWarning)
        return _trajectory_errors(pb, mj, dt, checkpoints, live, out)


def _trajectory_errors(pb: np.ndarray, mj: np.ndarray, dt: float, checkpoints: tuple[float, ...],
                       live: np.ndarray, out: dict[str, Any]) -> dict[str, Any]:
    for nm, k in (("distance", DIST), ("speed", SPEED), ("x", X)):
        e = np.abs(pb[..., k] - mj[..., k])
        e_live = np.where(live, e, np.nan)
        mean_t = np.nanmean(e_live, 1)
        out[nm] = {"mean_abs_vs_step": _round(mean_t), "max_abs": float(np.nanmax(e_live)),
                   "at": {f"{c:g}s": _maybe(mean_t, int(round(c / dt))) for c in checkpoints},
                   "pybullet_mean_vs_step": _round(np.nanmean(np.where(live, pb[..., k], np.nan), 1)),
                   "mjx_mean_vs_step": _round(np.nanmean(np.where(live, mj[..., k], np.nan), 1))}
        # growth: error late vs early among the starts still live in both halves
        n_live = live.sum(1)
        last = int(np.nonzero(n_live > 0)[0].max())
        out[nm]["growth"] = {"first_step": _maybe(mean_t, 1), "last_live_step": last,
                             "at_last_live_step": _maybe(mean_t, last)}
    # relative speed error (a drift in acceleration shows as a steady relative gap)
    rel = np.where(live[1:], (pb[1:, :, SPEED] - mj[1:, :, SPEED]) / np.maximum(mj[1:, :, SPEED], 0.05), np.nan)
    out["speed_signed_rel_vs_step"] = _round(np.nanmean(rel, 1))
    out["end_step"] = {"pybullet": _first_end(pb).tolist(), "mjx": _first_end(mj).tolist()}
    return out


def _first_end(raw: np.ndarray) -> np.ndarray:
    e = ended(raw)
    return np.where(e.any(0), e.argmax(0), e.shape[0])


def _maybe(a: np.ndarray, i: int) -> float | None:
    return float(a[i]) if 0 <= i < len(a) and np.isfinite(a[i]) else None


def _round(a: np.ndarray, k: int = 4) -> list[float | None]:
    return [None if not np.isfinite(v) else round(float(v), k) for v in a]


def action_sequences(steps: int, n: int, seed: int) -> dict[str, np.ndarray]:
    """'zero' and 'random' (uniform in [-1, 1], the same draws for both simulators) actions [T, n]."""
    rng = np.random.default_rng(seed + 7)
    return {"zero": np.zeros((steps, n)), "random": rng.uniform(-1, 1, (steps, n))}


# ---------------------------------------------------------------------------------- runs
def compare_trajectories(mirror: InclineMirror, bullet: BulletSide, cfg: InclineParityConfig) -> dict[str, Any]:
    """Trajectory errors for both set-ups and both push sequences from `cfg.worlds` bulb draws."""
    rng = np.random.default_rng(cfg.seed)
    params = [pbi.draw_params(rng) for _ in range(cfg.worlds)]
    dt = pbi.BULLET_DT * pbi.STEPS_PER_ACTION
    out: dict[str, Any] = {"params": [asdict(p) for p in params]}
    reset_state = mirror.reset(params)
    mj_start = mirror.raw(reset_state)
    starts = mj_start[:, :13]
    for kind, acts in action_sequences(cfg.steps, cfg.worlds, cfg.seed).items():
        mj = mirror.play(reset_state, acts)
        res = {"same_state": trajectory_errors(bullet.play(params, acts, starts), mj, dt, cfg.checkpoints),
               "own_reset": trajectory_errors(pb_own := bullet.play(params, acts), mj, dt, cfg.checkpoints)}
        if kind == "zero":
            res["own_reset"]["start_difference"] = {
                "x": _round(pb_own[0, :, X] - mj_start[:, X]), "speed": _round(pb_own[0, :, SPEED] - mj_start[:, SPEED]),
                "distance": _round(pb_own[0, :, DIST] - mj_start[:, DIST])}
        out[kind] = res
    return out


def sweep_values(cfg: InclineParityConfig) -> dict[str, np.ndarray]:
    n = cfg.worlds
    return {"friction": np.linspace(*pbi.FRICTION, n), "mass": np.linspace(*pbi.MASS, n),
            "theta": np.linspace(*pbi.PITCH, n)}


SWEEP_BASE = pbi.InclineParams(mass=0.2, friction=0.3, theta=0.4, texture=0, eps=0.0, start_x=0.1)


def sweeps(mirror: InclineMirror, bullet: BulletSide, cfg: InclineParityConfig) -> dict[str, Any]:
    """Distance after `sweep_steps` steps vs friction, mass (push `sweep_push`) and pitch, from
    bulb's own reset on both sides and from the same (MJX post-reset) state."""
    out: dict[str, Any] = {"base": asdict(SWEEP_BASE), "steps": cfg.sweep_steps}
    for param, values in sweep_values(cfg).items():

        params = [replace(SWEEP_BASE, **{param: float(v)}) for v in values]
        push = cfg.sweep_push if param == "mass" else 0.0
        acts = np.full((cfg.steps, cfg.worlds), push)
        state = mirror.reset(params)
        mj = mirror.play(state, acts)
        pb_own = bullet.play(params, acts[:cfg.sweep_steps])
        pb_same = bullet.play(params, acts[:cfg.sweep_steps], mirror.raw(state)[:, :13])
        k = cfg.sweep_steps
        d_mj = mj[k, :, DIST] - mj[0, :, DIST]
        d_own = pb_own[k, :, DIST] - pb_own[0, :, DIST]
        d_same = pb_same[k, :, DIST] - pb_same[0, :, DIST]
        row = {"values": _round(values), "push": push, "mjx_distance": _round(d_mj),
               "pybullet_distance_own_reset": _round(d_own), "pybullet_distance_same_state": _round(d_same)}
        for nm, d in (("own_reset", d_own), ("same_state", d_same)):
            row[f"{nm}_max_abs_diff"] = float(np.max(np.abs(d - d_mj)))
            row[f"{nm}_slope_pybullet"] = float(np.polyfit(values, d, 1)[0])
        row["slope_mjx"] = float(np.polyfit(values, d_mj, 1)[0])
        row["same_trend"] = bool(np.sign(row["slope_mjx"]) == np.sign(row["same_state_slope_pybullet"]))
        row["spearman_same_state"] = _spearman(d_mj, d_same)
        out[param] = row
    return out


def _spearman(a: np.ndarray, b: np.ndarray) -> float:
    ra, rb = np.argsort(np.argsort(a)), np.argsort(np.argsort(b))
    if ra.std() == 0 or rb.std() == 0:
        return float("nan")
    return float(np.corrcoef(ra, rb)[0, 1])


# ---------------------------------------------------------------------------------- analytic slide
def on_incline_pose(theta: float, extent: float, s: float = 0.25) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(position, quaternion w-x-y-z, downslope unit vector) of an object lying on the incline's
    top face in bulb's start orientation (its z axis down the slope, its x axis into the face),
    `extent` from its centre to the face, `s` m down the slope from the incline's centre."""
    from scipy.spatial.transform import Rotation

    ry = Rotation.from_euler("y", theta)
    r0 = Rotation.from_matrix(np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]))
    rot = ry * r0
    n, t = ry.apply([0.0, 0.0, 1.0]), ry.apply([1.0, 0.0, 0.0])
    pos = np.asarray(pbi.INCLINE_POS) + (pbi.INCLINE_HALF[2] + extent) * n + s * t
    xyzw = rot.as_quat()
    return pos, np.array([xyzw[3], *xyzw[:3]]), t


def contact_extent(shape: pbi.ObjectShape) -> float:
    """Distance from the object's centre to the face it lies on in bulb's start orientation."""
    if shape.kind == "box":
        return float(shape.half_extents[0])
    if shape.kind == "cylinder":
        return float(shape.radius)
    raise ValueError("the analytic slide is defined for the Geom objects (box, cylinders)")


def analytic_acceleration(theta: float, friction: float, mass: float, action: float) -> float:
    """g (sin theta - mu cos theta) + F / m with mu = friction^2 and F = 2 a N along the slope."""
    mu = friction ** 2
    return pbi.GRAVITY * (math.sin(theta) - mu * math.cos(theta)) + pbi.MAX_FORCE * action / mass


# (theta, friction, mass, action): pitch, friction and push (with and against the slide) varied;
# the last one decelerates (a ~ -1 m/s^2: from v0 = 0.5 m/s it stops after ~0.5 s, beyond the fit)
ANALYTIC_CASES = (
    (0.30, 0.30, 0.20, 0.0), (0.45, 0.30, 0.20, 0.0), (0.40, 0.10, 0.20, 0.0), (0.40, 0.50, 0.20, 0.0),
    (0.40, 0.30, 0.10, 0.5), (0.40, 0.30, 0.40, -0.5), (0.25, 0.45, 0.30, 0.0), (0.30, 0.45, 0.30, -0.3),
)


def fit_acceleration(speed_along: np.ndarray, dt: float, skip: int = 1) -> np.ndarray:
    """Least-squares slope of the along-slope velocity [T + 1, n] from step `skip` on."""
    t = np.arange(speed_along.shape[0]) * dt
    return np.polyfit(t[skip:], speed_along[skip:], 1)[0]


def analytic_check(mirror: InclineMirror, cfg: InclineParityConfig, steps: int = 6, skip: int = 1,
                   cases: tuple[tuple[float, float, float, float], ...] = ANALYTIC_CASES) -> dict[str, Any]:
    """Measured slide acceleration in each simulator vs the analytic one (see module docstring)."""
    cases = cases[:cfg.worlds]
    shape = pbi.object_shape(pbi.incline_domain(cfg.name), cfg.version, cfg.ycb_dir, cfg.cache_dir)
    extent = contact_extent(shape)
    dt = pbi.BULLET_DT * pbi.STEPS_PER_ACTION
    v0 = cfg.analytic_v0
    params, starts, tangents = [], [], []
    for theta, fric, mass, _ in cases:
        params.append(pbi.InclineParams(mass, fric, theta, 0, 0.0, 0.1))
        pos, quat, t = on_incline_pose(theta, extent)
        starts.append(np.concatenate([pos, quat, v0 * t, np.zeros(3)]))
        tangents.append(t)
    starts_a, tang = np.stack(starts), np.stack(tangents)
    acts = np.repeat(np.array([c[3] for c in cases])[None], cfg.steps, 0)
    mj = mirror.play(mirror.place(params, starts_a[:, :7], starts_a[:, 7:13]), acts)[: steps + 1, :len(cases)]
    out: dict[str, Any] = {"v0": v0, "steps": steps, "fit_from_step": skip, "dt": dt, "cases": []}
    runs = {"mjx": mj}
    for label, damping in (("pybullet", True), ("pybullet_no_damping", False)):
        side = BulletSide(cfg, bullet_damping=damping)
        runs[label] = side.play(params, acts[:steps], starts_a)
        side.close()
    along = {k: np.einsum("tnk,nk->tn", r[..., 7:10], tang) for k, r in runs.items()}
    acc = {k: fit_acceleration(v, dt, skip) for k, v in along.items()}
    for i, (theta, fric, mass, a) in enumerate(cases):
        expect = analytic_acceleration(theta, fric, mass, a)
        v_mid = float(np.mean(along["pybullet"][1:, i]))
        row = {"theta": theta, "friction": fric, "mass": mass, "action": a, "analytic": expect,
               "analytic_with_bullet_damping": expect - pbi.BULLET_DAMPING * v_mid * (1 + abs(v_mid))}
        for k, v in acc.items():
            row[k] = float(v[i])
        out["cases"].append(row)
    for k in acc:
        ref = "analytic_with_bullet_damping" if k == "pybullet" else "analytic"
        err = np.array([abs(r[k] - r[ref]) for r in out["cases"]])
        out[f"{k}_max_abs_err"] = float(err.max())
        out[f"{k}_max_rel_err"] = float(max(e / max(abs(r[ref]), 0.5) for e, r in zip(err, out["cases"])))
        out[f"{k}_vs_analytic_without_damping_max_abs_err"] = float(
            max(abs(r[k] - r["analytic"]) for r in out["cases"]))
    return out


# ---------------------------------------------------------------------------------- frames
def compare_frames(cfg: InclineParityConfig, seed: int = 0, keep_frames: bool = False) -> dict[str, Any]:
    """Frames of the same states in both renderers: the MJX env (rendering on) resets `worlds`
    bulb draws, PyBullet is put in each post-reset state; the object's pixels (PyBullet's
    segmentation; MJX: pixels that change when the object is parked out of view) compared by
    IoU and centroid distance, and the whole frames by mean absolute RGB difference (lighting and
    the renderers differ; the plane/incline/object colours are the same numbers)."""
    import jax
    import jax.numpy as jnp

    import bulbjax

    env = bulbjax.make(cfg.name, num_envs=cfg.worlds, version=cfg.version, render=True,
                       **({"ycb_dir": cfg.ycb_dir} if cfg.ycb_dir else {}))
    rng = np.random.default_rng(seed + 11)
    params = [pbi.draw_params(rng) for _ in range(cfg.worlds)]
    fixed = {k: jnp.asarray([getattr(p, k) for p in params]) for k in pbi.RESET_FIELDS}
    fixed["texture"] = fixed["texture"].astype(jnp.int32)
    state = jax.jit(lambda k, fx: env.reset_with(k, **fx))(jax.random.PRNGKey(seed), fixed)
    ri = state.render_input
    parked = ri.replace(qpos=jnp.broadcast_to(env._qpos_park, ri.qpos.shape))
    render = jax.jit(env.render_frames)
    mj_frames = np.asarray(render(ri)).astype(int)
    mj_mask = np.abs(mj_frames - np.asarray(render(parked)).astype(int)).sum(-1) > 30
    raw = np.asarray(state.info["lowdim_raw"], np.float64)
    side = pbi.InclineBulletEnv(cfg.name, cfg.version, resolution=env.resolution, ycb_dir=cfg.ycb_dir,
                                cache_dir=cfg.cache_dir)
    rows, pb_frames = [], []
    for i, pr in enumerate(params):
        side.place(pr)
        side.set_pose_velocity(raw[i, :3], raw[i, 3:7], raw[i, 7:10], raw[i, 10:13])
        pb_frame = side.render().astype(int)
        pb_frames.append(pb_frame)
        pb_mask = side.object_mask()
        inter, union = (pb_mask & mj_mask[i]).sum(), (pb_mask | mj_mask[i]).sum()
        c_pb = np.argwhere(pb_mask).mean(0) if pb_mask.any() else np.full(2, np.nan)
        c_mj = np.argwhere(mj_mask[i]).mean(0) if mj_mask[i].any() else np.full(2, np.nan)
        rows.append({"iou": float(inter / max(union, 1)), "centroid_px": float(np.linalg.norm(c_pb - c_mj)),
                     "pixels_pybullet": int(pb_mask.sum()), "pixels_mjx": int(mj_mask[i].sum()),
                     "mean_abs_rgb": float(np.abs(pb_frame - mj_frames[i]).mean())})
    side.close()
    out = {"worlds": rows, "mean_iou": float(np.mean([r["iou"] for r in rows])),
           "max_centroid_px": float(np.nanmax([r["centroid_px"] for r in rows])),
           "mean_abs_rgb": float(np.mean([r["mean_abs_rgb"] for r in rows]))}
    if keep_frames:  # [N, H, W, 3] uint8 each, for looking at them
        out["_frames"] = {"pybullet": np.stack(pb_frames).astype(np.uint8), "mjx": mj_frames.astype(np.uint8)}
    return out


# ---------------------------------------------------------------------------------- policy transfer
def paired_policy_returns(cfg: InclineParityConfig, policy: Callable[[Any, Any], Any], episodes: int | None = None,
                          seed: int = 1) -> dict[str, Any]:
    """Returns of a deterministic policy `(states [N, D], key) -> actions [N, 1]` (jittable, e.g.
    `pybullet_compat.transfer.policy_fn`) over the same `episodes` bulb draws in both simulators
    (PyBullet: `reset(**draws)`; MJX: `reset_with` the same draws), each closed loop on its own
    state until its episode ends: a paired transfer comparison."""
    import jax
    import jax.numpy as jnp

    import bulbjax

    n = episodes or cfg.worlds
    rng = np.random.default_rng(seed + 23)
    params = [pbi.draw_params(rng) for _ in range(n)]
    env = bulbjax.make(cfg.name, num_envs=n, version=cfg.version, render=False,
                       **({"ycb_dir": cfg.ycb_dir} if cfg.ycb_dir else {}))
    fixed = {k: jnp.asarray([getattr(p, k) for p in params]) for k in pbi.RESET_FIELDS}
    fixed["texture"] = fixed["texture"].astype(jnp.int32)
    steps = env.episode_length

    @jax.jit
    def run_mjx(key: jax.Array, fx: dict[str, jax.Array]) -> tuple[jax.Array, jax.Array]:
        def body(es, k):
            es = env.step(es, policy(es.obs, k))
            return es, (es.done, es.info["episode_return"])
        k0, k1 = jax.random.split(key)
        return jax.lax.scan(body, env.reset_with(k0, **fx), jax.random.split(k1, steps))[1]

    done, ret = (np.asarray(x) for x in run_mjx(jax.random.PRNGKey(seed), fixed))
    mj = ret[np.argmax(done > 0, axis=0), np.arange(n)]
    pi = jax.jit(policy)
    side = pbi.InclineBulletEnv(cfg.name, cfg.version, render=False, ycb_dir=cfg.ycb_dir, cache_dir=cfg.cache_dir)
    pb = []
    for pr in params:
        _, s = side.reset(**asdict(pr))
        while True:
            r = side.step(np.asarray(pi(jnp.asarray(s[None]), jax.random.PRNGKey(0)))[0])
            s = r.state
            if r.terminated or r.truncated:
                pb.append(r.info["episode_return"])
                break
    side.close()
    pb_a = np.asarray(pb)
    return {"episodes": n, "pybullet": pb_a.round(3).tolist(), "mjx": mj.round(3).tolist(),
            "pybullet_mean": float(pb_a.mean()), "mjx_mean": float(mj.mean()),
            "mean_abs_paired_diff": float(np.abs(pb_a - mj).mean()),
            "corr": float(np.corrcoef(pb_a, mj)[0, 1]) if pb_a.std() > 0 and mj.std() > 0 else None}


# ---------------------------------------------------------------------------------- report
def run(cfg: InclineParityConfig, log: Callable[[str], None] = print, frames: bool = False) -> dict[str, Any]:
    """Every comparison for one Incline domain/version (`frames`: also `compare_frames`)."""
    t0 = time.time()
    mirror = InclineMirror(cfg)
    report: dict[str, Any] = {"config": asdict(cfg), "dt": pbi.BULLET_DT * pbi.STEPS_PER_ACTION}
    log(f"{cfg.name} v{cfg.version}: MJX mirror of {cfg.worlds} worlds built ({time.time() - t0:.0f} s)")
    bullet = BulletSide(cfg)
    report["pybullet_dynamics"] = {k: v for k, v in bullet.env.dynamics().items()}
    report["analytic"] = analytic_check(mirror, cfg) if cfg.name.startswith("Geom") else {"skipped": "YCB meshes"}
    log("analytic: " + analytic_line(report["analytic"]))
    report["trajectories"] = compare_trajectories(mirror, bullet, cfg)
    for kind in ("zero", "random"):
        for setup in ("same_state", "own_reset"):
            log(f"trajectories {kind} {setup}: " + trajectory_line(report["trajectories"][kind][setup]))
    for label, damping, inertia in (("no_damping", False, "bullet"), ("mirror_inertia", True, "mirror")):
        alt = BulletSide(cfg, bullet_damping=damping, inertia=inertia)
        report["trajectories"]["zero"][f"same_state_{label}"] = _same_state_only(mirror, alt, cfg, report)
        alt.close()
        log(f"trajectories zero same_state {label}: " + trajectory_line(report["trajectories"]["zero"][f"same_state_{label}"]))
    report["sweeps"] = sweeps(mirror, bullet, cfg)
    for param in ("friction", "mass", "theta"):
        log(f"sweep {param}: " + sweep_line(report["sweeps"][param]))
    bullet.close()
    if frames:
        report["frames"] = compare_frames(cfg)
        f = report["frames"]
        log(f"frames: object mask IoU {f['mean_iou']:.2f} (mean), centroids within {f['max_centroid_px']:.1f} px, "
            f"mean |RGB difference| {f['mean_abs_rgb']:.1f}")
    report["seconds_taken"] = round(time.time() - t0, 1)
    return report


def _same_state_only(mirror: InclineMirror, side: BulletSide, cfg: InclineParityConfig,
                     report: dict[str, Any]) -> dict[str, Any]:
    params = [pbi.InclineParams(**p) for p in report["trajectories"]["params"]]
    state = mirror.reset(params)
    acts = action_sequences(cfg.steps, cfg.worlds, cfg.seed)["zero"]
    mj = mirror.play(state, acts)
    return trajectory_errors(side.play(params, acts, mirror.raw(state)[:, :13]), mj,
                             pbi.BULLET_DT * pbi.STEPS_PER_ACTION, cfg.checkpoints)


def analytic_line(a: dict[str, Any]) -> str:
    if "skipped" in a:
        return a["skipped"]
    return (f"max |a - analytic| MJX {a['mjx_max_abs_err']:.3f}, PyBullet (with its damping) "
            f"{a['pybullet_max_abs_err']:.3f}, PyBullet without damping {a['pybullet_no_damping_max_abs_err']:.3f} m/s^2")


def trajectory_line(r: dict[str, Any]) -> str:
    cells = " ".join(f"{k}: d {r['distance']['at'][k] if r['distance']['at'][k] is not None else float('nan'):.4f} "
                     f"v {r['speed']['at'][k] if r['speed']['at'][k] is not None else float('nan'):.4f} |"
                     for k in r["distance"]["at"])
    return f"{cells} max d {r['distance']['max_abs']:.4f} v {r['speed']['max_abs']:.4f}"


def sweep_line(r: dict[str, Any]) -> str:
    return (f"MJX {r['mjx_distance']} PyBullet(same state) {r['pybullet_distance_same_state']} "
            f"max diff {r['same_state_max_abs_diff']:.4f} (own reset {r['own_reset_max_abs_diff']:.4f}), "
            f"same trend {r['same_trend']}, spearman {r['spearman_same_state']:.2f}")


def print_tables(report: dict[str, Any]) -> None:
    """Markdown tables of the headline numbers of every run in `report['runs']`."""
    print("\n| run | push | set-up | distance err 0.2 / 0.4 / 0.8 s (m) | speed err 0.2 / 0.4 / 0.8 s (m/s) | max d / v |")
    print("|---|---|---|---|---|---|")
    fmt = lambda v: "-" if v is None else f"{v:.4f}"  # noqa: E731
    for run_name, r in report["runs"].items():
        for kind in ("zero", "random"):
            for setup, res in r["trajectories"][kind].items():
                d, v = res["distance"], res["speed"]
                cells = [" / ".join(fmt(x[k]) for k in ("0.2s", "0.4s", "0.8s")) for x in (d["at"], v["at"])]
                print(f"| {run_name} | {kind} | {setup} | {cells[0]} | {cells[1]} | "
                      f"{d['max_abs']:.4f} / {v['max_abs']:.4f} |")
    print("\n| run | sweep | MJX distance | PyBullet distance (same state) | max diff same state / own reset | Spearman |")
    print("|---|---|---|---|---|---|")
    for run_name, r in report["runs"].items():
        for param in ("friction", "mass", "theta"):
            w = r["sweeps"][param]
            print(f"| {run_name} | {param} {w['values'][0]:.2f}..{w['values'][-1]:.2f} | "
                  f"{w['mjx_distance'][0]:.3f}..{w['mjx_distance'][-1]:.3f} | "
                  f"{w['pybullet_distance_same_state'][0]:.3f}..{w['pybullet_distance_same_state'][-1]:.3f} | "
                  f"{w['same_state_max_abs_diff']:.4f} / {w['own_reset_max_abs_diff']:.4f} | {w['spearman_same_state']:.2f} |")
    print("\n| run | max abs err of the slide acceleration vs analytic (m/s^2): MJX | PyBullet (bulb, vs analytic - damping) | PyBullet no damping |")
    print("|---|---|---|---|")
    for run_name, r in report["runs"].items():
        a = r["analytic"]
        if "skipped" not in a:
            print(f"| {run_name} | {a['mjx_max_abs_err']:.3f} | {a['pybullet_max_abs_err']:.3f} | "
                  f"{a['pybullet_no_damping_max_abs_err']:.3f} |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--name", default="GeomOnIncline")
    ap.add_argument("--version", type=int, default=0)
    ap.add_argument("--worlds", type=int, default=InclineParityConfig.worlds)
    ap.add_argument("--steps", type=int, default=InclineParityConfig.steps)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--ycb-dir", default=None)
    ap.add_argument("--cache-dir", default=None)
    ap.add_argument("--json", default=DEFAULT_JSON)
    ap.add_argument("--frames", action="store_true", help="also compare frames of the same states (Warp render)")
    ap.add_argument("--frames-only", action="store_true", help="only the frame comparison")
    a = ap.parse_args(argv)
    cfg = InclineParityConfig(name=a.name, version=a.version, worlds=a.worlds, steps=a.steps, seed=a.seed,
                              ycb_dir=a.ycb_dir, cache_dir=a.cache_dir)
    if a.frames_only:
        f = compare_frames(cfg)
        print(json.dumps({k: v for k, v in f.items() if k != "worlds"}))
        return 0
    report = {"versions": _versions(),
              "runs": {f"{cfg.name}-v{cfg.version}": run(cfg, lambda s: print(s, flush=True), frames=a.frames)}}
    if os.path.exists(a.json):  # keep other domains/versions already in the report
        try:
            with open(a.json) as f:
                old = json.load(f)
            report["runs"] = {**old.get("runs", {}), **report["runs"]}
        except (OSError, ValueError):
            pass
    print_tables(report)
    os.makedirs(os.path.dirname(a.json) or ".", exist_ok=True)
    with open(a.json, "w") as f:
        json.dump(report, f, indent=1)
    print(f"wrote {a.json}")
    return 0


def _versions() -> dict[str, str]:
    from pybullet_compat.parity import versions
    return versions()


if __name__ == "__main__":
    sys.exit(main())
