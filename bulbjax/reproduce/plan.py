"""The paper's experiment plan as data: which figures run which presets, with how many seeds and
epochs, cut into jobs; which jobs a host of a sharded plan takes (`estimate` says how long).

A *job* is one `bulbjax run` of one seed of a preset (`--seeds 1 --seed K`: seed K of the figure
is the run's base seed K; the quick scale runs a preset's seeds as one job), or, for Fig. 4, one
`bulbjax recon` of a Fig. 2 run's last checkpoint.
The cut does not depend on the machine: a plan run on 1, 4 or 8 GPUs, or sharded over hosts,
runs the same jobs with the same seeds, so its numbers are the same (`--merge-seeds` pools the
seeds of a figure's jobs afterwards, `bulbjax.reproduce.results`). One seed per job is what keeps
every GPU busy: 6 seeds on 4 GPUs are 6 jobs, and a short job fills a GPU beside a long one.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from typing import Any, Sequence

from bulbjax.config import PRESETS

SCALES = ("paper", "quick", "tiny")
FIGURES = ("fig2", "fig3", "fig4", "fig5")  # the paper's
# entries of the plan beyond the paper's figures, planned by "all" with them and after them (their
# jobs last, so a plan saved before one joined is the start of the plan with it): "fp32", Fig. 2's
# InvertedPendulum with the learners in fp32, beside its bf16 runs (the verdicts in both)
EXTRAS = ("fp32",)
ENTRIES = FIGURES + EXTRAS  # what `--figures all` plans
# "all" as it was before an entry joined it: a plan folder saved under one of these continues as
# today's "all" while its jobs are the new plan's first jobs, unchanged (`plan_differences`)
FORMER_ALL = (FIGURES,)
FIG4_LEARNERS = ("vae_rpl", "svae", "pred", "dsa")  # the paper's Fig. 4 columns


@dataclass(frozen=True)
class FigureSpec:
    """One figure of the paper as runs: `presets` (each a `bulbjax run --preset`), `seeds` per
    preset, `epochs` per seed (per preset where `epochs_of` says otherwise), how often the runs
    probe and draw reconstructions, and extra `bulbjax run` flags."""

    name: str
    title: str
    presets: tuple[str, ...]
    seeds: int
    epochs: int
    probe_every: int = 10
    recon_every: int = 0
    epochs_of: tuple[tuple[str, int], ...] = ()  # (preset, epochs) where a preset differs
    flags: tuple[str, ...] = ()
    # seeds per job: 1 keeps every GPU busy on a plan of many jobs; the quick scale puts a
    # preset's seeds in one job, so it starts (compiles) once
    seeds_per_job: int = 1
    checkpoint_every: int = 0  # epochs between a job's checkpoints (0: about every 5 minutes)
    # before a job's id and under runs/: an entry that runs presets of a figure again in another
    # way ("fp32/": fp32/fig2-invpend/seed0 in runs/fp32/fig2-invpend/seed0) keeps its own
    prefix: str = ""

    def epochs_for(self, preset: str) -> int:
        return dict(self.epochs_of).get(preset, self.epochs)


_FIG2 = ("fig2-cartpole", "fig2-invpend", "fig2-halfcheetah", "fig2-ant")
TITLES = {
    "fig2": "Fig. 2: latent state alignment on the multicolour pendulums and locomotion",
    "fig3": "Fig. 3: SPAIR and VAE_rpl on RearrangeGeom (the paper's fixed scene)",
    "fig4": "Fig. 4: reconstructions of VAE_rpl, SVAE, PRED and DSA after long training",
    "fig5": "Fig. 5: SPAIR 4x4 and 6x6 on RearrangeYCB",
    "fp32": "fp32: Fig. 2's InvertedPendulum with the learners in fp32, beside its bf16 runs",
}


# Fig. 2's runs at the paper and quick scales compute the probe protocol's variants beside the
# present probe (issue 59: one run answers whether a verdict is the latent's or the probe's; ~3-4%
# of a run on two H200s, docs/probes.md); the results page adds their table across domains
VARIANTS = ("--probe-variants", "common,window,raw")


def figure_specs(scale: str) -> dict[str, FigureSpec]:
    """The figures at `scale`: "paper" (the paper's settings: Fig. 2 4 domains x 6 seeds x 1,000
    epochs with the probe variants, Figs. 3 and 5 3 seeds x 1,000; bf16, probes every 10th epoch), "quick" (every figure
    short: 2 seeds, short runs, ~11 min on four H200s) or "tiny" (the CPU-sized
    `--small` config, 2 seeds x 2 epochs, two learners: what the tests run). Fig. 4 has no runs
    of its own: it is drawn from Fig. 2's seed-0 runs (`plan_jobs`). "fp32" runs Fig. 2's
    InvertedPendulum again as Fig. 2 does at the scale, without `--bf16` (`fp32_spec`)."""
    if scale not in SCALES:
        raise ValueError(f"unknown --scale {scale!r}; accepted: {', '.join(SCALES)}")
    if scale == "paper":
        specs = {
            "fig2": FigureSpec("fig2", TITLES["fig2"], _FIG2, 6, 1000, flags=("--bf16", *VARIANTS)),
            "fig3": FigureSpec("fig3", TITLES["fig3"], ("fig3-rearrange-geom",), 3, 1000, recon_every=250,
                               flags=("--bf16",)),
            "fig5": FigureSpec("fig5", TITLES["fig5"], ("fig5-rearrange-ycb",), 3, 1000, recon_every=250,
                               flags=("--bf16",)),
        }
    elif scale == "quick":
        specs = {
            "fig2": FigureSpec("fig2", TITLES["fig2"], _FIG2, 2, 60, probe_every=10, seeds_per_job=2,
                               epochs_of=(("fig2-halfcheetah", 20), ("fig2-ant", 20)), flags=("--bf16", *VARIANTS)),
            "fig3": FigureSpec("fig3", TITLES["fig3"], ("fig3-rearrange-geom",), 2, 40, probe_every=10,
                               recon_every=40, seeds_per_job=2, flags=("--bf16",)),
            "fig5": FigureSpec("fig5", TITLES["fig5"], ("fig5-rearrange-ycb",), 2, 40, probe_every=10,
                               recon_every=40, seeds_per_job=2, flags=("--bf16",)),
        }
    else:
        tiny = ("--small", "--learners", "vae,vae_rpl")
        rearrange = ("--small", "--learners", "vae_rpl,spair")
        specs = {
            "fig2": FigureSpec("fig2", TITLES["fig2"], _FIG2, 2, 2, probe_every=1, flags=tiny, checkpoint_every=1),
            "fig3": FigureSpec("fig3", TITLES["fig3"], ("fig3-rearrange-geom",), 2, 2, probe_every=1,
                               recon_every=2, flags=rearrange, checkpoint_every=1),
            "fig5": FigureSpec("fig5", TITLES["fig5"], ("fig5-rearrange-ycb",), 2, 2, probe_every=1,
                               recon_every=2, flags=rearrange, checkpoint_every=1),
        }
    return {**specs, "fp32": fp32_spec(specs["fig2"])}


FP32_PRESETS = ("fig2-invpend",)  # the "at least InvertedPendulum 6 x 1,000 in fp32"


def fp32_spec(fig2: FigureSpec) -> FigureSpec:
    """The "fp32" entry at a scale: Fig. 2's spec there (seeds, epochs, probes, seeds per job,
    the probe variants) for `FP32_PRESETS`, its flags without `--bf16`, so that each claim's
    verdict can be read in fp32 beside Fig. 2's bf16 runs of the same seeds. At the paper scale 6
    seeds x 1,000 epochs, each seed a job; quick 2 x 60 in one job; tiny, which runs fp32 in both
    (no `--bf16`), the same runs as Fig. 2's: a check of the page, not of the precision."""
    return dataclasses.replace(fig2, name="fp32", title=TITLES["fp32"], presets=FP32_PRESETS, epochs_of=(),
                               epochs=fig2.epochs_for(FP32_PRESETS[0]),
                               flags=tuple(f for f in fig2.flags if f != "--bf16"), prefix="fp32/")


@dataclass(frozen=True)
class Job:
    """One unit of the plan. `kind` "run": `bulbjax run --preset preset --seeds seeds --seed seed`
    for `epochs` epochs into `run_dir` (seeds `seed .. seed + seeds - 1` of its figure); "recon":
    `bulbjax recon` of the run of job `after` into `run_dir` (Fig. 4). `id` is unique in the
    plan and names the job everywhere."""

    id: str
    figure: str
    kind: str
    preset: str
    seed: int  # the run's base seed (`--seed`): its first seed's index in the figure
    epochs: int
    run_dir: str  # relative to the plan's --out
    probe_every: int = 10
    recon_every: int = 0
    flags: tuple[str, ...] = ()
    after: str | None = None  # the job this one reads (Fig. 4: the Fig. 2 run it redraws)
    seeds: int = 1
    checkpoint_every: int = 0  # epochs between checkpoints (0: about every 5 minutes of epochs)

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def parse_figures(text: str | Sequence[str]) -> tuple[str, ...]:
    """`--figures fig2,fig5` or preset names (`fig2-cartpole`), or an entry beyond the paper's
    figures (`fp32`): the entries and presets asked for, each checked; "all" (or empty) is every
    entry (`ENTRIES`)."""
    items = [t.strip() for t in (text.split(",") if isinstance(text, str) else text) if t.strip()]
    if not items or items == ["all"]:
        return ENTRIES
    bad = [t for t in items if t not in ENTRIES and t not in PRESETS]
    if bad:
        raise ValueError(f"unknown figure(s) {', '.join(bad)}; accepted: {', '.join(ENTRIES)}, all, or a "
                         f"preset of one ({', '.join(p for p in PRESETS if p != 'fig3-rearrange-geom-random')})")
    return tuple(dict.fromkeys(items))


def plan_jobs(figures: Sequence[str], scale: str, add_learners: Sequence[str] = (),
              learners_of: dict[str, tuple[str, ...]] | None = None) -> list[Job]:
    """The jobs of `figures` (figure names or presets, `parse_figures`) at `scale`, in a fixed
    order. `add_learners`: learner specs (`name` or `pkg.module:Name`) run beside each preset's
    own learners in every run job. `learners_of`: each preset's learners (default: the preset's);
    the tiny scale's `--learners` flag replaces them. Fig. 4 adds one recon job per Fig. 2 domain
    planned, reading that domain's seed-0 run, and plans those seed-0 runs if Fig. 2 is not. The
    jobs of the entries beyond the paper's figures (`EXTRAS`) come last, after Fig. 4's."""
    specs = figure_specs(scale)
    wanted = parse_figures(figures)
    runs: dict[tuple[str, str], None] = {}  # (figure, preset), ordered
    for w in wanted:
        if w in specs:
            runs.update({(w, p): None for p in specs[w].presets})
        elif w != "fig4":
            fig = next((f for f, s in specs.items() if w in s.presets), None)
            if fig is None:
                raise ValueError(f"preset {w} is in no figure of the plan; accepted: "
                                 f"{', '.join(dict.fromkeys(p for s in specs.values() for p in s.presets))}")
            runs[(fig, w)] = None
    fig4_presets: list[str] = []
    if "fig4" in wanted:  # the Fig. 2 domains planned, or all four when Fig. 4 comes alone
        planned = [p for p in specs["fig2"].presets if ("fig2", p) in runs]
        fig4_presets = planned or list(specs["fig2"].presets)
    jobs: list[Job] = []
    for fig, preset in runs:
        if fig not in EXTRAS:
            jobs += _run_jobs(specs[fig], preset, add_learners, learners_of)
    fig2 = specs["fig2"]
    for preset in fig4_presets:
        first = _run_jobs(fig2, preset, add_learners, learners_of)[0]  # the job of seed 0
        if not any(j.id == first.id for j in jobs):  # Fig. 4 alone: the seed-0 runs it draws
            jobs.append(first)
        jobs.append(Job(f"fig4/{preset}", "fig4", "recon", preset, 0, first.epochs, f"fig4/{preset}",
                        after=first.id))
    for fig, preset in runs:  # the entries beyond the paper's figures last (`EXTRAS`)
        if fig in EXTRAS:
            jobs += _run_jobs(specs[fig], preset, add_learners, learners_of)
    return jobs


def _run_jobs(s: FigureSpec, preset: str, add_learners: Sequence[str],
              learners_of: dict[str, tuple[str, ...]] | None) -> list[Job]:
    """The run jobs of one preset of figure `s`: its seeds cut into jobs of `seeds_per_job`."""
    flags = _with_learners(s.flags, preset, add_learners, learners_of)
    out = []
    for first in range(0, s.seeds, s.seeds_per_job):
        n = min(s.seeds_per_job, s.seeds - first)
        name = f"seed{first}" if n == 1 else f"seeds{first}-{first + n - 1}"
        out.append(Job(f"{s.prefix}{preset}/{name}", s.name, "run", preset, first, s.epochs_for(preset),
                       f"runs/{s.prefix}{preset}/{name}", s.probe_every, s.recon_every, flags, seeds=n,
                       checkpoint_every=s.checkpoint_every))
    return out


def _with_learners(flags: Sequence[str], preset: str, add: Sequence[str],
                   learners_of: dict[str, tuple[str, ...]] | None) -> tuple[str, ...]:
    """The run flags of a preset's jobs with `add` learners beside its own."""
    flags = list(flags)
    if not add:
        return tuple(flags)
    if "--learners" in flags:
        i = flags.index("--learners")
        own = flags[i + 1].split(",")
        del flags[i:i + 2]
    else:
        own = list((learners_of or {}).get(preset) or PRESETS[preset].learners)
    names = list(dict.fromkeys([*own, *add]))
    return (*flags, "--learners", ",".join(names))


def fig4_learners(learners: Sequence[str]) -> list[str]:
    """The Fig. 4 columns a run can draw: the paper's (`FIG4_LEARNERS`) it has, then each learner
    beyond the paper's set that reconstructs frames (an added one without `reconstruct` has no
    row to draw)."""
    from bulbjax.learners import LearnerConfig, make_learner

    paper = {n for p in PRESETS.values() for n in p.learners} | {"stdim", "curl"}
    extra = [n for n in learners if n not in paper
             and hasattr(make_learner(n, latent_dim=2, config=LearnerConfig(), action_dim=1), "reconstruct")]
    return [n for n in FIG4_LEARNERS if n in learners] + extra


# ---------------------------------------------------------------------------- shards
def parse_shard(text: str | None) -> tuple[int, int] | None:
    """`--shard K/N` (1 <= K <= N) -> (K, N); None for the whole plan."""
    if text is None:
        return None
    k, sep, n = str(text).partition("/")
    try:
        k_i, n_i = int(k), int(n)
    except ValueError:
        k_i = n_i = 0
    if not sep or not 1 <= k_i <= n_i:
        raise ValueError(f"--shard {text!r} must be K/N with 1 <= K <= N (this host's share K of N hosts), "
                         "e.g. --shard 1/2; with a SLURM array: --shard $((SLURM_ARRAY_TASK_ID+1))/$SLURM_ARRAY_TASK_COUNT")
    return k_i, n_i


def shard_of(jobs: Sequence[Job], cost: dict[str, float], n: int) -> dict[str, int]:
    """Each job's shard (0..n-1), balanced by estimated cost: longest first, each to the shard
    with the least work so far (ties: the lowest shard, then the job's place in the plan), a
    Fig. 4 job with the run it reads. Depends only on the plan and the estimates, so every host
    of a sharded plan computes the same split. The jobs of `EXTRAS` are placed after all others,
    so the paper's figures' jobs keep the shards they had in a plan without them (a sharded plan
    saved before an entry joined "all" continues with each host's jobs where they were)."""
    order = sorted((j for j in jobs if j.after is None),
                   key=lambda j: (j.figure in EXTRAS, -cost[j.id], jobs.index(j)))
    load = [0.0] * n
    out: dict[str, int] = {}
    for j in order:
        k = min(range(n), key=lambda i: (load[i], i))
        out[j.id] = k
        load[k] += cost[j.id]
    for j in jobs:
        if j.after is not None:
            out[j.id] = out[j.after]
    return out


def with_partners(jobs: Sequence[Job], chosen: Sequence[str]) -> list[Job]:
    """The jobs named in `chosen` with their partners, in plan order: a Fig. 4 job and the run it
    reads go together (the run's last checkpoint is drawn on the host that ran it, and a host's
    disk may not outlive it)."""
    ids = set(chosen)
    ids |= {j.after for j in jobs if j.id in ids and j.after}
    ids |= {j.id for j in jobs if j.after in ids}
    return [j for j in jobs if j.id in ids]


def parse_jobs(text: str | Sequence[str] | None, jobs: Sequence[Job]) -> list[Job] | None:
    """`--jobs ID,ID` (job ids as `--dry-run` lists them, e.g. fig2-cartpole/seed3): those jobs of
    the plan with their partners (`with_partners`); None for all. An id the plan does not hold
    is a one-line error listing the plan's."""
    if text is None:
        return None
    items = [t.strip() for t in (text.split(",") if isinstance(text, str) else text) if t.strip()]
    known = [j.id for j in jobs]
    bad = [t for t in items if t not in known]
    if bad or not items:
        groups = list(dict.fromkeys(i.rsplit("/", 1)[0] for i in known))
        hint = ""
        if bad and not any(b.rsplit("/", 1)[0] in groups for b in bad):
            hint = " (a job of a figure the plan leaves out? add it to --figures)"
        raise ValueError(f"--jobs: {', '.join(bad) or 'no job named'} not in this plan{hint}; its jobs, as --dry-run "
                         f"lists them: {', '.join(f'{g}/...' for g in groups)} (e.g. {known[0]})")
    return with_partners(jobs, items)


# ---------------------------------------------------------------------------- the plan file
PLAN_FILE = "plan.json"
# what a plan's identity is: a rerun with other values of these is refused (--overwrite to start afresh)
IDENTITY = ("scale", "figures", "add_learners")


def plan_record(figures: Sequence[str], scale: str, add_learners: Sequence[str], jobs: Sequence[Job]) -> dict:
    return {"scale": scale, "figures": list(figures), "add_learners": list(add_learners),
            "jobs": [j.as_dict() for j in jobs]}


def plan_differences(saved: dict, new: dict) -> list[str]:
    """What differs between a saved plan and a new one, as 'field: saved X, given Y'. A plan saved
    as a former "all" (`FORMER_ALL`, e.g. before the fp32 entry joined) is today's "all" when its
    jobs are the new plan's first ones unchanged (`grown_from`): the same plan, grown."""
    return [f"{k}: saved {saved.get(k)!r}, given {new.get(k)!r}" for k in IDENTITY
            if saved.get(k) != new.get(k) and not (k == "figures" and grown_from(saved, new))]


def grown_from(saved: dict, new: dict) -> list[str]:
    """The ids of the jobs `new` adds to `saved` when `new` is "all" and `saved` a plan of a
    former "all" whose jobs are `new`'s first jobs, each the same (id, folder, flags, seeds,
    epochs: every field); [] otherwise. A plan folder of the campaign made before an entry joined
    "all" so continues (its runs kept) with the entry's jobs added at its end."""
    if tuple(saved.get("figures", ())) not in FORMER_ALL or tuple(new.get("figures", ())) != ENTRIES:
        return []
    old = [job_of(d) for d in saved.get("jobs", [])]
    jobs = [job_of(d) for d in new.get("jobs", [])]
    if not old or jobs[:len(old)] != old:
        return []
    return [j.id for j in jobs[len(old):]]


def part_of(small: dict, big: dict) -> bool:
    """Whether `small` is a plan of fewer figures whose every job is the job of the same id in
    `big` (same scale and added learners; each job's every field equal): a host that ran
    `--figures fig2-cartpole` ran jobs of the plan of every figure, and its folder gathers into
    that plan's."""
    if any(small.get(k) != big.get(k) for k in IDENTITY if k != "figures"):
        return False
    theirs = {d["id"]: job_of(d) for d in big.get("jobs", [])}
    mine = [job_of(d) for d in small.get("jobs", [])]
    return bool(mine) and all(theirs.get(j.id) == j for j in mine)


def read_plan(path: str) -> dict:
    with open(path) as f:
        return json.load(f)


def job_of(d: dict) -> Job:
    return Job(**{**d, "flags": tuple(d.get("flags", ()))})
