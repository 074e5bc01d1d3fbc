"""The run loop (`bulbjax.run.loop`): checkpoints and exact resume, keep-K, SIGTERM,
config mismatches, provenance, TensorBoard events and `bulbjax report`, on a tiny CPU config
with a frame learner that retains replay and a sequential learner (window buffers)."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import struct

import jax
import numpy as np
import pytest

from bulbjax.config import RunOptions, config_from_dict
from bulbjax.epoch import Experiment, ExperimentConfig
from bulbjax.epoch.programs import Programs
from bulbjax.report import records, report
from bulbjax.run import check_resume, run
from bulbjax.run.checkpoint import Checkpointer
from bulbjax.run.provenance import source_hash

from tiny_experiment import tiny_config


def tiny() -> ExperimentConfig:
    """The shared tiny config with a sequential learner and the probe variants (the common set's
    init part is checkpointed)."""
    return tiny_config().replace(learners=("vae_rpl", "svae"), epochs=4, sequence_length=4, learner_batches=1,
                                 probe_variants=("common", "window", "raw"))


@pytest.fixture(scope="module")
def exp():
    return Experiment(tiny())  # one compile serves every run below


@pytest.fixture(scope="module")
def straight(exp, tmp_path_factory):
    """4 epochs in one go, a checkpoint every epoch, 2 kept, TensorBoard on."""
    d = str(tmp_path_factory.mktemp("straight"))
    res = run(exp.config, RunOptions(checkpoint_every=1, keep=2, tensorboard=True), d,
              experiment=exp, progress=False, log=lambda s: None, argv=["bulbjax", "run", "--test"])
    return d, res


def _lines(d: str) -> list[str]:
    with open(os.path.join(d, "metrics.jsonl")) as f:
        return f.read().splitlines()


def test_resume_is_bit_identical(exp, straight, tmp_path):
    d0, res0 = straight
    assert res0.epochs_done == 4 and res0.stopped == "done"
    d = str(tmp_path / "resumed")
    first = run(exp.config, RunOptions(stop_after=2), d, experiment=exp, progress=False, log=lambda s: None)
    assert (first.epochs_done, first.stopped, first.checkpoint) == (2, "stop-after", 2)
    assert len(_lines(d)) == 2 * 2
    # an epoch written after the checkpoint (killed before the next one): cut off on resume
    with open(os.path.join(d, "metrics.jsonl"), "a") as f:
        f.write(json.dumps({"epoch": 2, "seed": 0, "rl_return": -1.0, "probes": {}}) + "\n")
        f.write('{"epoch": 2, "seed": 1, "rl_ret')  # half-written line
    second = run(exp.config, RunOptions(), d, resume=True, experiment=exp, progress=False, log=lambda s: None)
    assert (second.epochs_done, second.stopped) == (4, "done")
    a, b = _lines(d0), _lines(d)
    assert len(a) == len(b) == 4 * 2
    assert [json.loads(x)["epoch"] for x in b] == [0, 0, 1, 1, 2, 2, 3, 3]
    assert a == b  # every float of every record, bit for bit (JSON round-trips float64 exactly)
    assert all({"probes_common", "probes_window", "probes_raw"} <= set(json.loads(x)) for x in b)
    cfg = json.load(open(os.path.join(d, "config.json")))
    assert cfg["resumes"][0]["from_epoch"] == 2 and cfg["run"] == {"seed": 0, "probe_every": 1}
    assert os.path.getsize(os.path.join(d, "fig2.png")) > 10_000


def test_probe_every_k_runs_one_program_with_a_flag(exp, straight, tmp_path):
    """`--probe-every 2`: one epoch program (`Experiment.epoch_flag`) runs probing and
    non-probing epochs. Epochs 0, 2 and the last (3) probe, epoch 1 has no probes; training is
    the straight run's (every epoch probing, the specialised program) to rounding, and so is
    epoch 0's probe (same state, same keys); later probes differ, as the held-out worlds of a
    non-probing epoch do not move."""
    d0, _ = straight
    d = str(tmp_path / "every2")
    res = run(exp.config, RunOptions(probe_every=2), d, experiment=exp, progress=False, log=lambda s: None)
    assert res.epochs_done == 4
    assert Programs.of(exp, (True, False)).flag and not Programs.of(exp, (True,)).flag
    a, b = [json.loads(x) for x in _lines(d0)], [json.loads(x) for x in _lines(d)]
    assert [bool(r["probes"]) for r in b] == [True, True, False, False, True, True, True, True]
    for ra, rb in zip(a, b):
        assert (ra["epoch"], ra["seed"]) == (rb["epoch"], rb["seed"])
        np.testing.assert_allclose(rb["learners"]["vae_rpl"]["loss"], ra["learners"]["vae_rpl"]["loss"], rtol=1e-5)
        np.testing.assert_allclose(rb["learners"]["svae"]["loss"], ra["learners"]["svae"]["loss"], rtol=1e-5)
        assert rb["rl_return"] == ra["rl_return"] or np.isnan(rb["rl_return"]) and np.isnan(ra["rl_return"])
    for ra, rb in zip(a[:2], b[:2]):  # epoch 0
        for name in ("vae_rpl", "svae"):
            x, y = ra["probes"][name]["rand"]["overall"]["mae_norm"], rb["probes"][name]["rand"]["overall"]["mae_norm"]
            assert np.isfinite(y) and abs(x - y) <= 1e-4 * abs(x) + 1e-6
    later = [(ra["probes"]["svae"]["rand"]["overall"]["mae_norm"], rb["probes"]["svae"]["rand"]["overall"]["mae_norm"])
             for ra, rb in zip(a[4:], b[4:])]
    assert all(np.isfinite(y) for _, y in later) and any(x != y for x, y in later)


def test_keep_k_and_checkpoint_contents(exp, straight):
    d, _ = straight
    ck = Checkpointer(d, keep=2)
    assert ck.steps() == [3, 4]  # a checkpoint every epoch, the last 2 kept
    like = {"run": exp.abstract_state(), "key": exp.abstract_key()}
    state, host, epoch = ck.restore(like)
    assert epoch == 4 and host == {"epoch": 4} and int(state["run"].epoch) == 4
    rs = state["run"]
    # zero-size leaves (mjx.Data of CartPole has many) come back with their shapes
    shapes = jax.tree.map(lambda x: x.shape, like)
    assert jax.tree.map(lambda x: x.shape, state) == shapes
    assert rs.windows and rs.buffers  # window and frame buffers are in the checkpoint
    state3, _, e3 = ck.restore(like, epoch=3)
    assert e3 == 3 and not np.array_equal(np.asarray(state3["key"]), np.asarray(state["key"]))
    ck.close()
    # a state of another layout is refused, naming the difference
    with pytest.raises(ValueError, match="does not fit"):
        Checkpointer(d).restore({"run": exp.abstract_state().replace(learners={}), "key": exp.abstract_key()})


def test_sigterm_stops_at_epoch_end_with_a_checkpoint(exp, tmp_path):
    d = str(tmp_path / "term")
    before = signal.getsignal(signal.SIGTERM)

    def on_epoch(done: int) -> None:
        if done == 1:
            os.kill(os.getpid(), signal.SIGTERM)  # a real SIGTERM, mid-run

    res = run(exp.config, RunOptions(), d, experiment=exp, progress=False, log=lambda s: None, on_epoch=on_epoch)
    assert (res.epochs_done, res.stopped, res.checkpoint) == (1, "signal SIGTERM", 1)
    assert signal.getsignal(signal.SIGTERM) is before  # the run's handler is gone again
    state, _, epoch = Checkpointer(d).restore({"run": exp.abstract_state(), "key": exp.abstract_key()})
    assert epoch == 1 and int(state["run"].epoch) == 1
    assert len(_lines(d)) == 2  # one epoch of two seeds


def test_max_minutes_stops_after_the_epoch_that_ran_late(exp, tmp_path, monkeypatch):
    """--max-minutes: checked before the first epoch and after each; the last epoch is "done"."""
    import bulbjax.run.loop as run_module

    clock = [0.0]
    monkeypatch.setattr(run_module.time, "time", lambda: clock[0])

    def late_after(n: int):
        def on_epoch(done: int) -> None:
            if done == n:
                clock[0] += 3600.0  # an hour passes during epoch n
        return on_epoch

    opts = RunOptions(max_minutes=30)
    res = run(exp.config, opts, str(tmp_path / "a"), experiment=exp, progress=False,
              log=lambda s: None, on_epoch=late_after(1))
    assert (res.epochs_done, res.stopped, res.checkpoint) == (1, "max-minutes", 1)
    res = run(exp.config, opts, str(tmp_path / "b"), experiment=exp, progress=False,
              log=lambda s: None, on_epoch=late_after(exp.config.epochs))
    assert (res.epochs_done, res.stopped) == (exp.config.epochs, "done")  # late after the last epoch: nothing was cut
    clock[0] = 0.0

    def late_before(*args, **kwargs):  # the build and compile took longer than the budget
        clock[0] += 3600.0
        return real_check(*args, **kwargs)

    real_check = run_module.rundir.check_out_dir
    monkeypatch.setattr(run_module.rundir, "check_out_dir", late_before)
    said: list[str] = []
    res = run(exp.config, opts, str(tmp_path / "c"), experiment=exp, progress=False, log=said.append)
    assert (res.epochs_done, res.stopped, res.checkpoint) == (0, "max-minutes", 0)
    # the budget went on start-up: said so, not "stopped after epoch 0"
    assert any("start-up took 3600 s of the 1800 s allowed (--max-minutes 30); no epoch ran" in s for s in said), said
    assert not any("stopped after epoch" in s for s in said)


def test_config_mismatch_on_resume_is_an_error(exp, straight):
    d, _ = straight
    with pytest.raises(ValueError, match=r"learners: saved \('vae_rpl', 'svae'\), given \('vae',\)"):
        check_resume(d, exp.config.replace(learners=("vae",)), RunOptions())
    with pytest.raises(ValueError, match="learner.lr"):
        check_resume(d, exp.config.replace(learner=dataclasses.replace(exp.config.learner, lr=1.0)), RunOptions())
    with pytest.raises(ValueError, match="seed: saved 0, given 3"):
        check_resume(d, exp.config, RunOptions(seed=3))
    check_resume(d, exp.config.replace(epochs=10), RunOptions(keep=5, max_minutes=3))  # allowed
    from bulbjax.cli import main
    assert main(["run", "--resume", d, "--learners", "vae"]) == 2
    assert main(["run", "--resume", d, "--seeds", "3"]) == 2
    assert main(["run", "--resume", d, "--out", d + "_other"]) == 2


def test_provenance_in_config_json(straight):
    d, _ = straight
    raw = json.load(open(os.path.join(d, "config.json")))
    p = raw["provenance"]
    assert p["command"] == "bulbjax run --test"
    for pkg in ("jax", "jaxlib", "flax", "optax", "mujoco", "mujoco-mjx", "warp-lang"):
        assert p["versions"][pkg], pkg
    assert p["versions"]["jax"] == jax.__version__
    assert len(p["git_commit"]) == 40 and isinstance(p["git_dirty"], bool)
    assert p["source_sha256"] == source_hash() and len(p["source_sha256"]) == 64
    assert p["device_count"] == jax.device_count() and p["device_kind"] and p["mesh"] == {"seeds": 1, "worlds": 1}
    assert p["compiler_options"] == {}
    assert config_from_dict(raw["experiment"]) == tiny()


def _tb_scalars(folder: str) -> dict[tuple[str, int], float]:
    """Scalars of TensorBoard event files (TFRecord framing around Event protos)."""
    from tensorboardX.proto import event_pb2
    out = {}
    for name in sorted(os.listdir(folder)):
        with open(os.path.join(folder, name), "rb") as f:
            data = f.read()
        i = 0
        while i < len(data):
            (n,) = struct.unpack("<Q", data[i:i + 8])
            ev = event_pb2.Event.FromString(data[i + 12:i + 12 + n])
            i += 12 + n + 4
            for v in ev.summary.value:
                out[(v.tag, ev.step)] = v.simple_value
    return out


def test_tensorboard_has_the_metrics(straight):
    d, res = straight
    tb = _tb_scalars(os.path.join(d, "tb"))
    recs = records.read_jsonl(os.path.join(d, "metrics.jsonl"))
    r = recs[-1]
    assert tb[("seed1/rl_return", 3)] == pytest.approx(r["rl_return"], rel=1e-6)
    mae = r["probes"]["svae"]["rand"]["overall"]["mae_norm"]
    assert tb[("seed1/probes/svae/rand/overall/mae_norm", 3)] == pytest.approx(mae, rel=1e-6)
    assert len(records.scalars(r)) == len([k for k in tb if k[1] == 3 and k[0].startswith("seed1/")])


def test_report_redraws_a_run_in_progress(straight, tmp_path):
    d, _ = straight
    import shutil
    run_dir = tmp_path / "copy"
    run_dir.mkdir()
    for name in ("config.json", "metrics.jsonl"):
        shutil.copy(os.path.join(d, name), run_dir / name)
    lines = _lines(d)
    # in progress: the last epoch has one seed written and the next line is half written
    (run_dir / "metrics.jsonl").write_text("\n".join(lines[:-1]) + "\n" + lines[-1][:40])
    from bulbjax.cli import main
    assert main(["report", str(run_dir)]) == 0
    assert os.path.getsize(run_dir / "fig2.png") > 10_000
    tab = (run_dir / "table.md").read_text()
    assert "3 epochs" in tab and "epoch 0, 1, 2;" in tab  # epoch 3 (incomplete) left out
    assert "| svae (window) | π_rand |" in tab and "## Raw MAE" in tab  # the probe variants' rows
    assert "## The claims under the probe protocol's variants" in (run_dir / "findings.md").read_text()
    assert main(["report", str(tmp_path / "nothing")]) == 2


def test_report_reads_gzipped_metrics(straight, tmp_path):
    """Committed long runs keep metrics.jsonl.gz: report and read_jsonl take it as it is."""
    import gzip
    import shutil
    d, _ = straight
    shutil.copy(os.path.join(d, "config.json"), tmp_path / "config.json")
    with open(os.path.join(d, "metrics.jsonl"), "rb") as f, gzip.open(tmp_path / "metrics.jsonl.gz", "wb") as g:
        g.write(f.read())
    assert records.metrics_path(str(tmp_path)).endswith(".gz")
    assert records.read_jsonl(str(tmp_path / "metrics.jsonl.gz")) == records.read_jsonl(os.path.join(d, "metrics.jsonl"))
    report.redraw(str(tmp_path))
    tab = (tmp_path / "table.md").read_text()
    assert "4 epochs" in tab and "epoch 1, 2, 3;" in tab and os.path.getsize(tmp_path / "fig2.png") > 10_000
    os.remove(tmp_path / "metrics.jsonl.gz")
    with pytest.raises(ValueError, match="does not exist"):
        records.metrics_path(str(tmp_path))


def test_report_reads_old_run_folders(tmp_path):
    """Runs written before config.json had sections (docs/results) redraw too."""
    import shutil
    src = os.path.join(os.path.dirname(__file__), "..", "docs", "results", "fig2_invpend_h100")
    if not os.path.isdir(src):
        pytest.skip("no docs/results/fig2_invpend_h100")
    for name in ("config.json", "metrics.jsonl.gz"):  # committed runs keep their metrics gzipped
        shutil.copy(os.path.join(src, name), tmp_path / name)
    tab = report.redraw(str(tmp_path))
    assert "| pred | π_rand |" in tab


def test_source_hash_names_the_code(tmp_path):
    """The same sources give the same hash wherever they are; one changed byte changes it."""
    import shutil

    import bulbjax

    copy = str(tmp_path / "bulbjax")
    shutil.copytree(os.path.dirname(bulbjax.__file__), copy, ignore=shutil.ignore_patterns("__pycache__"))
    assert source_hash(copy) == source_hash()
    with open(os.path.join(copy, "run", "loop.py"), "a") as f:
        f.write("\n")
    assert source_hash(copy) != source_hash()


def test_compiler_options_parse_and_reach_the_jits():
    """`--xla-option KEY=VALUE` values are typed; a malformed one says the form; the options
    reach the jitted init and epoch (XLA refuses an unknown key there, so a bogus one fails)."""
    from bulbjax.xla_options import parse_compiler_options

    opts = parse_compiler_options(["xla_gpu_enable_command_buffer=FUSION,WHILE",
                                   "xla_gpu_graph_min_graph_size=1", "a=0.5", "b=true"])
    assert opts == {"xla_gpu_enable_command_buffer": "FUSION,WHILE", "xla_gpu_graph_min_graph_size": 1,
                    "a": 0.5, "b": True}
    with pytest.raises(ValueError, match="KEY=VALUE"):
        parse_compiler_options(["xla_gpu_graph_min_graph_size"])
    from bulbjax.xla_options import parse_named_options
    assert parse_named_options("cb=xla_gpu_enable_command_buffer:FUSION+WHILE;b:true") == (
        "cb", {"xla_gpu_enable_command_buffer": "FUSION,WHILE", "b": True})
    bad = Experiment(tiny(), compiler_options={"xla_no_such_option": 1})
    assert bad.compiler_options == {"xla_no_such_option": 1}
    with pytest.raises(Exception, match="xla_no_such_option"):
        bad.init.lower(jax.random.PRNGKey(0)).compile()


_PROGRAM_SCRIPT = """
import hashlib, json, sys
sys.path.insert(0, {tests!r})
import jax
from warp._src.jax.ffi import _FFI_CALLABLE_REGISTRY
from bulbjax.epoch import Experiment
from bulbjax.epoch.programs import Programs
from test_run import tiny
exp = Experiment(tiny())
mode = sys.argv[1]
if mode == "epoch_first":  # an epoch traced before init: other FFI target names
    exp.epoch.trace(exp.abstract_state(), exp.abstract_key(), probe=False)
if mode == "init_traced_twice":  # what a retrace of init does (a fresh GPU run's init call did)
    exp.init.trace(jax.ShapeDtypeStruct((2,), jax.numpy.uint32))
progs = Programs.of(exp)
text = progs.lowered("epoch").as_text()
calls = lambda: {{c.name: c.call_id for c in _FFI_CALLABLE_REGISTRY.values()}}
before, traced_after = calls(), None
if mode == "fresh":  # a new run: init and one epoch run, and nothing is traced again
    rs = progs.init(jax.random.PRNGKey(0))
    rs, m = progs.epoch(rs, jax.random.PRNGKey(1), probe=False)
    jax.block_until_ready(m)
    traced_after = calls() != before
print(json.dumps({{"hash": hashlib.sha256(text.encode()).hexdigest(), "traced_after": traced_after}}))
"""


@pytest.mark.slow  # the slow tier: `make test-all` runs it, `make test` does not (tests/conftest.py)
def test_resumed_process_compiles_the_same_epoch_program():
    """MuJoCo Warp numbers its FFI targets and call sites by per-process trace order, and the
    numbers are in the program (so in the compilation cache key). `Programs.of` traces
    init and the epoch in one order and then only calls what it compiled: the epoch of a
    fresh run (which runs init and an epoch, tracing nothing more) and of a resume (no init)
    lower to the same text; an epoch traced first, or init traced one more time (what a fresh GPU run's init call did), give another text: what made resumed GPU
    stretches recompile for minutes."""
    import json
    import subprocess
    import sys

    here = os.path.dirname(os.path.abspath(__file__))
    script = _PROGRAM_SCRIPT.format(tests=here)
    modes = ("fresh", "resume", "epoch_first", "init_traced_twice")
    # Warp's own per-trace numbering (the test suite turns on the signature ids, under which an
    # epoch traced first lowers to the same text: tests/test_compile_cache.py)
    env = dict(os.environ, BULBJAX_STABLE_WARP_IDS="0")
    procs = {o: subprocess.Popen([sys.executable, "-c", script, o], stdout=subprocess.PIPE, text=True,
                                 cwd=os.path.dirname(here), env=env)
             for o in modes}
    out = {o: p.communicate(timeout=900)[0].strip().splitlines()[-1] for o, p in procs.items()}
    assert all(p.returncode == 0 for p in procs.values()), out
    out = {o: json.loads(v) for o, v in out.items()}
    assert out["fresh"]["traced_after"] is False
    assert out["fresh"]["hash"] == out["resume"]["hash"]
    assert out["epoch_first"]["hash"] != out["fresh"]["hash"]
    assert out["init_traced_twice"]["hash"] != out["fresh"]["hash"]


def test_overwrite_refused_then_starts_afresh(exp, straight, tmp_path):
    """A fresh run over a run folder is a ValueError naming it, touching nothing; `overwrite`
    deletes the earlier run's metrics and checkpoints and starts afresh."""
    from bulbjax.run.rundir import RunFolderExists

    d0, _ = straight
    d = str(tmp_path / "again")
    run(exp.config, RunOptions(stop_after=1, seed=5), d, experiment=exp, progress=False, log=lambda s: None)
    before = _lines(d)
    with pytest.raises(RunFolderExists, match=r"holds a run \(CartPole \(vae_rpl, svae\), 1 of 4 epochs in "
                                              r"metrics.jsonl, newest checkpoint at epoch 1\)"):
        run(exp.config, RunOptions(), d, experiment=exp, progress=False, log=lambda s: None)
    assert _lines(d) == before and Checkpointer(d).steps() == [1]
    said = []
    run(exp.config, RunOptions(checkpoint_every=1, keep=2), d, overwrite=True, experiment=exp, progress=False,
        log=said.append)
    assert any("starting afresh: removing" in s for s in said)
    assert _lines(d) == _lines(d0)  # the seed-5 epoch is gone: the records of a fresh seed-0 run
    assert Checkpointer(d).steps() == [3, 4]
    # the start-up stages, in order, each with its elapsed time
    stages = [s.split("] ", 1)[1] for s in said if s.startswith("[")]
    assert stages[:2] == ["tracing and lowering init and the epoch ...", "compiling init and the epoch in the "
                          "background (or loading them from the compile cache)"] or \
        stages[1].startswith("tracing and lowering init and the epoch: ")
    order = [next(i for i, s in enumerate(stages) if s.startswith(x)) for x in
             ("tracing and lowering init and the epoch ...", "compiling init ...", "compiling init: ",
              "running init ...", "running init: ", "compiling the epoch ...", "first epoch (0) ...",
              "first epoch (0): ")]
    assert order == sorted(order)


def _fail_on_call(monkeypatch, module, name, n, make_error):
    """Make `module.name` fail on its `n`-th call (counting from 1) with `make_error(args)`."""
    real = getattr(module, name)
    calls = [0]

    def wrapped(*args, **kw):
        calls[0] += 1
        if calls[0] == n:
            return make_error(real, *args, **kw)
        return real(*args, **kw)

    monkeypatch.setattr(module, name, wrapped)
    return calls


def test_disk_full_while_appending_metrics_keeps_whole_records(exp, straight, tmp_path, monkeypatch):
    """The third epoch's metrics append fails half-way (ENOSPC): the run stops with an error
    saying what was kept, metrics.jsonl holds the two whole epochs (no half record), the
    checkpoint of epoch 2 stays, and a resume gives the straight run's records."""
    import errno

    from bulbjax.report import records as records_mod
    from bulbjax.run import rundir

    d0, _ = straight
    d = str(tmp_path / "full")

    def half_then_enospc(real, fd, data):
        os.write(fd, bytes(data[: len(data) // 2]))
        raise OSError(errno.ENOSPC, "No space left on device")

    # calls of records._write_all: one per epoch's metrics
    _fail_on_call(monkeypatch, records_mod, "_write_all", 3, half_then_enospc)
    with pytest.raises(ValueError, match=r"writing metrics.jsonl \(epoch 2\) in .* failed \(OSError: .*No space "
                                         r"left.*newest complete checkpoint is epoch 2; .*bulbjax run --resume"):
        run(exp.config, RunOptions(checkpoint_every=1), d, experiment=exp, progress=False, log=lambda s: None)
    monkeypatch.undo()
    assert _lines(d) == _lines(d0)[:4] and not records_mod.ends_mid_line(os.path.join(d, "metrics.jsonl"))
    assert rundir.checkpoint_steps(d) == [1, 2]
    res = run(exp.config, RunOptions(), d, resume=True, experiment=exp, progress=False, log=lambda s: None)
    assert res.epochs_done == 4 and _lines(d) == _lines(d0)


def test_failed_checkpoint_write_keeps_the_last_one(exp, straight, tmp_path, monkeypatch):
    """The checkpoint of epoch 2 fails at orbax's final rename (a full disk): the run stops
    naming checkpoint 1 as the newest; its unfinished folder is removed when the run resumes,
    which continues from 1 and gives the straight run's records."""
    import errno

    from orbax.checkpoint._src.path import async_path

    from bulbjax.run import rundir

    d0, _ = straight
    d = str(tmp_path / "ckfail")

    real = async_path.rename

    async def rename(src, dst):  # the final rename of checkpoint 2 (orbax renames a few things)
        if os.path.basename(str(dst)) == "2":
            raise OSError(errno.ENOSPC, "No space left on device")
        return await real(src, dst)

    monkeypatch.setattr(async_path, "rename", rename)
    with pytest.raises(ValueError, match=r"writing the checkpoint of epoch 2 .*newest complete checkpoint is "
                                         r"epoch 1"):
        run(exp.config, RunOptions(checkpoint_every=1), d, experiment=exp, progress=False, log=lambda s: None)
    monkeypatch.undo()
    assert rundir.checkpoint_steps(d) == [1] and rundir.partial_checkpoints(d)
    # checkpoint 2 is written in the background while epoch 2 runs: its failure stops the run at
    # the next checkpoint, with epochs 0-2 in metrics.jsonl (ahead of the newest checkpoint, never behind)
    assert len(_lines(d)) == 6
    said = []
    run(exp.config, RunOptions(), d, resume=True, experiment=exp, progress=False, log=said.append)
    assert any("resuming" in s and "at epoch 1" in s for s in said)
    assert _lines(d) == _lines(d0) and not rundir.partial_checkpoints(d)


def test_resume_cuts_a_half_written_last_line(exp, straight, tmp_path):
    """Killed in the middle of an append, with every whole record older than the checkpoint:
    the half line is cut before the resumed run appends (it used to stay, and the next record
    was glued onto it)."""
    d0, _ = straight
    d = str(tmp_path / "half")
    run(exp.config, RunOptions(stop_after=2), d, experiment=exp, progress=False, log=lambda s: None)
    with open(os.path.join(d, "metrics.jsonl"), "a") as f:
        f.write(_lines(d0)[4][:50])  # epoch 2, seed 0, half written
    run(exp.config, RunOptions(), d, resume=True, experiment=exp, progress=False, log=lambda s: None)
    assert _lines(d) == _lines(d0)
