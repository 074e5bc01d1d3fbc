"""Test-session settings: one persistent JAX compilation cache shared by every process of a test
session (issue 38).

Most of the suite's time is XLA compiling tiny jitted epochs, env steps and learners. A session
compiles some programs more than once: a subprocess rebuilds what its parent already compiled
(`test_run`'s resumed process, the stretches of `test_kill_resume`), a test builds a second
`Experiment` of a configuration it compiled before, and files share configurations. With one
cache directory for the session, the second compile of a program loads the executable from disk
(the same executable, so the same numbers). The directory is fresh for each session, so a test
never reads what another session (or other code) compiled, and it is removed at the end.

The pytest process (and each xdist worker, which inherits its environment) sets JAX's own cache
variables, which every Python subprocess also reads, and `$BULBJAX_COMPILE_CACHE`, which the
CLI's `compile_cache.enable()` reads. A cache the caller chose (`$BULBJAX_COMPILE_CACHE` set,
`off` included) is left alone.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile

import pytest

MIN_COMPILE_SECS = "0.5"  # programs that compile faster than this are not worth a disk round trip

_created: str | None = None
if "BULBJAX_COMPILE_CACHE" not in os.environ:
    _created = tempfile.mkdtemp(prefix="bulbjax-test-jax-cache-")
    os.environ["BULBJAX_COMPILE_CACHE"] = _created
# MJX-Warp programs only load from the cache if their Warp calls are numbered by signature (Warp's
# own per-trace counter makes every re-trace new text): `bulbjax.envs.warp_graphs.stable_call_ids`,
# installed when an env is built. Measured alone on this 2-core machine (2026-11-27):
# tests/test_incline.py 175 s -> 140 s.
os.environ.setdefault("BULBJAX_STABLE_WARP_IDS", "1")
_cache = os.environ["BULBJAX_COMPILE_CACHE"]
if _cache.strip().lower() not in ("", "0", "off", "false", "no"):  # compile_cache.OFF_VALUES (importing
    # bulbjax here would import JAX before it reads the variables below)
    os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", _cache)
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", MIN_COMPILE_SECS)
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")
    if "jax" in sys.modules:  # a plugin imported JAX before this file: its config read the environment already
        from bulbjax import compile_cache

        compile_cache.enable(os.environ["JAX_COMPILATION_CACHE_DIR"], float(MIN_COMPILE_SECS))


# XLA at its lowest effort (`jax_disable_most_optimizations`: LLVM -O0, no expensive passes) for the
# files whose time is compiling small jitted epochs, not running them: measured alone on this 2-core
# machine, tests/test_recon.py took 219 s optimised and 177 s unoptimised (2026-11-26); an epoch's
# split programs compiled in 82 s against 57 s. Not for the whole session: files that run real
# work (PPO and learner training loops, long env rollouts) ran far slower unoptimised
# (tests/test_ppo.py's pixel PPO bandit: 123 s -> 1,173 s; the whole suite 73 -> 89 min).
# The flag is read when a program is compiled (and is part of the compile-cache key); the
# environment variable carries it to the subprocesses these files start.
COMPILE_BOUND = (
    "test_experiment.py", "test_object_probe.py", "test_recon.py", "test_rl_sequential.py",
    "test_extending.py", "test_run.py", "test_sharding.py", "test_distributed.py", "test_kill_resume.py",
    "test_reproduce.py", "test_plugins.py", "test_apart.py",
)


@pytest.fixture(autouse=True)
def _cold_reproduce_estimates(request, monkeypatch):
    """`bulbjax reproduce`'s estimates in the suite are cold: the session's one compile cache
    gathers the warm notes (`compile_cache.mark_warm`) of whichever tiny plans ran before, so an
    estimate would depend on the order tests ran in. tests/test_reproduce_warm.py gives each test
    a cache of its own and checks the notes."""
    if request.path.name != "test_reproduce_warm.py":
        from bulbjax import compile_cache

        monkeypatch.setattr(compile_cache, "warm_keys", lambda kind: frozenset())
    yield


@pytest.fixture(autouse=True, scope="module")
def _least_xla_effort_for_compile_bound_files(request):
    if request.path.name not in COMPILE_BOUND:
        yield
        return
    import jax

    before_flag, before_env = jax.config.values["jax_disable_most_optimizations"], os.environ.get("JAX_DISABLE_MOST_OPTIMIZATIONS")
    jax.config.update("jax_disable_most_optimizations", True)
    os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] = "1"
    try:
        yield
    finally:
        jax.config.update("jax_disable_most_optimizations", before_flag)
        if before_env is None:
            os.environ.pop("JAX_DISABLE_MOST_OPTIMIZATIONS", None)
        else:
            os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] = before_env


def pytest_unconfigure(config) -> None:
    """The process that made the session's cache removes it (under xdist: the controller, after
    its workers have finished)."""
    if _created is not None and not hasattr(config, "workerinput"):
        shutil.rmtree(_created, ignore_errors=True)


# The slow tier: `make test` (what CI runs, on 2 cores within its 90 minutes) leaves out the tests marked
# `slow`; `make test-all` runs every test. The slow tier is the equivalence of one computation
# done another way, each a whole tiny experiment compiled twice or more (three in subprocesses):
#   test_distributed.py::test_two_processes_equal_one (jax.distributed, 3 processes + a resume), ~550 s
#   test_kill_resume.py::test_kills_at_the_worst_moments_resume_exactly (killed processes), ~220-320 s
#   test_run.py::test_resumed_process_compiles_the_same_epoch_program (4 processes lowering), ~200 s
#   test_experiment.py::test_split_programs_give_the_fused_epoch (the optional split form), ~290-440 s
#   test_lean_step.py::test_kinematics_after_resets_gives_the_forward_passes_episodes[chunks] (the kinematics
#     pass after chunked resets, which run only with the pool off or fixed draws; the pool case stays), ~110 s
#   test_plugins.py::test_cli_run_resume_report_fit (a learner of one's own through `bulbjax run`, a
#     `--resume`, `report` and `fit` in fresh processes, each compiling), ~430 s on a shared 2-core machine
#   test_distributed.py::test_launcher_run_ends_without_error_lines_and_a_refused_folder_is_one_line
#     (two processes through the launcher compile a run; their consoles checked), ~3-4 min
#   test_rl_frames.py::test_latents_of_the_last_two_frames[stdim] (ST-DIM's per-frame features stacked
#     for PPO, step by step; the vae_rpl case stays, and test_contrastive runs an epoch with PPO on
#     ST-DIM's latent), ~110-120 s
#   test_ppo.py::test_pixel_ppo_learns_a_visual_bandit[2] (the bandit learnt with pixel shifts; shift 0
#     stays, and test_pixel_shift_moves_the_update_and_only_for_frames checks the shift's effect), ~90 s
#   test_rl_latent.py's two runs of PPO on what a learner gives it (one frame's latent through the run
#     loop; the pixel policy's torso), ~105 + ~80 s: test_rl_frames checks the latents of the last two
#     frames that PPO observes, step by step, and its pixels stacked along the channels;
#     test_contrastive runs an epoch with PPO on ST-DIM's latent; test_ppo trains a pixel torso
#   test_experiment.py::test_the_pipelined_epoch_gives_the_plain_epochs (--overlap pipeline, probing and
#     not, against the six-learner fixture), ~125 s: test_apart's epochs, which take the same pending
#     keys and metrics (`RunState.pending`, `insert_data`), stay against the plain epoch
#   test_apart.py::test_a_run_with_the_learners_apart_resumes (--overlap apart through `bulbjax run` and
#     `--resume` in fresh processes on two CPU devices), ~95 s: the apart epochs' equivalence stays
#   the second case of four equivalences whose first stays (each ~20-60 s, mostly its own compile):
#     test_chunked_reset's ReacherRearrangeGeom (GeomOnIncline stays), test_sequential_learners'
#     rnn_unroll for dsa (svae stays), test_per_seed's svae-remat (dsa-remat and svae-saved stay),
#     test_learners' conv forms for pred (vae stays)
# (2026-11-28: make test with issue 57-59's tests took 52.6 min while the machine was shared; 41.5 min
# at 6d83063 alone, 748 tests, before the last group above and test_object_probe's CartPole run
# folded into test_experiment's test_reports)
# (durations of the 2-worker suite, 2026-11-26; without them `make test` took 64 min, `bash .ci/run`
# on a fresh clone 65.6 min with its venv, against 88 min for the whole suite before; 2026-11-27, with
# test_lean_step, 73 min while other jobs shared the 2 cores). Each feature
# keeps in-process tests in `make test`:
# test_run's bit-identical resume in one process, test_multiprocess's two real jax.distributed
# processes (gather, flags, per-process checkpoints), test_distributed's settings and checkpoint
# round trip, test_experiment's seed-loop and shared-update equivalences. test_sharding (one device
# against a 2 x 2 mesh, 333 s at least effort, 500-700 s before) stays in `make test`: it is the
# only test of a sharded epoch.


# Files by their time in the 2-worker suite, longest first (measured on a 2-core CPU; each is a
# few jitted epochs compiled in a module fixture or a subprocess). `--dist loadfile` hands files to
# the two workers in collection order; sending the long ones first lets the short ones fill the
# gaps at the end, so both workers finish together. xdist's default order (most tests first) put
# single-test files such as test_kill_resume and test_distributed at the very end, on one worker.
LONGEST_FIRST = (
    "test_experiment.py", "test_reproduce.py", "test_sharding.py", "test_object_probe.py", "test_incline.py",
    "test_run.py", "test_plugins.py", "test_interop.py",
    "test_reset_pool.py", "test_chunked_reset.py", "test_synthetic.py", "test_rl_sequential.py",
    "test_rl_frames.py",
    "test_recon.py", "test_ppo.py", "test_rearrange.py", "test_sequential_learners.py", "test_learners.py",
    "test_contrastive.py", "test_ppo_stability.py", "test_spair.py", "test_extending.py", "test_packaging.py",
)


def pytest_configure(config) -> None:
    config.addinivalue_line(
        "markers", "slow: the slow tier, run by `make test-all`, not by `make test` (CI): equivalence across "
        "processes, devices and program forms (the list above LONGEST_FIRST)")
    if hasattr(config.option, "loadscopereorder"):  # xdist: keep the order below
        config.option.loadscopereorder = False


def pytest_collection_modifyitems(config, items) -> None:
    """Long files first, then the others by their number of tests (xdist's own order), the tests
    of a file in their order."""
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    count: dict[str, int] = {}
    for item in items:
        count[item.path.name] = count.get(item.path.name, 0) + 1
    items.sort(key=lambda item: (rank.get(item.path.name, len(rank)), -count[item.path.name]))
