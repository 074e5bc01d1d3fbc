"""The raw MuJoCo Warp probe: the ceiling of an env's step + render, with no JAX and no resets.

For a bulbjax env (its compiled scene `env.mj_model`, its contact and constraint capacities, its
camera and render settings), `probe` runs MuJoCo Warp's own Python API on the same scene:
`frame_skip` x `mujoco_warp.step`, then `refit_bvh` + `render` of the bulb camera at the env's
resolution, per env step, for `worlds` worlds started from a bulbjax reset of that env (so the
objects rest where the env puts them) and held controls drawn once per world. On a GPU the
`steps` env steps are captured in one CUDA graph and launched `repeats` times; on the CPU
(a smoke test) they run as plain calls. Frames/s = worlds x steps / median launch time.

What it leaves out, on purpose: resets (the probe never ends an episode), the state vector and
reward, per-world colours, JAX's FFI dispatch. A bulbjax rate at or near this probe's means the
wrapper adds little; a rate far below it is the wrapper's (resets, dispatch) to explain.

    from raw_warp import probe
    probe("GeomOnIncline", worlds=4096)                   # inside a family bench, same process
"""

from __future__ import annotations

import statistics
import time
from typing import Any

import numpy as np


def probe(name: str, worlds: int, steps: int = 50, repeats: int = 5, resolution: int = 64, seed: int = 0,
          pushed: bool = False, **env_kwargs: Any) -> dict[str, Any]:
    """Rendered frames/s of raw MuJoCo Warp on env `name`'s scene (see the module doc); `warm_s`
    is the first (compiling) pass plus the graph capture, not timed in the rate.

    `pushed` (the Incline only): the workload of the env's episodes rather than of a resting
    scene: each world's incline at its own pitch (the reset's mocap pose), its object pushed by a
    force drawn once per world in bulb's range (+-2 N) along the object's z axis at the start
    (held in the world frame; the env recomputes the axis every substep), and every launch
    starting again from the reset state (a copy inside the graph), so that `steps` of about an
    episode's length (~16) keep the objects on the slope."""
    import jax
    import mujoco
    import mujoco_warp as mjw
    import warp as wp

    import bulbjax
    from bulbjax.envs.render import FRAME_GROUPS, warp_devices

    env = bulbjax.make(name, num_envs=worlds, render=False, resolution=resolution, **env_kwargs)
    state = env.reset(jax.random.PRNGKey(seed))
    mjm = env.mj_model
    devices = warp_devices()
    device = devices[0] if devices else "cpu"
    rng = np.random.default_rng(seed)
    with wp.ScopedDevice(device):
        m = mjw.put_model(mjm)
        # as the env's `_post_put` does for the Incline and locomotion: no in-kernel prints for the
        # intended iteration caps (overflows of contacts and constraints still warn)
        m.opt.warn_overflow &= ~int(mjw.OverflowType.ITERATIONS | mjw.OverflowType.LS_ITERATIONS)
        d = mjw.make_data(mjm, nworld=worlds, njmax=env.njmax, naconmax=env.naconmax_per_world * worlds)
        d.qpos.assign(np.asarray(state.data.qpos, np.float32))
        d.qvel.assign(np.asarray(state.data.qvel, np.float32))
        restart = None
        if pushed:
            from bulbjax.envs.objects.incline import Incline, _quat_mat

            if not isinstance(env, Incline):
                raise ValueError(f"pushed=True is for the Incline domains (their push), not {name}")
            d.mocap_pos.assign(np.asarray(state.data.mocap_pos, np.float32))
            d.mocap_quat.assign(np.asarray(state.data.mocap_quat, np.float32))
            slot = np.asarray(env._slot(state.params))
            body = env._obj_bodies[slot]
            qpos, adr = np.asarray(state.data.qpos), env._obj_qadr[slot]
            quat = np.stack([qpos[i, a + 3:a + 7] for i, a in enumerate(adr)])
            axis = np.asarray(jax.vmap(_quat_mat)(quat))[:, :, 2]  # each object's z axis
            xfrc = np.zeros((worlds, mjm.nbody, 6), np.float32)
            xfrc[np.arange(worlds), body, :3] = rng.uniform(-2.0, 2.0, (worlds, 1)) * axis
            d.xfrc_applied.assign(xfrc)
            restart = (wp.clone(d.qpos), wp.clone(d.qvel))
        if mjm.nu:
            lo, hi = mjm.actuator_ctrlrange[:, 0], mjm.actuator_ctrlrange[:, 1]
            limited = mjm.actuator_ctrllimited.astype(bool)
            lo, hi = np.where(limited, lo, -1.0), np.where(limited, hi, 1.0)
            d.ctrl.assign(rng.uniform(lo, hi, (worlds, mjm.nu)).astype(np.float32))
        cam = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_CAMERA, "bulb")
        rc = mjw.create_render_context(mjm, nworld=worlds, cam_res=(resolution, resolution), render_rgb=True,
                                       render_depth=False, use_textures=True, use_shadows=False,
                                       cam_active=[cam] if cam >= 0 else None,
                                       enabled_geom_groups=list(FRAME_GROUPS), background_color=(1.0, 1.0, 1.0, 1.0))
        skip = int(getattr(env, "frame_skip", 1))

        def run() -> None:
            if restart is not None:  # every launch from the reset state (pushed)
                wp.copy(d.qpos, restart[0])
                wp.copy(d.qvel, restart[1])
            for _ in range(steps):
                for _ in range(skip):
                    mjw.step(m, d)
                mjw.refit_bvh(m, d, rc)
                mjw.render(m, d, rc)

        t0 = time.perf_counter()
        graph = None
        run()  # loads (compiles) every kernel module before timing or capturing
        wp.synchronize_device(device)
        if device != "cpu":
            with wp.ScopedCapture(device=device) as cap:
                run()
            graph = cap.graph
        warm = time.perf_counter() - t0
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            wp.capture_launch(graph) if graph is not None else run()
            wp.synchronize_device(device)
            times.append(time.perf_counter() - t)
    call = statistics.median(times)
    return {"env": name, "worlds": worlds, "steps": steps, "frame_skip": skip, "resolution": resolution,
            "device": str(device), "cuda_graph": graph is not None, "pushed": pushed, "warm_s": warm, "call_s": call,
            "call_times_s": times, "frames_per_s": worlds * steps / call,
            "finite": bool(np.isfinite(d.qpos.numpy()).all())}


if __name__ == "__main__":  # smoke test: python benchmarks/raw_warp.py GeomOnIncline 8 3
    import json
    import sys

    args = sys.argv[1:]
    print(json.dumps(probe(args[0] if args else "GeomOnIncline", int(args[1]) if len(args) > 1 else 8,
                           steps=int(args[2]) if len(args) > 2 else 3, repeats=2), indent=1))
