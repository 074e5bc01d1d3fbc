"""The line-length limit of the style notes (`../shared/reference/style-notes.md`: "pick a limit
(100) and hold it"), held by the files that were brought under it: the command line
(`bulbjax/cli.py`, `bulbjax/run_command.py`) and PPO's policy and observation modes
(`bulbjax/epoch/rollouts/policy.py`, `.../observations.py`). A file joins `HELD` once it keeps
the limit; the test reads the files as text (nothing is imported). And the size of a folder."""

from __future__ import annotations

import os

import pytest

LIMIT = 100
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
HELD = ("bulbjax/cli.py", "bulbjax/run_command.py", "bulbjax/env_commands.py", "bulbjax/epoch/rollouts/policy.py",
        "bulbjax/epoch/rollouts/observations.py", "bulbjax/envs/warp_steps.py", "tests/test_warp_steps.py",
        "tests/test_reproduce_device_kind.py", "benchmarks/bench_split.py", "bulbjax/reproduce/mps.py",
        "tests/test_reproduce_mps.py", "bulbjax/report/merge.py", "tests/test_reproduce_warm.py",
        "bulbjax/epoch/apart.py")


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


# a folder of the package a reader takes in at a glance (issue 66: "no folder in bulbjax/ over
# ~15 files or ~3K lines"); a folder that grows past them splits into folders named for what
# they hold, as envs/objects, learners/spair and epoch/rollouts did
MAX_FILES, MAX_LINES = 15, 3000


def folder_sizes(root: str) -> dict[str, tuple[int, int]]:
    """Every folder under `root` holding Python files: (its .py files, their lines), its own
    files only (a subfolder counts for itself)."""
    out = {}
    for here, _, names in os.walk(root):
        py = [n for n in names if n.endswith(".py")]
        if py and "__pycache__" not in here:
            lines = 0
            for n in py:
                with open(os.path.join(here, n), encoding="utf-8") as f:
                    lines += sum(1 for _ in f)
            out[os.path.relpath(here, ROOT)] = (len(py), lines)
    return out


def test_folders_stay_small() -> None:
    sizes = folder_sizes(os.path.join(ROOT, "bulbjax"))
    assert "bulbjax/epoch/rollouts" in sizes and "bulbjax" in sizes  # it looked
    big = {d: s for d, s in sizes.items() if s[0] > MAX_FILES or s[1] > MAX_LINES}
    assert not big, f"folders over {MAX_FILES} files or {MAX_LINES} lines (files, lines): {big}"


# a Python file a reader takes in whole (the brief: "no tracked Python file over ~500 lines");
# a test file that grows past it moves its helpers to a module of their own (tests/doc_checks.py,
# env_bundles.py, tiny_experiment.py) or a topic to a file of its own (test_env_registry.py)
MAX_FILE_LINES = 500
SOURCE_FOLDERS = ("bulbjax", "tests", "benchmarks", "pybullet_compat", "examples")


def long_files(root: str, folders: tuple[str, ...] = SOURCE_FOLDERS,
               limit: int = MAX_FILE_LINES) -> dict[str, int]:
    """{path: lines} of every .py file under `root`'s `folders` longer than `limit` lines."""
    out = {}
    for folder in folders:
        for here, dirs, names in os.walk(os.path.join(root, folder)):
            dirs[:] = [d for d in dirs if d != "__pycache__" and not d.startswith(".")]
            for n in names:
                if n.endswith(".py"):
                    path = os.path.join(here, n)
                    with open(path, encoding="utf-8") as f:
                        lines = sum(1 for _ in f)
                    if lines > limit:
                        out[os.path.relpath(path, root)] = lines
    return out


def test_files_stay_short(tmp_path) -> None:
    assert not long_files(ROOT), f"Python files over {MAX_FILE_LINES} lines: {long_files(ROOT)}"
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "long.py").write_text("x = 1\n" * (MAX_FILE_LINES + 1))
    (tmp_path / "tests" / "short.py").write_text("x = 1\n" * MAX_FILE_LINES)
    assert long_files(str(tmp_path)) == {os.path.join("tests", "long.py"): MAX_FILE_LINES + 1}
