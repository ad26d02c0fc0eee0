"""A real multi-process dask cluster on loopback: a scheduler and two worker processes."""
import contextlib
import os
import shutil
import socket
import subprocess
import sys
import time

import pytest

from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.runner import run_workflow
from tests.workflow_helpers import ROOT, SMALL, assert_identical, read_outputs, small_config

BIN = os.path.dirname(sys.executable)


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def _loopback(workdir):
    """A dask scheduler and two single-threaded worker processes on the loopback interface."""
    port = _free_port()
    addr = f"tcp://127.0.0.1:{port}"
    env = dict(os.environ, MMFLOW_THREADS="1")
    dask = shutil.which("dask", path=BIN) or "dask"
    procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", str(port),
                               "--dashboard-address", ":0"], env=env, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)]
    workers = []
    for i in range(2):
        w = subprocess.Popen([dask, "worker", addr, "--nthreads", "1", "--nworkers", "1", "--no-nanny",
                              "--memory-limit", "2GiB", "--name", f"w{i}", "--local-directory", str(workdir / f"w{i}")],
                             env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        workers.append(w)
    from distributed import Client

    client = Client(addr, timeout=60)
    client.wait_for_workers(2, timeout=60)
    try:
        yield client, workers
    finally:
        client.close()
        for p in workers + procs:
            p.kill()
            p.wait()


@pytest.fixture(scope="module")
def loopback_cluster(tmp_path_factory):
    """One cluster for the tests that leave its workers alive (starting one costs ~10 s)."""
    with _loopback(tmp_path_factory.mktemp("cluster")) as cluster:
        yield cluster


@pytest.fixture
def own_cluster(tmp_path):
    """A cluster of the test's own, for a test that kills a worker."""
    with _loopback(tmp_path) as cluster:
        yield cluster


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("cref") / "run"
    run_workflow(small_config(run_dir), progress=False, log=lambda *a: None)
    return read_outputs(run_dir)


def test_workflow_on_two_worker_processes_matches_synchronous_run(loopback_cluster, reference, tmp_path):
    client, _ = loopback_cluster
    run_dir = tmp_path / "dist"
    summaries = run_workflow(small_config(run_dir), client=client, progress=False, log=lambda *a: None)
    assert summaries["transfer"]["tasks_run"] >= 2
    workers_used = {info["name"] for info in client.scheduler_info()["workers"].values()}
    assert len(workers_used) == 2
    assert_identical(reference, read_outputs(run_dir))


def test_killing_a_worker_mid_stage_still_gives_identical_outputs(own_cluster, reference, tmp_path):
    client, workers = own_cluster
    run_dir = tmp_path / "killw"
    os.environ["MMFLOW_TASK_DELAY_S"] = "0.3"
    client.run(lambda: os.environ.__setitem__("MMFLOW_TASK_DELAY_S", "0.3"))
    import threading

    def killer():
        marker_dir = run_dir / "_status" / "transfer"
        deadline = time.time() + 120
        while time.time() < deadline and not (marker_dir.exists() and any(marker_dir.glob("*.done"))):
            time.sleep(0.02)
        workers[0].kill()

    t = threading.Thread(target=killer)
    t.start()
    try:
        run_workflow(small_config(run_dir), client=client, progress=False, log=lambda *a: None)
    finally:
        t.join()
        os.environ.pop("MMFLOW_TASK_DELAY_S", None)
    assert workers[0].poll() is not None  # the worker really died mid-run
    assert_identical(reference, read_outputs(run_dir))


def test_cli_joins_an_existing_scheduler(loopback_cluster, reference, tmp_path, capsys):
    from mmflow.cli import main

    client, _ = loopback_cluster
    run_dir = tmp_path / "cli"
    rc = main(["run", "workflows/demo.yaml", *[o for o in SMALL if not o.startswith("cluster.")],
               f"run.directory={run_dir}", "--scheduler", client.scheduler.address, "--no-progress"])
    assert rc == 0
    assert "dask dashboard:" in capsys.readouterr().out
    assert_identical(reference, read_outputs(run_dir))
    # the same run again on a local cluster: every stage is finished, so no cluster is started
    # (mmflow.workflow.engine.cluster.LazyClient: no worker processes, no batch jobs for a run with no work)
    rc = main(["run", "workflows/demo.yaml", *[o for o in SMALL if not o.startswith("cluster.")],
               f"run.directory={run_dir}", "--cluster", "local", "--no-progress"])
    out = capsys.readouterr().out
    assert rc == 0 and "dask dashboard:" not in out and "simulate kept (" in out, out[-2000:]
    assert_identical(reference, read_outputs(run_dir))


@pytest.mark.parametrize("kind, marker", [("slurm", "#SBATCH"), ("pbs", "#PBS")])
def test_jobqueue_cluster_from_workflow_options(kind, marker):
    from mmflow.workflow.engine.cluster import jobqueue_cluster

    cfg = load_config("workflows/hpc-slurm.yaml", [f"cluster.kind={kind}",
                                                   "cluster.jobqueue={cores: 8, memory: 32GB, queue: normal, "
                                                   "walltime: '01:00:00', processes: 2}"])
    cluster = jobqueue_cluster(cfg, kind)
    try:
        script = cluster.job_script()
    finally:
        cluster.close()
    assert marker in script and "normal" in script
    assert "--nworkers 2" in script or "--nprocs 2" in script
    assert "export MMFLOW_WORKERS_PER_HOST=2" in script  # the two processes of a job share its cores


def test_relative_run_directory_with_workers_in_another_cwd(loopback_cluster, reference, tmp_path, monkeypatch):
    """The driver resolves run.directory: workers whose cwd differs still write into the same run."""
    client, _ = loopback_cluster
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    client.run(os.chdir, str(elsewhere))
    monkeypatch.chdir(tmp_path)
    cfg = load_config(os.path.join(ROOT, "workflows", "demo.yaml"),
                      SMALL + ["run.directory=rel/run"])
    run_workflow(cfg, client=client, progress=False, log=lambda *a: None)
    assert not (elsewhere / "rel").exists()
    assert_identical(reference, read_outputs(tmp_path / "rel" / "run"))


def _worker_state(_):
    from threadpoolctl import threadpool_info

    from mmflow.mmode import fringe_kernels, legendre

    # the imaging kernels compiled (or loaded from numba's cache) before the fork: the Legendre
    # recurrence for float32 and float64 tables, the fringe kernel in both precisions (not the full-Stokes
    # kernel folds, compiled by the stokes stage where it runs)
    compiled = (legendre._kernel.cache_info().currsize == 1 and len(legendre._kernel().signatures) == 2
                and fringe_kernels._kernels.cache_info().currsize == 2
                and all(len(fringe_kernels._kernels(r)[0].signatures) == 1 for r in ("float32", "float64")))
    return (os.getpid(), os.getppid(), "mmflow.workflow.pipeline" in sys.modules and compiled,
            os.environ.get("PYTHONHASHSEED"), os.environ.get("MMFLOW_WORKERS_PER_HOST"),
            {i["internal_api"]: i["num_threads"] for i in threadpool_info()})


def test_local_workers_fork_from_one_server_with_the_stages_imported(tmp_path):
    """A local cluster's workers are forks of one server process that imported the stages and loaded
    the compiled imaging kernels once (mmflow.workflow.engine.cluster.fork_workers_from_a_preloaded_server,
    mmflow.workflow.engine.worker_start) and see the environment dask
    gives spawned workers: one BLAS thread until a task sets its budget, dask's hash seed, mmflow's
    per-host worker count. A cluster opened again in the same process forks from the same server."""
    from mmflow.workflow.engine.cluster import open_cluster

    cfg = small_config(tmp_path / "r", "cluster.kind=local", "cluster.n_workers=2", "cluster.dashboard_address=:0")
    parents = set()
    for _ in range(2):
        with open_cluster(cfg, log=lambda *a: None) as client:
            states = list(client.run(_worker_state, 0).values())
        assert len(states) == 2 and len({s[0] for s in states}) == 2
        for pid, ppid, preloaded, seed, per_host, threads in states:
            assert preloaded and seed == "6640" and per_host == "2" and ppid != os.getpid()
            assert set(threads.values()) == {1}, threads
        parents |= {s[1] for s in states}
    assert len(parents) == 1  # every worker of both clusters: a child of the one server


def test_a_start_method_the_user_chose_is_kept(monkeypatch):
    import dask

    from mmflow.workflow.engine.cluster import START_METHOD, fork_workers_from_a_preloaded_server

    monkeypatch.setenv("DASK_DISTRIBUTED__WORKER__MULTIPROCESSING_METHOD", "spawn")
    with dask.config.set({START_METHOD: "spawn"}):
        fork_workers_from_a_preloaded_server()
        assert dask.config.get(START_METHOD) == "spawn"
