"""The order in which a run's programs compile (`BULBJAX_COMPILE_ORDER`): side by side by default,
one after another in trace order when asked, each result and error where it is asked for."""

from __future__ import annotations

import threading
import time

import pytest

from bulbjax.epoch.programs import Programs


class _Lowered:
    """Stands for a lowered program: `compile` takes `seconds` and records when it ran."""

    def __init__(self, name: str, log: list, seconds: float = 0.3, fail: bool = False):
        self.name, self.log, self.seconds, self.fail = name, log, seconds, fail

    def compile(self) -> str:
        start = time.perf_counter()
        time.sleep(self.seconds)
        self.log.append((self.name, start, time.perf_counter(), threading.current_thread().name))
        if self.fail:
            raise RuntimeError(f"{self.name} failed to compile")
        return f"executable of {self.name}"


class _Traced:
    def __init__(self, lowered: _Lowered):
        self._lowered = lowered

    def lower(self) -> _Lowered:
        return self._lowered


def _programs(log: list, fail: str = "") -> Programs:
    p = Programs.__new__(Programs)  # the compile machinery alone, no experiment traced
    p._traced = {n: _Traced(_Lowered(n, log, fail=n == fail)) for n in ("init", "epoch")}
    p._lowered, p._compiled, p._chain, p.compile_spans = {}, {}, None, {}
    p._t0 = time.perf_counter()
    return p


@pytest.mark.parametrize("order", ["side-by-side", "sequential"])
def test_programs_compile_side_by_side_or_one_after_another(order, monkeypatch):
    monkeypatch.setenv("BULBJAX_COMPILE_ORDER", order)
    log: list = []
    p = _programs(log).prepare("init", "epoch")
    assert p.compiled("epoch") == "executable of epoch" and p.compiled("init") == "executable of init"
    (first, s0, e0, _), (second, s1, e1, _) = sorted(log, key=lambda r: r[1])
    if order == "sequential":
        assert (first, second) == ("init", "epoch") and s1 >= e0  # in trace order, no overlap
    else:
        assert s1 < e0  # both compiling at once


def test_a_failed_compile_is_raised_where_asked_and_the_next_still_compiles(monkeypatch):
    monkeypatch.setenv("BULBJAX_COMPILE_ORDER", "sequential")
    p = _programs([], fail="init").prepare("init", "epoch")
    assert p.compiled("epoch") == "executable of epoch"
    with pytest.raises(RuntimeError, match="init failed to compile"):
        p.compiled("init")


def test_an_unknown_order_is_one_clear_error(monkeypatch):
    monkeypatch.setenv("BULBJAX_COMPILE_ORDER", "parallel")
    with pytest.raises(ValueError, match="side-by-side, sequential"):
        _programs([]).prepare("init")


def test_a_failed_physics_warm_up_is_one_line_and_not_the_runs_failure():
    """`run`'s wait for the physics warm-up (`SeedGroups.warm_physics`): a warm-up that failed is
    said once, in one line, and the run goes on (init builds the kernels itself)."""
    from concurrent.futures import Future

    from bulbjax.run.console import StageLog
    from bulbjax.run.loop import _physics_ready

    lines: list[str] = []
    stages = StageLog(lines.append)
    failed: Future = Future()
    failed.set_exception(RuntimeError("no CUDA context"))
    assert _physics_ready(failed, stages) is None and _physics_ready(None, stages) is None
    assert len(lines) == 1 and "warming MuJoCo Warp's kernels failed (RuntimeError: no CUDA context)" in lines[0]
    done: Future = Future()
    done.set_result(None)
    assert _physics_ready(done, stages) is None and len(lines) == 1
