"""Failures that are the input's: refused before the cluster starts where a check can find them, never
retried, no worker traceback, no half-made store, and a rerun with the fix needs no ``--force``.

Also the small things of the same issue: ``~`` and variables expanded in the jobqueue log directory,
and ``--cluster`` recorded in the run's ``config.yaml``.
"""
import getpass
import os
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml

from mmflow.errors import InputError, StaleOutputError
from mmflow.io.stores import ArraySpec, StoreSpec
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.config.errors import ConfigError
from mmflow.workflow.pipeline import PIPELINE
from mmflow.workflow.engine.rundir import RunDir
from mmflow.workflow.engine.runner import run_workflow
from mmflow.workflow.stages.base import Stage
from mmflow.workflow.engine.task_key import TaskKey
from tests.uvh5_helpers import JD_2023, gaussian_power_beamfits, matvis_uvdata
from tests.workflow_helpers import ROOT, small_config

QUIET = dict(progress=False, log=lambda *a: None)


def _mmflow(*args):
    """``mmflow ARGS`` in a fresh process: (exit status, stdout, stderr)."""
    env = dict(os.environ, PYTHONPATH=ROOT)
    p = subprocess.run([sys.executable, "-m", "mmflow.cli", *args], cwd=ROOT, env=env, capture_output=True,
                       text=True, timeout=600)
    return p.returncode, p.stdout, p.stderr


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    """A small drift scan (pyuvdata ``UVData``, nothing flagged) and a directory to write it to."""
    root = tmp_path_factory.mktemp("scan")
    uv, _ = matvis_uvdata(gaussian_power_beamfits(root / "beam.fits"), n_times=8, radius_m=12.0, start_jd=JD_2023)
    uv.flag_array[:] = False
    return uv, root


def _write(uv, path, nan_rows=(), times=None):
    """``uv`` (the integrations ``times`` of it) as UVH5 at ``path``, with unflagged NaN in the cross-correlation
    rows ``nan_rows`` (counted over the cross-correlations)."""
    uv = uv.copy() if times is None else uv.select(times=times, inplace=False)
    cross = np.flatnonzero(uv.ant_1_array != uv.ant_2_array)
    uv.data_array[cross[list(nan_rows)], 0, 0] = np.nan
    path.parent.mkdir(parents=True, exist_ok=True)
    uv.write_uvh5(str(path), run_check=False)
    return path


@pytest.fixture(scope="module")
def nan_file(scan):
    uv, root = scan
    return _write(uv, root / "nan" / "scan.uvh5", nan_rows=[3])


# ----------------------------------------------------------------------------- found before the cluster

def test_nan_input_refused_before_the_cluster_starts_and_fixed_without_force(nan_file, tmp_path):
    run_dir = tmp_path / "run"
    args = ["workflows/uvh5-image.yaml", f"run.directory={run_dir}", f"input.path={nan_file}", "--no-progress"]
    rc, out, err = _mmflow("run", *args, "--cluster", "local")
    assert rc == 2, err
    assert "dask dashboard:" not in out  # the cluster never started (it prints its link when it does)
    assert "Traceback" not in err and "Compute Failed" not in err, err
    assert err.startswith(f"mmflow: error: {nan_file}: field 'data_array': 1 unflagged samples are NaN or inf")
    assert "Fix: flag them in the file, or set input.nonfinite=flag" in err
    assert sorted(os.listdir(run_dir)) == ["mmflow.log"]  # no store, no record: the log alone
    assert "stopped: InputError" in (run_dir / "mmflow.log").read_text()
    # the fix the message names, without --force (the ingest stage: 8 integrations cannot make m-modes)
    rc, out, err = _mmflow("ingest", *args, "input.nonfinite=flag", "--cluster", "synchronous")
    assert rc == 0, err
    assert "nonfinite flagged: 1" in out
    recorded = yaml.safe_load((run_dir / "config.yaml").read_text())
    assert recorded["cluster"]["kind"] == "synchronous"  # --cluster recorded as cluster.kind
    assert recorded["input"]["nonfinite"] == "flag"


def test_nan_scan_names_every_file_and_runs_only_for_a_stage_with_work(scan, tmp_path, monkeypatch):
    from mmflow.io import ingest as ingest_mod
    from mmflow.io import readers

    monkeypatch.setattr(readers, "SCAN_BLOCK_BYTES", 7 * 16)  # 7 rows at a time (one channel, one hand)
    uv, _ = scan
    times = np.unique(uv.time_array)
    day = tmp_path / "day"
    for k in range(4):  # two integrations a file; NaN in files 0 and 2
        nan_rows = {0: [1, 5], 2: [2]}.get(k, [])
        _write(uv, day / f"t{k}.uvh5", nan_rows=nan_rows, times=times[2 * k:2 * k + 2])
    cfg_of = lambda path, *o: load_config("workflows/uvh5-image.yaml", [  # noqa: E731
        f"run.directory={tmp_path / 'run'}", f"input.path={path}", "cluster.kind=synchronous", *o])
    with pytest.raises(InputError, match=rf"t0.uvh5: field 'data_array': 2 unflagged samples are NaN or inf "
                                         rf"\(of \d+\); so are samples of 1 more file\(s\): {day}/t2.uvh5 \(1\)"):
        run_workflow(cfg_of(day / "*.uvh5"), only=["ingest"], **QUIET)
    scanned = []
    real = ingest_mod.unflagged_nonfinite
    monkeypatch.setattr(ingest_mod, "unflagged_nonfinite", lambda path, *a: scanned.append(path) or real(path, *a))
    clean = str(day / "t[13].uvh5")
    run_workflow(cfg_of(clean), only=["ingest"], **QUIET)
    assert len(scanned) == 2  # each file once, before any task
    run_workflow(cfg_of(clean), only=["ingest"], **QUIET)
    assert len(scanned) == 2  # a complete stage is kept: its files are not read again
    run_workflow(cfg_of(day / "*.uvh5", "input.nonfinite=flag", "run.directory=" + str(tmp_path / "flag")),
                 only=["ingest"], **QUIET)
    assert len(scanned) == 2  # nonfinite=flag: the tasks flag and count them, no scan
    assert RunDir(tmp_path / "flag").completion("ingest")["counts"]["nonfinite_flagged"] == 3


# ----------------------------------------------------------------------------- raised inside a task

def _toy_prepare(ctx):
    ctx.create(StoreSpec("toy.zarr", (ArraySpec("x", ("k",), (4,), (1,), "float64"),)))
    return [TaskKey(phase="g", freq=0, interval=k) for k in range(4)]


def _calls(ctx):
    return ctx.run.path.parent / "calls.txt"


def _toy_bad_input(ctx, key):
    """The chunks from ``TOY_GOOD_FROM`` on (default: none) take a second, then write; the others are bad."""
    with open(_calls(ctx), "a") as fh:
        fh.write(f"{key.interval}\n")
    k = key.interval
    if k < int(os.environ.get("TOY_GOOD_FROM", "99")):
        raise InputError("toy.uvh5", "data_array", f"chunk {k} is bad", "fix the file")
    time.sleep(1.0)
    ctx.write(ctx.open("toy.zarr", mode="r+"), "x", (slice(k, k + 1),), np.array([float(k)]))


def _toy_crash(ctx, key):
    with open(_calls(ctx), "a") as fh:
        fh.write(f"{key.interval}\n")
    if key.interval >= int(os.environ.get("TOY_CRASH_FROM", "0")):
        raise Crash()


class Crash(BaseException):
    """Stands for a kill of the driver while a stage runs: nothing after it runs."""


def _toy(task):
    return PIPELINE.replace(Stage("simulate", ("mmode.baseline_chunk",), (), ("toy.zarr",), _toy_prepare, task,
                                  enabled=lambda cfg: cfg.source == "simulate", description="toy"))


def test_every_input_error_survives_the_trip_from_a_worker():
    import pickle

    from mmflow.errors import CoverageError

    for exc in (InputError("f.uvh5", "data_array", "bad", "fix it"), CoverageError("d", "input.path", "short", "more"),
                ConfigError([("a.yaml, line 2", "mmode.lmax", "-1 is not allowed", "set it >= 1"),
                             ("a.yaml, line 3", "imaging.eps", "0 is not allowed", "set it > 0")])):
        back = pickle.loads(pickle.dumps(exc))
        assert type(back) is type(exc) and str(back) == str(exc) and back.field == exc.field


def _run_on_local_cluster(run_dir, threads):
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=threads, processes=False, dashboard_address=":0") as cluster, \
            Client(cluster) as client:
        with pytest.raises(InputError, match=r"toy.uvh5: field 'data_array': chunk 0 is bad. Fix: fix the file"):
            run_workflow(small_config(run_dir), client=client, only=["simulate"], pipeline=_toy(_toy_bad_input),
                         **QUIET)
        files = sorted(run_dir.rglob("*"))
        time.sleep(1.5)
        assert sorted(run_dir.rglob("*")) == files  # no task of the stage still runs: nothing written since
    return (run_dir.parent / "calls.txt").read_text().split()


def test_input_error_in_a_task_fails_once_without_traceback_and_leaves_no_store(tmp_path, capfd):
    run_dir = tmp_path / "run"
    calls = _run_on_local_cluster(run_dir, threads=1)  # every chunk is bad
    assert calls.count("0") == 1 and len(calls) == len(set(calls))  # each task at most once: never retried
    err = capfd.readouterr().err
    assert "Compute Failed" not in err and "Traceback" not in err, err
    assert not (run_dir / "toy.zarr").exists() and not (run_dir / "_status").exists()  # no half-made store
    assert {"mmflow.log", "config.yaml", "run.json"} >= set(os.listdir(run_dir))


def test_a_stage_stopped_by_an_input_error_waits_for_its_running_tasks(tmp_path, capfd, monkeypatch):
    monkeypatch.setenv("TOY_GOOD_FROM", "1")  # chunk 0 is bad, chunk 1 runs beside it for a second
    run_dir = tmp_path / "run"
    calls = _run_on_local_cluster(run_dir, threads=2)
    assert calls.count("0") == 1 and len(calls) == len(set(calls))
    assert "Compute Failed" not in capfd.readouterr().err
    run = RunDir(run_dir)
    assert run.has_results("simulate")  # chunk 1 ran to its end and was recorded: the stage keeps it
    problems = run.verify(["simulate"])["simulate"]
    assert problems and all(p.startswith("chunk key ") and p.endswith(": not done") for p in problems), problems


def test_a_stage_that_never_finished_a_task_reruns_with_other_settings_without_force(tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    with pytest.raises(Crash):  # killed before any task finished: the prepared store is left
        run_workflow(small_config(run_dir), only=["simulate"], pipeline=_toy(_toy_crash), **QUIET)
    assert (run_dir / "toy.zarr").exists() and not RunDir(run_dir).has_results("simulate")
    lines = []
    monkeypatch.setenv("TOY_CRASH_FROM", "2")  # now two tasks finish before the kill
    with pytest.raises(Crash):
        run_workflow(small_config(run_dir, "mmode.baseline_chunk=32"), only=["simulate"], pipeline=_toy(_toy_crash),
                     progress=False, log=lines.append)
    assert any("no task had finished: starting afresh: mmode.baseline_chunk: 64 -> 32" in x for x in lines), lines
    assert RunDir(run_dir).has_results("simulate")
    with pytest.raises(StaleOutputError, match="mmode.baseline_chunk: 32 -> 16.*--force"):  # finished tasks: refused
        run_workflow(small_config(run_dir, "mmode.baseline_chunk=16"), only=["simulate"], pipeline=_toy(_toy_crash),
                     **QUIET)


# ----------------------------------------------------------------------------- input.path

def test_an_empty_directory_is_named_as_such(tmp_path):
    empty = tmp_path / "day"
    empty.mkdir()
    (empty / "notes.txt").write_text("not data")
    cfg = load_config("workflows/uvh5-image.yaml", [f"run.directory={tmp_path / 'run'}", f"input.path={empty}",
                                                      "cluster.kind=synchronous"])
    with pytest.raises(InputError, match=rf"{empty}: field 'input.path': no data files in {empty} .*Fix: point "
                                         "input.path at the data"):
        run_workflow(cfg, **QUIET)
    assert sorted(os.listdir(tmp_path / "run")) == ["mmflow.log"]
    (empty / "a.uvh5").write_text("")
    (empty / "b.uvh5").write_text("")
    with pytest.raises(InputError, match=rf"a directory of 2 data files.*input.path='{empty}/\*.uvh5'"):
        run_workflow(cfg, **QUIET)


# ----------------------------------------------------------------------------- small things

def test_jobqueue_log_directory_expands_home_and_variables(tmp_path, monkeypatch):
    from mmflow.workflow.engine.cluster import jobqueue_cluster

    monkeypatch.setenv("USER", "alice")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    want = str(tmp_path / "home" / "alice" / "logs")
    cfgs = [load_config("workflows/hpc-slurm.yaml", [f"cluster.jobqueue={{cores: 1, memory: 1GB, log_directory: "
                                                     f"'{written}'}}"])
            for written in ("${HOME}/${USER}/logs", "$HOME/$USER/logs", "~/alice/logs")]
    assert [c.cluster.jobqueue["log_directory"] for c in cfgs] == [want] * 3
    cluster = jobqueue_cluster(cfgs[0], "slurm")
    try:
        script = cluster.job_script()
    finally:
        cluster.close()
    assert f"{want}/" in script and "$USER" not in script and "${" not in script
    monkeypatch.delenv("USER")  # unset (containers, cron): the login name, as ~ is the home without $HOME
    cfg = load_config("workflows/hpc-slurm.yaml", ["cluster.jobqueue={log_directory: '/x/${USER}/logs'}"])
    assert cfg.cluster.jobqueue["log_directory"] == f"/x/{getpass.getuser()}/logs"
    monkeypatch.delenv("NOPE_NOT_SET", raising=False)
    with pytest.raises(ConfigError, match=r"cluster.jobqueue.log_directory.*\$\{NOPE_NOT_SET\} is not set"):
        load_config("workflows/hpc-slurm.yaml", ["cluster.jobqueue={log_directory: '/x/${NOPE_NOT_SET}/logs'}"])


def test_cluster_option_is_recorded_as_cluster_kind(monkeypatch):
    from mmflow import cli

    seen = {}

    class Stop(Exception):
        pass

    def open_cluster(cfg, scheduler=None, kind=None):
        seen.update(kind=cfg.cluster.kind, address=cfg.cluster.address)
        raise Stop

    monkeypatch.setattr("mmflow.workflow.engine.cluster.open_cluster", open_cluster)
    with pytest.raises(Stop):
        cli.main(["run", "workflows/demo.yaml", "--cluster", "slurm"])
    assert seen["kind"] == "slurm"  # the configuration the run writes to config.yaml
    with pytest.raises(Stop):
        cli.main(["run", "workflows/demo.yaml", "--scheduler", "tcp://127.0.0.1:8786"])
    assert seen["kind"] == "address" and seen["address"] == "tcp://127.0.0.1:8786"
