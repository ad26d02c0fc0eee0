"""SLURM/PBS job shapes without a batch system: worker lifetimes from the walltime, requests no
node can hold, the options --cluster slurm fills in (tests/cluster runs them on a real SLURM)."""
import time

import pytest

from mmflow.errors import InputError
from mmflow.workflow.engine.batch import QueueState, job_options, lifetime_args, refuse_impossible
from tests.workflow_helpers import small_config


@pytest.mark.parametrize("walltime, lifetime, stagger", [
    ("00:01:00", 40, 5), ("00:30:00", 1440, 90), ("2-00:00:00", 172200, 150), ("10", 480, 30), ("5:00", 240, 15)])
def test_workers_retire_before_the_walltime(walltime, lifetime, stagger):
    args = lifetime_args(walltime)
    assert args == ["--lifetime", f"{lifetime}s", "--lifetime-stagger", f"{stagger}s"]
    assert lifetime + stagger < {"00:01:00": 60, "00:30:00": 1800, "2-00:00:00": 172800, "10": 600,
                                 "5:00": 300}[walltime]
    assert lifetime_args(None) == [] and lifetime_args("soon") == []


def test_a_workers_lifetime_counts_from_its_jobs_start(monkeypatch):
    """A worker that took 28 s to start in a job whose lifetime is 30 s retires ~2 s after it started
    (dask alone would give it 30 s): the job script's start time, read by the preload's dask_setup."""
    import asyncio

    from distributed import Scheduler, Worker
    from distributed.core import Status

    from mmflow.workflow.engine.batch import JOB_START_VAR
    from mmflow.workflow.engine.pools import job_prologue
    from mmflow.workflow.engine.worker_start import dask_setup, lifetime_left

    assert lifetime_left(30.0, 100.0, 128.0) == 2.0 and lifetime_left(30.0, 100.0, 200.0) == 0.0
    assert lifetime_left(None, 100.0, 128.0) is None and lifetime_left(30.0, None, 128.0) is None
    assert f"export {JOB_START_VAR}=$(date +%s)" in job_prologue(1)

    async def run():
        async with Scheduler(dashboard_address=":0") as s:
            async with Worker(s.address, lifetime="30s", lifetime_stagger="0s", nthreads=1) as w:
                dask_setup(w)  # no job start in the environment: dask's count stands
                monkeypatch.setenv(JOB_START_VAR, str(time.time() - 28.0))
                dask_setup(w)
                t0 = time.time()
                while w.status != Status.closed and time.time() - t0 < 20:
                    await asyncio.sleep(0.1)
                return w.status, time.time() - t0

    status, waited = asyncio.run(run())
    assert status == Status.closed and waited < 10


def test_a_request_no_node_can_hold_is_refused_naming_the_limit():
    nodes = [(2, 3000), (4, 1000)]
    refuse_impossible({"cores": 2, "memory": "2GB"}, "slurm", nodes)  # the first node holds it
    refuse_impossible({"cores": 64, "memory": "500GB"}, "slurm", None)  # no sinfo: not checked
    with pytest.raises(InputError) as e:
        refuse_impossible({"cores": 64, "memory": "1GB"}, "slurm", nodes)
    assert e.value.field == "cluster.jobqueue.cores" and "at most 4 CPUs" in str(e.value)
    with pytest.raises(InputError) as e:
        refuse_impossible({"cores": 3, "memory": "2GB", "queue": "small"}, "slurm", nodes)  # 3 CPUs: 1000 MB only
    assert e.value.field == "cluster.jobqueue.memory" and "small" in str(e.value)


def test_cluster_slurm_alone_gets_cores_memory_logs_and_lifetime(tmp_path, monkeypatch):
    import dask_jobqueue  # noqa: F401  (loads dask's jobqueue.yaml defaults, as jobqueue_cluster does)

    monkeypatch.setenv("PATH", str(tmp_path))  # no sinfo: node sizes unknown
    said = []
    opts, sizes = job_options(small_config(tmp_path / "run", "cluster.kind=slurm"), "slurm", said.append)
    assert sizes is None and opts["cores"] == 1 and opts["processes"] == 1 and opts["memory"] == "1.86GiB"
    assert opts["log_directory"] == str(tmp_path / "run" / "cluster-logs")
    assert "--lifetime" in opts["worker_extra_args"] and "memory 1.86GiB" in said[0]
    monkeypatch.setenv("MMFLOW_TEST_USER", "someone")
    jq = ("cluster.jobqueue={cores: 4, memory: 8GB, log_directory: '/x/${MMFLOW_TEST_USER}/logs', "
          "worker_extra_args: [--lifetime, 1h]}")
    opts, _ = job_options(small_config(tmp_path / "run", "cluster.kind=slurm", jq), "slurm", said.append)
    assert opts["log_directory"] == "/x/someone/logs"
    assert opts["worker_extra_args"] == ["--lifetime", "1h", "--preload", "mmflow.workflow.engine.worker_start"]
    assert opts["cores"] == 4 and opts["memory"] == "8GB"


def test_a_jobs_default_memory_holds_its_own_process_beside_its_worker(tmp_path, monkeypatch):
    """A job's own `dask worker` process (nannies; it imports the workers' --preload) is SLURM's to count
    with the worker: a largest task of 2 GB with the worker's baseline asks 1.5 x 2 GB and 296 MiB,
    rounded up to half a GB (3.5 GB), where the worker alone would have asked 3.0 GB."""
    import dask_jobqueue  # noqa: F401  (loads dask's jobqueue.yaml defaults, as jobqueue_cluster does)
    from dask.utils import parse_bytes

    from mmflow.workflow.engine import batch
    from mmflow.workflow.plan.nodes import JOB_PROCESS_BYTES

    monkeypatch.setenv("PATH", str(tmp_path))  # no sinfo: node sizes unknown
    monkeypatch.setattr(batch, "largest_task_gb", lambda cfg: 2.0)
    said = []
    opts, _ = job_options(small_config(tmp_path / "run", "cluster.kind=slurm"), "slurm", said.append)
    assert 3.0e9 < 3.0e9 + JOB_PROCESS_BYTES <= parse_bytes(opts["memory"]) == pytest.approx(3.5e9, rel=1e-3)
    assert "the job's own process 0.31 GB" in said[0]


def test_queued_jobs_are_described_with_their_reasons():
    assert QueueState().waiting() is None
    st = QueueState(pending=[("1", "Priority"), ("2", "Resources"), ("3", "Priority")])
    assert st.waiting() == "waiting for 3 queued jobs (Priority, Resources)"


#: ``qstat -f -F json`` of OpenPBS 2022.1.1 on ALCF's Polaris, as printed there (a queued, a held and a
#: running job; attributes the parser does not read left out, values as printed)
QSTAT_JSON = """{
    "timestamp":1699637718,
    "pbs_version":"2022.1.1.20220926110806",
    "pbs_server":"polaris-pbs-01.hsn.cm.polaris.alcf.anl.gov",
    "Jobs":{
        "359322.polaris-pbs-01.hsn.cm.polaris.alcf.anl.gov":{
            "Job_Name":"STDIN",
            "job_state":"Q",
            "queue":"debug",
            "Resource_List":{"ncpus":64, "ngpus":8, "nodect":1, "select":"1:ngpus=8", "walltime":"01:00:00"},
            "substate":10,
            "comment":"Not Running: Job is requesting an exclusive node and node is in use",
            "eligible_time":"8199:09:40"
        },
        "412020.polaris-pbs-01.hsn.cm.polaris.alcf.anl.gov":{
            "Job_Name":"pyannote",
            "job_state":"H",
            "queue":"preemptable",
            "Hold_Types":"s",
            "substate":20,
            "comment":"job held, too many failed attempts to run",
            "run_count":21
        },
        "1147579.polaris-pbs-01.hsn.cm.polaris.alcf.anl.gov":{
            "Job_Name":"xgc1_core",
            "resources_used":{"ncpus":160, "walltime":"22:28:30"},
            "job_state":"R",
            "queue":"large",
            "exec_host":"x3006c0s31b1n0/0+x3006c0s37b0n0/0+x3006c0s37b1n0/0"
        }
    }
}"""
#: plain ``qstat`` of OpenPBS (a tutorial's listing, an OpenPBS cluster on Azure): a queued job's time is "0"
QSTAT_TABLE = """\
Job id            Name             User              Time Use S Queue
----------------  ---------------- ----------------  -------- - -----
6.scheduler       sys-dashboard-s  clusteradmin      00:00:17 R workq
7.scheduler       STDIN            clusteradmin      03:24:08 R workq
8.scheduler       OPM              clusteradmin             0 Q workq
"""


def test_pbs_queued_jobs_are_read_with_the_schedulers_reason():
    from mmflow.workflow.engine.batch import parse_qstat, parse_qstat_json

    got = parse_qstat_json(QSTAT_JSON, ["359322", "412020", "1147579", "5"])
    assert got == {"359322": ("PENDING", "Not Running: Job is requesting an exclusive node and node is in use", ""),
                   "412020": ("PENDING", "job held, too many failed attempts to run", ""),
                   "1147579": ("RUNNING", "queued", "x3006c0s31b1n0")}  # a job qstat no longer lists: gone
    assert parse_qstat_json(QSTAT_JSON, ["1147579"]).keys() == {"1147579"}
    for not_json in (None, QSTAT_TABLE):  # Torque has no -F json: the plain listing is read instead
        with pytest.raises((TypeError, ValueError)):
            parse_qstat_json(not_json, ["8"])
    assert parse_qstat(QSTAT_TABLE, ["7", "8"]) == {"7": ("RUNNING", "queued", ""), "8": ("PENDING", "queued", "")}
    st = QueueState(pending=[(j, r) for j, (s, r, _) in got.items() if s == "PENDING"])
    assert st.waiting() == ("waiting for 2 queued jobs (Not Running: Job is requesting an exclusive node and node "
                            "is in use, job held, too many failed attempts to run)")


FIRST_TIME_CYCLES = """
import gc, sys, types
if sys.argv[1] == "preload":
    import mmflow.workflow.engine.worker_start  # noqa: F401  (what every job-queue worker imports first)
from mmflow.sky.frames import apparent_sidereal_time, rotation_matrix
gc.collect()
gc.set_debug(gc.DEBUG_SAVEALL)
rotation_matrix("icrs", "date", 2460000.25)  # a task placing sources at its data's epoch
apparent_sidereal_time(2460000.25, -118.3)
gc.collect()
print(sum(isinstance(o, types.FrameType) for o in gc.garbage))
"""


def test_the_preload_leaves_a_workers_first_task_no_frames_in_reference_cycles():
    """astropy's first time parse in a process leaves reference cycles whose frames hold their callers'
    frames, so a worker's first task that places sources kept its arrays until the next garbage collection
    (the 352-antenna array's first m-mode task traced 96.7 MB, the next ones 69.9). After the workers'
    preload (:func:`mmflow.workflow.engine.worker_start.load_time_tables`) such a task leaves none; a
    process without it does (the check can fail)."""
    import os
    import subprocess
    import sys

    from tests.workflow_helpers import ROOT

    env = dict(os.environ, PYTHONPATH=ROOT)
    frames = {}
    for how in ("bare", "preload"):
        out = subprocess.run([sys.executable, "-c", FIRST_TIME_CYCLES, how], cwd=ROOT, env=env, check=True,
                             capture_output=True, text=True)
        frames[how] = int(out.stdout.split()[-1])
    assert frames["bare"] > 0 and frames["preload"] == 0, frames


def test_a_jobs_worker_waits_minutes_not_seconds_to_join_unless_told(tmp_path, monkeypatch):
    """dask-jobqueue's default death timeout of 60 s killed preloaded workers still starting on a busy node:
    mmflow asks for DEATH_TIMEOUT_S where nothing else is set, and keeps what cluster.jobqueue sets."""
    import dask_jobqueue  # noqa: F401  (loads dask's jobqueue.yaml defaults, as jobqueue_cluster does)

    from mmflow.workflow.engine.batch import DEATH_TIMEOUT_S, JOBQUEUE_DEATH_TIMEOUT_S, jobqueue_default

    monkeypatch.setenv("PATH", str(tmp_path))  # no sinfo
    assert jobqueue_default("slurm", "death_timeout") == JOBQUEUE_DEATH_TIMEOUT_S  # dask-jobqueue's, unchanged
    base = ["cluster.kind=slurm", "cluster.jobqueue={cores: 1, memory: 2GB}"]
    opts, _ = job_options(small_config(tmp_path / "run", *base), "slurm", lambda *a: None)
    assert opts["death_timeout"] == DEATH_TIMEOUT_S > JOBQUEUE_DEATH_TIMEOUT_S
    opts, _ = job_options(small_config(tmp_path / "run", "cluster.kind=slurm",
                                       "cluster.jobqueue={cores: 1, memory: 2GB, death_timeout: 15}"), "slurm",
                          lambda *a: None)
    assert opts["death_timeout"] == 15
