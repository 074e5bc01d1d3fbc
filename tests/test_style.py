"""The line-length limit of the style notes (`../shared/reference/style-notes.md`: "pick a limit
(100) and hold it"), held by the files that were brought under it: the command line
(`bulbjax/cli.py`, `bulbjax/run_command.py`) and PPO's policy and observation modes
(`bulbjax/epoch/policy.py`, `bulbjax/epoch/observations.py`). A file joins `HELD` once it keeps
the limit; the test reads the files as text (nothing is imported)."""

from __future__ import annotations

import os

import pytest

LIMIT = 100
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
HELD = ("bulbjax/cli.py", "bulbjax/run_command.py", "bulbjax/epoch/policy.py",
        "bulbjax/epoch/observations.py")


def long_lines(text: str, limit: int = LIMIT) -> list[str]:
    """Every line of `text` longer than `limit` characters, as 'line n: length'."""
    return [f"line {i}: {len(line)}" for i, line in enumerate(text.splitlines(), 1)
            if len(line) > limit]


@pytest.mark.parametrize("path", HELD)
def test_lines_keep_to_the_limit(path: str) -> None:
    with open(os.path.join(ROOT, path), encoding="utf-8") as f:
        bad = long_lines(f.read())
    assert not bad, f"{path}: lines over {LIMIT} characters:\n" + "\n".join(bad)


def test_the_check_sees_a_long_line() -> None:
    """The check counts characters, not bytes, and names the line."""
    assert long_lines("a\n" + "x" * 100 + "\n" + "é" * 101) == ["line 3: 101"]
