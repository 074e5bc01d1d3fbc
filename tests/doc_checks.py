"""What tests/test_docs.py checks the docs with: the pages it reads, the CLI's own parser (its
subcommands and flags, read without running anything) and `problems`, which finds every flag or
preset a page names that the CLI does not have."""

from __future__ import annotations

import argparse
import glob
import os
import re
from unittest import mock

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# pages a user looks things up in: every flag-like code span must be a CLI flag there
PAGES = ["README.md", *sorted(os.path.relpath(p, ROOT) for p in glob.glob(os.path.join(ROOT, "docs", "*.md")))]
# pages that also document other scripts' flags: only `bulbjax ...` commands and presets are checked
COMMAND_PAGES = ["benchmarks/README.md"]
# the READMEs of docs/ subfolders (result folders) and of benchmarks/diagnostics: their links and
# the scripts they name must exist
README_PAGES = sorted({os.path.relpath(p, ROOT)
                       for p in glob.glob(os.path.join(ROOT, "docs", "*", "**", "README.md"), recursive=True)}
                      | {"benchmarks/diagnostics/README.md"})

# `bulbjax run`, `.venv/bin/bulbjax run`, `python -m bulbjax.cli run` (not `bulbjax/cli.py`)
_COMMAND = re.compile(r"(?<![\w/.-])(?:[\w./-]*/)?bulbjax(?:\.cli)?\s+([a-z]+)\b")
# a long option: `--probe-every`, not `--xla_gpu_autotune_level` (XLA's) nor `---`
_FLAG = re.compile(r"(?<![\w-])--([a-z][a-z0-9]*(?:-[a-z0-9]+)*)(?![\w-])")
_PRESET_ARG = re.compile(r"--preset[ =]+([\w.-]+)")
_PRESET_LIKE = re.compile(r"^fig\d+-[a-z0-9-]+$")
_FENCE = re.compile(r"^\s*(```|~~~)")
_SPAN = re.compile(r"`([^`\n]+)`")


class _Parser(Exception):
    def __init__(self, parser: argparse.ArgumentParser):
        super().__init__("parser")
        self.parser = parser


def cli_flags() -> dict[str, set[str]]:
    """{subcommand: its long options} of the parser `bulbjax.cli.main` builds."""
    from bulbjax import cli

    def hand_back(self, *args, **kwargs):
        raise _Parser(self)

    with mock.patch.object(argparse.ArgumentParser, "parse_args", hand_back):
        with pytest.raises(_Parser) as caught:
            cli.main(["envs"])
    parser = caught.value.parser
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    assert len(subs) == 1, "bulbjax's CLI should have one set of subcommands"
    return {name: {o[2:] for a in sub._actions for o in a.option_strings if o.startswith("--")}
            for name, sub in subs[0].choices.items()}


def preset_names() -> set[str]:
    from bulbjax import config

    return set(config.PRESETS)


def _commands(text: str) -> list[tuple[str, str]]:
    """(subcommand, the rest of the line) for each `bulbjax <cmd>` in `text` (one line or span)."""
    found = list(_COMMAND.finditer(text))
    out = []
    for i, m in enumerate(found):
        end = found[i + 1].start() if i + 1 < len(found) else len(text)
        out.append((m.group(1), text[m.end():end]))
    return out


def _code_lines(text: str) -> list[tuple[int, str]]:
    """Lines of fenced code blocks (continuation backslashes joined, `# ...` comments cut)."""
    out, inside, buf, start = [], False, "", 0
    for no, line in enumerate(text.splitlines(), 1):
        if _FENCE.match(line):
            inside = not inside
            continue
        if not inside:
            continue
        if not buf:
            start = no
        if line.rstrip().endswith("\\"):
            buf += line.rstrip()[:-1] + " "
            continue
        full, buf = buf + line, ""
        out.append((start, re.split(r"(?:^|\s)#(?:\s|$)", full, maxsplit=1)[0]))
    return out


def _spans(text: str) -> list[tuple[int, str, str | None]]:
    """Inline code spans outside fenced blocks: (line number, span, the subcommand of the table
    row it sits in: a row whose first command span is `bulbjax <cmd>`, else None)."""
    out, inside = [], False
    for no, line in enumerate(text.splitlines(), 1):
        if _FENCE.match(line):
            inside = not inside
            continue
        if inside:
            continue
        spans = [m.group(1) for m in _SPAN.finditer(line)]
        row = None
        if line.lstrip().startswith("|"):
            row = next((c for sp in spans for c, _ in _commands(sp)), None)
        out += [(no, sp, row) for sp in spans]
    return out


def problems(text: str, flags: dict[str, set[str]], presets: set[str], where: str = "",
             lone_flags: bool = True) -> list[str]:
    """What in `text` names a flag or preset the CLI does not have, one line each.

    `lone_flags`: a code span that is not a `bulbjax` command but holds `--flag`s (and no script:
    `.py`, `.sh`, `python`) must name flags of its table row's subcommand, or else of some
    subcommand."""
    every = set().union(*flags.values())
    out = []

    def check_command(no: int, piece: str) -> None:
        for cmd, rest in _commands(piece):
            if cmd not in flags:
                if not (_FLAG.search(rest) or piece.lstrip().startswith(f"bulbjax {cmd}")):
                    continue  # prose ("bulbjax and PyTorch"), not a command
                out.append(f"{where}:{no}: `bulbjax {cmd}`: no such subcommand (has {', '.join(sorted(flags))})")
                continue
            for f in _FLAG.findall(rest):
                if f not in flags[cmd]:
                    out.append(f"{where}:{no}: `bulbjax {cmd} --{f}`: no such flag of `bulbjax {cmd}`")

    def check_presets(no: int, piece: str) -> None:
        for name in _PRESET_ARG.findall(piece):
            if name.upper() != name and name not in presets:  # NAME, PRESET: placeholders
                out.append(f"{where}:{no}: --preset {name}: no such preset (has {', '.join(sorted(presets))})")

    for no, line in _code_lines(text):
        check_command(no, line)
        check_presets(no, line)
    for no, span, row in _spans(text):
        check_presets(no, span)
        if _PRESET_LIKE.match(span.strip()) and span.strip() not in presets:
            out.append(f"{where}:{no}: `{span}` reads as a preset name and is none (has {', '.join(sorted(presets))})")
        if _commands(span):
            check_command(no, span)
        elif lone_flags and not re.search(r"\.py\b|\.sh\b|\bpython\b", span):
            for f in _FLAG.findall(span):
                if row in flags and f not in flags[row]:
                    out.append(f"{where}:{no}: `{span}` in the row of `bulbjax {row}`: no such flag of it")
                elif f not in every:
                    out.append(f"{where}:{no}: `{span}`: --{f} is no flag of any bulbjax subcommand")
    return out
