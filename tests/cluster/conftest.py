"""The cluster tier: a real SLURM cluster of three nodes, each a network namespace of its own
(:mod:`tests.cluster.slurm_netns`), started once per session. Skipped, saying why, where it cannot
start (not root, no network namespaces, no slurm-wlm/munge and no apt-get to install them)."""
import os

import pytest

from tests.cluster.slurm_netns import NamespacedSlurm, unavailable


@pytest.fixture(scope="session")
def slurm(tmp_path_factory):
    """A started :class:`NamespacedSlurm` (3 nodes of 2 CPUs, 3000 MB); SLURM_CONF points SLURM's
    commands (and so dask-jobqueue's sbatch, squeue, scancel) at it for the session."""
    why = unavailable()
    if why:
        pytest.skip(f"no namespaced SLURM cluster: {why}")
    cluster = NamespacedSlurm(tmp_path_factory.mktemp("slurm"), n_nodes=3, cpus=2, memory_mb=3000)
    cluster.start()
    saved = os.environ.get("SLURM_CONF")
    os.environ["SLURM_CONF"] = str(cluster.conf)
    try:
        yield cluster
    finally:
        if saved is None:
            os.environ.pop("SLURM_CONF", None)
        else:
            os.environ["SLURM_CONF"] = saved
        cluster.stop()
