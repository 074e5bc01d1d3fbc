"""Run folders (`bulbjax.run.rundir`, `console`): `bulbjax run` / `bulbjax fit` over a
folder that holds a run is a one-line error that deletes nothing, `--overwrite` starts afresh, an
unwritable folder fails before anything is built, metrics appends are whole records or nothing,
the start-up stages are named with a ticker, and C++ log lines go to the run's log.txt."""

from __future__ import annotations

import errno
import json
import os
import sys
import time

import pytest

from bulbjax.cli import main
from bulbjax.report import records
from bulbjax.run import rundir
from bulbjax.run.console import StageLog, log_to_file

RUN_ARGS = ["run", "--env", "CartPole", "--learners", "vae", "--seeds", "1", "--epochs", "2", "--small"]


def _fake_run(d, epochs_done: int = 3, checkpoint: int | None = 2) -> dict[str, bytes]:
    """A run folder as `bulbjax run` leaves it (config.json, metrics.jsonl, a checkpoint);
    returns every file's bytes, to check that nothing was touched."""
    os.makedirs(d, exist_ok=True)
    with open(os.path.join(d, "config.json"), "w") as f:
        json.dump({"experiment": {"env": "CartPole", "learners": ["vae", "vae_rpl"], "epochs": 6}}, f)
    records.write_jsonl(os.path.join(d, "metrics.jsonl"),
                       [{"epoch": e, "seed": s} for e in range(epochs_done) for s in range(2)])
    with open(os.path.join(d, "fig2.png"), "wb") as f:
        f.write(b"png")
    if checkpoint is not None:
        os.makedirs(os.path.join(d, "checkpoints", str(checkpoint)))
        with open(os.path.join(d, "checkpoints", str(checkpoint), "state"), "wb") as f:
            f.write(b"state")
    return _snapshot(d)


def _snapshot(d) -> dict[str, bytes]:
    out = {}
    for root, _, files in os.walk(d):
        for name in files:
            p = os.path.join(root, name)
            with open(p, "rb") as f:
                out[os.path.relpath(p, d)] = f.read()
    return out


def test_run_over_a_run_is_one_line_naming_it(tmp_path, capsys):
    d = str(tmp_path / "demo")
    before = _fake_run(d)
    assert main([*RUN_ARGS, "--out", d]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert f"{d} holds a run (CartPole (vae, vae_rpl), 3 of 6 epochs in metrics.jsonl, " \
           "newest checkpoint at epoch 2)" in err
    assert f"--resume {d}" in err and "--overwrite" in err
    assert _snapshot(d) == before  # nothing deleted or written (no log.txt either)
    # the same for the Python API
    from bulbjax.config import ExperimentConfig, RunOptions
    from bulbjax.run import run

    with pytest.raises(rundir.RunFolderExists, match="holds a run"):
        run(ExperimentConfig(), RunOptions(), d)
    assert _snapshot(d) == before
    # a run killed before any checkpoint still holds its metrics: refused as well
    d2 = str(tmp_path / "nockpt")
    _fake_run(d2, epochs_done=1, checkpoint=None)
    assert main([*RUN_ARGS, "--out", d2]) == 2
    assert "1 of 6 epochs in metrics.jsonl, no complete checkpoint" in capsys.readouterr().err
    # --resume with --overwrite: a contradiction, said as such
    assert main(["run", "--resume", d, "--overwrite"]) == 2
    assert "give one of them" in capsys.readouterr().err
    assert _snapshot(d) == before


def test_overwrite_reaches_the_run(tmp_path, monkeypatch):
    """`--overwrite` is passed on (the run itself, deleting and starting afresh, is tested in
    test_run.py on a prebuilt experiment); the log file starts afresh too."""
    import bulbjax.run as run_mod  # the face `bulbjax run` calls `run` through

    d = str(tmp_path / "demo")
    _fake_run(d)
    got = {}

    def fake_run(cfg, opts, out, **kw):
        got.update(kw, out=out)
        print("inside the run")

    monkeypatch.setattr(run_mod, "run", fake_run)
    with open(os.path.join(d, "log.txt"), "w") as f:
        f.write("the old run's log\n")
    assert main([*RUN_ARGS, "--out", d, "--overwrite"]) == 0
    assert got["overwrite"] is True and got["resume"] is False and got["out"] == d
    log = open(os.path.join(d, "log.txt")).read()
    assert "old run" not in log and "inside the run" in log and "--overwrite" in log.splitlines()[0]


def test_an_empty_or_unrelated_folder_is_not_a_run(tmp_path):
    d = tmp_path / "x"
    (d / "checkpoints").mkdir(parents=True)  # a run stopped while compiling leaves this
    (d / "log.txt").write_text("compiling\n")
    (d / "data").mkdir()  # a fit's dataset cache
    assert rundir.holds(str(d)) == [] and rundir.holds(str(d), rundir.FIT_FILES) == []
    rundir.check_out_dir(str(d), resume=False, overwrite=False)
    (d / "checkpoints" / "4.orbax-checkpoint-tmp-123").mkdir()  # a checkpoint being written
    assert rundir.holds(str(d)) == ["checkpoints"]
    assert rundir.checkpoint_steps(str(d)) == [] and len(rundir.partial_checkpoints(str(d))) == 1


def test_unwritable_out_folder_fails_before_the_run(tmp_path, monkeypatch, capsys):
    """A read-only or full folder: one line before anything is built. Root ignores permission
    bits, so the error is injected at the probe's write (as a read-only mount answers it)."""
    d = str(tmp_path / "ro")
    os.makedirs(d)
    real = rundir._write_all

    def refuse(fd, data):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(rundir, "_write_all", refuse)
    with pytest.raises(ValueError, match=r"cannot write to the run folder .*Read-only file system \(EROFS\)"):
        rundir.check_out_dir(d, resume=False, overwrite=False)
    t = time.time()
    assert main([*RUN_ARGS, "--out", d]) == 2
    assert time.time() - t < 10  # before the environment is built
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "cannot write to the run folder" in err and "EROFS" in err
    assert os.listdir(d) == []  # the probe file is gone
    monkeypatch.setattr(rundir, "_write_all", real)
    if os.geteuid() != 0:  # a real read-only folder where permissions apply
        os.chmod(d, 0o500)
        try:
            with pytest.raises(ValueError, match="cannot write to the run folder"):
                rundir.check_out_dir(d, resume=False, overwrite=False)
        finally:
            os.chmod(d, 0o700)
    rundir.check_out_dir(d, resume=False, overwrite=False)
    f = tmp_path / "afile"
    f.write_text("x")
    with pytest.raises(ValueError, match="is a file"):
        rundir.check_out_dir(str(f), resume=False, overwrite=False)


def test_append_is_whole_records_or_nothing(tmp_path, monkeypatch):
    """A write that fails half-way (disk full) is cut back to the file's previous end."""
    p = str(tmp_path / "metrics.jsonl")
    records.write_jsonl(p, [{"epoch": 0, "seed": 0}])
    before = open(p, "rb").read()

    def half_then_full(fd, data):
        os.write(fd, bytes(data[: len(data) // 2]))
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(records, "_write_all", half_then_full)
    with pytest.raises(OSError, match="No space"):
        records.write_jsonl(p, [{"epoch": 1, "seed": 0, "x": "y" * 100}, {"epoch": 1, "seed": 1}])
    assert open(p, "rb").read() == before and not records.ends_mid_line(p)
    with open(p, "a") as f:
        f.write('{"epoch": 1, "se')
    assert records.ends_mid_line(p)


def test_stage_log_names_stages_and_ticks():
    lines = []
    stages = StageLog(lines.append, tick=0.05)
    with stages("compiling the epoch"):
        time.sleep(0.23)
    with stages("first epoch"):
        pass
    assert lines[0].endswith("] compiling the epoch ...") and lines[0].startswith("[")
    ticks = [x for x in lines if "still compiling the epoch (" in x]
    assert len(ticks) >= 2
    assert "] compiling the epoch: 0.2" in lines[len(ticks) + 1]
    assert lines[-2].endswith("first epoch ...") and "first epoch: 0.0 s" in lines[-1]
    assert not any("still first epoch" in x for x in lines)


def test_cpp_log_lines_go_to_the_log_file(tmp_path, capfd):
    """What C++ writes to file descriptor 2 (absl/XLA log lines) lands in log.txt only; Python's
    stdout and stderr reach the console and the file; an unexpected error names the log."""
    path = str(tmp_path / "log.txt")
    with log_to_file(path, header="bulbjax run --test"):
        os.write(2, b"E1125 22:11:59.962145 gpu_timer.cc:87] Delay kernel timed out\n")
        print("[    1.0 s] compiling the epoch ...")
        print("a Python warning", file=sys.stderr)
        sys.stderr.write("\rbar 1/2")  # a progress-bar redraw: console only
    out, err = capfd.readouterr()
    assert "Delay kernel" not in err and "Delay kernel" not in out
    assert "compiling the epoch" in out and "a Python warning" in err and "bar 1/2" in err
    log = open(path).read()
    assert log.startswith("==== ") and "bulbjax run --test" in log.splitlines()[0]
    assert "Delay kernel timed out" in log and "compiling the epoch" in log and "a Python warning" in log
    assert "bar 1/2" not in log
    os.write(2, b"after the block\n")  # fd 2 is the console again
    assert "after the block" in capfd.readouterr().err
    with pytest.raises(RuntimeError):
        with log_to_file(path):
            raise RuntimeError("boom")
    assert f"log lines of this run: {path}" in capfd.readouterr().err
    with pytest.raises(ValueError):  # a user's error: its own message, no pointer to the log
        with log_to_file(path):
            raise ValueError("bad flag")
    assert "log lines" not in capfd.readouterr().err and "ValueError: bad flag" in open(path).read()


FIT_ARGS = ["fit", "--env", "SyntheticMovers", "--learners", "vae", "--small", "--seeds", "1",
            "--updates", "2", "--probe-every", "2", "--data-worlds", "8", "--data-steps", "16",
            "--heldout-steps", "8", "--resolution", "16"]


def test_fit_over_a_fit_is_refused_and_overwrite_starts_afresh(tmp_path, capsys):
    d = str(tmp_path / "fit")
    assert main([*FIT_ARGS, "--out", d]) == 0
    first = open(os.path.join(d, "curves.jsonl")).read()
    assert os.path.isdir(os.path.join(d, "checkpoints", "2"))
    assert "Delay" not in open(os.path.join(d, "log.txt")).read()
    capsys.readouterr()
    before = _snapshot(d)
    assert main([*FIT_ARGS, "--out", d]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert f"{d} holds a run (SyntheticMovers (vae), 2 of 2 updates in curves.jsonl, newest checkpoint " \
           "at update 2)" in err and "--resume" in err and "--overwrite" in err
    assert _snapshot(d) == before
    with open(os.path.join(d, "curves.jsonl"), "a") as f:
        f.write('{"update": 99, "seed": 0}\n')  # a mark: --overwrite must replace the curves
    assert main([*FIT_ARGS, "--out", d, "--overwrite"]) == 0
    assert open(os.path.join(d, "curves.jsonl")).read() == first  # afresh, and deterministic
    assert main([*FIT_ARGS, "--out", d, "--overwrite", "--resume"]) == 2
