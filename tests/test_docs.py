"""The docs name only flags and presets that exist.

Every `--flag` of a `bulbjax <cmd> ...` command in README.md, docs/*.md and benchmarks/README.md
(in a code block or an inline code span) must be an option of that subcommand's argparse parser
in bulbjax/cli.py; a lone `--flag` code span in README.md or docs/*.md must be an option of the
subcommand whose table row it sits in, or else of some subcommand; every `--preset NAME` and every code span that reads as a preset name (`fig2-...`)
must be a preset of bulbjax.config. The parser is the CLI's own: `main` is called with
`ArgumentParser.parse_args` patched to hand back the parser it built, so nothing runs.
"""

from __future__ import annotations

import argparse
import glob
import os
import re
from unittest import mock

import pytest

from doc_checks import (COMMAND_PAGES, PAGES, README_PAGES, ROOT, _FENCE, _SPAN, _Parser, _code_lines,
                        cli_flags, preset_names, problems)


@pytest.fixture(scope="module")
def flags() -> dict[str, set[str]]:
    return cli_flags()


@pytest.fixture(scope="module")
def presets() -> set[str]:
    return preset_names()


def test_parser_is_found(flags, presets):
    assert {"run", "report", "fit", "recon", "envs", "render"} <= set(flags)
    assert {"preset", "resume", "probe-every", "small"} <= flags["run"]
    assert "merge-seeds" in flags["report"] and "merge-seeds" not in flags["run"]
    assert {"fig2-cartpole", "fig2-invpend"} <= presets


@pytest.mark.parametrize("page", PAGES + COMMAND_PAGES)
def test_docs_name_only_existing_flags_and_presets(page, flags, presets):
    path = os.path.join(ROOT, page)
    assert os.path.exists(path), f"{page} is missing"
    with open(path, encoding="utf-8") as f:
        text = f.read()
    found = problems(text, flags, presets, where=page, lone_flags=page not in COMMAND_PAGES)
    assert not found, "the docs name flags or presets the CLI does not have:\n" + "\n".join(found)


def test_docs_cover_the_pages():
    names = {os.path.basename(p) for p in PAGES}
    assert {"README.md", "environments.md", "experiments.md", "probes.md", "performance.md", "results.md",
            "extending.md", "interop.md"} <= names


def test_the_checker_catches_what_does_not_exist(flags, presets):
    """The checks can fail: made-up flags, a flag of another subcommand, a made-up preset."""
    def bad(text: str) -> list[str]:
        return problems(text, flags, presets, where="t")

    assert bad("`bulbjax run --no-such-flag 3`") and "--no-such-flag" in bad("`bulbjax run --no-such-flag`")[0]
    assert bad("```bash\nbulbjax run --env CartPole \\\n    --no-such-flag 3\n```")  # continued line
    assert bad("```\n.venv/bin/bulbjax run --updates 5\n```")  # a flag of `bulbjax fit`, not of run
    assert bad("```\npython -m bulbjax.cli report runs/a --resume runs/a\n```")
    assert bad("`bulbjax frobnicate`") and bad("```\nbulbjax frobnicate --x 1\n```")
    assert bad("flags such as `--made-up-flag` exist")
    assert bad("```\nbulbjax run --preset fig9-nothing\n```") and bad("`--preset fig2-cartpol`")
    assert bad("the `fig2-pendulum` preset")
    assert bad("| `bulbjax report RUN` | redraw | `--merge-seeds`, `--updates` |")  # fit's flag in report's row
    assert not bad("| `bulbjax report RUN` | redraw | `--merge-seeds`, `--compare-rl` |")
    # and what exists passes
    assert not bad("```bash\nbulbjax run --preset fig2-invpend --bf16 --probe-every 10  # --no-such in a comment\n"
                   "bulbjax fit --updates 5 --resume\n```")
    assert not bad("`--probe-every` and `bulbjax report RUN --merge-seeds --out d` and `--preset NAME`")
    assert not bad("`python benchmarks/profile_epoch.py --trace-from-start DIR` and `--xla_gpu_autotune_level=0`")
    assert not bad("the file `bulbjax/cli.py --whatever` path")  # a path, not a command
    assert not bad("```\n# bulbjax and PyTorch side by side --compare\n```")  # a comment


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower().replace("`", ""))
    return text.replace(" ", "-")


def _anchors(path: str) -> set[str]:
    with open(path, encoding="utf-8") as f:
        text = f.read()
    heads, inside = [], False
    for line in text.splitlines():
        if _FENCE.match(line):
            inside = not inside
        elif not inside and (m := re.match(r"#{1,6}\s+(.*)", line)):
            heads.append(_slug(m.group(1)))
    return set(heads)


@pytest.mark.parametrize("page", PAGES + COMMAND_PAGES + README_PAGES)
def test_relative_links_resolve(page):
    """Every relative link of a page names a file of the repository (and a heading, with #)."""
    with open(os.path.join(ROOT, page), encoding="utf-8") as f:
        text = f.read()
    broken = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if target.startswith(("http://", "https://", "mailto:")):
            continue
        path, _, anchor = target.partition("#")
        full = os.path.normpath(os.path.join(ROOT, os.path.dirname(page), path)) if path else os.path.join(ROOT, page)
        if not os.path.exists(full):
            broken.append(f"{target}: no such file")
        elif anchor and full.endswith(".md") and anchor not in _anchors(full):
            broken.append(f"{target}: no heading #{anchor} in {os.path.relpath(full, ROOT)}")
    assert not broken, f"{page}: " + "; ".join(broken)


def test_slugs_follow_github():
    assert _slug("Several GPUs and hosts") == "several-gpus-and-hosts"
    assert _slug("metrics.jsonl") == "metricsjsonl"
    assert _slug("Interop (`bulbjax/interop/`, host-side adapters)") == "interop-bulbjaxinterop-host-side-adapters"


# a path of the repository naming a script: `benchmarks/before_after.py`, `tests/test_run.py`
_SCRIPT = re.compile(r"(?<![\w./-])((?:benchmarks|bulbjax|tests|examples|pybullet_compat|docs)/"
                     r"[\w./-]*\.(?:py|sh))\b")
# a commit before a path (`git show d5ec66c:benchmarks/diagnostics/bench_lstm.py`): that commit's file
_AT_COMMIT = re.compile(r"\b[0-9a-f]{7,40}:$")


def missing_scripts(text: str) -> list[str]:
    """The repository paths of scripts (`.py`, `.sh`) named anywhere in `text` that do not exist
    (a path named at a commit, `REV:path`, is that commit's and is not checked)."""
    named = {m.group(1) for m in _SCRIPT.finditer(text)
             if not _AT_COMMIT.search(text[max(0, m.start() - 41):m.start()])}
    return sorted(p for p in named if not os.path.exists(os.path.join(ROOT, p)))


@pytest.mark.parametrize("page", PAGES + COMMAND_PAGES + README_PAGES)
def test_named_scripts_exist(page):
    """A script a page names by its path exists there (issue 57: the before/after READMEs named
    `benchmarks/before_after.py` after it moved to `benchmarks/diagnostics/`; issue 66: it moved
    back, and the answered diagnostics left)."""
    with open(os.path.join(ROOT, page), encoding="utf-8") as f:
        gone = missing_scripts(f.read())
    assert not gone, f"{page} names scripts that do not exist: {', '.join(gone)}"


def test_the_script_check_catches_a_moved_script():
    assert len(README_PAGES) > 20 and "docs/results/before_after_dgrad/README.md" in README_PAGES
    moved = ("made by `benchmarks/diagnostics/before_after.py`:\n"
             "    python benchmarks/diagnostics/before_after.py run")
    assert missing_scripts(moved) == ["benchmarks/diagnostics/before_after.py"]
    assert not missing_scripts("`benchmarks/before_after.py`, `tests/test_docs.py`, "
                               "../shared/device/stage-wheels.sh, warp/_src/jax/ffi.py, "
                               "`git show d5ec66c:benchmarks/diagnostics/bench_lstm.py`")
    gone = "`d5ec66c benchmarks/diagnostics/bench_lstm.py`"  # a commit beside it, not before it
    assert missing_scripts(gone) == ["benchmarks/diagnostics/bench_lstm.py"]


# ---------------------------------------------------------------------------- lists and signatures
def _read(page: str) -> str:
    with open(os.path.join(ROOT, page), encoding="utf-8") as f:
        return f.read()


def _table_rows(text: str, header_start: str) -> list[list[str]]:
    """The body rows (cells, stripped) of the first markdown table whose header row starts with
    `header_start`."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(header_start))
    rows = []
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip().strip("|").split("|")])
    return rows


@pytest.mark.parametrize("page", ["README.md", "docs/experiments.md"])
def test_preset_lists_name_every_preset(page, presets):
    """The pages that list the presets list all of them (README named 5 of 7 once)."""
    spans = {m.group(1) for m in _SPAN.finditer(_read(page))}
    missing = sorted(presets - spans)
    assert not missing, f"{page} does not list the presets {missing}"


def test_preset_table_matches_the_presets(presets):
    from bulbjax.config import PRESETS

    rows = _table_rows(_read("docs/experiments.md"), "| preset |")
    names = [r[0].strip("`") for r in rows]
    assert sorted(names) == sorted(presets)
    for row, name in zip(rows, names):
        env = _SPAN.search(row[1]).group(1)
        assert env == PRESETS[name].env, f"docs/experiments.md: {name} is {PRESETS[name].env}, not {env}"


def test_make_signature_in_the_docs_is_the_code_s():
    """docs/environments.md's `bulbjax.make(...)` names every parameter of `bulbjax.make` with its
    default, in order."""
    import ast
    import inspect

    import bulbjax

    text = _read("docs/environments.md")
    start = text.index("env = bulbjax.make(name,")
    end = text.index(")\n", start)
    call = ast.parse(text[start + len("env = "):end + 1]).body[0].value
    doc = [(a.id, inspect.Parameter.empty) for a in call.args] + \
          [(k.arg, ast.literal_eval(k.value)) for k in call.keywords]
    code = [(p.name, p.default) for p in inspect.signature(bulbjax.make).parameters.values()]
    assert doc == code, f"docs/environments.md's make signature {doc} is not bulbjax.make's {code}"


def _bulbjax_args(line: str) -> list[str]:
    return line.split("#")[0].split("bulbjax ", 1)[1].split()


def test_demo_command_is_the_makefile_s():
    """README and docs/experiments.md give `make demo`'s command as the Makefile runs it."""
    make = next(line for line in _read("Makefile").splitlines() if "bin)/bulbjax run" in line.lower())
    want = _bulbjax_args(make.replace("$(BIN)/", ""))
    readme = next(line for _, line in _code_lines(_read("README.md")) if "runs/demo" in line)
    assert _bulbjax_args(readme) == want, f"README's demo command {readme!r} is not the Makefile's"
    exp = " ".join(_read("docs/experiments.md").split())
    span = re.search(r"`make demo` is `(bulbjax run [^`]+)`", exp).group(1)
    assert _bulbjax_args(span) == want, f"docs/experiments.md's demo {span!r} is not the Makefile's"


def test_readme_speedups_are_performance_md_s():
    """The README's "N x - M x more frames per second than PyBullet" ranges are those of the
    tables in performance.md's "Against PyBullet" (each table's, and both together)."""
    perf = _read("docs/performance.md")
    section = perf[perf.index("## Against PyBullet"):]
    section = section[:section.index("\n## ", 3)]
    ranges = []
    for header in ("| env | PyBullet, 16 processes |", "| env | PyBullet, 16 processes (frames/s)"):
        rows = _table_rows(section, header)
        ratios = [int(c[:-1]) for r in rows for c in r if re.fullmatch(r"\d+x", c)]
        assert len(ratios) == len(rows), f"performance.md: one ratio per row expected in {header}"
        ranges.append((min(ratios), max(ratios)))
    ranges.append((min(r[0] for r in ranges), max(r[1] for r in ranges)))
    readme = " ".join(_read("README.md").split())
    for lo, hi in ranges:
        assert f"{lo}x-{hi}x" in readme, f"README.md should give performance.md's {lo}x-{hi}x"


def test_domain_table_matches_the_classes():
    """docs/environments.md's "All domains" table: every registered domain in a row, with its
    action space, episode length and solved return ("-" where it has none)."""
    from bulbjax.envs.registry import ENV_NAMES, env_class

    rows = _table_rows(_read("docs/environments.md"), "| name | state entries")
    seen = set()
    for row in rows:
        spans = [m.group(1) for m in _SPAN.finditer(row[0])]
        names = [s for s in spans if s in ENV_NAMES]
        names += [n + s for n in names for s in spans if s in ("Md", "Sm") and n + s in ENV_NAMES]
        assert names, f"docs/environments.md: no domain in the row {row}"
        for name in names:
            cls = env_class(name)
            act = f"discrete({cls.num_actions})" if cls.discrete else f"box({cls.action_size})"
            solved = "-" if cls.solved_return is None else f"{cls.solved_return:,.0f}"
            assert (row[2], row[3], row[4]) == (act, f"{cls.episode_length:,}", solved), (name, row)
            seen.add(name)
    assert seen == set(ENV_NAMES), f"docs/environments.md lacks {sorted(set(ENV_NAMES) - seen)}"


def test_slow_tier_count_in_the_docs_is_the_suites() -> None:
    """README and docs/experiments.md say how many tests `make test` leaves out: the number that
    carries the `slow` mark (collected, not run)."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-m", "slow", "-p", "no:cacheprovider",
                          "-p", "no:xdist", os.path.join(ROOT, "tests")], capture_output=True, text=True, cwd=ROOT,
                         timeout=300).stdout
    n = sum("::" in line for line in out.splitlines())
    assert n > 0, out[-2000:]
    for page, pattern in (("README.md", r"slow tier of (\d+) tests"), (os.path.join("docs", "experiments.md"),
                                                                         r"The slow tier is (\d+) tests")):
        with open(os.path.join(ROOT, page), encoding="utf-8") as f:
            said = re.search(pattern, f.read())
        assert said and int(said.group(1)) == n, f"{page} says {said and said.group(1)} slow tests; the suite has {n}"


# ---------------------------------------------------------------------------- docs true to the folders
# a line that is only a placeholder name, as `KILL_RESUME_TABLE` stood in docs/runs.md (issue 65)
_PLACEHOLDER = re.compile(r"^[A-Z][A-Z0-9]*(?:_[A-Z0-9]+)+$")


def placeholders(text: str) -> list[int]:
    """Line numbers, outside code blocks, of lines that hold nothing but an ALL_CAPS_NAME."""
    out, inside = [], False
    for no, line in enumerate(text.splitlines(), 1):
        if _FENCE.match(line):
            inside = not inside
        elif not inside and _PLACEHOLDER.match(line.strip()):
            out.append(no)
    return out


@pytest.mark.parametrize("page", PAGES + COMMAND_PAGES + README_PAGES)
def test_no_placeholder_is_left(page):
    found = placeholders(_read(page))
    assert not found, f"{page}: a placeholder where text belongs, line(s) {found}"


def test_the_placeholder_check_catches_one():
    assert placeholders("results:\n\nKILL_RESUME_TABLE\n\nWhat the kills found") == [3]
    assert not placeholders("```\nBULBJAX_YCB_DIR\n```\n`BULBJAX_CACHE_DIR` is read\nA_b\n")


def test_readme_lists_every_docs_page():
    """README's Documentation list links every page of docs/ (issue 65: runs.md and soak.md were
    missing)."""
    text = _read("README.md")
    section = text[text.index("## Documentation"):]
    section = section[:section.index("\n## ")]
    linked = set(re.findall(r"\]\((docs/[^)#\s]+\.md)\)", section))
    pages = {p for p in PAGES if p.startswith("docs" + os.sep)}
    missing = sorted(p for p in pages if p.replace(os.sep, "/") not in linked)
    assert not missing, f"README's Documentation list lacks {missing}"


def test_kill_resume_table_is_the_json_s():
    """docs/runs.md's table of the kills is the newest committed `benchmarks/kill_resume.py`
    result, counted again from its JSON (it was a literal `KILL_RESUME_TABLE` once)."""
    import json

    results = sorted(glob.glob(os.path.join(ROOT, "benchmarks", "results", "kill_resume_*.json")))
    assert results, "no committed kill_resume result"
    text = _read("docs/runs.md")
    newest = os.path.basename(results[-1])
    assert f"](../benchmarks/results/{newest})" in text, f"docs/runs.md should link {newest}"
    with open(results[-1], encoding="utf-8") as f:
        result = json.load(f)
    rows = {r[0]: [int(c) for c in r[1:]] for r in _table_rows(text, "| where the kill landed |")}
    want: dict[str, list[int]] = {}
    for k in result["kills"]:
        counts = want.setdefault(k["doing"], [0] * 5)
        for i, hit in enumerate((True, k["state_after_kill"]["half_line"],
                                 k["state_after_kill"]["partial_checkpoints"] > 0,
                                 k.get("resume_ok") is True, k.get("resume_ok") is None)):
            counts[i] += bool(hit)
    want["all"] = [sum(c[i] for c in want.values()) for i in range(5)]
    assert rows == want, f"docs/runs.md's kill table {rows} is not {newest}'s {want}"
    s = result["summary"]
    assert want["all"][0] == s["kills"] and want["all"][3] == s["resumes_from_newest_complete_checkpoint"]
    said = " ".join(text.split())
    assert f"The {s['kills']} kills went to {s['runs_finished']} runs" in said
    assert f"all {s['runs_equal_to_reference']} finished" in said and s["runs_equal_to_reference"] == s["runs_finished"]
    assert f"reported {len(s['failures'])} failures" in said


def test_merged_folder_regenerates_as_the_docs_say(monkeypatch):
    """README's headline figure is a merged folder: it holds no metrics, and docs/experiments.md
    gives the `--merge-seeds` command over the halves it pooled (issue 65: the docs said every
    committed folder redraws with `bulbjax report DIR`)."""
    from bulbjax.report import merge

    monkeypatch.chdir(ROOT)
    image = re.search(r"!\[[^\]]*\]\((docs/results/[^)]+)/fig2\.png\)", _read("README.md")).group(1)
    assert os.path.exists(os.path.join(image, "config.json")) and not any(
        os.path.exists(os.path.join(image, n)) for n in ("metrics.jsonl", "metrics.jsonl.gz")), image
    halves = [os.path.normpath(h) for h in merge.merge_sources(image)]
    commands = [line for _, line in _code_lines(_read("docs/experiments.md"))
                if "--merge-seeds" in line and os.path.dirname(image) in line]
    assert commands, f"docs/experiments.md gives no --merge-seeds command for {image}"
    args = [a for a in _bulbjax_args(commands[0])[1:] if not a.startswith("--")]
    assert args[:len(halves)] == halves, f"docs/experiments.md merges {args}, the folder pooled {halves}"
    text = " ".join(_read("docs/experiments.md").split())
    assert f"e.g. README's headline `{image}`) holds no metrics" in text


def test_checkpoint_sizes_in_the_docs_are_the_states():
    """docs/experiments.md's in-memory sizes of the run state (what a checkpoint holds) are the
    state's: the Makefile's demo and a six-learner Fig. 2 preset, built as `bulbjax run` builds them
    (shapes only). The demo's checkpoint on disk (orbax compresses it) is smaller than its state."""
    import jax
    import numpy as np

    from bulbjax.epoch.loop import Experiment
    from bulbjax.run.settings import resolve
    from bulbjax.run_command import _settings

    def state_bytes(cfg) -> int:
        return sum(int(np.prod(x.shape)) * x.dtype.itemsize for x in jax.tree.leaves(Experiment(cfg).abstract_state()))

    def hand_back(self, *args, **kwargs):
        raise _Parser(self)

    from bulbjax import cli

    with mock.patch.object(argparse.ArgumentParser, "parse_args", hand_back):
        with pytest.raises(_Parser) as caught:
            cli.main(["envs"])
    make = next(line for line in _read("Makefile").splitlines() if "bin)/bulbjax run" in line.lower())
    args = caught.value.parser.parse_args(_bulbjax_args(make.replace("$(BIN)/", "")))
    demo = state_bytes(resolve(args.preset, **_settings(args)))
    preset = state_bytes(resolve("fig2-cartpole"))
    text = " ".join(_read("docs/experiments.md").split())
    m = re.search(r"the run state is ~([\d.]+) GB in memory for a six-learner Fig\. 2 preset with 6 seeds "
                  r"and ([\d.]+) MB for `make demo`", text)
    assert m, "docs/experiments.md should give the run state's size for a Fig. 2 preset and for make demo"
    assert float(m.group(1)) == round(preset / 1e9, 1), f"a Fig. 2 preset's state is {preset / 1e9:.2f} GB"
    assert float(m.group(2)) == round(demo / 1e6, 1), f"make demo's state is {demo / 1e6:.1f} MB"
    disk = re.search(r"`make demo`'s checkpoint is (\d+) MB", text)
    assert disk and int(disk.group(1)) < demo / 1e6


def test_readme_front_door():
    """README opens with what bulbjax is (at most three lines), then the two set-up commands in one
    block; it gives the GPU install with an extra pyproject.toml has, the paper's citation
    (BibTeX with an arXiv id) and the project's licence file beside the data licences (issue 65)."""
    tomllib = pytest.importorskip("tomllib")
    text = _read("README.md")
    head = text[:text.index("```")].splitlines()
    assert head[0] == "# bulbjax" and 1 <= len([x for x in head[1:] if x.strip()]) <= 3, head
    block = text[text.index("```bash\n") + 8:]
    block = block[:block.index("```")]
    assert [line.split()[:2] for line in block.splitlines()] == [["make", "demo"], ["make", "test"]], block
    with open(os.path.join(ROOT, "pyproject.toml"), "rb") as f:
        extras = tomllib.load(f)["project"]["optional-dependencies"]
    for extra in re.findall(r"pip install -e '\.\[(\w+)\]'", text):
        assert extra in extras, f"README installs the extra {extra!r}; pyproject.toml has {sorted(extras)}"
    assert "pip install -e '.[cuda]'" in text
    assert re.search(r"```bibtex\n@\w+\{[^`]*arXiv:\d{4}\.\d{4,5}", text), "README should give a BibTeX entry"
    assert "](LICENSE)" in text and os.path.exists(os.path.join(ROOT, "LICENSE"))
