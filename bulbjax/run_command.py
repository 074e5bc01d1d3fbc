"""`bulbjax run`: from its flags to `bulbjax.run.run`, in this process or as one process per GPU
of this host (`bulbjax.local_processes`); split from `bulbjax.cli`, which parses the flags and
uses `_settings` (the flags as the arguments of `bulbjax.run.resolve`) from here. The flags are
resolved once (`bulbjax.run.resolve_run`; a resume reads its run's config.json there) and what
they resolve to is handed down to the checks, the processes and the run."""

from __future__ import annotations

import argparse
import os
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the names of the annotations only: `bulbjax run --help` imports no JAX
    from bulbjax.config import ExperimentConfig, RunOptions
    from bulbjax.run import Resume


def _settings(args: argparse.Namespace) -> dict:
    """The flags of `run` and `fit` as the arguments of `bulbjax.run.resolve` (the flags given;
    text values are parsed and checked there)."""
    flags = (("env", "env"), ("seeds", "seeds"), ("epochs", "epochs"),
             ("sequence_length", "sequence_length"), ("learners", "learners"),
             ("version", "version"), ("rl_input", "rl_input"), ("rl_frames", "rl_frames"),
             ("seed_loop", "learner_seed_loop"), ("programs", "programs"), ("overlap", "overlap"),
             ("apart_env_learners", "apart_env_learners"),
             ("ppo_updates", "ppo_updates_per_epoch"), ("resolution", "resolution"),
             ("graph_mode", "graph_mode"), ("probe_variants", "probe_variants"))
    overrides = {field: getattr(args, flag) for flag, field in flags
                 if getattr(args, flag, None) is not None}
    if getattr(args, "multicolour", False):
        overrides["multicolour"] = True
    learner = {}
    if getattr(args, "lr", None) is not None:
        learner["lr"] = args.lr
    if getattr(args, "bf16", False):
        learner["compute_dtype"] = "bfloat16"
    if getattr(args, "rnn_unroll", None) is not None:
        learner["rnn_unroll"] = args.rnn_unroll
    return dict(overrides=overrides, learner=learner,
                learner_options=getattr(args, "learner_option", None) or (),
                small=bool(getattr(args, "small", False)),
                ppo_options=getattr(args, "ppo_option", None) or ())


def _parse_ids(text: str | None) -> tuple[int, ...] | None:
    """`--local-devices 0,1` -> (0, 1)."""
    if text is None:
        return None
    try:
        return tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError as err:
        raise ValueError(f"--local-devices {text!r} must be device numbers separated by commas, "
                         "e.g. 0,1") from err


def _stretch_options(args: argparse.Namespace) -> dict:
    return dict(checkpoint_every=args.checkpoint_every, keep=args.keep,
                max_minutes=args.max_minutes, stop_after=args.stop_after,
                tensorboard=args.tensorboard, recon_every=args.recon_every)


def _per_gpu(args: argparse.Namespace, out: str, cfg: ExperimentConfig,
             resume: Resume | None) -> int | None:
    """On a host with several GPUs (`--layout auto` or `processes`): run one process per GPU
    (`bulbjax.local_processes`: in one process the GPUs would take turns in MJX-Warp's Python
    callbacks) and return its exit code; None where one process is the layout. What would make
    every worker refuse the run (the folder, a resume's settings or process count) is refused
    here, in one line, before any worker starts."""
    from bulbjax import local_processes

    gpus = local_processes.visible_gpus()[: args.devices or None]
    if cfg.overlap == "apart":  # two GPUs a process: the environment's and the learners'
        gpus = [f"{a},{b}" for a, b in zip(gpus[0::2], gpus[1::2])]
    if len(gpus) < 2:
        if args.layout == "processes":
            raise ValueError("--layout processes runs one process per GPU and this host has "
                             f"{len(gpus)} (CUDA_VISIBLE_DEVICES / nvidia-smi): leave --layout at "
                             "auto")
        return None
    n = local_processes.process_count(cfg.seeds, len(gpus))
    if n < len(gpus):
        unit = "GPU pair" if cfg.overlap == "apart" else "GPU"
        print(f"{cfg.seeds} seeds on {len(gpus)} {unit}s: {n} process(es), one {unit} each, "
              f"{len(gpus) - n} {unit}(s) idle (every process runs as many seeds: give --seeds a "
              f"multiple of {len(gpus)} to use all)", flush=True)
    if n < 2:
        return None
    if resume is not None:
        resume.check(processes=n)
    return local_processes.run_per_gpu(args.argv, gpus[:n], out)


def cmd_run(args: argparse.Namespace) -> int:
    """Map the flags to (config, options, folder), once (`bulbjax.run.resolve_run`: a resumed run
    starts from its own config.json, read there, and `Resume.check` refuses any flag that changes
    what it computes: only --epochs may grow it), and hand what they resolve to over to
    `bulbjax.run.run`. The flags are parsed first, so that a bad one is refused before anything is
    done. The console names each start-up stage with the seconds since the process started
    (Python and the imports, joining `jax.distributed`, the JAX backend, then `run`'s own
    stages)."""
    import shutil
    import tempfile

    from bulbjax import distributed
    from bulbjax.envs.registry import env_class
    from bulbjax.run import StageLog, check_out_dir, process_start_time, resolve_run
    from bulbjax.xla_options import parse_compiler_options

    t_start = process_start_time()
    said: list[str] = []  # the start-up lines before the log file opens: copied into it
    stages = StageLog(lambda line: (print(line, flush=True), said.append(line)), t_start)
    stages.line(f"Python start-up and imports: {getattr(args, 't_main', t_start) - t_start:.1f} s")
    ids, settings, stretch = _parse_ids(args.local_devices), _settings(args), _stretch_options(args)
    dist = distributed.DistributedConfig.from_env(
        coordinator=args.coordinator, num_processes=args.num_processes, process_id=args.process_id,
        local_device_ids=ids, auto=args.distributed)
    compiler_options = parse_compiler_options(args.xla_option or [])
    if args.resume and args.overwrite:
        raise ValueError("--resume continues the run in its folder and --overwrite deletes it: "
                         "give one of them")
    if (args.resume and args.out is not None
            and os.path.abspath(args.out) != os.path.abspath(args.resume)):
        raise ValueError(f"--resume {args.resume} continues that run in its own folder; leave out "
                         f"--out {args.out}")
    if args.compile_only and args.resume:
        raise ValueError("--compile-only compiles a fresh run's programs (a resume loads the same "
                         "ones): leave out --resume")
    # --compile-only: a throw-away folder (its logs too), no run folder of the user's is touched
    out = tempfile.mkdtemp(prefix="bulbjax-compile-only-") if args.compile_only else (
        args.resume or args.out or "runs/latest")
    made = not os.path.exists(out)  # a folder this command creates goes again if it fails empty
    try:
        # before any process starts or joins: a run in the way or an unwritable folder is one line
        # (a resume's missing folder is left to resolve_resume's message, not created here)
        if not args.resume or os.path.isdir(out):
            check_out_dir(out, resume=bool(args.resume),
                          overwrite=args.overwrite or args.compile_only)
        # before anything else touches JAX's devices, and before the settings are resolved (so that
        # its processes refuse bad settings together): a multi-process run joins its peers first
        if dist.wanted:
            pid = "?" if dist.process_id is None else dist.process_id
            count = "?" if dist.num_processes is None else dist.num_processes
            with stages(f"joining jax.distributed as process {pid} of {count}"):
                distributed.initialize(dist)
        cfg, opts, resume = resolve_run(args.preset, resume=args.resume, seed=args.seed,
                                        probe_every=args.probe_every, stretch=stretch, **settings)
        # before the run's log.txt is made or a process starts: a missing YCB folder or pybullet
        # is one line
        env_class(cfg.env).check_sources()
        if not dist.wanted and args.layout in ("auto", "processes"):
            spread = _per_gpu(args, out, cfg, resume)
            if spread is not None:
                return spread
        import jax

        with stages("starting the JAX backend"):
            local = jax.local_devices()
        return _run_here(args, out, local, t_start, said, cfg, opts, resume, compiler_options)
    except ValueError:  # bad input changes nothing: no empty run folder left behind
        if made and os.path.isdir(out) and not os.listdir(out):
            os.rmdir(out)
        raise
    finally:
        if args.compile_only:
            shutil.rmtree(out, ignore_errors=True)


def _run_here(args: argparse.Namespace, out: str, local: list, t_start: float, said: list[str],
              cfg: ExperimentConfig, opts: RunOptions, resume: Resume | None,
              compiler_options: dict) -> int:
    """`cmd_run` in this process, once it joined its peers (if any) and its backend is up."""
    import jax

    from bulbjax import distributed
    from bulbjax.run import log_name, log_to_file, run

    if args.devices is not None and not 1 <= args.devices <= len(local):
        raise ValueError(f"--devices {args.devices}: this machine has {len(local)} local devices")
    # every process's first D local devices (D: --devices, default all of them)
    devices = [d for p in range(jax.process_count())
               for d in [x for x in jax.devices() if x.process_index == p][: args.devices or None]]
    argv = ["bulbjax", *getattr(args, "argv", [])]
    with log_to_file(os.path.join(out, log_name(jax.process_index())), fresh=args.overwrite,
                     header=" ".join(argv), preamble=said):
        run(cfg, opts, out, resume=resume or False, overwrite=args.overwrite, devices=devices,
            argv=argv, compiler_options=compiler_options,
            layout="groups" if args.layout == "processes" else args.layout,
            t0=t_start, compile_only=args.compile_only)
    distributed.shutdown()
    return 0


def leave_failed_run(code: int) -> None:
    """A process of a multi-process run that failed exits now, its error printed: on the way out
    JAX would wait at its shutdown barrier (up to 5 minutes) for processes that wait for this one
    in a collective. The launcher (or the cluster manager) stops them; with process 0 gone its
    coordination service goes and the others stop too. Nothing for one process."""
    from bulbjax import distributed

    if not distributed.active():
        return
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)


