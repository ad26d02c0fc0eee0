"""mmflow on a real SLURM cluster of three nodes, each a network namespace with a hostname of its own
(tests/cluster/conftest.py): workers reach the driver's scheduler over the cluster's bridge, the run
directory is the shared filesystem, and every map is compared bit for bit with a synchronous run."""
import socket

import pytest

from mmflow.cli import main
from mmflow.workflow.cluster import open_cluster
from mmflow.workflow.passes import run_with_passes
from tests.workflow_helpers import SMALL, assert_identical, read_outputs, small_config

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


def test_workflow_on_three_nodes_matches_a_local_run(slurm, reference, tmp_path):
    """Three worker jobs spread over the nodes; the scheduler listens on cluster.interface (the
    bridge), the dashboard link printed is where the dashboard listens; maps bit-identical."""
    run_dir = tmp_path / "run"
    cfg = small_config(run_dir, "cluster.kind=slurm", "cluster.n_workers=3", "cluster.dashboard_address=:0",
                       f"cluster.interface={slurm.bridge}", JOB)
    logs = []
    with open_cluster(cfg, log=logs.append) as client:
        client.wait_for_workers(3, timeout=120)
        hosts = client.run(socket.gethostname)  # each node's UTS namespace: its own hostname
        addresses = {a.split("://")[1].rsplit(":", 1)[0] for a in hosts}
        run_with_passes(cfg, client, progress=False, log=logs.append)
        assert client.scheduler.address.startswith(f"tcp://{slurm.host_address}:")
    assert len(set(hosts.values())) >= 2 and set(hosts.values()) <= set(slurm.nodes), hosts
    assert addresses <= {slurm.address(n) for n in slurm.nodes}, addresses  # over the bridge, not loopback
    link = next(line for line in logs if line.startswith("dask dashboard:"))
    assert "http://127.0.0.1:" in link, link  # the jobqueue dashboard listens on loopback only
    assert_identical(reference, read_outputs(run_dir))


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


def test_cluster_slurm_alone_finishes(slurm, reference, tmp_path, capsys):
    """No cluster setting but --cluster slurm: job cores and memory from the plan and sinfo, the
    scheduler on the interface of the nodes' network (sinfo's node addresses)."""
    run_dir = tmp_path / "run"
    rc = main(["run", *WORKFLOW, f"run.directory={run_dir}", "--cluster", "slurm", "--no-progress"])
    out = capsys.readouterr().out
    assert rc == 0, out[-3000:]
    assert f"listens on {slurm.bridge}" in out and "cores 1, memory" in out, out[:3000]
    assert_identical(reference, read_outputs(run_dir))
