"""Parity suite: bulbjax's MJX mirrors against the PyBullet originals, from the same states.

For each domain: draw starting states from the PyBullet env's own reset distribution, put both
simulators there, play the same action sequences (zero, random, and for the pendulums a PPO
policy's, closed loop in each simulator on its own state) and report
- per-entry absolute state error at 0.5 s, 1 s and 2 s (mean over starts), and the time until the
  trajectories diverge (first time any entry differs by more than `diverge_tol`, median),
- return difference (each up to its own episode end) and termination agreement (same step),
- for every sequence, per-entry mean and spread of the visited states in each simulator and
  two-sample statistics (Kolmogorov-Smirnov, energy distance), the right measure for
  locomotion, where contacts make single trajectories diverge;
- the masses, inertias and joint damping each simulator actually uses (`model_comparison`;
  `patch_mirror` edits the MJX model to test a suspected cause of a gap).

`python -m pybullet_compat.parity [--domains ...] [--json docs/parity/parity_report.json]`.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from typing import Any, Callable

import numpy as np

from pybullet_compat.envs import DOMAINS, BulletPixelEnv, domain

PENDULUMS = ("CartPole", "InvertedPendulum")
LOCOMOTION = ("HalfCheetah", "Ant")
DEFAULT_JSON = os.path.join("docs", "parity", "parity_report.json")


@dataclass(frozen=True)
class ParityConfig:
    """Sizes of the comparison (defaults: a few minutes on a 2-core CPU for all four domains)."""

    starts: int = 8  # starting states (PyBullet reset seeds seed .. seed + starts - 1)
    seconds: float = 2.0  # horizon of each trajectory
    checkpoints: tuple[float, ...] = (0.5, 1.0, 2.0)
    diverge_tol: float = 0.1  # state units (rad, m, m/s, or bulb's scaled locomotion units)
    seed: int = 0
    sequences: tuple[str, ...] = ("zero", "random", "policy")
    policy_updates: dict[str, int] = field(default_factory=lambda: {"CartPole": 100, "InvertedPendulum": 30})


# ---------------------------------------------------------------------------------- starts
def pybullet_starts(name: str, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(qpos [n, nq], qvel [n, nv]) of PyBullet resets with seeds seed .. seed + n - 1."""
    env = BulletPixelEnv(name, render=False)
    qs, vs = [], []
    for i in range(n):
        env.reset(seed=seed + i)
        q, v = env.get_qpos_qvel()
        qs.append(q)
        vs.append(v)
    env.close()
    return np.stack(qs), np.stack(vs)


def clip_to_joint_ranges(mirror: Any, qpos: np.ndarray, frac: float = 0.9) -> np.ndarray:
    """Joint positions moved inside `frac` of each limited hinge's range (the mirror's model).

    PyBullet's walker reset draws every joint in +-0.1 rad, outside the range of HalfCheetah's
    ffoot and Ant's ankles; there MuJoCo's limit constraint kicks the joint back into range in one
    step (~7 rad/s) while Bullet leaves it, so locomotion trajectories start from in-range states."""
    import mujoco

    m = mirror.env.mj_model
    qpos = qpos.copy()
    for j in range(m.njnt):
        if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE and m.jnt_limited[j]:
            lo, hi = m.jnt_range[j]
            mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
            a = m.jnt_qposadr[j]
            qpos[:, a] = np.clip(qpos[:, a], mid - frac * half, mid + frac * half)
    return qpos


def action_sequence(name: str, kind: str, steps: int, n: int, seed: int = 0) -> np.ndarray:
    """[steps, n, ...] actions: 'zero' (no force; CartPole, which has only +-10 N, alternates
    left/right so the mean force is zero) or 'random' (uniform, same draws for both simulators)."""
    spec = domain(name)
    rng = np.random.default_rng(seed)
    if spec.discrete:
        if kind == "zero":
            return np.broadcast_to((np.arange(steps) % 2)[:, None], (steps, n)).astype(np.int32).copy()
        return rng.integers(0, spec.num_actions, (steps, n)).astype(np.int32)
    if kind == "zero":
        return np.zeros((steps, n, spec.action_size), np.float32)
    return rng.uniform(-1.0, 1.0, (steps, n, spec.action_size)).astype(np.float32)


# ---------------------------------------------------------------------------------- PyBullet side
def pybullet_play(name: str, qpos: np.ndarray, qvel: np.ndarray, steps: int,
                  actions: np.ndarray | None = None,
                  policy: Callable[[np.ndarray], np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """PyBullet from each (qpos[i], qvel[i]) for `steps` steps, open loop (`actions` [T, n, ...])
    or closed loop (`policy(state [D]) -> action`); it keeps stepping after an episode ends, as
    the mirror's physics path does. Returns state [T, n, D], reward, terminated [T, n]."""
    n = qpos.shape[0]
    env = BulletPixelEnv(name, render=False)
    states = np.zeros((steps, n, env.spec.state_dim), np.float32)
    rewards = np.zeros((steps, n), np.float32)
    term = np.zeros((steps, n), bool)
    acts = []
    for i in range(n):
        _, s = env.set_qpos_qvel(qpos[i], qvel[i])
        run_acts = []
        for t in range(steps):
            a = actions[t, i] if actions is not None else policy(s)
            r = env.step(a)
            s = r.state
            states[t, i], rewards[t, i], term[t, i] = r.state, r.reward, r.terminated
            run_acts.append(np.asarray(a))
        acts.append(np.stack(run_acts))
    env.close()
    return dict(state=states, reward=rewards, terminated=term, action=np.stack(acts, 1))


# ---------------------------------------------------------------------------------- metrics
def _first(mask: np.ndarray) -> np.ndarray:
    """Index of the first True along axis 0 per column, or len when none."""
    any_ = mask.any(0)
    return np.where(any_, mask.argmax(0), mask.shape[0])


def trajectory_metrics(pb: dict[str, np.ndarray], mj: dict[str, np.ndarray], dt: float,
                       names: tuple[str, ...], cfg: ParityConfig) -> dict[str, Any]:
    """Errors over time (max over entries: non-contact entries), divergence (first time a
    non-contact entry differs by more than `diverge_tol`), returns and termination agreement."""
    err = np.abs(pb["state"].astype(np.float64) - mj["state"].astype(np.float64))  # [T, n, D]
    steps = err.shape[0]
    # foot-contact flags are binary and PyBullet's lag one step behind its state (its env updates
    # them after calc_state); they get their own agreement rate and stay out of max / divergence
    contact = np.array([n.endswith("_contact") for n in names])
    cont = ~contact
    at = {}
    for t in cfg.checkpoints:
        k = int(round(t / dt)) - 1
        if 0 <= k < steps:
            e = err[k].mean(0)
            at[f"{t:g}s"] = {"per_entry": dict(zip(names, np.round(e, 5).tolist())), "max_entry": float(e[cont].max())}
    diverged = _first(err[..., cont].max(2) > cfg.diverge_tol)  # [n]
    div_time = (diverged + 1) * dt
    end_pb = _first(pb["terminated"])
    mj_term = (mj["done"] > 0) & (mj["truncated"] == 0)
    end_mj = _first(mj_term)
    both = (end_pb < steps) & (end_mj < steps)
    ret_pb = np.array([pb["reward"][: e + 1, i].sum() for i, e in enumerate(end_pb)])
    ret_mj = np.array([mj["reward"][: e + 1, i].sum() for i, e in enumerate(end_mj)])
    out_contact = ({"contact_flag_agreement": float((err[..., contact] < 0.5).mean())} if contact.any() else {})
    return {
        **out_contact,
        "error_at": at,
        "divergence_time_s": {"median": float(np.median(div_time)), "min": float(div_time.min()),
                              "never_diverged": int((diverged == steps).sum()), "horizon_s": steps * dt},
        "termination": {"same_step": float((end_pb == end_mj).mean()),
                        "both_ended": int(both.sum()),
                        "only_pybullet_ended": int(((end_pb < steps) & (end_mj == steps)).sum()),
                        "only_mjx_ended": int(((end_mj < steps) & (end_pb == steps)).sum()),
                        "mean_abs_step_diff_where_both": float(np.abs(end_pb - end_mj)[both].mean()) if both.any() else None,
                        "pybullet_end_step": end_pb.tolist(), "mjx_end_step": end_mj.tolist()},
        "return": {"pybullet_mean": float(ret_pb.mean()), "mjx_mean": float(ret_mj.mean()),
                   "mean_abs_diff": float(np.abs(ret_pb - ret_mj).mean())},
    }


def distribution_metrics(a: np.ndarray, b: np.ndarray, names: tuple[str, ...]) -> dict[str, Any]:
    """Per-entry mean/std of two state samples (a: PyBullet, b: MJX; [M, D]) and two-sample
    statistics: Kolmogorov-Smirnov D (0 same, 1 disjoint) and energy distance on the entry
    standardised by the pooled spread (0 same)."""
    from scipy import stats

    out = {}
    for d, nm in enumerate(names):
        x, y = a[:, d].astype(np.float64), b[:, d].astype(np.float64)
        scale = np.concatenate([x, y]).std() + 1e-9
        ks = stats.ks_2samp(x, y)
        out[nm] = {"pybullet_mean": float(x.mean()), "mjx_mean": float(y.mean()),
                   "pybullet_std": float(x.std()), "mjx_std": float(y.std()),
                   "ks": float(ks.statistic), "ks_p": float(ks.pvalue),
                   "energy": float(stats.energy_distance(x / scale, y / scale))}
    ks_all = np.array([v["ks"] for v in out.values()])
    return {"per_entry": out, "median_ks": float(np.median(ks_all)), "max_ks": float(ks_all.max()),
            "worst_entry": names[int(ks_all.argmax())]}


# ---------------------------------------------------------------------------------- models
def pybullet_dynamics(name: str) -> tuple[dict[str, Any], dict[str, float]]:
    """(link masses/inertias, joint damping) as PyBullet simulates domain `name`."""
    env = BulletPixelEnv(name, render=False)
    env.reset(seed=0)
    out = env.link_inertias(), env.joint_damping()
    env.close()
    return out


def model_comparison(name: str, mj_model: Any) -> dict[str, Any]:
    """Mass and principal moments per body and damping per joint as each simulator uses them,
    with the worst relative gaps."""
    import mujoco

    pb, damping = pybullet_dynamics(name)
    joints, worst_d = {}, 0.0
    for jn, d_pb in damping.items():
        jid = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_JOINT, jn)
        if jid >= 0:
            d_mj = float(mj_model.dof_damping[mj_model.jnt_dofadr[jid]])
            joints[jn] = {"pybullet_damping": d_pb, "mjx_damping": d_mj}
            worst_d = max(worst_d, abs(d_mj - d_pb))
    out, worst = {}, 0.0
    for body, (m_pb, i_pb) in pb.items():
        bid = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_BODY, body)
        if bid < 0:
            out[body] = {"pybullet_mass": m_pb, "mjx": None}
            continue
        m_mj, i_mj = float(mj_model.body_mass[bid]), np.sort(mj_model.body_inertia[bid])
        rel = max(abs(m_mj - m_pb) / m_pb, float(np.max(np.abs(i_mj - np.sort(i_pb)) / np.maximum(np.sort(i_pb), 1e-9))))
        worst = max(worst, rel)
        out[body] = {"pybullet_mass": round(m_pb, 5), "mjx_mass": round(m_mj, 5),
                     "pybullet_inertia": np.round(np.sort(i_pb), 6).tolist(), "mjx_inertia": np.round(i_mj, 6).tolist(),
                     "max_rel_diff": round(rel, 4)}
    return {"bodies": out, "max_rel_diff": round(worst, 4), "joints": joints, "max_damping_diff": worst_d}


def patch_mirror(mirror: Any, inertias: dict[str, tuple[float, tuple[float, float, float]]] | None = None,
                 damping: dict[str, float] | None = None, mass_scale: dict[str, float] | None = None,
                 timestep_scale: float = 1.0) -> Any:
    """Edit the mirror's MJX model in place (diagnostics and tests): set bodies' masses and
    principal moments (matched by rank of the moments) and joints' damping, scale masses, or
    scale the timestep."""
    import mujoco
    from mujoco import mjx

    env = mirror.env
    m = env.mj_model
    for body, (mass, moments) in (inertias or {}).items():
        bid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, body)
        if bid < 0:
            continue
        new = np.asarray(moments, np.float64)
        if np.ptp(m.body_inertia[bid]) > 0:  # match principal axes by the rank of the moments
            new = np.empty(3)
            new[np.argsort(m.body_inertia[bid])] = np.sort(moments)
        m.body_mass[bid], m.body_inertia[bid] = mass, new
    for jn, d in (damping or {}).items():
        jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, jn)
        if jid >= 0:
            m.dof_damping[m.jnt_dofadr[jid]] = d
    for body, s in (mass_scale or {}).items():
        bid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, body)
        m.body_mass[bid] *= s
        m.body_inertia[bid] *= s
    m.opt.timestep *= timestep_scale
    env.mx = mjx.put_model(m, impl="warp")
    mirror.dt *= timestep_scale
    return mirror


# ---------------------------------------------------------------------------------- runs
def compare_sequence(name: str, mirror: Any, qpos: np.ndarray, qvel: np.ndarray, kind: str,
                     cfg: ParityConfig, policy: tuple[Any, Any] | None = None) -> dict[str, Any]:
    """One sequence kind from the given starts in both simulators -> metrics (+ raw arrays under '_')."""
    import jax
    import jax.numpy as jnp

    steps = int(round(cfg.seconds / mirror.dt))
    names = mirror.state_names
    if kind == "policy":
        ppo, pstate = policy
        from pybullet_compat.transfer import policy_fn
        pi = policy_fn(ppo, pstate)
        pi_jit = jax.jit(pi)
        key = jax.random.PRNGKey(0)
        pb = pybullet_play(name, qpos, qvel, steps, policy=lambda s: np.asarray(pi_jit(jnp.asarray(s[None]), key))[0])
        mj = mirror.play_policy(qpos, qvel, pi, steps, key, policy_id=(name, id(pstate)))
    else:
        acts = action_sequence(name, kind, steps, qpos.shape[0], cfg.seed)
        pb = pybullet_play(name, qpos, qvel, steps, actions=acts)
        mj = mirror.play(qpos, qvel, acts)
    res = trajectory_metrics(pb, mj, mirror.dt, names, cfg)
    res["distribution"] = distribution_metrics(pb["state"].reshape(-1, len(names)), mj["state"].reshape(-1, len(names)), names)
    res["_"] = {"pb": pb, "mj": mj}
    return res


def run_domain(name: str, cfg: ParityConfig, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Every comparison for one domain (see the module docstring)."""
    from pybullet_compat.mirror import MjxMirror

    t0 = time.time()
    mirror = MjxMirror(name, cfg.starts)
    if tuple(mirror.state_names) != DOMAINS[name].state_names:
        raise AssertionError(f"{name}: state layouts differ: {mirror.state_names} vs {DOMAINS[name].state_names}")
    qpos, qvel = pybullet_starts(name, cfg.starts, cfg.seed)
    if name in LOCOMOTION:
        qpos = clip_to_joint_ranges(mirror, qpos)
    out: dict[str, Any] = {"dt": mirror.dt, "in_range_starts": name in LOCOMOTION, "starts": cfg.starts, "seconds": cfg.seconds,
                           "model": model_comparison(name, mirror.env.mj_model), "sequences": {}}
    policy = None
    if name in PENDULUMS and "policy" in cfg.sequences:
        from pybullet_compat.transfer import TransferConfig, get_policy
        ppo, pstate, meta = get_policy(name, "bulbjax", TransferConfig(updates=cfg.policy_updates.get(name, 30)), log=log)
        policy = (ppo, pstate)
        out["policy"] = {"trained_in": "bulbjax", **meta}
    for kind in cfg.sequences:
        if kind == "policy" and policy is None:
            continue
        res = compare_sequence(name, mirror, qpos, qvel, kind, cfg, policy)
        res.pop("_")
        out["sequences"][kind] = res
        log(f"  {name} {kind}: {summary_line(res)}")
    out["seconds_taken"] = round(time.time() - t0, 1)
    return out


def summary_line(res: dict[str, Any]) -> str:
    at = res["error_at"]
    errs = "  ".join(f"{k}: {v['max_entry']:.3g}" for k, v in at.items())
    d = res["divergence_time_s"]
    t = res["termination"]
    return (f"max entry error {errs} | diverge median {d['median']:.2f}s | same end step {t['same_step']:.2f} | "
            f"return {res['return']['pybullet_mean']:.1f} vs {res['return']['mjx_mean']:.1f} | "
            f"KS median {res['distribution']['median_ks']:.2f}")


def print_table(report: dict[str, Any]) -> None:
    """Markdown table of the headline numbers per domain and sequence."""
    print("\n| domain | sequence | max entry err 0.5 s | 1 s | 2 s | diverge (median) | same end step | "
          "return PyBullet | return MJX | median KS | worst entry (KS) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name, dom in report["domains"].items():
        if "error" in dom:
            print(f"| {name} | - | {dom['error']} |")
            continue
        for kind, r in dom["sequences"].items():
            at = r["error_at"]
            cells = [f"{at[k]['max_entry']:.3g}" if k in at else "-" for k in ("0.5s", "1s", "2s")]
            dist = r["distribution"]
            print(f"| {name} | {kind} | {' | '.join(cells)} | {r['divergence_time_s']['median']:.2f} s | "
                  f"{r['termination']['same_step']:.2f} | {r['return']['pybullet_mean']:.1f} | "
                  f"{r['return']['mjx_mean']:.1f} | {dist['median_ks']:.2f} | "
                  f"{dist['worst_entry']} ({dist['max_ks']:.2f}) |")


def locomotion_available() -> tuple[bool, str]:
    """Whether bulbjax has the HalfCheetah and Ant mirrors yet."""
    try:
        import bulbjax
        names = bulbjax.env_names(with_variants=False) if hasattr(bulbjax, "env_names") else []
    except Exception as err:  # pragma: no cover
        return False, f"bulbjax import failed: {err!r}"
    missing = [n for n in LOCOMOTION if n not in names]
    return (not missing, f"bulbjax has no {', '.join(missing)} mirror yet" if missing else "")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--domains", default=",".join(DOMAINS), help="comma-separated subset of " + ",".join(DOMAINS))
    ap.add_argument("--starts", type=int, default=ParityConfig.starts)
    ap.add_argument("--seconds", type=float, default=ParityConfig.seconds)
    ap.add_argument("--sequences", default="zero,random,policy")
    ap.add_argument("--transfer", action="store_true", help="also run the policy transfer check (pendulums)")
    ap.add_argument("--json", default=DEFAULT_JSON)
    args = ap.parse_args(argv)
    cfg = ParityConfig(starts=args.starts, seconds=args.seconds, sequences=tuple(args.sequences.split(",")))
    report: dict[str, Any] = {"config": {k: v for k, v in asdict(cfg).items()}, "versions": versions(), "domains": {}}
    for name in args.domains.split(","):
        domain(name)
        if name in LOCOMOTION:
            ok, why = locomotion_available()
            if not ok:
                print(f"{name}: skipped ({why})")
                report["domains"][name] = {"error": f"skipped: {why}"}
                continue
        print(f"{name}: comparing {cfg.starts} starts over {cfg.seconds} s", flush=True)
        report["domains"][name] = run_domain(name, cfg, log=lambda s: print(s, flush=True))
    if args.transfer:
        from pybullet_compat.transfer import transfer_report
        report["transfer"] = transfer_report(log=lambda s: print(s, flush=True))
    print_table(report)
    os.makedirs(os.path.dirname(args.json) or ".", exist_ok=True)
    with open(args.json, "w") as f:
        json.dump(report, f, indent=1, default=_json_default)
    print(f"\nwrote {args.json}")
    return 0


def versions() -> dict[str, str]:
    from importlib import metadata
    out = {"python": sys.version.split()[0]}
    for pkg in ("pybullet", "gym", "jax", "mujoco", "mujoco-mjx", "mujoco-warp"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def _json_default(x: Any) -> Any:
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.floating,)):
        return float(x)
    if isinstance(x, np.ndarray):
        return x.tolist()
    return str(x)


if __name__ == "__main__":
    sys.exit(main())
