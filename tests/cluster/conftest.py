"""The cluster tier: a real SLURM cluster of three nodes, each a network namespace of its own
(:mod:`mmflow.bench.netns_slurm`), started once per session. Skipped, saying why, where it cannot
start (not root, no network namespaces, no slurm-wlm/munge and no apt-get to install them)."""
import pytest

from mmflow.bench.netns_slurm import NamespacedSlurm, unavailable


@pytest.fixture(scope="session")
def slurm_session(tmp_path_factory):
    """A started :class:`NamespacedSlurm` (3 nodes of 2 CPUs and 1500 MB: a job of 1 GiB at most, as dask-jobqueue
    asks SLURM for whole GiB; small nodes, so that a small workflow plans workers of two sizes), stopped (every
    process by PID, the namespaces, veths and bridge deleted) at the end of the session."""
    why = unavailable()
    if why:
        pytest.skip(f"no namespaced SLURM cluster: {why}")
    cluster = NamespacedSlurm(tmp_path_factory.mktemp("slurm"), n_nodes=3, cpus=2, memory_mb=1500)
    cluster.start()
    try:
        yield cluster
    finally:
        cluster.stop()


@pytest.fixture
def slurm(slurm_session, monkeypatch):
    """The session's cluster, with SLURM_CONF pointing SLURM's commands (and so dask-jobqueue's
    sbatch, squeue, scancel) at it for this test only: other tests in the same process see no SLURM.

    The nodes' 1500 MB make workers of 512 MiB where jobs are sized from the plan, smaller than any real
    cluster's (a worker with mmflow's stages imported is resident at ~0.4 GB before its task): dask's
    pause and kill thresholds are off in the workers (sbatch passes the environment on); SLURM enforces
    no memory here either. The tests check which workers were asked for and served, not their memory."""
    monkeypatch.setenv("SLURM_CONF", str(slurm_session.conf))
    for key in ("PAUSE", "TERMINATE"):
        monkeypatch.setenv(f"DASK_DISTRIBUTED__WORKER__MEMORY__{key}", "False")
    return slurm_session
