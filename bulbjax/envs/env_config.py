"""`EnvConfig`, the construction options shared by all domains, and the checks they must pass.

Kept apart from the environment base class (`base.MjxPixelEnv`, which runs `check_config` first
thing in its constructor) so that the options and their limits read in one place. The checks
that depend on the domain (targets, object versions, the reset chunk and pool) stay with the
domain's constructor and `resets.chunk_size` / `resets.pool_multiple`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_RES, MAX_RES = 8, 1024
OBSERVATIONS = ("rgb", "depth", "pointcloud")


@dataclass(frozen=True)
class EnvConfig:
    """Construction options shared by all domains."""

    num_envs: int = 64
    resolution: int = 64
    render: bool = True  # make a renderer; `render_frames` needs it
    render_steps: bool = True  # put frames in every `reset`/`step` state (else pixels are [N,0,0,3])
    multicolour: bool = False
    # What `reset`/`step` observe besides the state: "rgb" (uint8 frames in `pixels`), "depth"
    # (float32 metres in `depth`, with the frames) or "pointcloud" (`points`, bulb's PT mode).
    observation: str = "rgb"
    num_points: int = 1024  # points per cloud ("pointcloud")
    # Multi-object domains: the object version (an int, or "random" to draw one per world and
    # episode) and the folder of the YCB models (default: $BULBJAX_YCB_DIR).
    version: int | str = 0
    ycb_dir: str | None = None
    # Draw the task's targets as visual-only marks (Rearrange: bulb's two target areas on the
    # tray floor). Off by default: bulb's frames show none.
    show_targets: bool = False
    # Ended worlds reset per chunk in `step` (`MjxPixelEnv.reset_chunk`): None, the domain's
    # default (`reset_chunk_fraction`); 0, every world's reset computed and the ended ones kept.
    reset_chunk: int | None = None
    # Ended worlds in `step` take pre-settled initial states from a pool (`resets.reset_from_pool`)
    # of reset_pool * num_envs entries: None, the domain's default (2 for Incline and Rearrange,
    # 0 for the others); 0, no pool (the chunked resets above).
    reset_pool: int | None = None
    # The worlds as this many equal, consecutive blocks (e.g. the experiment's seeds), each with a
    # pool of its own: a block's resets then depend on its own worlds only, so a seed's episodes do
    # not depend on which other seeds share the batch. num_envs must be a multiple of it.
    pool_segments: int = 1
    # How MJX-Warp's calls run on a GPU (`mjx.put_model`'s graph_mode): None, MJX's default ("warp":
    # Warp captures and replays a CUDA graph per call and buffer addresses); "jax" (XLA captures the
    # calls into its own graphs), "warp_staged", "warp_staged_ex" (Warp's graphs over fixed staging
    # buffers) or "none" (no graphs). Same physics; a speed setting (benchmarks/diagnostics/
    # incline_gap.py --graph-modes). The CPU never captures graphs: there it has no effect.
    graph_mode: str | None = None
    # An env step's physics substeps (and the kinematics pass after them) as one MJX-Warp call
    # (`warp_steps.multi_step`) where the action is the same controls at every substep: the same
    # numbers bit for bit, one host callback per env step instead of `frame_skip` + 1 (the
    # locomotion domains: 5). False: MJX's separate calls. A speed setting.
    fuse_substeps: bool = True
    # How `step` gives the worlds it resets their poses (`MjxPixelEnv._poses`), where it does not
    # pass every world through the pose pass anyway: "cond", a `lax.cond` that runs the pass only
    # in steps where some world was reset, or "select", the pass in every step and its result
    # taken by `jnp.where` in those steps: the same numbers. On a GPU XLA reads a cond's predicate
    # on the host, a sync each step; the select pays a pose pass each step instead. "auto"
    # (`pose_select`): the select on a GPU where the pass is the kinematics pass alone (Fig. 5's
    # epoch measured 3% faster), else the cond (HalfCheetah's pass is the full forward pass, and
    # the select measured 6% slower there; a CPU reads no predicate): docs/performance.md, "What
    # each setting does". A speed setting.
    reset_pose_branch: str = "auto"


POSE_BRANCHES = ("auto", "cond", "select")
GRAPH_MODES = ("none", "jax", "warp", "warp_staged", "warp_staged_ex")


def pose_select(branch: str, pose_pass: str, platform: str) -> bool:
    """Whether `step` gives reset worlds their poses by a select (`EnvConfig.reset_pose_branch`):
    "auto" picks it on a GPU ("gpu" `platform`) where `pose_pass` is "kinematics"."""
    if branch == "auto":
        return platform == "gpu" and pose_pass == "kinematics"
    return branch == "select"


def check_config(config: EnvConfig) -> None:
    """Raise a ValueError naming the first option of `config` that no domain accepts."""
    if not isinstance(config.show_targets, (bool, np.bool_)):
        raise ValueError(f"show_targets must be True or False, got {config.show_targets!r}")
    if config.observation not in OBSERVATIONS:
        raise ValueError(f"observation must be one of {OBSERVATIONS}, got {config.observation!r}")
    if config.observation == "depth" and not config.render:
        raise ValueError('observation "depth" needs render=True (depth comes from the frame renderer)')
    if not isinstance(config.num_points, (int, np.integer)) or config.num_points < 1:
        raise ValueError(f"num_points must be a positive integer, got {config.num_points!r}")
    if not isinstance(config.num_envs, (int, np.integer)) or config.num_envs < 1:
        raise ValueError(f"num_envs must be a positive integer, got {config.num_envs!r}")
    if config.graph_mode is not None and config.graph_mode not in GRAPH_MODES:
        raise ValueError(f"graph_mode must be None (MJX's default) or one of {GRAPH_MODES}, got {config.graph_mode!r}")
    if not isinstance(config.fuse_substeps, (bool, np.bool_)):
        raise ValueError(f"fuse_substeps must be True or False, got {config.fuse_substeps!r}")
    if config.reset_pose_branch not in POSE_BRANCHES:
        raise ValueError(f"reset_pose_branch must be one of {POSE_BRANCHES}, got {config.reset_pose_branch!r}")
    seg = config.pool_segments
    if (isinstance(seg, (bool, np.bool_)) or not isinstance(seg, (int, np.integer)) or seg < 1
            or config.num_envs % seg):
        raise ValueError(f"pool_segments must be a positive divisor of num_envs ({config.num_envs}): the worlds "
                         f"as that many equal blocks with a reset pool each, got {seg!r}")
    res = config.resolution
    if not isinstance(res, (int, np.integer)) or not MIN_RES <= res <= MAX_RES:
        raise ValueError(f"resolution must be an integer side length in [{MIN_RES}, {MAX_RES}] "
                         f"(frames are square; 64 is the paper's), got {res!r}")


def scene_versions(name: str, version: object, count: int, note: str = "") -> tuple[tuple[int, ...], bool]:
    """The versions a scene's worlds draw from and whether they draw at random: `version` is
    "random" (each world one of `count` at random) or one int in 0..count-1; anything else is one
    line naming what is accepted (`note`: what some versions are). The multi-object scenes
    (Incline, Rearrange) read `EnvConfig.version` through it."""
    if version == "random":
        return tuple(range(count)), True
    if isinstance(version, (int, np.integer)) and 0 <= version < count:
        return (int(version),), False
    raise ValueError(f"{name}: version must be an int in 0..{count - 1}{note} or 'random', got {version!r}")
