"""The `bulbjax reproduce` subcommand's flags (the main CLI adds them with `add_parser`)."""

from __future__ import annotations

import argparse

from bulbjax.reproduce.plan import ENTRIES, SCALES


# the flags that shape or run a plan, with their defaults: --gather refuses them (it takes the
# plan the folders hold and runs nothing)
_RUN_ONLY = (("--figures", "all"), ("--scale", "paper"), ("--gpus", None), ("--shard", None), ("--jobs", None),
             ("--fit-minutes", 0.0), ("--learners-apart", False), ("--jobs-per-gpu", 1), ("--add-learner", None),
             ("--overwrite", False), ("--max-minutes", 0.0), ("--device-kind", None), ("--mps", False),
             ("--apart-env-learners", None))


def cmd_reproduce(args: argparse.Namespace) -> int:
    if args.gather is not None:
        from bulbjax.reproduce.gather import gather_and_report

        given = [f for f, default in _RUN_ONLY if getattr(args, f.lstrip("-").replace("-", "_")) != default]
        if given:
            raise ValueError(f"--gather runs nothing and takes only --out (and --dry-run), not {', '.join(given)}: "
                             "gather first, then run the plan with those")
        gather_and_report(args.out, [d for d in args.gather.split(",") if d], dry_run=args.dry_run)
        return 0
    from bulbjax.reproduce.main import reproduce

    summary = reproduce(args.figures, args.scale, args.out, gpus=args.gpus, shard=args.shard,
                        add_learners=args.add_learner or (), dry_run=args.dry_run, overwrite=args.overwrite,
                        max_minutes=args.max_minutes, progress_every=args.progress_every, jobs=args.jobs,
                        fit_minutes=args.fit_minutes, learners_apart=args.learners_apart,
                        jobs_per_gpu=args.jobs_per_gpu, device_kind=args.device_kind, mps=args.mps,
                        apart_env_learners=args.apart_env_learners)
    return 1 if summary.get("failed") else 0


def add_parser(sub: argparse._SubParsersAction,
               formatter_class: type[argparse.HelpFormatter] = argparse.HelpFormatter) -> argparse.ArgumentParser:
    """`bulbjax reproduce`: the paper's figures as one plan of jobs over this host's GPUs. Its help
    takes the formatter of the other subcommands (`bulbjax.cli.HelpFormatter`, given by the main
    CLI: a default shown once, where the help text does not say it already, and none for switches
    and unset options); the help texts say the defaults the parser cannot show (None)."""
    rp = sub.add_parser(
        "reproduce", help="run the paper's figures (Figs. 2-5) as one plan of jobs, one process per GPU",
        description="Run the paper's figures as a plan of jobs (one seed of a preset each), one `bulbjax run` "
                    "process per GPU taking the next job, then write OUT/results.md. Run the same command "
                    "again to continue unfinished jobs (finished ones are skipped).",
        formatter_class=formatter_class)
    rp.add_argument("--figures", default="all",
                    help=f"comma-separated figures ({', '.join(ENTRIES)}, all) or presets of them (e.g. fig2-ant); "
                         "fp32: Fig. 2's InvertedPendulum again without --bf16, beside its bf16 runs")
    rp.add_argument("--scale", default="paper", choices=SCALES,
                    help="paper: the paper's seeds and epochs; quick: every figure, short (~11 min on four H200s, ~40 on one); "
                         "tiny: CPU-sized, 2 epochs (tests)")
    rp.add_argument("--out", default="runs/reproduce", help="the plan's folder (runs, logs, results.md)")
    rp.add_argument("--gpus", type=int, default=None,
                    help="GPUs of this host to use, or CPU worker processes on a host without GPUs "
                         "(default: every visible GPU, else 1 CPU worker)")
    rp.add_argument("--shard", default=None, metavar="K/N",
                    help="this host's share K of a plan split over N hosts (e.g. a SLURM array task), "
                         "balanced by estimated cost; every host computes the same split (default: the whole "
                         "plan on this host)")
    rp.add_argument("--jobs", default=None, metavar="ID,...",
                    help="only these jobs of the plan (ids as --dry-run lists them, e.g. fig2-cartpole/seed3), each "
                         "with the Fig. 4 job that reads it (default: every job of the plan or shard)")
    rp.add_argument("--fit-minutes", type=float, default=0.0, metavar="M",
                    help="of the unfinished jobs left, run those the estimate fits in M minutes on this host "
                         "(longest first): for a host held for a limited time whose disk goes with it "
                         "(default: 0, every job)")
    rp.add_argument("--learners-apart", action="store_true",
                    help="each job on two GPUs, its learners on the second beside its PPO work on the first "
                         "(bulbjax run --overlap apart: the same numbers)")
    rp.add_argument("--apart-env-learners", default=None, metavar="NAMES",
                    help="with --learners-apart: the learners updated on each job's first GPU beside its PPO "
                         "work (bulbjax run --apart-env-learners: auto, none, or names; default: auto)")
    rp.add_argument("--jobs-per-gpu", type=int, default=1, metavar="N",
                    help="N jobs side by side on each GPU, each its own process with 0.75/N of its memory: one "
                         "job's launch-bound rollouts beside another's learners (3 on one H200: 1.14x the "
                         "seed-epochs of one job at a time)")
    rp.add_argument("--mps", action="store_true",
                    help="run the jobs' processes under a CUDA MPS daemon started for the stretch (and quit at "
                         "its end): jobs side by side on a GPU (--jobs-per-gpu) run their kernels at once instead "
                         "of taking turns; needs nvidia-cuda-mps-control")
    rp.add_argument("--add-learner", action="append", metavar="SPEC",
                    help="a learner of your own (pkg.module:Name, docs/extending.md) run beside the paper's in "
                         "every figure; repeatable (default: none)")
    rp.add_argument("--gather", default=None, metavar="DIR,...",
                    help="run nothing: copy into --out the jobs these plan folders (brought back from other "
                         "hosts) finished and --out has not, with their stretch summaries, then write its "
                         "results page (default: none, run the plan)")
    rp.add_argument("--dry-run", action="store_true", help="print the jobs and the estimated time, run nothing")
    rp.add_argument("--device-kind", default=None, metavar="KIND",
                    help="with --dry-run: estimate the plan on --gpus GPUs (1 if not given) of this kind, "
                         "as nvidia-smi names it (e.g. 'NVIDIA H200'), not this host's: for a node without "
                         "them (default: this host's devices)")
    rp.add_argument("--overwrite", action="store_true", help="start afresh: delete the plan's folder first")
    rp.add_argument("--max-minutes", type=float, default=0.0,
                    help="stop every job (checkpointed) after this wall time; the same command continues "
                         "(default: 0, no limit)")
    rp.add_argument("--progress-every", type=float, default=30.0, help="seconds between progress lines")
    rp.set_defaults(fn=cmd_reproduce)
    return rp
