"""What a newcomer meets on the command line (issue 58): every option of every subcommand has a
help text and shows its default, generated from the parser; the preset and learner lists of the
help come from the code; `bulbjax envs` prints no solved return where a domain has none;
`bulbjax report RUN_DIR --out OUT` writes into OUT and leaves RUN_DIR alone; Warp's no-driver
line is dropped from what its start-up prints (that a CPU run prints none: tests/test_packaging.py).
Nothing here compiles a program."""

from __future__ import annotations

import argparse
import os
from unittest import mock

import pytest

from bulbjax import cli


class _Parser(Exception):
    def __init__(self, parser: argparse.ArgumentParser):
        super().__init__("parser")
        self.parser = parser


@pytest.fixture(scope="module")
def subparsers() -> dict[str, argparse.ArgumentParser]:
    """{subcommand: its parser}, as `cli.main` builds them (parse_args patched to hand back the
    parser: nothing runs)."""
    def hand_back(self, *args, **kwargs):
        raise _Parser(self)

    with mock.patch.object(argparse.ArgumentParser, "parse_args", hand_back):
        with pytest.raises(_Parser) as caught:
            cli.main(["envs"])
    subs = [a for a in caught.value.parser._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(subs[0].choices)


def _options(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    return [a for a in parser._actions
            if a.option_strings and not isinstance(a, argparse._HelpAction)]


def _help_of(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    return parser._get_formatter()._expand_help(action)


def _shows_default(default: object, text: str) -> bool:
    """Whether a help text shows the default (None and False: nothing to show)."""
    if default is None or default is False:
        return True
    forms = {str(default)} | ({f"{default:g}"} if isinstance(default, float) else set())
    return any(f in text for f in forms)


def test_every_option_has_help_and_shows_its_default(subparsers):
    missing, hidden = [], []
    for cmd, parser in subparsers.items():
        for action in _options(parser):
            text = _help_of(parser, action)
            flag = f"bulbjax {cmd} {action.option_strings[-1]}"
            if not (action.help or "").strip():
                missing.append(flag)
            if not _shows_default(action.default, text):
                hidden.append(f"{flag} (default {action.default!r}): {text}")
    assert not missing, f"options without help: {missing}"
    assert not hidden, "options whose help does not show their default:\n" + "\n".join(hidden)
    render = subparsers["render"].format_help()
    for shown in ("(default: CartPole)", "(default: frames.png)", "(default: 8)", "(default: 64)"):
        assert shown in " ".join(render.split()), render


def test_help_lists_every_preset_and_learner(subparsers):
    from bulbjax.config import PRESETS
    from bulbjax.learners import learner_names

    for cmd in ("run", "fit"):
        parser = subparsers[cmd]
        preset = next(a for a in _options(parser) if "--preset" in a.option_strings)
        learners = next(a for a in _options(parser) if "--learners" in a.option_strings)
        for name in PRESETS:
            assert name in preset.help, f"`bulbjax {cmd} --help` lacks preset {name}"
        listed = learners.help.split("learner names: ", 1)[1].split(" ", 1)[0].split(",")
        assert listed == list(learner_names()), learners.help
        assert "MODULE:NAME" in learners.help


def test_reproduce_help_states_each_default_once(subparsers):
    """`bulbjax reproduce --help` uses the other subcommands' formatter (it alone used argparse's
    ArgumentDefaultsHelpFormatter: `(default all visible) ... (default 1) (default: None)`, and
    `(default: False)` on switches): every option's help says its default once, switches none;
    no subcommand shows a default of None or False."""
    parser = subparsers["reproduce"]
    assert parser.formatter_class is cli.HelpFormatter
    twice = []
    for action in _options(parser):
        text = _help_of(parser, action)
        if text.count("default") != (0 if action.default is False else 1):
            twice.append(f"{action.option_strings[-1]}: {text}")
    assert not twice, "\n".join(twice)
    for cmd, sub in subparsers.items():
        text = " ".join(sub.format_help().split())
        assert "(default: None)" not in text and "(default: False)" not in text, cmd


def test_the_top_level_help_says_what_bulbjax_is(capsys):
    """`bulbjax --help` opens with what the tool is and what each command does (it opened with the
    module's internal note, "parsing only: the flags map to `bulbjax.run.settings`")."""
    with pytest.raises(SystemExit) as caught:
        cli.main(["--help"])
    assert caught.value.code == 0
    opening = capsys.readouterr().out.split("\n\n")[1]
    assert opening.startswith("bulbjax: the bulb benchmark of unsupervised representation learning")
    assert "parsing only" not in opening and "bulbjax." not in opening  # no module of the code
    for cmd in ("run", "fit", "report", "recon", "envs", "render", "reproduce"):
        assert f"`{cmd}`" in opening, cmd


def test_envs_prints_no_solved_return_where_there_is_none(capsys):
    from bulbjax.envs.registry import env_class

    assert cli.main(["envs"]) == 0
    lines = {line.split()[0]: line for line in capsys.readouterr().out.splitlines() if line.strip()}
    assert "solved 190;" in lines["CartPole"] and "solved 950;" in lines["InvertedPendulum"]
    for name in ("GeomOnIncline", "YcbOnInclineSm", "ReacherRearrangeGeom",
                 "FrankaRearrangeOneYcb"):
        assert env_class(name).solved_return is None
        assert "solved -;" in lines[name], lines[name]


def _run_dir(path: str) -> str:
    """A run folder as `bulbjax run` leaves it (config.json, metrics.jsonl), synthetic records."""
    from bulbjax.config import ExperimentConfig
    from run_folders import write_synthetic_run

    return write_synthetic_run(path, ExperimentConfig(env="InvertedPendulum", learners=("vae", "vae_rpl"),
                                                      seeds=2, epochs=2))


def test_report_out_writes_elsewhere_and_leaves_the_run_alone(tmp_path, capsys):
    run = _run_dir(str(tmp_path / "run"))
    before = sorted(os.listdir(run))
    out = str(tmp_path / "redrawn")
    assert cli.main(["report", run, "--out", out]) == 0
    assert sorted(os.listdir(run)) == before  # nothing written into the run folder
    for name in ("fig2.png", "table.md", "findings.md"):
        assert os.path.getsize(os.path.join(out, name)) > 0
    said = capsys.readouterr().out  # where each file went, one line each
    for what, name in (("plot", "fig2.png"), ("table", "table.md"), ("findings", "findings.md")):
        assert f"{what}: {os.path.join(out, name)}" in said
    assert "objects:" not in said  # no objects in InvertedPendulum: no line for a file not there
    stale = os.path.join(out, "objects.png")  # another report's file, left in the folder long ago
    open(stale, "wb").close()
    os.utime(stale, (0, 0))
    assert cli.main(["report", run, "--out", out]) == 0
    assert "objects:" not in capsys.readouterr().out  # not said as written
    assert cli.main(["report", run]) == 0  # without --out: into the run folder, as before
    assert {"fig2.png", "table.md", "findings.md"} <= set(os.listdir(run))


def _cut(path: str, line: int, keep: int = 40) -> tuple[str, str]:
    """Cut line `line` (1-based) of `path` to its first `keep` characters (with no newline after it
    where it is the last, as a run killed while writing it leaves it); returns the cut text and
    the JSON parser's complaint about it."""
    import json

    with open(path) as f:
        lines = f.read().splitlines()
    lines[line - 1] = lines[line - 1][:keep]
    with open(path, "w") as f:
        f.write("\n".join(lines) + ("\n" if line < len(lines) else ""))
    try:
        json.loads(lines[line - 1])
    except json.JSONDecodeError as err:
        return lines[line - 1], f"{err.msg}, column {err.colno}"
    raise AssertionError("the cut line still parses")


def test_report_names_the_file_and_line_of_a_corrupt_record(tmp_path, capsys):
    """A line cut in the middle of metrics.jsonl is a one-line error naming the file and the line
    (it was the JSON parser's `Expecting ',' delimiter: line 1 column 51` alone); nothing is drawn."""
    run = _run_dir(str(tmp_path / "run"))
    path = os.path.join(run, "metrics.jsonl")
    _, why = _cut(path, 2)
    assert cli.main(["report", run]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"bulbjax: error: {path}:2: not a whole JSON record ({why}): the file is corrupt; "
                   "repair or delete that line")
    assert not os.path.exists(os.path.join(run, "table.md"))


def test_report_skips_a_cut_last_line_and_says_so(tmp_path, capsys):
    """A last line cut short (a run killed while writing it) is skipped with one warning line
    naming the file and the line (it was skipped silently); the report draws the rest."""
    run = _run_dir(str(tmp_path / "run"))
    path = os.path.join(run, "metrics.jsonl")
    _cut(path, 4)  # 2 epochs x 2 seeds: the last record cut
    assert cli.main(["report", run]) == 0
    err = capsys.readouterr().err.strip()
    assert err == (f"bulbjax: warning: {path}:4: skipped its last line, cut short (a run stopped while "
                   "writing it); read the 3 whole records before it")
    with open(os.path.join(run, "table.md")) as f:
        assert "from 3 records" in f.read()


def test_a_closed_stdout_ends_the_command_quietly():
    """`bulbjax envs | head -2`: the reader is gone before the listing is written; the command
    ends with no traceback (it ended in a BrokenPipeError's) and the status of a command a closed
    pipe ended, 141 (128 + SIGPIPE). The pipe's reader is closed before the process starts, so
    every write fails, whatever the timing."""
    import subprocess
    import sys

    read, write = os.pipe()
    os.close(read)
    try:
        r = subprocess.run([sys.executable, "-m", "bulbjax", "envs"], stdout=write,
                           stderr=subprocess.PIPE, text=True, timeout=120)
    finally:
        os.close(write)
    assert r.returncode == 141, r.stderr
    assert not any(w in r.stderr for w in ("Traceback", "BrokenPipeError", "Exception ignored")), r.stderr


def test_warp_line_is_dropped_and_everything_else_kept(capfd):
    from bulbjax.envs.render import NO_DRIVER_LINE, without_stderr_line

    def native_init() -> int:  # what Warp's C++ init does: write straight to file descriptor 2
        os.write(2, f"{NO_DRIVER_LINE} GPU execution will not be available.\n".encode())
        os.write(2, b"Warp CUDA error: a real one\n")
        return 7

    assert without_stderr_line(native_init, NO_DRIVER_LINE) == 7
    err = capfd.readouterr().err
    assert "a real one" in err and NO_DRIVER_LINE not in err


def test_report_over_plan_folders_points_to_gather(tmp_path, capsys):
    """`bulbjax report` over two `bulbjax reproduce` folders (a plan's shards brought back from
    their hosts) says to gather them, in one line (it said it redraws one run, and with
    --merge-seeds that a run's config.json is missing)."""
    hosts = [tmp_path / "h1", tmp_path / "h2"]
    for h in hosts:
        h.mkdir()
        (h / "plan.json").write_text("{}")
    for extra in ([], ["--merge-seeds", "--out", str(tmp_path / "m")]):
        assert cli.main(["report", *map(str, hosts), *extra]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and f"bulbjax reproduce --out DIR --gather {hosts[0]},{hosts[1]}" in err, err
