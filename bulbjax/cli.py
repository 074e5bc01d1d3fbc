"""Command line: `bulbjax run | report | fit | recon | envs | render | reproduce` (parsing only:
the flags map to the arguments of `bulbjax.run`'s `resolve`, `resolve_resume` and
`resolve_offline`, which resolve the settings; the run loop is `bulbjax.run.run`, the offline fit
`bulbjax.run.fit`, the reports `bulbjax.report`)."""

from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Sequence

from bulbjax.env_commands import cmd_envs, cmd_render
from bulbjax.run_command import _settings, leave_failed_run
from bulbjax.run_command import cmd_run as _cmd_run

# What `bulbjax --help` opens with: for a user, what the tool is and which command does what (the
# module's docstring above is for whoever reads the code).
DESCRIPTION = (
    "bulbjax: the bulb benchmark of unsupervised representation learning for continuous "
    "control, on batched MuJoCo (MJX, Warp) environments. Does a learned latent hold the true "
    "state of a robot scene? `run` trains PPO and unsupervised learners side by side and probes "
    "their latents; `fit` trains learners on one cached random-policy dataset; `report` and "
    "`recon` redraw a run's figures and tables; `envs` lists the environments and `render` saves "
    "frames of one; `reproduce` runs the paper's figures. `bulbjax COMMAND --help` gives a "
    "command's flags.")


def build_config(args: argparse.Namespace):
    """The ExperimentConfig of `bulbjax run`'s flags (`bulbjax.run.resolve`)."""
    from bulbjax.run import resolve

    return resolve(args.preset, **_settings(args))


def cmd_run(args: argparse.Namespace) -> int:
    """`bulbjax run` (`bulbjax.run_command.cmd_run`)."""
    return _cmd_run(args)


def cmd_recon(args: argparse.Namespace) -> int:
    """`bulbjax recon RUN_DIR`: the run's figures from its newest (or --epoch) checkpoint."""
    from bulbjax.report import FigureConfig
    from bulbjax.run import redraw_figures

    learners = [s.strip() for s in args.learners.split(",") if s.strip()] if args.learners else None
    redraw_figures(args.run_dir, epoch=args.epoch, learners=learners,
           config=FigureConfig(frames=args.frames, seed=args.seed), out_dir=args.out)
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from bulbjax import report

    plans = [d for d in args.run_dirs if os.path.exists(os.path.join(d, "plan.json"))]
    if len(args.run_dirs) > 1 and plans:  # e.g. the folders of a plan's shards, brought back
        raise ValueError(f"{plans[0]} is the folder of a `bulbjax reproduce` plan: bring plan "
                         "folders together with `bulbjax reproduce --out DIR --gather "
                         f"{','.join(args.run_dirs)}`, which writes DIR/results.md")
    if args.compare_rl:
        out = args.out or os.path.dirname(os.path.normpath(args.run_dirs[0])) or "."
        tab = report.rl_compare(args.run_dirs, out)
        print(f"{tab}\nplot: {os.path.join(out, 'rl_compare.png')}\n"
              f"table: {os.path.join(out, 'rl_compare.md')}")
        return 0
    if getattr(args, "probe_protocol", False):
        if not args.out:
            raise ValueError("--probe-protocol writes table.md into a folder: give it with "
                             "--out DIR (e.g. docs/results/probe_protocol)")
        fp32 = getattr(args, "fp32", None) or ()
        print(report.probe_protocol_table(args.run_dirs, fp32, args.out))
        print(f"table: {os.path.join(args.out, 'table.md')}")
        return 0
    if args.merge_seeds:
        if not args.out:
            raise ValueError("--merge-seeds writes a new run folder: give it with --out DIR")
        began = time.time()
        tab = report.merge_seeds(args.run_dirs, args.out)
        print(f"{tab}\n{report.files_written(args.out, since=began)}")
        return 0
    if len(args.run_dirs) != 1:
        raise ValueError("`bulbjax report` redraws one run; to compare PPO returns of several runs "
                         "add --compare-rl, to pool the seeds of runs of one configuration "
                         "--merge-seeds --out DIR")
    run_dir = args.run_dirs[0]
    # a results folder: its page's claims tables
    if os.path.exists(os.path.join(run_dir, "claims.json")):
        from bulbjax.reproduce import claims

        print(f"claims tables rewritten: {claims.write_page(run_dir)}")
        return 0
    if os.path.exists(os.path.join(run_dir, "plan.json")):  # a `bulbjax reproduce` folder: its page
        from bulbjax.reproduce import results

        print(f"results: {results.write(run_dir, results.read_summary(run_dir))}")
        return 0
    out = args.out or run_dir
    began = time.time()
    tab = report.redraw(run_dir, out)
    print(f"{tab}\n{report.files_written(out, since=began)}")
    return 0


def build_offline_config(args: argparse.Namespace):
    """The OfflineConfig of `bulbjax fit`'s flags (`bulbjax.run.resolve_offline`)."""
    from bulbjax.run import resolve_offline

    dataset = {n: getattr(args, n) for n in ("data_worlds", "data_steps", "heldout_steps")
               if getattr(args, n) is not None}
    return resolve_offline(args.preset, **_settings(args), dataset=dataset, updates=args.updates,
                           probe_every=args.probe_every, data_seed=args.data_seed)


def cmd_fit(args: argparse.Namespace) -> int:
    from bulbjax.run import LOG_FILE, check_out_dir, fit, log_to_file

    cfg = build_offline_config(args)
    if args.seed < 0:
        raise ValueError("--seed must be a non-negative integer (the learners' base PRNG seed), "
                         f"got {args.seed}")
    check_out_dir(args.out, resume=args.resume, overwrite=args.overwrite, fit=True)
    with log_to_file(os.path.join(args.out, LOG_FILE), fresh=args.overwrite,
                     header=" ".join(["bulbjax", *getattr(args, "argv", [])])):
        fit(cfg, args.out, cache_dir=args.cache_dir, max_minutes=args.max_minutes, seed=args.seed,
            resume=args.resume, overwrite=args.overwrite)
    recon = os.path.join(args.out, "recon.png")
    print(f"curves: {args.out}/curves.png, {args.out}/curves.jsonl; table: {args.out}/table.md"
          + (f"; reconstructions: {recon}" if os.path.exists(recon) else ""))
    return 0


class HelpFormatter(argparse.HelpFormatter):
    """Every option's default in `bulbjax CMD --help`, taken from the parser (so it cannot drift
    from the code), unless its help already says it or there is none (None, False)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        d = action.default
        if not action.option_strings or d is None or d is False or d == argparse.SUPPRESS:
            return text
        if "default" in text:
            return text
        return f"{text} (default: %(default)s)"


def learners_help(names: Sequence[str], defaults: str) -> str:
    """`--learners`' help: the registered names (`learners.learner_names()`), and the plugin forms
    (`bulbjax.learners.plugins`)."""
    return (f"comma-separated learner names: {','.join(names)} ({defaults}); or a learner of "
            "your own as MODULE:NAME or path/to/file.py:NAME (imported; NAME its learner class, "
            "factory or registered name: docs/extending.md), or a name of an installed "
            "package's `bulbjax.learners` entry point")


def _stdout_gone() -> bool:
    """Whether stdout is a pipe whose reader has gone (`bulbjax envs | head -2` once `head` has
    its lines): the pipe polls as an error. True where that cannot be asked (no descriptor, no
    `select.poll`), as Python's docs treat every BrokenPipeError."""
    import select

    try:
        poll = select.poll()
        poll.register(sys.stdout.fileno(), select.POLLOUT)
        return any(events & select.POLLERR for _, events in poll.poll(0))
    except (AttributeError, OSError, ValueError):
        return True


def _leave_quietly() -> int:
    """The command's exit on a closed stdout: no traceback (Python's docs, "Note on SIGPIPE": stdout
    pointed at devnull, so that the flush at exit has nowhere to fail) and exit status 141
    (128 + SIGPIPE), what a shell reports for a command a closed pipe ended (`yes | head`)."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (AttributeError, OSError, ValueError):  # a stdout without a descriptor: nothing to flush
        pass
    return 141


def main(argv: Sequence[str] | None = None) -> int:
    from bulbjax.config import PRESETS
    from bulbjax.learners import learner_names

    # the end of Python's start-up and imports (`bulbjax run` says how long they took)
    t_main = time.time()

    presets = ", ".join(PRESETS)
    p = argparse.ArgumentParser(prog="bulbjax", description=DESCRIPTION,
                                formatter_class=HelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="train PPO + unsupervised learners and probe their latents",
                       formatter_class=HelpFormatter)
    r.add_argument("--preset", default=None,
                   help=f"named settings ({presets}); the flags below override it")
    r.add_argument("--env", default=None, help="environment (`bulbjax envs`; default CartPole)")
    r.add_argument("--learners", default=None,
                   help=learners_help(learner_names(), "default vae,vae_rpl,beta_vae"))
    r.add_argument("--seeds", type=int, default=None, help="seeds run side by side (default 3)")
    r.add_argument("--epochs", type=int, default=None, help="epochs (default 50)")
    r.add_argument("--sequence-length", type=int, default=None,
                   help="window length of the sequential learners (default 24 pendulums, "
                        "16 locomotion)")
    r.add_argument("--seed", type=int, default=None, help="base PRNG seed (default 0)")
    r.add_argument("--out", default=None, help="run folder (default runs/latest)")
    r.add_argument("--multicolour", action="store_true", help="bulb's multicolour variant")
    r.add_argument("--version", default=None,
                   help="object version of the multi-object domains (Incline 0-5, Rearrange "
                        "0-11), or random (one per world and episode); default 0, fig3/fig5 "
                        "presets 6 (black background), fig3-rearrange-geom-random random")
    r.add_argument("--seed-loop", default=None, choices=("auto", "vmap", "map", "hybrid"),
                   help="learner work over the seed axis: vmap, map (one seed at a time: ~1.9x "
                        "faster conv updates on a GPU), hybrid (map, but DSA vmapped with its "
                        "convolutions one seed at a time: its LSTMs batched), auto (hybrid on one "
                        "GPU, else vmap; default)")
    r.add_argument("--programs", default=None, choices=("fused", "split"),
                   help="init and the epoch as one program each (fused, default) or as several "
                        "compiled side by side (split, one device); the same numbers either way")
    r.add_argument("--overlap", default=None, choices=("none", "pipeline", "apart"),
                   help="pipeline: one program does this epoch's learner updates and the next "
                        "epoch's PPO rollouts and updates (as fast on one GPU); apart: the "
                        "learners on a GPU of their own beside them (two GPUs a process). The "
                        "same numbers; a checkpoint resumes in its own mode; not with PPO on a "
                        "latent (default: none)")
    r.add_argument("--apart-env-learners", default=None, metavar="NAMES",
                   help="with --overlap apart, the learners updated on the environment's GPU "
                        "beside PPO, on copies of their buffers there: auto (default: pred, "
                        "evening the two GPUs' shares: fig2-ant 0.997 s an epoch against 1.132 s "
                        "on two H200s), none, or names joined by commas")
    r.add_argument("--small", action="store_true", help="CPU-sized settings (not the paper's)")
    r.add_argument("--bf16", action="store_true", help="bf16 compute in the learners (GPU)")
    r.add_argument("--rnn-unroll", type=int, default=None, metavar="N",
                   help="LSTM steps per loop iteration in the sequential learners (same function; "
                        "default 1; on a GPU 4 is as fast as longer unrolls and compiles sooner: "
                        "docs/performance.md)")
    r.add_argument("--learner-option", action="append", default=None, metavar="KEY=VALUE",
                   help="set a LearnerConfig field (repeatable), e.g. lr=3e-4, or the conv forms "
                        "channel_pad=1 / bias_grad=reduce / edge_layers=strided (same network, "
                        "other kernels: docs/performance.md)")
    r.add_argument("--rl-input", default=None,
                   help="what PPO observes: state (default), latent:<learner> (the learner's "
                        "latent of the current frame, its current parameters, no gradient into "
                        "it; for svae, pred, dsa: of the current step in the window of the last L "
                        "steps ending at it), or pixels (the frame through a conv encoder PPO "
                        "trains end to end)")
    r.add_argument("--rl-frames", type=int, default=None, metavar="K",
                   help="with --rl-input pixels or latent:<frame learner or stdim>: PPO observes "
                        "the last K frames (stacked) or their latents (concatenated), so that it "
                        "can see velocities (default 1)")
    r.add_argument("--graph-mode", default=None,
                   help="how MJX-Warp's calls use CUDA graphs on a GPU: warp (MJX's default), jax "
                        "(left to XLA's command buffers), warp_staged, warp_staged_ex or none; the "
                        "same numbers, another speed; jax and warp_staged fail with mujoco-warp "
                        "4.0 (docs/performance.md)")
    r.add_argument("--ppo-updates", type=int, default=None, help="PPO updates per epoch")
    r.add_argument("--ppo-option", action="append", default=None, metavar="KEY=VALUE",
                   help="set a PPOConfig field (repeatable; applied last, over the preset's and "
                        "the domain's PPO settings), e.g. ent_coef=0.01 or min_log_std=none")
    r.add_argument("--lr", type=float, default=None,
                   help="learners' Adam learning rate (paper: 1e-4)")
    r.add_argument("--max-minutes", type=float, default=0.0,
                   help="stop after this wall time, checkpoint and report the epochs done "
                        "(0: no limit)")
    r.add_argument("--probe-every", type=int, default=None,
                   help="probe every k epochs (and at the first and last; default 1); plots keep "
                        "epochs on the x axis")
    r.add_argument("--probe-variants", default=None, metavar="LIST",
                   help="probe-protocol variants computed beside the present probe, "
                        "comma-separated: common (one probe set for every learner), window "
                        "(sequential learners' whole window), raw (raw MAE per group), or none "
                        "(default none; docs/probes.md)")
    r.add_argument("--resume", default=None, metavar="RUN_DIR",
                   help="continue the run in RUN_DIR from its newest checkpoint with its own "
                        "config.json (flags that would change it are an error; --epochs may "
                        "extend it)")
    r.add_argument("--overwrite", action="store_true",
                   help="start afresh in an --out folder that holds a run, deleting its metrics, "
                        "checkpoints and plots (without it such a folder is an error that names "
                        "the run)")
    r.add_argument("--checkpoint-every", type=int, default=0, metavar="N",
                   help="checkpoint every N epochs (0, default: only when the run stops: at the "
                        "end, --max-minutes, --stop-after, SIGINT/SIGTERM)")
    r.add_argument("--keep", type=int, default=2, metavar="K", help="checkpoints kept (default 2)")
    r.add_argument("--stop-after", type=int, default=0, metavar="E",
                   help="stop this stretch after E epochs and checkpoint (0: no limit)")
    r.add_argument("--devices", type=int, default=None,
                   help="use the first D local devices of each process (default all): the seeds "
                        "are split into one group per device (see --layout)")
    r.add_argument("--layout", default="auto",
                   choices=("auto", "processes", "groups", "sharded", "single"),
                   help="how the seeds lie over several devices: processes (one process per GPU "
                        "of this host, joined by jax.distributed on localhost; auto's choice with "
                        "several GPUs), groups (one program per device in this process, each on "
                        "its share of the seeds; auto's choice elsewhere), sharded (one program "
                        "over a mesh: CPU host devices only; on GPUs, where it does not compile "
                        "with MJX-Warp, the run says so and uses groups) or single (the first "
                        "device)")
    r.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                   help="multi-process run (jax.distributed): process 0's address, the same on "
                        "every process (or JAX_COORDINATOR_ADDRESS); with --num-processes and "
                        "--process-id")
    r.add_argument("--num-processes", type=int, default=None, metavar="P",
                   help="processes of a multi-process run (or JAX_NUM_PROCESSES)")
    r.add_argument("--process-id", type=int, default=None, metavar="I",
                   help="this process's index in [0, P) (or JAX_PROCESS_ID); process 0 writes the "
                        "run's files")
    r.add_argument("--local-devices", default=None, metavar="IDS",
                   help="a multi-process run's GPUs for this process, e.g. 0 or 0,1 (or "
                        "JAX_LOCAL_DEVICE_IDS; default all it sees): one process per GPU of a "
                        "host is the fastest layout")
    r.add_argument("--distributed", action="store_true",
                   help="multi-process run with the process count and index taken from SLURM / "
                        "Open MPI (jax.distributed's cluster detection)")
    r.add_argument("--xla-option", action="append", metavar="KEY=VALUE",
                   help="an XLA compile option for the jitted init and epoch (repeatable; how the "
                        "program runs, not what it computes), e.g. "
                        "xla_gpu_enable_command_buffer=FUSION,CUBLAS,WHILE")
    r.add_argument("--tensorboard", action="store_true",
                   help="also write the metrics as TensorBoard events under RUN_DIR/tb (needs "
                        "tensorboardX)")
    r.add_argument("--compile-only", action="store_true",
                   help="a warm-up: build, trace and compile init and the epoch of these settings "
                        "into the compile cache, run nothing and write no run folder (the next "
                        "run of the same settings, and its resumes, load them)")
    r.add_argument("--recon-every", type=int, default=0, metavar="N",
                   help="write recon_<epoch>.png (held-out frames above every learner's "
                        "reconstruction, seed 0) and, with spair, boxes_<epoch>.png every N "
                        "epochs and at the end (0: none)")
    r.set_defaults(fn=cmd_run)
    rc = sub.add_parser("recon", formatter_class=HelpFormatter,
                        help="redraw a run's reconstruction (and SPAIR box) figures from a "
                             "checkpoint")
    rc.add_argument("run_dir", metavar="RUN_DIR")
    rc.add_argument("--epoch", type=int, default=None,
                    help="the checkpoint of E epochs done (default the newest)")
    rc.add_argument("--learners", default=None,
                    help="comma-separated subset of the run's learners (default all)")
    rc.add_argument("--seed", type=int, default=0,
                    help="whose learners (seed index of the run, default 0)")
    rc.add_argument("--frames", type=int, default=8, help="frames per row (default 8)")
    rc.add_argument("--out", default=None, help="folder of the PNGs (default RUN_DIR)")
    rc.set_defaults(fn=cmd_recon)
    rp = sub.add_parser("report", formatter_class=HelpFormatter,
                        help="redraw fig2.png, table.md and findings.md of a run folder from its "
                             "metrics.jsonl")
    rp.add_argument("run_dirs", metavar="RUN_DIR", nargs="+")
    rp.add_argument("--compare-rl", action="store_true",
                    help="PPO return of several runs (state / pixels / latent:<learner>) in one "
                         "plot, rl_compare.png and rl_compare.md, with the epochs each seed "
                         "needed to solve")
    rp.add_argument("--merge-seeds", action="store_true",
                    help="one report over the seeds of several runs of one configuration made with "
                         "different --seed (e.g. half the seeds on each of two GPUs), into --out")
    rp.add_argument("--probe-protocol", action="store_true",
                    help="the Fig. 2 claims of the runs (one per domain, made with "
                         "--probe-variants) under each probe variant side by side, into "
                         "--out/table.md")
    rp.add_argument("--fp32", action="append", default=None, metavar="RUN_DIR",
                    help="with --probe-protocol: a domain's second run in fp32, its verdicts "
                         "as the last column (repeatable, one per domain)")
    rp.add_argument("--out", default=None,
                    help="folder of the outputs: fig2.png, table.md, findings.md of one run "
                         "(default: RUN_DIR itself), of --merge-seeds or --probe-protocol "
                         "(required), or of --compare-rl (default: the first run's parent folder)")
    rp.set_defaults(fn=cmd_report)
    o = sub.add_parser("fit", help="offline: train learners on one cached random-policy dataset, "
                                   "probe every M updates", formatter_class=HelpFormatter)
    o.add_argument("--env", default=None, help="an environment (`bulbjax envs`) or SyntheticMovers")
    o.add_argument("--preset", default=None, help=f"run settings of a preset ({presets})")
    o.add_argument("--learners", default=None,
                   help=learners_help(learner_names(),
                                      "default the preset's, else vae,vae_rpl,beta_vae"))
    o.add_argument("--updates", type=int, default=5000, help="learner updates")
    o.add_argument("--probe-every", type=int, default=250, help="probe every M updates")
    o.add_argument("--seeds", type=int, default=None, help="learner seeds, vmapped (default 3)")
    o.add_argument("--sequence-length", type=int, default=None,
                   help="window length L of sequential learners")
    o.add_argument("--resolution", type=int, default=None,
                   help="frame size (default 64; SyntheticMovers 32)")
    o.add_argument("--multicolour", action="store_true", help="bulb's multicolour variant")
    o.add_argument("--small", action="store_true",
                   help="CPU-sized learners and dataset (not the paper's)")
    o.add_argument("--bf16", action="store_true", help="bf16 compute in the learners (GPU)")
    o.add_argument("--lr", type=float, default=None,
                   help="learners' Adam learning rate (paper: 1e-4)")
    o.add_argument("--data-worlds", type=int, default=None,
                   help="worlds of the dataset (default 256)")
    o.add_argument("--data-steps", type=int, default=None,
                   help="steps per world of the dataset (default 200)")
    o.add_argument("--heldout-steps", type=int, default=None,
                   help="steps per world held out (default 48)")
    o.add_argument("--data-seed", type=int, default=0,
                   help="seed of the dataset (part of its cache key)")
    o.add_argument("--cache-dir", default=None, help="dataset cache (default OUT/data)")
    o.add_argument("--seed", type=int, default=0, help="base PRNG seed of the learners")
    o.add_argument("--max-minutes", type=float, default=0.0,
                   help="stop cleanly before this wall time, probe and write the plots "
                        "(0: no limit)")
    o.add_argument("--out", default="runs/fit",
                   help="folder of the fit's curves, table, checkpoints and dataset cache")
    o.add_argument("--resume", action="store_true",
                   help="continue the fit in --out from its checkpoint (same flags; a larger "
                        "--updates extends it)")
    o.add_argument("--overwrite", action="store_true",
                   help="start afresh in an --out folder that holds a fit, replacing its curves "
                        "and checkpoints (without it such a folder is an error that names the "
                        "fit)")
    o.set_defaults(fn=cmd_fit)
    e = sub.add_parser("envs", help="list the environments", formatter_class=HelpFormatter)
    e.set_defaults(fn=cmd_envs)
    d = sub.add_parser("render", help="save a strip of frames", formatter_class=HelpFormatter)
    d.add_argument("--env", default="CartPole", help="environment (`bulbjax envs`)")
    d.add_argument("--out", default="frames.png", help="the PNG written: the frames side by side")
    d.add_argument("--frames", type=int, default=8, help="frames in the strip, one world each")
    d.add_argument("--steps", type=int, default=10,
                   help="random-action steps before the frames are taken")
    d.add_argument("--resolution", type=int, default=64, help="frame size in pixels (square)")
    d.add_argument("--seed", type=int, default=0, help="PRNG seed of the reset and the actions")
    d.add_argument("--version", default="0",
                   help="object version of the multi-object domains (Incline 0-5, Rearrange "
                        "0-11), or random (one per frame)")
    d.add_argument("--show-targets", action="store_true",
                   help="Rearrange: draw the targets as discs on the tray floor (bulb's frames "
                        "have none)")
    d.set_defaults(fn=cmd_render)
    from bulbjax.reproduce.cli import add_parser as add_reproduce

    add_reproduce(sub, formatter_class=HelpFormatter)
    argv = list(sys.argv[1:] if argv is None else argv)
    args = p.parse_args(argv)
    args.argv, args.t_main = argv, t_main
    from bulbjax import compile_cache

    # reruns of a configuration load its executables ($BULBJAX_COMPILE_CACHE=off: no cache)
    compile_cache.enable()
    try:
        code = args.fn(args)
        sys.stdout.flush()  # a reader gone from stdout shows here, not in Python's flush at exit
        return code
    except (ValueError, FloatingPointError) as err:
        print(f"bulbjax: error: {err}", file=sys.stderr)
        leave_failed_run(2)
        return 2
    except (Exception, KeyboardInterrupt) as err:
        # `| head`; another pipe's is an error
        if isinstance(err, BrokenPipeError) and _stdout_gone():
            return _leave_quietly()
        from bulbjax import distributed

        if distributed.active():  # its traceback now, then out without JAX's shutdown barrier
            import traceback

            traceback.print_exc()
            leave_failed_run(1)
        raise


if __name__ == "__main__":
    sys.exit(main())
