"""SLURM/PBS job shapes without a batch system: worker lifetimes from the walltime, requests no
node can hold, the options --cluster slurm fills in (tests/cluster runs them on a real SLURM)."""
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
    assert opts["log_directory"] == "/x/someone/logs" and opts["worker_extra_args"] == ["--lifetime", "1h"]
    assert opts["cores"] == 4 and opts["memory"] == "8GB"


def test_queued_jobs_are_described_with_their_reasons():
    assert QueueState().waiting() is None
    st = QueueState(pending=[("1", "Priority"), ("2", "Resources"), ("3", "Priority")])
    assert st.waiting() == "waiting for 3 queued jobs (Priority, Resources)"
