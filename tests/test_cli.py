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
    from bulbjax.experiment.config import PRESETS
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
    from bulbjax.experiment.config import ExperimentConfig
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
    assert f"table: {os.path.join(out, 'table.md')}" in capsys.readouterr().out
    assert cli.main(["report", run]) == 0  # without --out: into the run folder, as before
    assert {"fig2.png", "table.md", "findings.md"} <= set(os.listdir(run))


def test_warp_line_is_dropped_and_everything_else_kept(capfd):
    from bulbjax.envs.render import NO_DRIVER_LINE, without_stderr_line

    def native_init() -> int:  # what Warp's C++ init does: write straight to file descriptor 2
        os.write(2, f"{NO_DRIVER_LINE} GPU execution will not be available.\n".encode())
        os.write(2, b"Warp CUDA error: a real one\n")
        return 7

    assert without_stderr_line(native_init, NO_DRIVER_LINE) == 7
    err = capfd.readouterr().err
    assert "a real one" in err and NO_DRIVER_LINE not in err
