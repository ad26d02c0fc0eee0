"""Where the graph runs: a local cluster, an existing scheduler, or SLURM/PBS via dask-jobqueue."""
from __future__ import annotations

import os
from contextlib import contextmanager

from mmflow.errors import InputError


def jobqueue_cluster(cfg, kind):
    """A dask-jobqueue SLURM or PBS cluster from ``cluster.jobqueue`` (rest from dask's jobqueue.yaml).

    Nothing is submitted until the cluster is scaled; ``cluster.job_script()`` shows the script.
    """
    import dask_jobqueue

    cls = dask_jobqueue.SLURMCluster if kind == "slurm" else dask_jobqueue.PBSCluster
    return cls(**cfg.cluster.jobqueue)


@contextmanager
def open_cluster(cfg, scheduler=None, kind=None, log=print):
    """Yield a ``distributed.Client`` (or None for the synchronous scheduler).

    ``scheduler`` (or ``DASK_SCHEDULER_ADDRESS``) joins an existing cluster; ``kind`` overrides
    ``cluster.kind``. Worker memory limits stay on: dask spills, pauses and restarts workers
    that exceed them.
    """
    c = cfg.cluster
    kind = kind or ("address" if (scheduler or os.environ.get("DASK_SCHEDULER_ADDRESS")) else c.kind)
    if kind == "synchronous":
        yield None
        return
    from distributed import Client

    cluster = None
    if kind == "address":
        addr = scheduler or c.address or os.environ.get("DASK_SCHEDULER_ADDRESS")
        if not addr:
            raise InputError("cluster", "address", "no scheduler address",
                             "pass --scheduler tcp://host:8786 or set DASK_SCHEDULER_ADDRESS")
        client = Client(addr)
    elif kind == "local":
        from distributed import LocalCluster

        cluster = LocalCluster(n_workers=c.n_workers, threads_per_worker=c.threads_per_worker,
                               memory_limit=c.memory_limit, dashboard_address=c.dashboard_address)
        client = Client(cluster)
    elif kind in ("slurm", "pbs"):
        cluster = jobqueue_cluster(cfg, kind)
        cluster.scale(jobs=c.n_workers)
        client = Client(cluster)
    else:
        raise InputError("cluster", "kind", f"unknown cluster kind '{kind}'", "use local, address, slurm or pbs")
    log(f"dask dashboard: {client.dashboard_link}")
    try:
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
