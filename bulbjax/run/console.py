"""The console of a run: each start-up stage named with its elapsed time, a ticker while one runs
long, and the C++ libraries' log lines (XLA's autotuner: "Delay kernel timed out", "Very slow
compile?") kept in the run's `log.txt` instead of the user's console.

Before its first epoch a run may compile for minutes (the six-learner preset: ~3 minutes on a
fresh H100). `StageLog` prints `[  12.3 s] compiling the epoch ...` when a stage starts, its
duration when it ends, and `still compiling the epoch (95 s)` after 10 and 20 s and every 30 s
while it runs.

`log_to_file(path)` points file descriptor 2 (where XLA, absl and other C++ code write their
log lines) at the log file and puts a tee in `sys.stdout` and `sys.stderr`: Python's output
(progress, stage lines, warnings, tracebacks) still reaches the console and is copied into the
file; C++ log lines go only to the file. A crash in C++ (abort, segfault) prints Python's
traceback on the console (`faulthandler`), and a run that ends in an error names the log file.
"""

from __future__ import annotations

import contextlib
import datetime
import faulthandler
import os
import sys
import threading
import time
from typing import Any, Callable, Iterator, Sequence, TextIO


class StageLog:
    """`with stages("compiling the epoch"): ...` prints `[elapsed] compiling the epoch ...`, then
    `[elapsed] compiling the epoch: 27.8 s`, and while the stage runs, `[elapsed] still compiling
    the epoch (20 s)` after `first_ticks` seconds (10 and 20) and then every `tick` seconds (from
    a background thread: the main thread is blocked in a compile), so that the console is never
    silent for long. Elapsed times count from `t0` (default: now; the CLI's: the process start).
    `log` may be swapped (e.g. for a progress bar's `write`)."""

    def __init__(self, log: Callable[[str], None] = print, t0: float | None = None, tick: float = 30.0,
                 first_ticks: Sequence[float] = (10.0, 20.0)):
        self.log = log
        self.t0 = time.time() if t0 is None else t0
        self.tick = tick
        self.first_ticks = tuple(first_ticks)

    def elapsed(self) -> float:
        return time.time() - self.t0

    def line(self, text: str) -> None:
        self.log(f"[{self.elapsed():7.1f} s] {text}")

    def _ticks(self) -> Iterator[float]:
        """Seconds into a stage at which it is said to be still running."""
        yield from (t for t in self.first_ticks if t < self.tick)
        k = 1
        while True:
            yield k * self.tick
            k += 1

    @contextlib.contextmanager
    def __call__(self, what: str) -> Iterator[None]:
        start = time.time()
        self.line(f"{what} ...")
        done = threading.Event()

        def ticker() -> None:
            for at in self._ticks():
                if done.wait(max(0.0, start + at - time.time())):
                    return
                self.line(f"still {what} ({time.time() - start:.0f} s)")

        t = threading.Thread(target=ticker, daemon=True, name="bulbjax-stage-ticker")
        if self.tick > 0:
            t.start()
        try:
            yield
        finally:
            done.set()
            if t.is_alive():
                t.join()
        self.line(f"{what}: {time.time() - start:.1f} s")


def process_start_time() -> float:
    """When this process started (Linux: from /proc; elsewhere, now): the CLI counts its stage
    times from there, so Python's start-up and imports are on the console too."""
    try:
        with open("/proc/self/stat") as f:
            ticks = int(f.read().rsplit(")", 1)[1].split()[19])  # field 22, starttime
        with open("/proc/stat") as f:
            boot = next(float(line.split()[1]) for line in f if line.startswith("btime "))
        return boot + ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return time.time()


class _Tee:
    """A text stream that writes to the console and copies to the log file. Progress-bar redraws
    (text with a carriage return) are not copied: the file gets the lines a reader wants."""

    def __init__(self, console: TextIO, log: TextIO):
        self._console = console
        self._log = log

    def write(self, s: str) -> int:
        n = self._console.write(s)
        if "\r" not in s:
            try:
                self._log.write(s)
            except (OSError, ValueError):  # a full disk or a closed log never hides console output
                pass
        return n if n is not None else len(s)

    def flush(self) -> None:
        self._console.flush()
        try:
            self._log.flush()
        except (OSError, ValueError):
            pass

    def isatty(self) -> bool:
        return self._console.isatty()

    @property
    def console(self) -> TextIO:
        """The console alone (not the log file): where a redirected progress bar's lines go."""
        return self._console

    def fileno(self) -> int:
        return self._console.fileno()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._console, name)


class BarLines:
    """Where a progress bar draws on a console that is not a terminal (a file, a pipe, a job's
    log): each redraw becomes one whole line (its carriage returns dropped), so a redirected
    console reads as lines, not a bar's fragments between the stage lines. Pair it with a long
    `mininterval` (`bar_options`)."""

    def __init__(self, stream: TextIO):
        self._stream = stream

    def write(self, s: str) -> int:
        line = s.replace("\r", "").strip()
        if line:
            self._stream.write(line + "\n")
        return len(s)

    def flush(self) -> None:
        self._stream.flush()


BAR_LINE_SECONDS = 30.0  # a redirected console's progress line at most this often


def bar_options(stream: TextIO) -> dict[str, Any]:
    """tqdm's `file` and `mininterval` for `stream`: itself on a terminal; on anything else
    `BarLines` over the console alone (a `_Tee`'s log file keeps the stage lines, not the bar's),
    a line every `BAR_LINE_SECONDS` at most."""
    isatty = getattr(stream, "isatty", None)
    if isatty is not None and isatty():
        return {"file": stream}
    return {"file": BarLines(getattr(stream, "console", stream)), "mininterval": BAR_LINE_SECONDS}


@contextlib.contextmanager
def log_to_file(path: str, fresh: bool = False, header: str = "", preamble: Sequence[str] = ()) -> Iterator[str]:
    """Within the block: C++ log output (file descriptor 2) goes to `path` (appended, or
    truncated when `fresh`, after the `header` line and the `preamble` lines: what was said on
    the console before the file could be opened), Python's stdout and stderr go to the console
    and into `path`. On
    leaving, everything is put back; if the block raised an unexpected error (not a ValueError,
    whose message says what to do), the console is told where the log is.
    Yields `path`."""
    sys.stdout.flush()
    sys.stderr.flush()
    log = open(path, "w" if fresh else "a", buffering=1, encoding="utf-8", errors="replace")
    now = datetime.datetime.now().isoformat(timespec="seconds")
    log.write(f"==== {now} {header}\n")
    for line in preamble:
        log.write(f"{line}\n")
    saved_fd2 = os.dup(2)
    console_err = os.fdopen(os.dup(saved_fd2), "w", buffering=1, encoding=getattr(sys.stderr, "encoding", None)
                            or "utf-8", errors="backslashreplace")
    old_out, old_err = sys.stdout, sys.stderr
    had_faulthandler = faulthandler.is_enabled()
    os.dup2(log.fileno(), 2)  # C/C++ writes to fd 2 (absl/XLA logging) now land in the file
    sys.stdout, sys.stderr = _Tee(old_out, log), _Tee(console_err, log)
    faulthandler.enable(file=console_err)  # a C++ crash still shows a traceback on the console
    failed = False
    try:
        yield path
    except (ValueError, KeyboardInterrupt, SystemExit) as err:  # the user's errors: their message says it all
        print(f"{type(err).__name__}: {err}", file=log)
        raise
    except BaseException:
        failed = True
        raise
    finally:
        for s in (sys.stdout, sys.stderr):
            try:
                s.flush()
            except (OSError, ValueError):
                pass
        os.dup2(saved_fd2, 2)
        os.close(saved_fd2)
        sys.stdout, sys.stderr = old_out, old_err
        if had_faulthandler:  # on again, on the console (its earlier file is not known)
            try:
                faulthandler.enable(file=sys.stderr)
            except (ValueError, OSError, AttributeError):  # a stream without a file descriptor
                faulthandler.enable(file=sys.__stderr__)
        else:
            faulthandler.disable()
        console_err.close()
        log.close()
        if failed:
            print(f"(XLA's and other libraries' log lines of this run: {path})", file=sys.stderr)
