"""The run's progress bar on a console that is not a terminal (a file, a pipe, a job's log): one
whole line per redraw, at most every `BAR_LINE_SECONDS`, written to the console alone, so a
redirected console reads as lines (a newcomer's `bulbjax run ... > out.txt` was `\\r` fragments
between the stage lines) and the run's log.txt keeps the stage lines only; on a terminal the bar
draws as tqdm draws it."""

from __future__ import annotations

import io

from tqdm import tqdm

from bulbjax.run import console


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_redirected_bar_writes_whole_lines_to_the_console_alone() -> None:
    screen, log = io.StringIO(), io.StringIO()
    tee = console._Tee(screen, log)
    opts = console.bar_options(tee)
    assert opts["mininterval"] == console.BAR_LINE_SECONDS
    bar = tqdm(total=3, desc="CartPole x2 seeds", unit="epoch", **{**opts, "mininterval": 0})
    for _ in range(3):
        bar.update(1)
    bar.close()
    tee.write("[ 12.0 s] a stage line\n")
    lines = screen.getvalue().splitlines()
    assert "\r" not in screen.getvalue()
    bars = [line for line in lines if line.startswith("CartPole x2 seeds")]
    assert len(bars) >= 2 and "3/3" in bars[-1]  # the start and the end at least, each a line
    assert log.getvalue() == "[ 12.0 s] a stage line\n"  # the log file: no bar


def test_on_a_terminal_the_bar_is_tqdm_s() -> None:
    term, log = _Terminal(), io.StringIO()
    assert console.bar_options(term) == {"file": term}
    tee = console._Tee(term, log)
    opts = console.bar_options(tee)
    assert opts == {"file": tee}  # redrawn in place, as tqdm does
    bar = tqdm(total=2, desc="d", **opts, mininterval=0)
    bar.update(2)
    bar.close()
    assert "\r" in term.getvalue() and log.getvalue().strip() == ""  # redraws on the screen only
