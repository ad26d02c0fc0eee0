"""mmflow on a real SLURM cluster of three nodes, each a network namespace with a hostname of its own
(tests/cluster/conftest.py): workers reach the driver's scheduler over the cluster's bridge, the run
directory is the shared filesystem, and every map is compared bit for bit with a synchronous run."""
import contextlib
import os
import socket
import subprocess
import sys
import threading
import time
from urllib.parse import urlparse

import numpy as np
import pytest
import yaml

from mmflow.bench.cluster import PAPER, PAPER_REDUCED
from mmflow.cli import main
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.cluster import open_cluster
from mmflow.workflow.engine.passes import run_with_passes
from mmflow.workflow.engine.pools import describe, plan_pools
from mmflow.workflow.engine.rundir import RunDir
from mmflow.workflow.pipeline import ORDER, PIPELINE
from mmflow.workflow.plan.planner import WORKER_BASE_BYTES, plan
from tests.workflow_helpers import ROOT, SMALL, assert_identical, read_outputs, small_config

pytestmark = [pytest.mark.slow, pytest.mark.cluster]

#: the reduced workflow's settings without its cluster.kind
WORKFLOW = ["workflows/demo.yaml", *[o for o in SMALL if not o.startswith("cluster.")]]
#: one small job per worker (nodes have 2 CPUs and 3000 MB)
JOB = 'cluster.jobqueue={cores: 1, memory: 1GB, walltime: "00:10:00"}'


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("sref") / "run"
    run_with_passes(small_config(run_dir), progress=False, log=lambda *a: None)
    return read_outputs(run_dir)


def _no_jobs(slurm):
    return slurm.slurm("squeue", "-h", "-o", "%i %T").strip() == ""


@pytest.fixture(scope="module")
def paper_reference(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("pref") / "run"
    run_with_passes(_paper(run_dir, "cluster.kind=synchronous"), progress=False, log=lambda *a: None)
    return read_outputs(run_dir)


def _paper(run_dir, *extra):
    return load_config(PAPER, [*PAPER_REDUCED, f"run.directory={run_dir}", *extra])


def _sample_jobs(slurm, seen, stop):
    """Every worker job squeue lists until ``stop`` is set: ``{job id: (cpus, memory, node)}`` of running ones."""
    while not stop.is_set():
        for line in slurm.slurm("squeue", "-h", "-t", "R", "-o", "%i %C %m %N", check=False).splitlines():
            job, cpus, mem, node = line.split()
            seen[job] = (int(cpus), mem, node)
        time.sleep(0.3)


def test_reduced_paper_scale_on_jobs_sized_per_stage_matches_a_local_run(slurm, paper_reference, tmp_path):
    """The reduced paper-scale workflow with no job shape given: the plan on the partition's nodes (sinfo:
    2 CPUs, 1500 MB: 1 GiB to a job, 296 MiB of it the job's own `dask worker` process) gives the stages
    workers of one 364 MiB share (two a job: solve, clean; normal runs with transfer) or of two (one a job:
    the rest, whose tasks need more); each stage's tasks ran on the running jobs' workers, holding its planned
    task in its share (dask's limit memory / processes, a worker of two cores running one task of a two-core
    stage at a time, two of a one-core stage), the one-core stages kept the two-core jobs (no queue wait),
    the workers were on two nodes (over the bridge: the scheduler on cluster.interface), the dashboard link
    printed is where it listens; maps bit-identical (the workers' memory thresholds: tests/cluster/conftest.py)."""
    run_dir = tmp_path / "run"
    cfg = _paper(run_dir, "cluster.kind=slurm", "cluster.n_workers=2", "cluster.dashboard_address=:0",
                 f"cluster.interface={slurm.bridge}")
    logs, seen, stop = [], {}, threading.Event()
    sampler = threading.Thread(target=_sample_jobs, args=(slurm, seen, stop), daemon=True)
    sampler.start()
    try:
        with open_cluster(cfg, log=logs.append) as client:
            run_with_passes(cfg, client, progress=False, log=logs.append)
            assert client.scheduler.address.startswith(f"tcp://{slurm.host_address}:")
            link = next(line for line in logs if line.startswith("dask dashboard:")).split()[-1]
            host, port = urlparse(link).hostname, urlparse(link).port
            assert host == "127.0.0.1", link  # the jobqueue dashboard listens on loopback only (cluster.expose)
            socket.create_connection((host, port), timeout=5).close()  # and really listens there
    finally:
        stop.set()
        sampler.join(5)
    planned_pools = plan_pools(cfg, "slurm", {}, log=lambda *a: None)  # what the run asked sinfo's nodes for
    # a stage run channel by channel after another (normal after transfer) runs in that one's pool
    pools = {st.name: planned_pools[st.by_channel_after or st.name] for st in PIPELINE if st.name in planned_pools}
    # the pool whose jobs run each stage: a stage of smaller workers than the running ones keeps them
    running, serving, ran_on, said = None, None, {}, []
    for name, p in pools.items():
        if p is not running and p is not serving:
            if running is not None and running["worker_cores"] >= p["worker_cores"]:
                said.append(f"stage {name}: the running jobs kept")
            else:
                running = p
                said.append(f"stage {name}: {describe(p)}")
        serving, ran_on[name] = p, running
    switches = [line for line in logs if line.startswith("stage ")]
    assert [line.split(":")[0] for line in switches] == [t.split(":")[0] for t in said], (switches, said)
    assert all(line.startswith(t) for line, t in zip(switches, said)), (switches, said)
    assert switches[0].startswith(f"stage simulate: {pools['simulate']['count']} jobs of 2 cores / 1.07 GB,"), logs
    assert any("the running jobs kept" in line for line in switches), switches  # solve's 1-core pool: no queue wait
    planned = {e["stage"]: e["task_bytes"] + WORKER_BASE_BYTES for e in plan(cfg, peak_gflops=100.0)["stages"]}
    run, several = RunDir(run_dir), False
    for name, need in planned.items():
        infos = [i for i in run.task_infos(name).values() if "worker" in i]
        limits = {i["worker_memory_bytes"] for i in infos}
        k, j = ran_on[name]["worker_cores"], pools[name]["worker_cores"]
        assert limits == {2 ** 30 // ran_on[name]["processes"]}, (name, limits, logs)  # a job: 1 GiB / its workers
        assert need < 0.95 * min(limits) * j / k, (name, need, limits)  # its share: below dask's kill threshold
        by_worker = {}
        for i in infos:
            by_worker.setdefault(i["worker"], []).append((i["started"], i["started"] + i["seconds"]))
        for spans in by_worker.values():  # at most k // j at once a worker (pools.TASK_SLOT), whatever its threads
            ends = sorted([(a, 1) for a, _ in spans] + [(b, -1) for _, b in spans], key=lambda e: (e[0], e[1]))
            at_once = np.cumsum([d for _, d in ends])
            assert at_once.max() <= k // j, (name, spans)
        # each task's own count of the tasks its worker process ran at once (TasksAtOnce: the traced and
        # resident peaks are one task's only at 1): at least the overlap of the recorded spans (the count's
        # block encloses each span; the others' spans shrunk by the 1-ms rounding of the records), at most the
        # bound
        for i in infos:
            a, b = i["started"], i["started"] + i["seconds"]
            spans = [(a, b)] + [(s0 + 0.002, s1 - 0.002) for s0, s1 in by_worker[i["worker"]] if (s0, s1) != (a, b)]
            spans = [(max(a, s0), min(b, s1)) for s0, s1 in spans if s0 < b and s1 > a]
            ends = sorted([(s0, 1) for s0, _ in spans] + [(s1, -1) for _, s1 in spans], key=lambda e: (e[0], e[1]))
            overlap = max(np.cumsum([d for _, d in ends]))
            assert overlap <= i["tasks_at_once"] <= k // j, (name, i, overlap)
        several = several or (k == j > 1 and any(len(v) > 1 for v in by_worker.values()))
    assert several  # a worker of two threads ran several tasks of its two-core stage, one after another
    assert {c for c, _, _ in seen.values()} == {2} and len({n for _, _, n in seen.values()}) >= 2, seen
    assert_identical(paper_reference, read_outputs(run_dir))


def test_an_impossible_request_is_refused_before_any_submission(slurm, tmp_path, capsys):
    rc = main(["run", *WORKFLOW, f"run.directory={tmp_path / 'run'}", "--cluster", "slurm", "--no-progress",
               "cluster.jobqueue={cores: 64, memory: 500GB}"])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "cluster.jobqueue.cores" in err and "at most 2 CPUs" in err, err
    assert _no_jobs(slurm)
    rc = main(["run", *WORKFLOW, f"run.directory={tmp_path / 'run'}", "--cluster", "slurm", "--no-progress",
               "cluster.jobqueue={cores: 1, memory: 500GB}"])
    err = capsys.readouterr().err
    assert rc == 2 and "cluster.jobqueue.memory" in err, err
    assert _no_jobs(slurm)


def test_cluster_slurm_alone_finishes(slurm, reference, tmp_path, capsys, monkeypatch):
    """No cluster setting but --cluster slurm: job cores and memory from the plan and sinfo, the
    scheduler on the interface of the nodes' network (sinfo's node addresses). The submitting shell
    exports ``OPENBLAS_NUM_THREADS=2``, which the worker jobs inherit: each task still runs its BLAS on
    one thread (its marker says), as the synchronous reference's (two worker threads restoring each
    other's BLAS limits made the Grams differ in the last bit)."""
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "2")
    run_dir = tmp_path / "run"
    rc = main(["run", *WORKFLOW, f"run.directory={run_dir}", "--cluster", "slurm", "--no-progress"])
    out = capsys.readouterr().out
    assert rc == 0, out[-3000:]
    assert f"listens on {slurm.bridge}" in out and "sized per stage from the plan" in out, out[:3000]
    assert "stage simulate: " in out and "jobs of 2 cores / 1.07 GB" in out, out[:3000]
    assert yaml.safe_load((run_dir / "config.yaml").read_text())["cluster"]["kind"] == "slurm"
    infos = [i for st in ORDER for i in RunDir(run_dir).task_infos(st).values() if "worker" in i]
    assert infos and {i["blas_threads"] for i in infos} == {1}
    assert_identical(reference, read_outputs(run_dir))


@contextlib.contextmanager
def _beside(fn):
    """Run ``fn`` in a thread while the ``with`` block runs; on leaving it, wait for ``fn`` (at most 120 s) and
    re-raise its exception, if any, in the test's thread."""
    errors = []

    def target():
        try:
            fn()
        except BaseException as e:  # re-raised in the test's thread
            errors.append(e)

    t = threading.Thread(target=target, daemon=True)
    t.start()
    try:
        yield
    finally:
        t.join(120)
    if errors:
        raise errors[0]


def _poll(ready, timeout, step):
    """The first truthy value of ``ready()``, asked every ``step`` s for at most ``timeout`` s, or None."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        got = ready()
        if got:
            return got
        time.sleep(step)
    return None


def test_a_drained_node_longer_than_worker_wait_s_then_resumed(slurm, reference, tmp_path):
    """The only node the job may use is drained for 3x worker_wait_s: the job is queued, not a dead
    worker; the run says what it waits for, and finishes once the node is resumed."""
    node, wait_s = slurm.nodes[-1], 3
    run_dir = tmp_path / "run"
    cfg = small_config(run_dir, "cluster.kind=slurm", "cluster.n_workers=1", "cluster.dashboard_address=:0",
                       f"cluster.worker_wait_s={wait_s}", "cluster.jobqueue={cores: 1, memory: 1GB, walltime: "
                       f"'00:10:00', job_extra_directives: ['--nodelist={node}']}}")
    logs = []
    slurm.slurm("scontrol", "update", f"nodename={node}", "state=drain", "reason=mmflow-test")

    def resume_later():
        _poll(lambda: any("waiting for 1 queued jobs" in line for line in logs), 60, 0.2)
        time.sleep(3 * wait_s)
        slurm.slurm("scontrol", "update", f"nodename={node}", "state=resume")

    try:
        with _beside(resume_later), open_cluster(cfg, log=logs.append) as client:
            run_with_passes(cfg, client, progress=False, log=logs.append)
    finally:
        slurm.slurm("scontrol", "update", f"nodename={node}", "state=resume", check=False)
    waiting = [line for line in logs if "waiting for 1 queued jobs (" in line]
    assert waiting and "ReqNodeNotAvail" in waiting[0], logs
    assert waiting[0] in (run_dir / "mmflow.log").read_text()
    assert_identical(reference, read_outputs(run_dir))


def test_a_node_killed_mid_transfer_is_survived(slurm, reference, tmp_path, monkeypatch):
    """slurmd and every process of a node with a task in flight killed mid-transfer: the tasks go to
    the other workers, the loss is logged, the run finishes without a rerun, bit-identical."""
    monkeypatch.setenv("MMFLOW_TASK_DELAY_S", "0.5")  # the jobs' workers get it through sbatch's environment
    run_dir = tmp_path / "run"
    cfg = small_config(run_dir, "cluster.kind=slurm", "cluster.n_workers=3", "cluster.dashboard_address=:0",
                       f"cluster.interface={slurm.bridge}", JOB)
    logs, killed = [], []
    with open_cluster(cfg, log=logs.append) as client:
        client.wait_for_workers(3, timeout=120)
        hosts = client.run(socket.gethostname)

        def kill_a_busy_node():
            busy = _poll(lambda: [w for w, keys in client.processing().items()
                                  if any(str(k).startswith("transfer-") for k in keys)], 120, 0.05)
            if busy:  # a transfer task in flight there
                killed.append(hosts[busy[0]])
                slurm.kill_node(hosts[busy[0]])

        with _beside(kill_a_busy_node):
            run_with_passes(cfg, client, progress=False, log=logs.append)
    try:
        assert killed, "no transfer task was seen in flight"
        assert any(f"on {killed[0]} lost" in line for line in logs), logs
        assert_identical(reference, read_outputs(run_dir))
    finally:
        if killed:
            slurm.start_node(killed[0])
            slurm.wait_idle(slurm.nodes, 60)


def test_a_cancelled_job_is_replaced_and_the_run_finishes(slurm, reference, tmp_path, monkeypatch):
    """Issue 38's own case: one of two worker jobs ``scancel``led after tasks of the run have finished. The
    loss is logged, a job is submitted in its place (squeue lists a third job), its worker joins and runs
    tasks (their markers name it), and the maps are bit-identical to a synchronous run's."""
    monkeypatch.setenv("MMFLOW_TASK_DELAY_S", "3")  # 19 tasks left: ~1 min for one worker, time for a new job's
    run_dir = tmp_path / "run"
    cfg = small_config(run_dir, "cluster.kind=slurm", "cluster.n_workers=2", "cluster.dashboard_address=:0",
                       f"cluster.interface={slurm.bridge}", JOB)
    logs, cancelled, seen, stop = [], [], {}, threading.Event()
    sampler = threading.Thread(target=_sample_jobs, args=(slurm, seen, stop), daemon=True)
    sampler.start()
    try:
        with open_cluster(cfg, log=logs.append) as client:
            client.wait_for_workers(2, timeout=120)
            first = dict(client.run(lambda dask_worker: str(dask_worker.name)))

            def cancel_one_after_two_tasks():  # two tasks finished (a stage's _prepare is not one)
                if _poll(lambda: len([m for m in (run_dir / "_status").glob("*/*.done")
                                      if not m.name.startswith("_")]) >= 2, 180, 0.1):
                    job = sorted(seen)[0]
                    slurm.slurm("scancel", job)
                    cancelled.append(job)

            with _beside(cancel_one_after_two_tasks):
                run_with_passes(cfg, client, progress=False, log=logs.append)
    finally:
        stop.set()
        sampler.join(5)
    assert cancelled, "no task finished within 180 s"
    job = cancelled[0]
    assert any(line.startswith(f"worker of job {job}") and "lost" in line for line in logs), logs
    assert any(line.startswith(f"worker job {job}") and "submitting a replacement" in line for line in logs), logs
    assert len(seen) >= 3, seen  # the two jobs asked for and the one in the cancelled one's place
    workers = {i["worker"] for st in ORDER for i in RunDir(run_dir).task_infos(st).values() if "worker" in i}
    assert workers - set(first.values()), (workers, first)  # the replacement's worker ran tasks
    assert_identical(reference, read_outputs(run_dir))


def test_a_run_longer_than_its_jobs_walltime_finishes(slurm, reference, tmp_path, monkeypatch):
    """Jobs of a 1-minute walltime, a run of more than a minute of work for its one worker: each
    worker retires before its walltime (--lifetime with a stagger), a new job takes over."""
    monkeypatch.setenv("MMFLOW_TASK_DELAY_S", "2.5")  # 21 tasks: > 50 s of work, a worker lives 40 +- 5 s
    run_dir = tmp_path / "run"
    cfg = small_config(run_dir, "cluster.kind=slurm", "cluster.n_workers=1", "cluster.dashboard_address=:0",
                       "cluster.jobqueue={cores: 1, memory: 1GB, walltime: '00:01:00'}")
    logs = []
    t0 = time.time()
    with open_cluster(cfg, log=logs.append) as client:
        run_with_passes(cfg, client, progress=False, log=logs.append)
    assert time.time() - t0 > 60
    replaced = [line for line in logs if "submitting a replacement" in line]
    assert replaced, logs
    assert_identical(reference, read_outputs(run_dir))
    job_logs = [p.read_text() for p in (run_dir / "cluster-logs").glob("*.err")]
    assert any("worker-lifetime-reached" in text for text in job_logs)  # retired, then replaced
    assert not any("DUE TO TIME LIMIT" in text for text in job_logs)  # before SLURM's walltime


def test_a_worker_that_cannot_reach_the_scheduler_is_reported_with_its_error(slurm, tmp_path, capsys,
                                                                              monkeypatch):
    """The scheduler on an interface the nodes cannot reach (loopback: each node has its own): the run
    stops naming the address the worker tried and the worker's own error (from its job's log), not
    "workers died"."""
    monkeypatch.setenv("DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT", "3s")  # the workers give up sooner
    rc = main(["run", *WORKFLOW, f"run.directory={tmp_path / 'run'}", "--cluster", "slurm", "--no-progress",
               "cluster.interface=lo", "cluster.dashboard_address=:0",
               "cluster.jobqueue={cores: 1, memory: 1GB, death_timeout: 15}"])
    err = capsys.readouterr().err
    assert rc != 0
    assert "could not reach the scheduler at tcp://127.0.0.1:" in err and "cluster.interface" in err, err
    assert "workers died" not in err
    deadline = time.time() + 30
    while not _no_jobs(slurm) and time.time() < deadline:
        time.sleep(0.5)
    assert _no_jobs(slurm)


def test_the_driver_as_a_batch_job(slurm, reference, tmp_path):
    """workflows/slurm-driver.sbatch: the driver on a node submits its worker jobs from there, its
    scheduler listens on that node's interface on the nodes' network, the maps are bit-identical."""
    run_dir, log = tmp_path / "run", tmp_path / "driver-%j.log"
    env = dict(os.environ, PATH=os.pathsep.join([os.path.dirname(sys.executable), os.environ["PATH"]]))
    out = subprocess.run(["sbatch", "--mem=1200M", f"--output={log}", "workflows/slurm-driver.sbatch",
                          *WORKFLOW, f"run.directory={run_dir}"], cwd=ROOT, env=env, capture_output=True,
                         text=True, check=True).stdout
    job = out.split()[-1]
    deadline = time.time() + 300
    while slurm.slurm("squeue", "-h", "-j", job, check=False).strip() and time.time() < deadline:
        time.sleep(1)
    text = (tmp_path / f"driver-{job}.log").read_text()
    assert "stage times:" in text, text[-3000:]
    listens = text.split("the scheduler listens on tcp://")[1].split(":")[0]
    assert listens in {slurm.address(n) for n in slurm.nodes}, text[:2000]  # on the driver's node
    assert_identical(reference, read_outputs(run_dir))
