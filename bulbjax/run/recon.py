"""Reconstruction figures of a run (`bulbjax run --recon-every N`, `bulbjax recon RUN_DIR`).

`RunFigures(exp)` draws, from a `RunState`, the paper's Fig. 4 grid (`recon_<epoch>.png`: true
frames above every learner's reconstruction) and, when SPAIR is among the learners, Fig. 5
(`boxes_<epoch>.png`), with `bulbjax.report.figures`. `<epoch>` is the number of epochs done,
as the checkpoints count them. The frames are held out: one window of `eval_length` steps from
each of the current policy's held-out worlds, rolled out from `rs.curr_env` by a separate jitted
call whose result is thrown away, so drawing figures leaves the run's state and key chain (and
so its metrics and resumes) unchanged. The rollout's key depends only on the run's seed and the
epoch: a figure redrawn from a checkpoint (`redraw_figures`) is the figure the run drew at that
epoch.

In the domains with objects (Rearrange) each drawing also writes `regions_<epoch>.json`: every
reconstructing learner's error per object region (`bulbjax.eval.regions`) on `REGION_FRAMES`
held-out frames of every seed the drawing process holds (one process: all seeds), which the
Fig. 5 claim "on YCB no learner's reconstruction is clear" reads (`findings_objects`).
"""

from __future__ import annotations

import glob
import json
import math
import os
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp

import numpy as np

from bulbjax.config import read_run_config
from bulbjax.data.sequence import Windows
from bulbjax.epoch import Experiment, RunState, object_pixels
from bulbjax.eval import objects, regions
from bulbjax.report import FigureConfig, boxes_figure, recon_figure, reconstructions, seed_params, spair_names
from bulbjax.run.checkpoint import CHECKPOINT_DIR, Checkpointer

RECON = "recon_{epoch}.png"
BOXES = "boxes_{epoch}.png"
REGIONS = regions.FILE
REGION_FRAMES = 64  # held-out frames per seed of the per-object reconstruction error
_FIGURE_TAG = 0x5EC0  # folded into the run's seed: a key stream of its own


def figure_files(run_dir: str) -> list[str]:
    """The figure PNGs and region errors in `run_dir` (removed when a fresh run starts there)."""
    return sorted(glob.glob(os.path.join(run_dir, "recon_*.png")) + glob.glob(os.path.join(run_dir, "boxes_*.png"))
                  + glob.glob(os.path.join(run_dir, "regions_*.json")))


class RunFigures:
    """Draws a run's figures from its RunState for one seed's learners (`config.seed`), the
    learners named in `learners` (default all that have `reconstruct`; an unknown name, or one
    without `reconstruct`, is an error)."""

    def __init__(self, exp: Experiment, run_seed: int = 0, config: FigureConfig = FigureConfig(),
                 learners: Sequence[str] | None = None):
        self.exp, self.run_seed, self.config = exp, run_seed, config
        # learners without `reconstruct` (contrastive ones) have no row unless named
        names = ([n for n, l in exp.learners.items() if hasattr(l, "reconstruct")] if learners is None
                 else list(learners))
        if not names and learners is None:
            raise ValueError(f"none of this run's learners ({', '.join(exp.learners)}) reconstructs frames: "
                             "no reconstruction figure to draw")
        unknown = [n for n in names if n not in exp.learners]
        if unknown or not names:
            raise ValueError(f"learners {unknown or names} are not in this run; it has "
                             f"{', '.join(exp.learners)} (pick some of those with --learners)")
        if not 0 <= config.seed < exp.config.seeds:
            raise ValueError(f"figure seed {config.seed}: the run has seeds 0..{exp.config.seeds - 1}")
        blind = [n for n in names if not hasattr(exp.learners[n], "reconstruct")]
        if blind:
            raise ValueError(f"learners {blind} do not reconstruct frames: no reconstruction figure for them")
        self.learners = {n: exp.learners[n] for n in names}
        self.objects = object_pixels(exp.env)
        le = exp.eval_length
        self._k_figure = min(exp.N, math.ceil(config.frames / le))
        self._k = max(self._k_figure, min(exp.N, math.ceil(REGION_FRAMES / le)) if self.objects else 0)
        self._held = jax.jit(self._held_out)

    def _held_out(self, ppo: Any, curr_env: Any, learners: dict | None, history: Any, key: jax.Array) -> Windows:
        """One window of `eval_length` steps per held-out world of the current policy (from
        the run state's `curr_env`, which is not updated), every seed's first few windows
        `[S, k, ...]`. Only the parts it reads: with the learners apart (`--overlap apart`) the
        state lies on two devices."""
        exp, le = self.exp, self.exp.eval_length
        # Experiment's own rollout and window cutting (as its eval phase), one round only.
        extra = {"learners": learners} if exp.policy.rl_learner else {}  # PPO on a latent
        if history is not None:  # ... of a sequential learner: the worlds' windows go on from the run's
            extra["history"] = history
        _, steps = exp.policy.rollout(ppo, curr_env, key, le, random=False, **extra)
        starts = jnp.zeros((1, exp.S * exp.N), jnp.int32)
        w = exp.streams.windows(steps, starts, le)  # [S, N, L, ...]
        return jax.tree.map(lambda x: x[:, : self._k], w)

    def key(self, epoch: int) -> jax.Array:
        return jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(self.run_seed), _FIGURE_TAG), epoch)

    def held_out(self, rs: RunState, epoch: int) -> Windows:
        """Host copy of the held-out windows the figures of `epoch` show."""
        return jax.tree.map(lambda x: x[self.config.seed, : self._k_figure], self._held_all(rs, epoch))

    def _held_all(self, rs: RunState, epoch: int) -> Windows:
        learners = rs.learners if self.exp.policy.rl_learner else None
        history = rs.policy_history["curr"] if rs.policy_history else None
        key = self.exp.put_key(self.key(epoch))
        return jax.device_get(self._held(rs.ppo, rs.curr_env, learners, history, key))

    def regions(self, rs: RunState, windows: Windows) -> dict[str, Any]:
        """Each learner's reconstruction error per object region (`bulbjax.eval.regions`) on the
        first `REGION_FRAMES` held-out frames of every seed (`windows` `[S, k, L, ...]`):
        `{"objects", "radius_px", "frames", "learners": {name: {"ratio"|"error"|"baseline":
        [S][M]}}}`."""
        names, pixels = self.objects
        radius = objects.default_radius(self.exp.config.resolution)
        seeds = jax.tree.leaves(windows)[0].shape[0]
        out: dict[str, dict[str, list]] = {n: {"ratio": [], "error": [], "baseline": []} for n in self.learners}
        frames_n = 0
        for s in range(seeds):
            w = jax.tree.map(lambda x: x[s], windows)
            params = jax.device_get(seed_params({n: rs.learners[n] for n in self.learners}, s))
            frames, recons = reconstructions(self.learners, params, w, REGION_FRAMES)
            frames_n = frames.shape[0]
            states = np.asarray(w.states).reshape((-1, w.states.shape[-1]))[:frames_n]
            pos = np.asarray(pixels(states))
            for n, rec in recons.items():
                sc = regions.region_scores(frames, rec, pos, radius)
                for k in ("ratio", "error", "baseline"):
                    out[n][k].append(sc[k])
        return {"objects": list(names), "radius_px": radius, "frames": frames_n, "seeds": seeds,
                "clear_below": regions.CLEAR, "learners": out}

    def draw(self, rs: RunState, out_dir: str, epoch: int) -> list[str]:
        """Write `recon_<epoch>.png` (and `boxes_<epoch>.png` per SPAIR learner) into
        `out_dir`; returns their paths."""
        every = self._held_all(rs, epoch)
        w = jax.tree.map(lambda x: x[self.config.seed, : self._k_figure], every)
        params = seed_params({n: rs.learners[n] for n in self.learners}, self.config.seed)
        params = jax.device_get(params)
        what = f"{self.exp.config.env}, epoch {epoch}, seed {self.config.seed}: held-out frames (current policy)"
        os.makedirs(out_dir, exist_ok=True)
        path = os.path.join(out_dir, RECON.format(epoch=epoch))
        recon_figure(path, self.learners, params, w, self.config, title=what)
        paths = [path]
        spairs = spair_names(self.learners)
        for name in spairs:
            suffix = "" if len(spairs) == 1 else f"_{name}"
            p = os.path.join(out_dir, BOXES.format(epoch=epoch).replace(".png", f"{suffix}.png"))
            boxes_figure(p, self.learners[name], params[name], w, self.config, title=f"{name}: {what}")
            paths.append(p)
        if self.objects is not None:
            p = os.path.join(out_dir, REGIONS.format(epoch=epoch))
            with open(p, "w") as f:
                json.dump({"epoch": epoch, **self.regions(rs, every)}, f)
            paths.append(p)
        return paths


def _devices_of(raw: dict[str, Any], run_dir: str) -> list[jax.Device]:
    """As many local devices as the run's mesh had (a checkpoint restores on that count only)."""
    mesh = raw.get("provenance", {}).get("mesh")
    n = math.prod(mesh.values()) if mesh else 1
    if raw.get("experiment", {}).get("overlap") == "apart":  # and the learners' device
        n += 1
    local = jax.local_devices()
    if n > len(local):
        raise ValueError(f"{run_dir} ran on {n} devices ({mesh}); its checkpoints restore on as many, "
                         f"this machine has {len(local)}")
    return local[:n]


def redraw_figures(run_dir: str, epoch: int | None = None, learners: Sequence[str] | None = None,
                   config: FigureConfig = FigureConfig(), out_dir: str | None = None,
                   experiment: Experiment | None = None, log: Callable[[str], None] = print) -> list[str]:
    """Redraw a run's figures from its newest checkpoint (or that of `epoch` epochs done) into
    `out_dir` (default `run_dir`); returns the paths written. `experiment` reuses a built
    `Experiment` of the run's config (tests)."""
    if not os.path.exists(os.path.join(run_dir, "config.json")):
        raise ValueError(f"{run_dir} is not a run folder (no config.json); give the --out of a `bulbjax run`")
    cfg, raw = read_run_config(run_dir)
    ck_dir = os.path.join(run_dir, CHECKPOINT_DIR)
    ckpt = Checkpointer(run_dir) if os.path.isdir(ck_dir) else None
    steps = ckpt.steps() if ckpt else []
    if not steps:
        raise ValueError(f"no checkpoint in {ck_dir}: `bulbjax recon` draws from a checkpoint. A run writes "
                         "one when it stops (its last epoch, --max-minutes, --stop-after, SIGINT/SIGTERM) and "
                         f"every --checkpoint-every N epochs; continue it with `bulbjax run --resume {run_dir}` "
                         "to get one, or use --recon-every N in the run itself")
    if epoch is not None and epoch not in steps:
        raise ValueError(f"no checkpoint of epoch {epoch} in {ck_dir}; there are {steps} "
                         "(older ones are dropped beyond --keep)")
    if experiment is not None and experiment.config != cfg:
        raise ValueError("redraw_figures(experiment=...) was built for another config than the run's")
    exp = experiment or Experiment(cfg, devices=_devices_of(raw, run_dir))
    figs = RunFigures(exp, run_seed=int(raw.get("run", {}).get("seed", 0)), config=config, learners=learners)
    try:
        state, _, got = ckpt.restore({"run": exp.abstract_state(), "key": exp.abstract_key()}, epoch)
    finally:
        ckpt.close()
    paths = figs.draw(state["run"], out_dir or run_dir, got)
    log(f"epoch {got} of {run_dir}: " + ", ".join(paths))
    return paths
